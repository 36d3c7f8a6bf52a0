"""The gatekeeper: champion and challenger on a real store and real policy files, outcomes fed as cycle records.

The cell is left out here (the daemon tests run the gate with the simulated cell): what is checked is which
network the agent acts with after each verdict, what the store records, and what a restart restores.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from flgd.cycle_record import CycleOutcome
from flgd.gate.keeper import GateError
from flgd.perception import Heightmaps
from flgd.store import Store
from tests.fakes.gate import GateCell, gate_config, make_network, same_weights

N = 32


def _scene(seed: int) -> Heightmaps:
    rng = np.random.default_rng(seed)
    h = np.zeros((N, N), np.float32)
    h[8:16, 8:16] = 0.03
    h[20:26, 18:28] = 0.04
    return Heightmaps(color=rng.integers(0, 255, (N, N, 3), dtype=np.uint8), height=h)


def test_first_start_makes_the_configured_policy_the_champion_file(tmp_path):
    c = GateCell(tmp_path, gate_config())
    ch = c.gate.champion
    assert ch.id == 1 and ch.origin == "policy P" and (tmp_path / ch.file).is_file()
    assert same_weights(c.agent.network, c.configured)
    assert [e["kind"] for e in c.gate.history()] == ["initial"]
    assert c.agent.champion_id == 1 and c.agent.challenger is None


def test_a_better_challenger_is_promoted_and_acts(tmp_path):
    c = GateCell(tmp_path, gate_config())
    better = make_network(2)
    c.hand_over(better)
    assert c.gate.challenger.id == 2 and same_weights(c.agent.challenger, better)
    verdict = None
    for k in range(400):
        verdict = c.act(2, True) if k % 2 else c.act(1, k % 4 == 0)  # 100 % against 50 %
        if verdict is not None:
            break
    assert verdict is not None and verdict.kind == "promote"
    assert c.gate.champion.id == 2 and c.gate.champion.predecessor == 1 and c.gate.challenger is None
    assert same_weights(c.agent.network, better) and c.agent.challenger is None and c.agent.champion_id == 2
    promote = c.gate.history()[-1]
    assert promote["kind"] == "promote" and promote["who"] == "gate"
    assert promote["evidence"]["challenger_tally"]["successes"] >= 10
    # the retired champion keeps the record of its tenure, for a rollback
    assert c.store.query("SELECT role, record FROM policies WHERE id=1")[0][0] == "retired"


def test_a_worse_challenger_is_dropped_and_never_acts_again(tmp_path):
    c = GateCell(tmp_path, gate_config())
    c.hand_over(make_network(3))
    file = tmp_path / c.gate.challenger.file
    verdict = None
    for k in range(400):
        verdict = c.act(2, False) if k % 2 else c.act(1, True)
        if verdict is not None:
            break
    assert verdict is not None and verdict.kind == "drop"
    assert c.gate.challenger is None and c.agent.challenger is None and not file.exists()
    roles = {c.agent.decide(_scene(s), 10_000).role for s in range(30)}
    assert roles == {"champion"}
    assert same_weights(c.agent.network, c.configured)


def test_with_a_challenger_the_share_of_decisions_is_its_own_and_epsilon_is_credited_to_neither(tmp_path):
    cfg = gate_config(share=0.5)
    cfg = dataclasses.replace(cfg, exploration=dataclasses.replace(cfg.exploration, epsilon_start=0.3,
                                                                   epsilon_end=0.3))
    c = GateCell(tmp_path, cfg)
    c.hand_over(make_network(4))
    decisions = [c.agent.decide(_scene(s), 0) for s in range(80)]
    by = {(d.role, d.policy_id) for d in decisions if d.rule != "epsilon"}
    assert by == {("champion", 1), ("challenger", 2)}
    assert {d.policy_id for d in decisions if d.rule == "epsilon"} == {None}
    assert 20 <= sum(d.role == "challenger" for d in decisions) <= 60


def test_a_promoted_champion_that_falls_below_its_predecessors_record_is_rolled_back(tmp_path):
    c = GateCell(tmp_path, gate_config())
    for k in range(40):
        c.act(1, k % 5 != 0)  # the first champion's tenure: 80 %
    c.hand_over(make_network(5))
    for k in range(400):
        if c.act(2, True) if k % 2 else c.act(1, k % 5 != 0):
            break
    assert c.gate.champion.id == 2
    verdict = None
    for k in range(400):
        verdict = c.act(2, k % 5 == 0)  # now 20 %
        if verdict is not None:
            break
    assert verdict is not None and verdict.kind == "rollback"
    assert c.gate.champion.id == 1 and same_weights(c.agent.network, c.configured)
    assert c.store.query("SELECT role FROM policies WHERE id=2") == [("rolled_back",)]
    assert c.gate.history()[-1]["evidence"]["predecessor_record"]["actions"] >= 40


def test_a_restart_acts_with_the_champion_and_keeps_the_tallies(tmp_path):
    c = GateCell(tmp_path, gate_config(min_attempts=150, max_attempts=200))
    challenger = make_network(6)
    c.hand_over(challenger)
    for k in range(30):
        c.act(2 if k % 3 == 0 else 1, k % 2 == 0)
    c.act(None, True)  # epsilon: credited to neither
    c.act(1, True, outcome=CycleOutcome.DISCARDED)  # the simulator gave up: not the policy's doing
    before = c.gate.status()
    c.reopen()  # a restart (the same store and files; nothing else kept)
    after = c.gate.status()
    assert after["champion"]["id"] == 1 and after["challenger"]["id"] == 2
    assert after["challenger"]["tally"] == before["challenger"]["tally"]
    assert after["challenger"]["champion_during_test"] == before["challenger"]["champion_during_test"]
    assert after["challenger"]["tally"]["actions"] == 10 and after["champion"]["live"]["actions"] == 20
    assert same_weights(c.agent.network, c.configured) and same_weights(c.agent.challenger, challenger)


def test_a_corrupt_champion_file_falls_back_to_its_predecessor_with_an_event(tmp_path):
    c = GateCell(tmp_path, gate_config())
    c.hand_over(make_network(8))
    c.gate.promote(c.step, "uid 0 pid 1", "by hand")
    file = tmp_path / c.gate.champion.file
    blob = bytearray(file.read_bytes())
    blob[-10] ^= 0xFF
    file.write_bytes(bytes(blob))
    c.reopen()
    assert c.gate.champion.id == 1 and same_weights(c.agent.network, c.configured)
    kinds = [(e["kind"], e["policy"]) for e in c.gate.history()]
    assert ("unusable", 2) in kinds and kinds[-1] == ("fallback", 1)
    unusable = [e for e in c.gate.history() if e["kind"] == "unusable"][0]
    assert str(file) in unusable["message"]


def test_a_missing_champion_without_predecessor_falls_back_to_the_configured_policy(tmp_path):
    c = GateCell(tmp_path, gate_config())
    (tmp_path / c.gate.champion.file).unlink()
    c.configured = make_network(9)
    c.reopen()
    assert c.gate.champion.id == 2 and c.gate.champion.origin == "policy P" and same_weights(c.agent.network, c.configured)
    assert [e["kind"] for e in c.gate.history()][-2:] == ["unusable", "fallback"]


def test_no_usable_champion_and_no_configured_policy_refuses_rather_than_act_fresh(tmp_path):
    c = GateCell(tmp_path, gate_config())
    (tmp_path / c.gate.champion.file).unlink()
    c.configured = False
    with pytest.raises(GateError, match="no usable champion"):
        c.reopen()


def test_without_any_policy_the_fresh_network_is_the_first_champion(tmp_path):
    c = GateCell(tmp_path, gate_config(), configured=False)
    assert c.gate.champion.origin == "fresh network" and c.gate.champion.training_steps == 0


def test_manual_overrides_are_recorded_with_who_asked(tmp_path):
    c = GateCell(tmp_path, gate_config())
    c.hand_over(make_network(10))
    c.gate.reject(c.step, "uid 1000 pid 42")
    assert c.gate.challenger is None
    c.hand_over(make_network(11))
    c.gate.promote(c.step, "uid 1000 pid 43", "by hand")
    c.gate.rollback(c.step, "uid 1000 pid 44", "by hand")
    events = [(e["kind"], e["who"]) for e in c.gate.history()]
    assert events[-4:] == [("reject", "uid 1000 pid 42"), ("challenger", "gate"),
                           ("manual-promote", "uid 1000 pid 43"), ("manual-rollback", "uid 1000 pid 44")]
    with pytest.raises(GateError, match="no challenger"):
        c.gate.promote(c.step, "x", "y")
    with pytest.raises(GateError, match="no predecessor"):
        c.gate.rollback(c.step, "x", "y")


def test_a_challenger_under_test_is_not_replaced_by_newer_hand_overs(tmp_path):
    c = GateCell(tmp_path, gate_config())
    c.hand_over(make_network(12))
    newer = make_network(13)
    c.gate.handovers.post(newer.state_dict(), version=999)
    assert not c.gate.take_handover(c.step)
    assert c.gate.challenger.id == 2
    c.gate.reject(c.step, "me")
    assert c.gate.take_handover(c.step) and c.gate.challenger.learner_updates == 999


def test_the_gate_off_never_takes_hand_overs_or_credits(tmp_path):
    c = GateCell(tmp_path, gate_config(enabled=False))
    c.gate.handovers.post(make_network(14).state_dict(), version=5)
    assert not c.gate.take_handover(0) and c.agent.champion_id is None
    assert c.act(None, True) is None
    assert json.dumps(c.gate.status())  # status is plain JSON


def test_a_rollback_is_checked_on_every_cycle_even_while_new_challengers_are_tested(tmp_path):
    resets: list = []
    c = GateCell(tmp_path, gate_config(min_attempts=500, max_attempts=500, drop_min_attempts=500),
                 reset_learner=resets.append)
    for k in range(40):
        c.act(1, k % 5 != 0)  # the first champion's tenure: 80 %
    c.hand_over(make_network(20))
    c.gate.promote(c.step, "gate", "test")  # by the gate, as a promotion
    c.gate.by_promotion = True
    c.hand_over(make_network(21))  # the next challenger arrives at once, as hand-overs on schedule do
    verdict = None
    for k in range(600):
        verdict = c.act(2 if k % 2 else 3, k % 5 == 0)  # champion #2 now at 20 %
        if verdict is not None:
            break
    assert verdict is not None and verdict.kind == "rollback"
    assert c.gate.champion.id == 1 and c.gate.challenger is None
    assert len(resets) == 1 and same_weights(resets[0], c.configured)  # the learner starts again from what acts


def test_a_challenger_dropped_as_worse_sends_the_learner_back_to_the_champion(tmp_path):
    resets: list = []
    c = GateCell(tmp_path, gate_config(), reset_learner=resets.append)
    c.hand_over(make_network(22))
    c.gate.handovers.post(make_network(23).state_dict(), version=7)  # of the rejected line: discarded with it
    for k in range(400):
        if (c.act(2, False) if k % 2 else c.act(1, True)) is not None:
            break
    assert c.gate.challenger is None and len(resets) == 1 and not c.gate.handovers.waiting


def test_a_restart_after_an_unusable_champion_never_lets_a_fresh_network_act(tmp_path):
    c = GateCell(tmp_path, gate_config(), configured=False)  # from scratch: the fresh network is the first champion
    (tmp_path / c.gate.champion.file).unlink()
    for _ in range(2):  # systemd restarts the daemon after the first refusal
        with pytest.raises(GateError, match="no usable champion"):
            c.reopen()


def test_a_challenger_doing_better_gets_a_rising_share_of_the_decisions(tmp_path):
    c = GateCell(tmp_path, gate_config(share=0.2, max_share=0.6, drop_min_attempts=10, min_attempts=200,
                               promote_confidence=0.999))
    c.hand_over(make_network(2))
    assert c.agent.challenger_share == 0.2
    for k in range(60):
        c.act(1, k % 2 == 0)                      # champion 50 %
        if k % 3 == 0:
            c.act(2, True)                        # challenger 100 %
    assert c.gate.challenger is not None and c.gate.verdict.kind == "testing"
    assert c.agent.challenger_share == pytest.approx(0.6)
    assert c.gate.status()["share"] == pytest.approx(0.6)
    # a restart keeps the share the evidence earned, from the first decision on
    c.reopen()
    assert c.gate.challenger.id == 2 and c.agent.challenger_share == pytest.approx(0.6)
    assert c.gate.status()["share"] == pytest.approx(0.6)
    # a new challenger starts again at gate.share; without one, the share is 0
    c.gate.reject(c.step, "test")
    assert c.agent.challenger is None and c.agent.challenger_share == 0.0
    c.hand_over(make_network(3))
    assert c.agent.challenger_share == 0.2


def test_the_learners_anchor_is_the_champion_from_the_start_and_follows_a_promotion(tmp_path):
    from flgd.learning_stack import GateStart, Handover, LearningStack

    config = gate_config()
    config = dataclasses.replace(config, learning=dataclasses.replace(config.learning, anchor_weight=1.0))
    store = Store(tmp_path)
    policy = make_network(1)
    stack = LearningStack(config, fine_tune=False, state_dir=tmp_path, store=store)  # the learning section's anchor
    parts = stack.build(make_network(98), handover=Handover.GATE, gate=GateStart(
        0, configured=lambda: (policy, {"training_steps": 4000}, "policy P"),
        fresh=lambda: (make_network(7), {"training_steps": 0}, "fresh network")))
    agent, learner, gate = parts.agent, parts.learner, parts.gate
    assert gate is not None and learner.mailbox is gate.handovers

    def anchored_to(net) -> bool:
        return all(torch.equal(learner._anchor[k], p.detach()) for k, p in net.named_parameters())

    assert anchored_to(policy) and not anchored_to(make_network(98))  # the champion, not the net it was built on
    c = GateCell.__new__(GateCell)  # drive this gate with the test cell's helpers
    c.tmp, c.config, c.step, c.store, c.agent, c.gate = tmp_path, config, 0, store, agent, gate
    better = make_network(2)
    c.hand_over(better)
    assert anchored_to(policy)  # a challenger under test does not move it
    for k in range(400):
        if (c.act(2, True) if k % 2 else c.act(1, k % 4 == 0)) is not None:
            break
    assert gate.champion.id == 2 and anchored_to(better)


def test_a_gate_directory_that_refuses_a_hand_over_is_retried_keeps_the_weights_and_says_what_to_do(tmp_path,
                                                                                                    monkeypatch):
    """As an unreadable gate file is: tried again over about 1.4 s; then an error naming the directory, the OS
    error and the remedy, and the learner's weights kept until the directory takes them."""
    import errno

    from flgd.gate.storage import GateDirUnwritable
    from flgd.learning import policy_file

    c = GateCell(tmp_path, gate_config())
    pauses: list[float] = []
    c.gate.files.sleep = pauses.append
    real_save = policy_file.save_policy

    def refused(path, *args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(policy_file, "save_policy", refused)
    learned = make_network(31)
    c.gate.handovers.post(learned.state_dict(), version=321)
    with pytest.raises(GateDirUnwritable) as err:
        c.gate.take_handover(c.step)
    message = str(err.value)
    assert str(tmp_path / "gate") in message and "Permission denied" in message and "4 tries" in message
    assert "must be able to write" in message and "flgctl reset" in message and "update 321 is kept" in message
    assert pauses == [0.1, 0.3, 1.0]
    assert c.gate.challenger is None and c.gate.status()["handover_waiting"]

    monkeypatch.setattr(policy_file, "save_policy", real_save)  # the directory is writable again
    assert c.gate.take_handover(c.step)
    assert c.gate.challenger.learner_updates == 321
    assert same_weights(c.gate.files.load(c.gate.challenger), learned)
