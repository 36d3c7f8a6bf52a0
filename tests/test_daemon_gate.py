"""The champion/challenger gate in the daemon, on the simulated cell.

In-process tests run the daemon's Controller (its setup, run loop and command handler) with a *rigged
learner*: its updates do not train but set the online weights to a chosen network, so the challenger it hands
over is known to be worse or better than the champion.  Process tests run the real ``flgd run``.
"""

from __future__ import annotations

import copy
import sqlite3
import threading
import time
from pathlib import Path

import pytest
import torch

from flgd.config import load_config
from flgd.daemon.controller import Controller
from flgd.daemon.protocol import ProtocolError, Request
from flgd.learning.learner import UpdateStats
from flgd.learning.policy_file import load_policy, save_policy

from tests.fakes.daemon import REPO, write_config

pytestmark = pytest.mark.slow  # every test here starts a daemon

SHIPPED = REPO / "policies" / "flg-sim.safetensors"


def _always_moves(path: Path) -> Path:
    """The shipped policy with its advantage head biased to moves: it never grasps, so it never picks."""
    net = load_policy(SHIPPED).network
    with torch.no_grad():
        net.advantage.bias.copy_(torch.tensor([-100.0, 100.0]))
    save_policy(path, net, {"training_steps": 4000, "cell": "test", "source": "rigged: always moves"})
    return path


def _rig(learner, network, seconds: float = 0.0) -> None:
    """Updates that set the online weights to ``network`` instead of training (optionally taking a while)."""
    def update():
        with learner._update_lock:  # as a real update holds it
            if seconds:
                time.sleep(seconds)
            learner.online.load_state_dict(network.state_dict())
            learner.updates += 1
            return UpdateStats(update=learner.updates, loss=0.0, mean_abs_td=0.0, batch_size=1, beta=0.0,
                               seconds=seconds)
    learner.update = update


