"""Motion safety of the real cell and the daemon around it: stop latch, envelope at the start, empty table.

The UR5e runs against ``FakeURController`` and its fake ur_rtde interfaces
(``tests.test_hardware_ur5e``), the RG2 against ``LoopbackRG2``.  The camera is
``FakeD415``, a fake of ``D415Camera`` (the cell's camera boundary) that sees an
empty table from the configured pose and models a camera that is gone.  The
daemon's ``Controller`` is the real one, with its real store, agent and learner.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from pathlib import Path

import numpy as np
import pytest
import torch

from flgd.cell import STOPPED_ON_REQUEST, CellFault, StopPending
from flgd.config import CellConfig
from flgd.daemon.controller import EMPTY_WORKSPACE_CAUSE, Controller
from flgd.daemon.protocol import ProtocolError, Request
from flgd.daemon.state import State
from flgd.geometry import matrix_to_rotvec, top_down_rotation
from flgd.plans import plan_home
from flgd.safety import check_plan
from flgd.store import StoreError
from tests.fakes.d415 import FakeD415Factory
from tests.fakes.ur5e import MOTION, FakeURController, make_cell, push, real_config

MOVES = MOTION - {"stopL"}  # what a stop must never be followed by (the stop itself sends stopL)

# --------------------------------------------------------------------------- helpers


def home_plan(cfg: CellConfig):
    return check_plan(plan_home(cfg), cfg)


def when_called(ctl: FakeURController, method: str, action) -> None:
    """Run ``action`` right after the first call of ``method`` reaches the fake controller."""
    record, fired = ctl.record, []

    def hooked(iface, m, *args):
        record(iface, m, *args)
        if m == method and not fired:
            fired.append(m)
            action()

    ctl.record = hooked


def when_waiting_for_unlock(ctl: FakeURController, action) -> None:
    """Run ``action`` at the first sleep while the arm is protective-stopped (recovery's 5 s wait)."""
    sleep, fired = ctl.sleep, []

    def hooked(dt):
        if ctl.protective and not fired:
            fired.append(dt)
            action()
        sleep(dt)

    ctl.sleep = hooked


@pytest.fixture
def cameras():
    return FakeD415Factory()


@pytest.fixture
def cell_cfg(rg2, tmp_path) -> CellConfig:
    return dataclasses.replace(real_config(xmlrpc_port=rg2.port), state_dir=str(tmp_path / "state"))


@pytest.fixture
def cell(ctl, rg2, cell_cfg, cameras):
    c = make_cell(ctl, rg2, cell_cfg, cameras)
    yield c
    c.close()


@pytest.fixture
def daemons(ctl, rg2, cell_cfg, cameras, monkeypatch):
    """Make real Controllers whose cell is the UR5e on the fakes; all shut down at the end."""
    made: list[Controller] = []
    monkeypatch.setattr("flgd.daemon.startup.make_cell",
                        lambda config, backend=None: make_cell(ctl, rg2, config, cameras))

    def make() -> Controller:
        c = Controller(cell_cfg)
        made.append(c)
        c.setup()
        return c

    yield make
    for c in made:
        if c.store is not None or c.cell is not None:
            c.shutdown()


def _loop_turns(n: int):
    """A run_loop ``stop_requested`` that asks to stop on the n-th turn (a signal arriving then)."""
    turns = {"n": 0}

    def stop_requested() -> bool:
        turns["n"] += 1
        return turns["n"] >= n

    return stop_requested


# --------------------------------------------------------------------------- the stop latch (cell)

def test_a_stop_before_a_plan_sends_nothing_until_it_is_cleared(ctl, rg2, cell):
    cell.stop_motion()
    n, grips = len(ctl.log), len(rg2.calls)
    result = cell.execute(home_plan(cell.config))
    assert not result.completed and STOPPED_ON_REQUEST in result.failure
    assert "moveL" not in ctl.names(n) and len(rg2.calls) == grips, "no move and no gripper command"
    assert cell.fault is None, "a stop is not a fault"
    cell.clear_stop()
    assert cell.execute(home_plan(cell.config)).completed


@pytest.mark.parametrize("lands_at", ["getRobotMode", "isPoseWithinSafetyLimits", "getActualTCPPose"])
def test_a_stop_landing_between_the_last_check_and_the_move_is_not_erased(ctl, rg2, cell, lands_at):
    """The cycle looks for a stop, then calls execute: a stop in between must still stop the plan.

    getRobotMode is asked by the check right before the plan begins; the other two just before moveL.
    """
    ctl.tcp[:3] = (0.50, 0.10, 0.20)  # away from home, so the home plan is a real move
    n = len(ctl.log)
    when_called(ctl, lands_at, cell.stop_motion)
    result = cell.execute(home_plan(cell.config))
    assert not result.completed and STOPPED_ON_REQUEST in result.failure
    assert "moveL" not in ctl.names(n)
    np.testing.assert_allclose(ctl.tcp[:3], (0.50, 0.10, 0.20))
    assert cell.arm.stop_requested, "the request stays latched"


def test_recovery_refuses_while_a_stop_is_pending_and_keeps_the_fault(ctl, rg2, cell):
    ctl.at(1, 0.5, ctl.protective_stop)
    with pytest.raises(CellFault, match="protective stop"):
        cell.execute(push(cell.config))
    cell.stop_motion()
    n = len(ctl.log)
    with pytest.raises(StopPending, match="stop was requested"):
        cell.recover()
    assert not MOVES & set(ctl.names(n)), "nothing unlocked, re-uploaded or moved"
    assert cell.fault is not None and cell.arm.stop_requested
    cell.clear_stop()
    cell.recover()
    assert cell.fault is None and cell.execute(push(cell.config)).completed


def test_a_stop_during_the_protective_stop_wait_cuts_the_recovery_short(ctl, rg2, cell):
    ctl.at(2, 0.5, ctl.protective_stop)
    with pytest.raises(CellFault, match="protective stop"):
        cell.execute(push(cell.config))
    when_waiting_for_unlock(ctl, cell.stop_motion)
    n, t0 = len(ctl.log), ctl.now
    with pytest.raises(StopPending, match="during the protective-stop wait"):
        cell.recover()
    assert not MOVES & set(ctl.names(n)), "not unlocked, nothing moved"
    assert ctl.now - t0 < 1.0, "the 5 s wait ended at the stop"
    assert cell.fault is not None and cell.arm.stop_requested


# --------------------------------------------------------------------------- the envelope at the start

_TILTED = matrix_to_rotvec(top_down_rotation(0.0) @ np.array(
    [[1.0, 0.0, 0.0], [0.0, math.cos(0.3), -math.sin(0.3)], [0.0, math.sin(0.3), math.cos(0.3)]]))


@pytest.mark.parametrize("where, rotvec, why", [
    ((0.20, 0.0, 0.30), None, "x = 0.2000 m is outside the envelope [0.25, 0.76]"),
    ((0.40, 0.0, 0.43), None, "z = 0.4300 m is outside the envelope [-0.02, 0.4]"),
    ((0.50, 0.0, -0.018), None, "below the table clearance floor"),
    ((0.40, 0.0, 0.30), _TILTED, "tool tilted 0.300 rad"),
])
def test_the_arm_outside_the_envelope_is_not_moved_from_where_it_stands(ctl, rg2, cell, where, rotvec, why):
    """A jog (or a start, or a recovery) may leave the arm anywhere; a straight moveL from there is unchecked."""
    ctl.tcp[:3] = where
    if rotvec is not None:
        ctl.tcp[3:] = rotvec
    n, grips = len(ctl.log), len(rg2.calls)
    with pytest.raises(CellFault) as err:
        cell.execute(home_plan(cell.config))
    msg = str(err.value)
    assert why in msg
    assert "the arm stands at [" + ", ".join(f"{v:.4f}" for v in where) + "] m" in msg
    assert "envelope x [0.25, 0.76], y [-0.4, 0.3], z [-0.02, 0.4] m" in msg
    assert "jog the arm inside the envelope" in msg and "flgctl reset" in msg
    assert "moveL" not in ctl.names(n) and len(rg2.calls) == grips, "nothing was sent"
    assert cell.fault is not None, "latched: no motion until a reset"
    # a reset with the arm still outside is refused the same way; once jogged inside it homes
    with pytest.raises(CellFault, match="outside the safety envelope"):
        cell.recover()
    assert "moveL" not in ctl.names(n)
    ctl.tcp[:] = (0.50, 0.10, 0.20, math.pi, 0.0, 0.0)
    cell.recover()
    assert len(ctl.calls("moveL", n)) == 1 and cell.fault is None
    np.testing.assert_allclose(ctl.tcp[:3], cell.config.robot.home.position, atol=1e-9)


def test_an_arm_stopped_on_the_table_floor_is_recovered_not_left_for_a_jog(ctl, rg2, cell):
    """A grasp descends to the clearance floor itself; a fault there (a gripper trip in the close) leaves the arm
    reading a hair below it, which is not outside the envelope: the reset homes it (2 mm below is refused)."""
    floor = cell.config.workspace.table_z + cell.config.safety.min_table_clearance
    ctl.tcp[:] = (0.50, 0.0, floor - 0.0002, math.pi, 0.0, 0.0)
    n = len(ctl.log)
    cell.recover()
    cell.execute(home_plan(cell.config))
    assert ctl.calls("moveL", n) and cell.fault is None
    np.testing.assert_allclose(ctl.tcp[:3], cell.config.robot.home.position, atol=1e-9)
    ctl.tcp[:] = (0.50, 0.0, floor - 0.002, math.pi, 0.0, 0.0)
    with pytest.raises(CellFault, match="below the table clearance floor"):
        cell.execute(home_plan(cell.config))


# --------------------------------------------------------------------------- the daemon: reset and stop

@pytest.mark.parametrize("stop_at", ["unlock wait", "closeSafetyPopup", "setTcp", "isPoseWithinSafetyLimits"])
def test_a_stop_during_reset_wins_nothing_moves_and_the_daemon_stops_cleanly(ctl, daemons, stop_at):
    c = daemons()
    ctl.tcp[:3] = (0.50, 0.10, 0.20)
    ctl.protective_stop()
    c.state.transition(State.FAULT, "cell fault: protective stop (test)")
    stop = lambda: c.handle(Request("stop"))  # noqa: E731  (flgctl stop, arriving mid-reset)
    if stop_at == "unlock wait":
        when_waiting_for_unlock(ctl, stop)
    else:
        when_called(ctl, stop_at, stop)
    n = len(ctl.log)
    loop = threading.Thread(target=c.run_loop, name="run-loop")
    loop.start()
    with pytest.raises(ProtocolError) as err:
        c.handle(Request("reset"))
    loop.join(30)
    assert not loop.is_alive(), "the run loop ended: the daemon is stopping"
    assert err.value.code == "failed"
    assert "reset interrupted by a stop (stop by operator)" in err.value.message
    assert "the arm was not homed" in err.value.message
    assert c.state.state is State.STOPPING
    assert "moveL" not in ctl.names(n), "the arm did not move after the stop"
    np.testing.assert_allclose(ctl.tcp[:3], (0.50, 0.10, 0.20))
    assert c.cell.arm.stop_requested, "the stop is still latched"
    if stop_at == "unlock wait":
        assert "unlockProtectiveStop" not in ctl.names(n)


def test_reset_homes_the_arm_once(ctl, daemons):
    c = daemons()
    ctl.tcp[:3] = (0.50, 0.10, 0.20)
    c.state.transition(State.FAULT, "cell fault (test)")
    n = len(ctl.log)
    assert c.reset() == {"state": "IDLE"}
    assert len(ctl.calls("moveL", n)) == 1, "the cell's recovery homes; the reset does not home again"
    np.testing.assert_allclose(ctl.tcp[:3], c.config.robot.home.position, atol=1e-9)


def test_a_stop_arriving_while_start_clears_the_latch_stays_latched(ctl, daemons):
    """start clears a stale latch; a stop landing right then must survive the clear."""
    c = daemons()
    clear = c.cell.clear_stop

    def clear_as_a_stop_arrives() -> None:
        c.request_stop("signal SIGTERM")  # latches the cell ...
        clear()                           # ... and the clear already under way runs after it

    c.cell.clear_stop = clear_as_a_stop_arrives
    n = len(ctl.log)
    with pytest.raises(ProtocolError) as err:
        c.handle(Request("start"))
    assert err.value.code == "wrong_state" and "stopping (signal SIGTERM)" in err.value.message
    assert c.cell.arm.stop_requested, "latched again"
    c.run_loop()  # returns at once: STOPPING
    assert c.state.state is State.STOPPING and "moveL" not in ctl.names(n)
    assert not c.cell.execute(home_plan(c.config)).completed, "nothing moves while the stop is latched"


# --------------------------------------------------------------------------- the daemon: an empty table

def test_an_empty_table_on_the_real_cell_pauses_once_with_a_clear_message(ctl, daemons, cameras):
    c = daemons()
    n = len(ctl.log)
    events = len(c.store.events())
    c.handle(Request("start"))
    c.run_loop(stop_requested=_loop_turns(6))  # a few turns of the loop, then a stop signal
    paused = [h for h in c.state.history() if h.new is State.PAUSED]
    assert [h.cause for h in paused] == [EMPTY_WORKSPACE_CAUSE]
    assert len(ctl.calls("moveL", n)) == 1, "homed once before the picture; nothing after"
    assert sum(cam.captures for cam in cameras.opened) == 1
    new = c.store.events()[events:]
    about_it = [e for e in new if "refill" in e["message"] or e["kind"] == "scene"]
    assert len(about_it) == 1 and about_it[0]["message"] == f"RUNNING -> PAUSED: {EMPTY_WORKSPACE_CAUSE}"
    assert c.last_record.outcome == "empty" and c.last_record.refill_needed
    assert c.runner.step == 0 and c.store.action_log() == []


def test_status_of_a_paused_empty_table_names_the_refill_and_start_looks_again(ctl, daemons, cameras):
    c = daemons()
    c.handle(Request("start"))
    c._one_cycle()
    assert c.state.state is State.PAUSED
    assert c.status()["cause"] == EMPTY_WORKSPACE_CAUSE
    assert EMPTY_WORKSPACE_CAUSE in c.status_text()
    # the operator starts again: the cycle takes a new picture (after homing) instead of the old one
    n = len(ctl.log)
    c.handle(Request("start"))
    c._one_cycle()
    assert sum(cam.captures for cam in cameras.opened) == 2 and len(ctl.calls("moveL", n)) == 1
    assert c.state.state is State.PAUSED and c.state.cause == EMPTY_WORKSPACE_CAUSE  # still empty here


# --------------------------------------------------------------------------- the daemon: learning state

def test_a_stale_checkpoint_failure_is_cleared_by_a_successful_reset(ctl, daemons):
    c = daemons()
    c.state.transition(State.FAULT, "cell fault: protective stop (test)")

    def full_disk(save, updates):
        raise StoreError(f"{c.checkpoints.directory}: the disk is full")

    c.checkpoints.write = full_disk
    with pytest.raises(StoreError):
        c.write_checkpoint(c.learner.snapshot(), 7)  # the learner's checkpoint, failing while in FAULT
    del c.checkpoints.write  # the disk has room again
    assert c.reset() == {"state": "IDLE"}
    cause = c.state.cause
    c.run_loop(stop_requested=_loop_turns(3))
    after = [h.new for h in c.state.history()]
    assert after[-2:] == [State.IDLE, State.STOPPING], "no FAULT again with the old message"
    assert "cleared the earlier problem: checkpoint failed" in cause and "the disk is full" in cause


def test_a_loaded_policy_is_checkpointed_at_once_and_a_restart_resumes_it(daemons, tmp_path):
    from flgd.learning.networks import build_network
    from flgd.learning.policy_file import save_policy

    c = daemons()
    lr = c.learner
    # the learner has trained a little: Adam moments of the old weights, written with a checkpoint
    for p in lr.online.parameters():
        p.grad = torch.ones_like(p)
    lr.optimizer.step()
    lr.optimizer.zero_grad(set_to_none=True)
    assert lr.optimizer.state
    c.write_checkpoint(lr.snapshot(), lr.updates)
    old = {k: v.clone() for k, v in lr.online.state_dict().items()}

    net = build_network(c.config.learning.network, rotations=c.config.learning.rotations, seed=1234)
    path = tmp_path / "other.safetensors"
    save_policy(path, net, {"training_steps": 10, "cell": "elsewhere"})
    stop = threading.Event()
    loop = threading.Thread(target=c.run_loop, args=(stop.is_set,), daemon=True)  # a load is done between cycles
    loop.start()
    reply = c.handle(Request("policy_load", {"path": str(path)}))
    assert reply["loaded"] == str(path)
    assert not lr.optimizer.state, "Adam moments of the old weights are gone"
    assert lr.running, "the learner runs on"
    stop.set()
    loop.join(60)
    c.shutdown()
    assert Path(reply["checkpoint"]) == c.checkpoints.checkpoints()[0], "the newest checkpoint"

    again = daemons()
    want = net.state_dict()
    got = again.learner.online.state_dict()
    assert any(not torch.equal(old[k], want[k]) for k in want), "the policies differ"
    for k in want:
        assert torch.equal(got[k].cpu(), want[k]), k
    assert again.policy_source.startswith("checkpoint ")
    assert not again.learner.optimizer.state, "the restart does not bring back the old Adam moments"
    acting = again.agent.network.state_dict()
    assert all(torch.equal(acting[k], want[k]) for k in want), "the loaded policy is the champion that acts"


# --------------------------------------------------------------------------- the sim cell is unchanged

def test_the_simulated_cell_lays_out_a_new_scene_on_an_empty_table_and_keeps_running(tmp_path):
    from flgd.config import load_config
    from tests.fakes.daemon import write_config

    cfg = load_config(write_config(tmp_path, tmp_path / "state", sim={"objects": 0}))
    c = Controller(cfg)
    try:
        c.setup()
        c.handle(Request("start"))
        c._one_cycle()
        assert c.state.state is State.RUNNING
        assert c.last_record.outcome == "empty" and not c.last_record.refill_needed
        assert [e["message"] for e in c.store.events("scene")] == ["workspace empty: new scene"]
    finally:
        c.shutdown()


def test_a_cell_that_overrides_reset_scene_can_reset_it_and_the_ur5e_cannot(cell):
    from flgd.cell import Cell

    class Resetting(Cell):
        def capture(self):
            raise NotImplementedError

        def execute(self, plan):
            raise NotImplementedError

        def gripper_width(self):
            return 0.0

        def reset_scene(self):
            pass

    assert Resetting(cell.config).can_reset_scene() is True
    assert cell.can_reset_scene() is False
