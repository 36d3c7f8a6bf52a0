"""The failure memory and the escalation ladder of the agent (flgd/learning/failure_memory.py, agent rules)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flgd.actions import Action
from flgd.config import CellConfig
from flgd.learning.agent import Agent
from flgd.learning.networks import build_network

N = 64
R = 16
RES = 0.002


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def config(**exploration) -> CellConfig:
    """Every grasp rotation allowed: a 64 px test map is barely wider than the open gripper (grasps in view:
    tests/test_grasp_view.py)."""
    base = dict(epsilon_start=0.0, epsilon_end=0.0, curriculum_steps=0, grasp_in_view=False)
    base.update(exploration)
    cfg = CellConfig()
    return dataclasses.replace(cfg, exploration=dataclasses.replace(cfg.exploration, **base))


def agent(**exploration) -> Agent:
    """Suppression from the first failure unless a test asks for retries (the shipped default is one)."""
    exploration.setdefault("failure_retries", 0)
    return Agent(config(**exploration), build_network("fast", R, seed=0), seed=0)


def wide_block() -> np.ndarray:
    """One 10 x 16 cm block (wider than the gripper opens) and a small one far from it."""
    h = np.zeros((N, N), np.float32)
    h[10:60, 10:36] = 0.05
    h[50:58, 48:56] = 0.03
    return h


def peaked_q(row: int = 30, col: int = 20) -> np.ndarray:
    """Grasp Q highest at (row, col), falling off slowly: the next best grasps lie a few millimetres away."""
    yy, xx = np.mgrid[:N, :N]
    bump = np.exp(-((yy - row) ** 2 + (xx - col) ** 2) / (2 * 6.0 ** 2)).astype(np.float32)
    q = np.zeros((R, 2, N, N), np.float32)
    q[:, 0] = bump[None] * np.linspace(1.0, 0.8, R, dtype=np.float32)[:, None, None]
    q[:, 1] = -1.0  # moves never win here
    return q


def _px_distance(a: Action, b: Action) -> float:
    return float(np.hypot(a.row - b.row, a.col - b.col))


@pytest.mark.parametrize("memory", [True, False])
def test_after_a_failed_grasp_the_next_greedy_grasps_stay_outside_its_region(memory: bool):
    height, q = wide_block(), peaked_q()
    a = agent(failure_memory=memory, failed_grasps_trigger=100)  # no forced move: grasps only
    radius = a.config.exploration.failure_radius / RES
    failed: list[Action] = []
    for step in range(5):
        d = a.select(q, height, step)
        assert d.action.primitive == "grasp"
        if memory:
            for f in failed:  # the same grasp (or its twin) a few millimetres away is never chosen again
                same_way = (d.action.rotation - f.rotation) % (R // 2) in (0, 1, R // 2 - 1)
                assert _px_distance(d.action, f) > radius or not same_way, (d.action, f)
        failed.append(d.action)
        a.record_outcome(d.action, False, height_after=height, kind="grasp")
    if not memory:  # the paper's rules: the same spot again and again (< 3 px, the anti-repeat's top-10)
        assert sum(_px_distance(f, failed[0]) < 3 for f in failed) >= 4


def test_a_region_is_released_when_the_heightmap_changes_there_and_everything_on_a_new_scene():
    height, q = wide_block(), peaked_q()
    a = agent(failed_grasps_trigger=100)
    first = a.select(q, height, 0)
    a.record_outcome(first.action, False, height_after=height, kind="grasp")
    second = a.select(q, height, 1)
    assert _px_distance(second.action, first.action) > a.memory.radius_px or second.action.rotation != first.action.rotation
    assert a.memory.entries and second.suppressed is not None and second.suppressed[first.action.row, first.action.col]
    # single-pixel noise inside the region does not release it
    noisy = height.copy()
    noisy[first.action.row, first.action.col] += 0.02
    a.select(q, noisy, 2)
    assert len(a.memory.entries) == 1
    # the block moved there: the region is free again, and the best grasp is chosen once more
    moved = height.copy()
    moved[20:40, 10:30] = 0.0
    moved[20:40, 30:36] = 0.05
    again = a.select(q, moved, 3)
    assert a.memory.entries == [] and a.memory.released == 1
    # a new scene forgets everything
    a.record_outcome(again.action, False, height_after=moved, kind="grasp")
    assert a.memory.entries
    a.reset_episode()
    assert a.memory.entries == [] and a.memory.since_success == 0


def test_a_move_that_changed_nothing_is_suppressed_and_one_that_changed_the_scene_is_not():
    height = wide_block()
    q = np.zeros((R, 2, N, N), np.float32)
    q[:, 0] = -1.0
    q[4, 1, 40, 38] = 2.0   # the best move, beside the block
    q[4, 1, 41, 38] = 1.9   # the same push one pixel on
    q[9, 1, 45, 60] = 1.0   # a different push, beside the small block
    a = agent()
    d = a.select(q, height, 0)
    assert (d.action.row, d.action.col) == (40, 38) and d.action.is_move
    a.record_outcome(d.action, None, move_changed=True, height_after=height, kind="push")
    assert a.memory.entries == []
    a.previous = None
    d = a.select(q, height, 1)
    a.record_outcome(d.action, None, move_changed=False, height_after=height, kind="push")
    assert len(a.memory.entries) == 1
    nxt = a.select(q, height, 2)
    assert (nxt.action.row, nxt.action.col, nxt.action.rotation) == (45, 60, 9)


def test_the_ladder_moves_near_the_failed_grasp_then_declares_the_cell_stuck():
    height, q = wide_block(), peaked_q(30, 20)
    q[:, 1] = 0.0
    q[3, 1, 45, 62] = 0.9    # the best move overall: far from the failing block
    q[6, 1, 38, 14] = 0.5    # a lesser move right beside the failing grasp
    a = agent(stuck_after=7)
    rules = []
    for step in range(10):
        reason = a.stuck_reason()
        if reason:
            break
        d = a.select(q, height, step)
        assert d is not None
        rules.append((d.rule, d.action.primitive, d.action.row, d.action.col))
        if d.action.is_move:
            a.record_outcome(d.action, None, move_changed=True, height_after=height, kind="push")
        else:
            a.record_outcome(d.action, False, height_after=height, kind="grasp")
    # rung 1: two failed grasps, then the best move anywhere; rung 2: two more, then a move at the failed grasp
    # (a greedy grasp at a failed pixel's other rotations is redirected by the anti-repeat rule)
    assert [r[0] for r in rules][2] == "two-failures" and rules[5][0] == "ladder-move"
    assert all(rules[i][0] in ("greedy", "anti-repeat") and rules[i][1] == "grasp" for i in (0, 1, 3, 4))
    assert rules[2][2:] == (45, 62) and rules[5][2:] == (38, 14)
    # rung 3: stuck_after actions without a successful grasp
    assert len(rules) == 7 and "7 actions without a successful grasp" in reason
    # a successful grasp resets the count
    a.record_outcome(Action("grasp", 55, 52, 0), True, height_after=height, kind="grasp")
    assert a.stuck_reason() == ""


def test_when_every_allowed_action_failed_the_agent_says_so_instead_of_repeating():
    h = np.zeros((N, N), np.float32)
    h[30:36, 30:36] = 0.04           # one small object (1.2 cm square)
    a = agent(failure_radius=0.1, failure_rotations=8, stuck_after=0, failed_grasps_trigger=100)
    q = peaked_q(32, 32)
    d = a.select(q, h, 0)
    a.record_outcome(d.action, False, height_after=h, kind="grasp")
    q[:, 1] = 0.0
    m = a.select(q, h, 1)            # no grasp left: a move
    assert m.action.is_move and m.rule == "ladder-move"
    a.record_outcome(m.action, None, move_changed=False, height_after=h, kind="push")
    assert a.select(q, h, 2) is None
    assert "every allowed action" in a.stuck_reason()


def test_the_learners_greedy_index_ignores_the_memory():
    height, q = wide_block(), peaked_q()
    a = agent(failed_grasps_trigger=100)
    first = a.select(q, height, 0)
    a.record_outcome(first.action, False, height_after=height, kind="grasp")
    second = a.select(q, height, 1)
    assert (second.action.row, second.action.col) != (first.action.row, first.action.col)
    assert second.greedy == first.greedy == (first.action.rotation, 0, first.action.row, first.action.col)


def test_with_one_retry_a_spot_is_suppressed_at_its_second_failure_not_its_first():
    height, q = wide_block(), peaked_q()
    a = agent(failed_grasps_trigger=100, failure_retries=1, failure_memory=True)
    first = a.select(q, height, 0)
    a.record_outcome(first.action, False, height_after=height, kind="grasp")
    assert a.memory.status()["pending_regions"] == 1 and a.memory.enforced == []
    a.previous = None   # (the anti-repeat rule alone would move it off the pixel)
    again = a.select(q, height, 1)
    assert (again.action.row, again.action.col) == (first.action.row, first.action.col), "one more try there"
    a.record_outcome(again.action, False, height_after=height, kind="grasp")
    assert [s.failures for s in a.memory.enforced] == [2]
    a.previous = None
    third = a.select(q, height, 2)
    assert np.hypot(third.action.row - first.action.row, third.action.col - first.action.col) > a.memory.radius_px \
        or (third.action.rotation - first.action.rotation) % 8 not in (0, 1, 7)