class InProcess:
    def __init__(self, tmp_path: Path, policy: Path, **sections):
        sections.setdefault("finetune", {"min_replay": 0, "updates_per_action": 1})
        self.config = load_config(write_config(tmp_path, tmp_path / "state", policy=str(policy), **sections))
        self.ctl = Controller(self.config)
        self.ctl.setup()
        self.thread: threading.Thread | None = None
        self.stop = threading.Event()

    def run(self) -> "InProcess":
        self.thread = threading.Thread(target=self.ctl.run_loop, args=(self.stop.is_set,), daemon=True)
        self.thread.start()
        self.ctl.handle(Request("start"))
        return self

    def wait(self, predicate, what: str, timeout: float = 600.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return
            assert self.thread is None or self.thread.is_alive(), "the run loop died"
            time.sleep(0.2)
        raise AssertionError(f"timed out waiting for {what}; status {self.ctl.status()}")

    def close(self) -> None:
        self.stop.set()
        if self.thread is not None:
            self.thread.join(120)
        self.ctl.shutdown()

    def actions(self) -> list[tuple]:
        db = sqlite3.connect(self.ctl.state_dir / "flgd.sqlite")
        try:
            return db.execute("SELECT step, policy, rule, outcome FROM actions ORDER BY step").fetchall()
        finally:
            db.close()


GATE_FAST = {"share": 0.5, "handover_every": 2, "min_attempts": 6, "drop_min_attempts": 6,
             "promote_confidence": 0.9, "drop_confidence": 0.9}


def test_a_worse_challenger_is_dropped_and_never_acts_again_and_hand_overs_come_with_a_backlog(tmp_path):
    d = InProcess(tmp_path, SHIPPED, gate=GATE_FAST, finetune={"min_replay": 0, "updates_per_action": 4})
    backlog_at_handover = []
    worse = load_policy(_always_moves(tmp_path / "moves.safetensors")).network
    _rig(d.ctl.learner, worse, seconds=0.3)
    post = d.ctl.gate.handovers.post

    def noting_post(state_dict, version=None):
        backlog_at_handover.append(d.ctl.learner.pending)
        post(state_dict, version)
    d.ctl.gate.handovers.post = noting_post
    try:
        d.run()
        d.wait(lambda: any(e["kind"] == "drop" for e in d.ctl.gate.history()), "a drop")
        drop = next(e for e in d.ctl.gate.history() if e["kind"] == "drop")
        dropped, when = drop["policy"], drop["step"]
        d.wait(lambda: d.ctl.runner.step > when + 15, "15 more cycles")
        restarts = [e["message"] for e in d.ctl.store.events("learner")]
    finally:
        d.close()
    rows = d.actions()
    assert any("learner restarted from the champion" in m for m in restarts), restarts  # the line dropped
    assert any(p == dropped for s, p, _, _ in rows if s < when)  # it did act while tested
    assert not [s for s, p, _, _ in rows if s >= when and p == dropped]  # and never after the drop
    assert drop["evidence"]["challenger_tally"]["successes"] == 0
    assert max(backlog_at_handover) > 0  # weights were handed over while updates were still owed


def test_a_better_challenger_is_promoted_and_then_acts_on_every_greedy_decision(tmp_path):
    d = InProcess(tmp_path, _always_moves(tmp_path / "moves.safetensors"), gate=GATE_FAST)
    better = load_policy(SHIPPED).network
    _rig(d.ctl.learner, better)
    try:
        d.run()
        d.wait(lambda: any(e["kind"] == "promote" for e in d.ctl.gate.history()), "a promotion")
        promote = next(e for e in d.ctl.gate.history() if e["kind"] == "promote")
        assert d.ctl.gate.champion.id == promote["policy"]
        acting = d.ctl.agent.network.state_dict()
        assert all(torch.equal(acting[k], v) for k, v in better.state_dict().items())
        status = d.ctl.status()
        assert status["gate"]["champion"]["id"] == promote["policy"]
    finally:
        d.close()
    assert promote["evidence"]["challenger_tally"]["successes"] > promote["evidence"]["champion_during_test"][
        "successes"]


def test_paced_the_hand_over_of_a_cycles_updates_is_the_challenger_right_after_that_cycle(tmp_path):
    """With ``learning.wait_for_updates`` the gate takes the hand-over a cycle's updates made right after that
    cycle, however long the updates take: when a challenger comes (and so which policy decides what) depends on
    the update count, not on thread timing, and a paced run is reproducible from its seeds."""
    d = InProcess(tmp_path, SHIPPED, learning={"wait_for_updates": True},
                  gate={"handover_every": 1, "min_attempts": 500, "max_attempts": 500, "drop_min_attempts": 500},
                  finetune={"min_replay": 0, "updates_per_action": 1})
    _rig(d.ctl.learner, load_policy(SHIPPED).network, seconds=1.0)  # far slower than the gate's bookkeeping
    try:
        d.run()
        d.wait(lambda: any(e["kind"] == "challenger" for e in d.ctl.gate.history()), "a challenger")
        challenger = next(e for e in d.ctl.gate.history() if e["kind"] == "challenger")
    finally:
        d.close()
    db = sqlite3.connect(d.ctl.state_dir / "flgd.sqlite")
    first = db.execute("SELECT MIN(step) FROM transitions").fetchone()[0]
    origin = db.execute("SELECT origin FROM policies WHERE id=?", (challenger["policy"],)).fetchone()[0]
    db.close()
    assert origin == "learner update 1"
    assert challenger["step"] == first + 1, challenger


def test_a_policy_load_while_the_learner_is_in_a_long_update_never_stops_the_learner(tmp_path):
    d = InProcess(tmp_path, SHIPPED, gate={"handover_every": 1000})
    _rig(d.ctl.learner, load_policy(SHIPPED).network, seconds=3.0)
    d.ctl.learner_quiet_timeout = 0.5
    try:
        d.run()
        d.wait(lambda: d.ctl.learner._busy, "an update in progress")
        with pytest.raises(ProtocolError) as busy:
            d.ctl.handle(Request("policy_load", {"path": str(SHIPPED)}, peer="uid 0 pid 1"))
        assert busy.value.code == "busy" and "keeps running" in busy.value.message
        assert d.ctl.learner.running and d.ctl.status()["learner_running"]
        d.ctl.learner_quiet_timeout = 30.0
        out = d.ctl.handle(Request("policy_load", {"path": str(SHIPPED)}, peer="uid 0 pid 1"))
        assert out["champion"] == 2
        assert d.ctl.learner.running
        d.wait(lambda: d.ctl.learner.updates >= 2, "the learner to go on updating")
        load = [e for e in d.ctl.gate.history() if e["kind"] == "load"]
        assert load and load[-1]["who"] == "uid 0 pid 1"
    finally:
        d.close()


def test_a_daemon_started_from_a_trained_policy_explores_at_its_recorded_epsilon(daemon_factory, tmp_path):
    """The policy records 250 training steps: on sim.yaml's schedule (0.5 -> 0.05 over 500 steps) that is 0.275,
    where a daemon counting from 0 would start at 0.5; the config's few-moves phase is not the daemon's."""
    policy = tmp_path / "p250.safetensors"
    save_policy(policy, load_policy(SHIPPED).network, {"training_steps": 250, "cell": "test"})
    d = daemon_factory(policy=str(policy), args=["--autostart"], finetune={"max_epsilon": 1.0},
                       exploration={"curriculum_steps": 500}).start().wait_ready()
    d.wait_for(lambda st: (st.get("cycles") or 0) >= 4, "4 cycles")
    status = d.ok("status")
    d.ok("stop")
    d.wait_exit()
    db = sqlite3.connect(d.state_dir / "flgd.sqlite")
    rows = db.execute("SELECT step, epsilon, rule FROM actions WHERE epsilon IS NOT NULL ORDER BY step").fetchall()
    db.close()
    assert rows[0][0] == 0 and abs(rows[0][1] - 0.275) < 1e-9, rows  # from the first cycle
    assert all(abs(eps - (0.5 - 0.45 * (250 + step) / 500)) < 1e-9 for step, eps, _ in rows), rows
    assert "curriculum" not in {rule for _, _, rule in rows}
    assert status["learning"] == "finetune" and status["gate"]["champion"]["origin"].startswith("policy ")


def test_kill_9_then_the_restart_acts_with_the_champion_and_keeps_the_tallies(daemon_factory, tmp_path):
    sections = dict(policy=str(SHIPPED), gate={"handover_every": 1, "share": 0.5, "min_attempts": 500,
                                               "max_attempts": 500, "drop_min_attempts": 500},
                    finetune={"min_replay": 0, "updates_per_action": 1})
    d = daemon_factory(args=["--autostart"], **sections).start().wait_ready()
    d.wait_for(lambda st: st["gate"]["challenger"] is not None and st["gate"]["challenger"]["tally"]["actions"] >= 3,
               "a challenger with 3 actions", timeout=600)
    d.kill9()
    db = sqlite3.connect(d.state_dir / "flgd.sqlite")
    champion, challenger = (db.execute("SELECT id FROM policies WHERE role=?", (r,)).fetchone()[0]
                            for r in ("champion", "challenger"))
    since = db.execute("SELECT since_step FROM policies WHERE id=?", (challenger,)).fetchone()[0]
    counted = db.execute("SELECT COUNT(*) FROM actions WHERE policy=? AND outcome IN ('executed','refused')",
                         (challenger,)).fetchone()[0]
    champion_meanwhile = db.execute("SELECT COUNT(*) FROM actions WHERE policy=? AND step>=? AND outcome IN "
                                    "('executed','refused')", (champion, since)).fetchone()[0]
    db.close()

    d2 = daemon_factory(config=d.config, state_dir=d.state_dir).start().wait_ready()
    gate = d2.ok("status")["gate"]
    assert gate["champion"]["id"] == champion and gate["challenger"]["id"] == challenger
    assert gate["challenger"]["tally"]["actions"] == counted >= 3
    assert gate["challenger"]["champion_during_test"]["actions"] == champion_meanwhile
    d2.ok("stop")
    d2.wait_exit()

    # a corrupt champion file: refused with an event naming it, the configured policy acts
    file = d.state_dir / "gate" / f"policy-{champion:06d}.safetensors"
    file.write_bytes(file.read_bytes()[:-100])
    d3 = daemon_factory(config=d.config, state_dir=d.state_dir).start().wait_ready()
    gate = d3.ok("status")["gate"]
    history = d3.ok("policy_history")["events"]
    assert gate["champion"]["id"] not in (champion, challenger) and gate["champion"]["origin"] == f"policy {SHIPPED}"
    unusable = [e for e in history if e["kind"] == "unusable" and e["policy"] == champion]
    assert unusable and str(file) in unusable[0]["message"]
    out = d3.ctl("policy", "history")
    assert out.returncode == 0 and "unusable" in out.stdout and "fallback" in out.stdout


def test_a_restarted_daemon_deals_new_scenes_instead_of_replaying_its_first_ones(tmp_path):
    """A simulated cell rebuilt from the configured seed after a restart dealt the run's first scenes (and the
    agent its first exploration draws) again: every restart replayed the same data to the learner."""
    import numpy as np

    def scene(ctl: Controller) -> list[tuple]:
        return sorted(tuple(np.round(s.position, 4)) for s in ctl.cell.object_states())

    def started(state: str) -> Controller:
        ctl = Controller(load_config(write_config(tmp_path, tmp_path / state, policy=str(SHIPPED))), autostart=True)
        ctl.setup()
        return ctl

    def draws(ctl: Controller) -> tuple:
        """The next draws of the agent's exploration and the replay's sampling (copies: nothing is consumed)."""
        return (copy.deepcopy(ctl.agent.rng).random(4).tolist(), copy.deepcopy(ctl.replay._rng).random(4).tolist())

    ctl = started("state")
    try:
        first, first_draws = scene(ctl), draws(ctl)
        ctl.run_loop(stop_requested=lambda: ctl.runner.step >= 2)
    finally:
        ctl.shutdown()
    again = started("state")   # the same state directory: the run continues at action 2
    try:
        assert again.runner.step == 2
        assert scene(again) != first
        assert draws(again)[0] != first_draws[0] and draws(again)[1] != first_draws[1]
    finally:
        again.shutdown()
    fresh = started("other")   # a first start is reproducible from the config alone
    try:
        assert scene(fresh) == first and draws(fresh) == first_draws
    finally:
        fresh.shutdown()


def test_an_action_log_that_cannot_be_read_at_start_up_is_a_startup_error_naming_it(tmp_path, monkeypatch):
    """Not a traceback: ``flgd run`` reports a StartupError and exits with its start-up code."""
    from flgd.daemon.controller import StartupError
    from flgd.store import Store, StoreError

    def broken(self):
        raise StoreError("database disk image is malformed")

    monkeypatch.setattr(Store, "next_step", broken)
    ctl = Controller(load_config(write_config(tmp_path, tmp_path / "state", policy=str(SHIPPED))))
    with pytest.raises(StartupError, match="action log .* cannot be read: database disk image is malformed"):
        ctl.setup()
    assert ctl.cell is None   # nothing was connected, nothing moved
    ctl.shutdown()
