"""A cell that does not repeat what fails: the stuck ladder through the cycle and the daemon, on both backends.

Sim: a drum wider than the gripper opens and too heavy to push -- every grasp fails, no move changes
anything.  The cycle keeps each new grasp outside the regions where grasps failed, declares the cell stuck
after ``exploration.stuck_after`` actions and lays out a new scene.  Real cell (the UR5e, RG2 and D415 fakes of
tests/test_motion_safety.py): a block the fingers close through -- the daemon pauses with the reason, says so
in status, events and metrics, and ``stuck_action: continue`` goes on instead.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml

from flgd.config import load_config
from flgd.cycle import CycleRunner
from flgd.daemon.metrics import compute_stats
from flgd.daemon.protocol import Request
from flgd.daemon.state import State
from flgd.learning.agent import Agent
from flgd.learning.networks import build_network
from tests.fakes.d415 import FakeD415, FakeD415Factory
from tests.fakes.ur5e import make_cell, real_config

REPO = Path(__file__).resolve().parents[1]


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _immovable_scene(path: Path) -> Path:
    """One drum 14 cm across and 20 kg: wider than the 8.5 cm opening everywhere, no corner a finger pair could
    pinch, and no push moves it."""
    path.write_text(yaml.safe_dump({"format": "flgd-scene", "version": 1, "objects": [
        {"shape": "cylinder", "size": [0.07, 0.06], "color": [0.8, 0.3, 0.2], "position": [0.0, 0.0, 0.03],
         "mass": 20.0, "friction": 1.5}]}))
    return path


def test_on_sim_failed_regions_are_avoided_then_the_cell_is_stuck_and_lays_a_new_scene(tmp_path):
    from sim_cell.cell import SimCell

    cfg = load_config(REPO / "cell_config" / "sim.yaml")
    cfg = dataclasses.replace(
        cfg, state_dir=str(tmp_path), sim=dataclasses.replace(cfg.sim, objects=3, seed=5),
        exploration=dataclasses.replace(cfg.exploration, epsilon_start=0.0, epsilon_end=0.0, stuck_after=6,
                                        failure_retries=0))
    cell = SimCell(cfg)
    try:
        cell.load_scene(_immovable_scene(tmp_path / "scene.yaml"))
        scenes = cell.stats["scenes"]
        agent = Agent(cfg, build_network(cfg.learning.network, rotations=16, seed=0), seed=0)
        runner = CycleRunner(cfg, cell, agent)
        radius = cfg.exploration.failure_radius / cfg.workspace.resolution
        records, failed = [], []
        for _ in range(10):
            rec = runner.run_once()
            records.append(rec)
            if rec.outcome == "stuck":
                break
            assert rec.outcome == "executed" and rec.reward == 0.0, rec  # nothing works on this block
            if rec.action.primitive == "grasp":
                for f in failed:  # never the same grasp again while the block has not moved there
                    same_way = (rec.action.rotation - f.rotation) % 8 in (0, 1, 7)
                    assert np.hypot(rec.action.row - f.row, rec.action.col - f.col) > radius or not same_way
                failed.append(rec.action)
        assert [r.outcome for r in records] == ["executed"] * 6 + ["stuck"]
        stuck = records[-1]
        assert "6 actions without a successful grasp" in stuck.failure and stuck.relaid
        assert stuck.step is None and runner.step == 6              # no action, no step
        assert cell.stats["scenes"] == scenes + 1 and cell.object_count == 3   # a new scene was laid out
        assert agent.memory.entries == [] and agent.memory.since_success == 0
    finally:
        cell.close()


class BlockD415(FakeD415):
    """The empty table of FakeD415 with a 6 x 6 cm, 4 cm tall block under the camera's centre."""

    def capture(self):
        frame = super().capture()
        depth = frame.depth.copy()
        h, w = depth.shape
        depth[h // 2 - 30:h // 2 + 30, w // 2 - 30:w // 2 + 30] -= 40   # mm: 4 cm nearer the camera
        return dataclasses.replace(frame, depth=depth)


class BlockCameras(FakeD415Factory):
    def __call__(self, config):
        cam = BlockD415(config, self)
        self.opened.append(cam)
        return cam


@pytest.fixture
def real_daemon(ctl, rg2, tmp_path, monkeypatch):  # noqa: F811
    """A Controller on the UR5e backend (fakes) that sees one block the RG2 closes through."""
    from flgd.daemon.controller import Controller

    made = []
    cameras = BlockCameras()
    monkeypatch.setattr("flgd.daemon.startup.make_cell",
                        lambda config, backend=None: make_cell(ctl, rg2, config, cameras))

    def make(**exploration) -> Controller:
        cfg = dataclasses.replace(real_config(xmlrpc_port=rg2.port), state_dir=str(tmp_path / "state"))
        cfg = dataclasses.replace(cfg, exploration=dataclasses.replace(
            cfg.exploration, epsilon_start=0.0, epsilon_end=0.0, stuck_after=4, **exploration))
        c = Controller(cfg)
        made.append(c)
        c.setup()
        return c

    yield make
    for c in made:
        c.shutdown()


def _metric(controller, name: str) -> float:
    from prometheus_client import generate_latest
    from prometheus_client.registry import CollectorRegistry

    from flgd.daemon.prometheus import CellCollector

    registry = CollectorRegistry()
    registry.register(CellCollector(controller))
    for line in generate_latest(registry).decode().splitlines():
        if line.startswith(name + " ") or line.startswith(name + "_total "):
            return float(line.split()[-1])
    raise AssertionError(f"{name} not on the metrics page")


def _cycle_while_running(c, most: int = 12) -> None:
    for _ in range(most):
        if c.state.state is not State.RUNNING:
            return
        c._one_cycle()


@pytest.mark.slow
def test_the_real_cell_pauses_when_stuck_and_says_why_in_status_events_and_metrics(real_daemon):
    c = real_daemon()
    c.handle(Request("start"))
    _cycle_while_running(c)
    assert c.state.state is State.PAUSED and c.state.cause.startswith("stuck: 4 actions without a successful grasp")
    assert len(c.store.action_log()) == 4, "nothing more after the cell declared itself stuck"
    status = c.status()
    assert status["last_stuck"]["reason"].startswith("4 actions") and not status["last_stuck"]["relaid"]
    assert status["failure_memory"]["actions_since_success"] == 0, "the scene's memory was cleared"
    assert "stuck" in c.status_text()
    from flgd.ctl import _human
    text = _human("status", {"result": status}, {})   # what `flgctl status` prints
    assert "last stuck" in text and "4 actions without a successful grasp" in text and "flgctl start" in text
    events = [e for e in c.store.events() if e["kind"] == "stuck"]
    assert len(events) == 1 and "paused" in events[0]["message"]
    stats = compute_stats(c.store)
    assert stats["stuck_events"] == 1 and stats["actions_since_pick"] == 4
    assert _metric(c, "flgd_stuck") == 1.0 and _metric(c, "flgd_actions_since_pick") == 4.0
    # the operator looked and starts again: four more tries, then paused again
    c.handle(Request("start"))
    _cycle_while_running(c)
    assert c.state.state is State.PAUSED and len(c.store.action_log()) == 8
    assert compute_stats(c.store)["stuck_events"] == 2


@pytest.mark.slow
def test_stuck_action_continue_records_it_and_goes_on(real_daemon):
    c = real_daemon(stuck_action="continue")
    c.handle(Request("start"))
    _cycle_while_running(c, 11)
    assert c.state.state is State.RUNNING
    assert len(c.store.action_log()) == 9   # 11 cycles, two of them declared the cell stuck
    events = [e for e in c.store.events() if e["kind"] == "stuck"]
    assert len(events) == 2 and all("continuing" in e["message"] for e in events)


def test_a_cycle_is_in_flight_until_the_gate_has_counted_it(real_daemon):
    """``flgctl status`` saying no cycle is in flight must agree with the gate's counts in the same status."""
    c = real_daemon()
    assert c.gate is not None
    seen = []
    counted = c.learning.after_cycle

    def after_cycle(record, runner):
        seen.append(c.cycle_in_flight)
        return counted(record, runner)

    c.learning.after_cycle = after_cycle
    c.handle(Request("start"))
    c._one_cycle()
    assert seen == [True] and c.cycle_in_flight is False
