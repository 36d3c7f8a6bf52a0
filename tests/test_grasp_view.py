"""Grasps the camera sees whole: no finger comes down beyond the heightmap's edge (exploration.grasp_in_view),
for the agent's decisions and the learner's a' alike."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from flgd.actions import Action
from flgd.config import CellConfig
from flgd.grasp_view import FINGER_DEPTH, FINGER_HALF_WIDTH, VIEW_MARGIN, grasps_in_view, moves_in_view
from flgd.learning.agent import Agent, greedy_index
from flgd.learning.learner import Learner
from flgd.learning.networks import build_network, q_maps
from flgd.learning.replay import PrioritizedReplay, Transition
from flgd.perception import Heightmaps

pytestmark = pytest.mark.usefixtures("one_torch_thread")

N, R, RES, OPEN = 224, 16, 0.002, 0.085


def config(**exploration) -> CellConfig:
    cfg = CellConfig()
    base = dict(epsilon_start=0.0, epsilon_end=0.0, curriculum_steps=0)
    base.update(exploration)
    return dataclasses.replace(cfg, exploration=dataclasses.replace(cfg.exploration, **base),
                               learning=dataclasses.replace(cfg.learning, batch_size=2, device="cpu"))


def fingers_inside(action: Action) -> bool:
    """Independent of the mask: every corner of both finger footprints lies VIEW_MARGIN inside the heightmap."""
    theta = action.angle
    u, v = np.array([math.cos(theta), math.sin(theta)]), np.array([-math.sin(theta), math.cos(theta)])
    centre = np.array([(action.col + 0.5) * RES, (action.row + 0.5) * RES])
    for along in (OPEN / 2, OPEN / 2 + FINGER_DEPTH, -OPEN / 2, -OPEN / 2 - FINGER_DEPTH):
        for across in (FINGER_HALF_WIDTH, -FINGER_HALF_WIDTH):
            x, y = centre + along * u + across * v
            lo, hi = VIEW_MARGIN - 1e-9, N * RES - VIEW_MARGIN + 1e-9
            if not (lo <= x <= hi and lo <= y <= hi):
                return False
    return True


def sliver_scene(top_row: int) -> np.ndarray:
    """A box pushed past the heightmap's bottom edge: only rows top_row.. of it are seen."""
    h = np.zeros((N, N), np.float32)
    h[top_row:, 90:140] = 0.06
    return h


def test_a_grasp_closing_across_the_border_is_left_out_and_one_closing_along_it_kept():
    view = grasps_in_view(N, N, R, RES, OPEN)
    assert view.shape == (R, N, N)
    # 21 mm from the bottom edge: closing along the edge (x) keeps both 22 mm wide fingers 10 mm inside,
    # closing across it (y) reaches 57.5 mm
    assert view[0, 213, 112] == 1 and view[8, 213, 112] == 1
    assert view[4, 213, 112] == 0 and view[12, 213, 112] == 0
    assert view[0, 214, 112] == 0   # 19 mm: the finger's side 8 mm from the edge
    # closing along y, the first row whose fingers stay 10 mm inside: (33 + 0.5) * 2 mm = 67 mm < 67.5 mm < 69 mm
    assert view[4, 33, 112] == 0 and view[4, 34, 112] == 1
    assert view[:, 112, 112].all()
    # 15 mm from the edge: no rotation keeps an 11 mm half-finger 10 mm inside
    assert not view[:, 216, 112].any()


def test_a_move_is_allowed_only_where_its_closed_fingers_come_down_and_end_their_travel_inside():
    moves = moves_in_view(N, N, R, RES, 0.10)
    # 41 mm from the bottom edge: a push away from the edge (-y) or along it (+x) stays inside; towards it (+y)
    # its travel would end 59 mm beyond the edge
    assert moves[12, 203, 112] == 1 and moves[0, 203, 112] == 1
    assert moves[4, 203, 112] == 0
    # where the closed fingers come down: 15 mm of finger either way along the travel, 10 mm margin
    assert moves[12, 211, 112] == 1 and moves[12, 212, 112] == 0    # 25 mm, 23 mm from the edge
    # the travel's end: a push along +x ends 100 mm on, its fingers 15 mm beyond that, 10 mm inside the edge
    assert moves[0, 112, 161] == 1 and moves[0, 112, 162] == 0      # (161 + 0.5) * 2 + 115 = 438 mm; 440 mm


def test_the_agent_never_brings_a_finger_down_beyond_the_edge_however_tempting_its_q():
    height = sliver_scene(212)
    height[100:120, 100:120] = 0.04   # and a box in the middle
    agent = Agent(config(epsilon_start=0.2, epsilon_end=0.2), build_network("fast", R, seed=0), seed=0)
    rng = np.random.default_rng(1)
    grasps = 0
    moves = 0
    for step in range(80):
        q = rng.normal(size=(R, 2, N, N)).astype(np.float32) * 0.01
        q[4, 0, 212:, 90:140] = 1.0    # grasps on the sliver closing across the border: the best values
        q[12, 0, 212:, 90:140] = 1.0
        q[4, 1, 195:, 80:150] = 2.0 if step % 2 else -1.0   # every other step, pushes towards the border best
        d = agent.select(q, height, step)
        agent.previous = None
        if d.action.primitive == "grasp":
            grasps += 1
            assert fingers_inside(d.action), d.action
        else:
            moves += 1
            end_row = d.action.row + 0.10 / RES * math.sin(d.action.angle)
            assert (end_row + 0.5) * RES + FINGER_DEPTH * abs(math.sin(d.action.angle)) <= N * RES - VIEW_MARGIN + 1e-9
    assert grasps > 10 and moves > 10


def acts_only_in_the_middle(agent: Agent, q: np.ndarray, sliver: np.ndarray) -> None:
    """With a box in the middle beside the sliver, 20 decisions all act at the box."""
    both = sliver.copy()
    both[100:120, 100:120] = 0.04
    for step in range(20):
        d = agent.select(q + np.random.default_rng(step).normal(size=q.shape).astype(np.float32) * 0.01, both, step)
        agent.previous = None
        assert d is not None and 80 <= d.action.row <= 140 and 80 <= d.action.col <= 140, d.action


def test_a_sliver_at_the_border_is_neither_grasped_nor_pushed_at_and_the_cell_says_why_it_stops():
    q = np.zeros((R, 2, N, N), np.float32)
    q[:, 1] = 1.0                 # moves the best choice anywhere
    sliver = sliver_scene(216)    # 8 rows seen: no grasp rotation keeps the fingers in view
    agent = Agent(config(), build_network("fast", R, seed=0), seed=0)
    assert agent.select(q, sliver, 0) is None
    assert "border" in agent.stuck_reason() and "beyond its edge" in agent.stuck_reason()
    # beside an object in the middle, the agent acts there and never beside the sliver
    acts_only_in_the_middle(agent, q, sliver)
    only = Agent(config(grasp_only=True), build_network("fast", R, seed=0), seed=0)
    assert only.select(q, sliver, 0) is None and "border" in only.stuck_reason()


def test_the_learners_a_prime_keeps_the_fingers_on_the_heightmap_as_the_agent_does():
    cfg = config(grasp_only=True)
    net = build_network("fast", R, seed=3)
    learner = Learner(cfg, net, PrioritizedReplay.from_config(cfg.learning))
    height = sliver_scene(208)
    color = np.full((N, N, 3), 90, np.uint8)
    color[height > 0] = (200, 40, 40)
    s2 = Heightmaps(color, height)
    learner.online.eval()
    with torch.no_grad():
        online = q_maps(learner.online, s2, R).numpy()
        target = q_maps(learner.target, s2, R).numpy()
    gmask, mmask = Agent(cfg, net).masks(height)
    assert gmask.shape == (R, N, N)
    rot, ch, row, col = greedy_index(online, gmask, mmask, grasp_only=True)
    assert fingers_inside(Action("grasp", row, col, rot, R))
    # the same network without the rule would take a' with a finger beyond the edge: the rule decides here
    plain = greedy_index(online, gmask.max(axis=0), mmask, grasp_only=True)
    assert plain is not None and not fingers_inside(Action("grasp", plain[2], plain[3], plain[0], R))
    t = Transition(s2, Action("grasp", 150, 150, 0, R), 0.25, s2, False)
    expected = 0.25 + cfg.learning.gamma * target[rot, 0, row, col]
    assert learner.targets([t])[0] == pytest.approx(expected, abs=1e-5)


def test_last_resort_grasps_take_a_border_sliver_only_when_nothing_else_is_in_view_and_never_push_there():
    q = np.zeros((R, 2, N, N), np.float32)
    q[:, 1] = 1.0                 # moves the best choice anywhere
    sliver = sliver_scene(216)    # no grasp rotation keeps the fingers in view
    agent = Agent(config(last_resort_grasps=True), build_network("fast", R, seed=0), seed=0)
    d = agent.select(q, sliver, 0)
    assert d is not None and d.action.primitive == "grasp" and d.action.row >= 216, d
    assert agent.stuck_reason() == ""
    # an object in view besides: the sliver waits, the limit holds
    acts_only_in_the_middle(agent, q, sliver)


def test_exploration_never_draws_a_move_where_no_move_is_allowed():
    sliver = sliver_scene(216)
    agent = Agent(config(last_resort_grasps=True, epsilon_start=1.0, epsilon_end=1.0), build_network("fast", R, seed=0),
                  seed=0)
    for step in range(20):
        d = agent.select(np.zeros((R, 2, N, N), np.float32), sliver, step)
        agent.previous = None
        assert d is not None and d.action.primitive == "grasp" and d.rule == "epsilon", d
