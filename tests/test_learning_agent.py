"""The agent's decision rules on hand-made Q-maps (``Agent.select``) and through the network (``decide``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from flgd.actions import Action
from flgd.config import CellConfig
from flgd.learning.agent import Agent, Decision, RULES, epsilon_at, masked_maps
from flgd.learning.networks import build_network, q_maps, twin_grasp_maps
from flgd.perception import Heightmaps

N = 32
R = 16


@pytest.fixture(autouse=True)
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def config(**exploration) -> CellConfig:
    """Exploration off unless a test turns it on: no epsilon, no curriculum; every grasp rotation allowed (a
    32 px test map is narrower than the open gripper: tests/test_grasp_view.py covers that rule)."""
    base = dict(epsilon_start=0.0, epsilon_end=0.0, curriculum_steps=0, grasp_in_view=False)
    base.update(exploration)
    cfg = CellConfig()
    return dataclasses.replace(cfg, exploration=dataclasses.replace(cfg.exploration, **base))


def scene_height() -> np.ndarray:
    """Two blocks: a tall one (rows 8-13, cols 8-13) and a flat-ish one (rows 20-25, cols 18-25)."""
    h = np.zeros((N, N), np.float32)
    h[8:14, 8:14] = 0.05
    h[20:26, 18:26] = 0.02
    return h


def agent(cfg: CellConfig | None = None, seed: int = 0) -> Agent:
    return Agent(cfg or config(), build_network("fast", R, seed=0), seed=seed)


def test_masked_out_pixels_are_never_chosen_even_when_their_q_is_highest():
    height = scene_height()
    a = agent(config(epsilon_start=0.3, epsilon_end=0.3))
    gmask, mmask = a.masks(height)
    rng = np.random.default_rng(0)
    for step in range(300):
        q = rng.normal(size=(R, 2, N, N)).astype(np.float32)
        q[:, 0][:, gmask == 0] = 100.0  # tempting values outside the masks
        q[:, 1][:, mmask == 0] = 100.0
        q -= 50.0  # and every value inside is negative: a 0/1 product would pick the outside
        d = a.select(q, height, step)
        mask = gmask if d.action.primitive == "grasp" else mmask
        assert mask[d.action.row, d.action.col] == 1, d
        a.previous = None


def test_greedy_takes_the_higher_of_the_best_grasp_and_the_best_move_and_names_push_or_shift():
    height = scene_height()
    a = agent()
    q = np.zeros((R, 2, N, N), np.float32)
    q[3, 0, 10, 10] = 0.7  # best grasp on the tall block
    q[5, 1, 22, 20] = 0.9  # best move on the low block (2 cm > shift_height 1 cm): a shift
    d = a.select(q, height, 0)
    assert (d.action.primitive, d.action.row, d.action.col, d.action.rotation, d.rule) == ("shift", 22, 20, 5, "greedy")
    assert d.q_value == pytest.approx(0.9)
    q[5, 1, 22, 20] = 0.0
    q[7, 1, 17, 17] = 0.8  # beside the blocks (inside the dilated move mask, height 0): a push
    d = a.select(q, height, 1)
    assert (d.action.primitive, d.action.row, d.action.col, d.action.rotation) == ("push", 17, 17, 7)
    q[7, 1, 17, 17] = 0.0
    d = a.select(q, height, 2)
    assert (d.action.primitive, d.action.row, d.action.col, d.action.rotation) == ("grasp", 10, 10, 3)


def test_anti_repeat_fires_exactly_when_the_chosen_pixel_repeats_and_picks_among_the_top_m():
    height = scene_height()
    a = agent(config(top_m=3, failure_memory=False))  # the paper's rule: only the pixel itself is excluded
    q = np.zeros((R, 2, N, N), np.float32)
    q[0, 0, 10, 10] = 1.0
    q[1, 0, 10, 10] = 0.95  # same pixel, other rotation: excluded too
    top = {(2, 11, 11): 0.9, (4, 12, 9): 0.8, (6, 9, 12): 0.7}
    for (r, y, x), v in top.items():
        q[r, 0, y, x] = v
    q[8, 0, 13, 13] = 0.5  # fourth best: outside the top 3
    first = a.select(q, height, 0)
    assert first.rule == "greedy" and (first.action.row, first.action.col) == (10, 10)
    seen = set()
    for step in range(60):
        a.previous = first.action
        d = a.select(q, height, step)
        assert d.rule == "anti-repeat"
        assert (d.action.rotation, d.action.row, d.action.col) in top
        seen.add((d.action.rotation, d.action.row, d.action.col))
    assert seen == set(top)  # uniform among the top M: all three show up
    # A different previous pixel, or the same pixel but a move, does not trigger the rule.
    a.previous = Action("grasp", 11, 11, 2)
    assert a.select(q, height, 0).rule == "greedy"
    a.previous = Action("push", 10, 10, 0)
    assert a.select(q, height, 0).rule == "greedy"


def test_two_failed_grasps_force_a_move_and_only_then():
    height = scene_height()
    a = agent()
    q = np.zeros((R, 2, N, N), np.float32)
    q[0, 0, 10, 10] = 1.0  # greedy says grasp
    q[2, 1, 16, 16] = 0.2
    grasp = Action("grasp", 10, 10, 0)
    a.record_outcome(grasp, False)
    a.previous = None  # (record_outcome also remembers the location for anti-repeat)
    assert a.select(q, height, 0).rule == "greedy"
    a.previous = None
    a.record_outcome(grasp, False)
    a.previous = None
    d = a.select(q, height, 0)
    assert d.rule == "two-failures" and d.action.is_move and (d.action.row, d.action.col) == (16, 16)
    a.record_outcome(d.action, None)  # the move ends the streak
    a.previous = None
    assert a.select(q, height, 0).rule == "greedy"
    # A success in between resets the count; an unknown grasp result leaves it unchanged.
    a.record_outcome(grasp, False)
    a.record_outcome(grasp, True)
    a.record_outcome(grasp, False)
    a.record_outcome(grasp, None)
    a.previous = None
    assert a.select(q, height, 0).rule == "greedy"
    a.record_outcome(grasp, False)
    a.previous = None
    assert a.select(q, height, 0).rule == "two-failures"


def test_a_loaded_policy_explores_and_counts_on_from_its_own_training_steps():
    cfg = config(epsilon_start=1.0, epsilon_end=0.1, epsilon_decay_steps=100)
    a = agent(cfg, seed=5)
    assert a.epsilon(10) == pytest.approx(epsilon_at(10, cfg.exploration)) and a.policy_steps(10) == 10
    a.continue_exploration_from(3000 - 200)  # a policy of 3,000 steps loaded at this cell's step 200
    assert a.policy_steps(250) == 3050 and a.epsilon(250) == pytest.approx(0.1)
    a.continue_exploration_from(-500)  # loaded at step 500 with no steps of its own
    assert a.policy_steps(100) == 0


def test_epsilon_decays_linearly_and_random_actions_stay_inside_the_masks():
    cfg = config(epsilon_start=1.0, epsilon_end=0.1, epsilon_decay_steps=100)
    assert epsilon_at(0, cfg.exploration) == 1.0
    assert epsilon_at(50, cfg.exploration) == pytest.approx(0.55)
    assert epsilon_at(100, cfg.exploration) == pytest.approx(0.1)
    assert epsilon_at(10_000, cfg.exploration) == pytest.approx(0.1)
    height = scene_height()
    a = agent(cfg, seed=5)
    gmask, mmask = a.masks(height)
    q = np.zeros((R, 2, N, N), np.float32)
    q[0, 0, 10, 10] = 1.0
    rules, primitives, rotations, pixels = [], set(), set(), set()
    for _ in range(400):
        d = a.select(q, height, 0)  # epsilon = 1: always random
        rules.append(d.rule)
        primitives.add(d.action.channel)
        rotations.add(d.action.rotation)
        pixels.add((d.action.channel, d.action.row, d.action.col))
        mask = gmask if d.action.channel == 0 else mmask
        assert mask[d.action.row, d.action.col] == 1
    assert set(rules) == {"epsilon"}
    assert primitives == {0, 1} and rotations == set(range(R))
    assert len(pixels) > 100  # spread over the masks, not a fixed point
    later = [a.select(q, height, 100).rule for _ in range(300)]
    assert 10 <= later.count("epsilon") <= 50  # about 10 % of 300


def test_curriculum_keeps_a_chosen_move_only_with_its_probability_during_the_first_steps():
    height = scene_height()
    a = agent(config(curriculum_steps=50, curriculum_move_probability=0.2), seed=1)
    q = np.zeros((R, 2, N, N), np.float32)
    q[0, 0, 10, 10] = 0.1
    q[3, 1, 17, 17] = 0.9  # greedy prefers the move
    early = []
    for _ in range(400):
        a.previous = None
        early.append(a.select(q, height, 10))
    kept = sum(d.action.is_move for d in early)
    assert {d.rule for d in early} == {"greedy", "curriculum"}
    assert all((d.action.row, d.action.col) == (10, 10) for d in early if d.rule == "curriculum")
    assert 50 <= kept <= 110  # ~20 % of 400
    a.previous = None
    assert a.select(q, height, 50).action.is_move  # after the curriculum the move stays


def test_dpen_ablation_uses_no_masks_and_an_empty_table_gives_no_decision():
    height = scene_height()
    a = agent(config(masks=False))
    gmask, mmask = a.masks(height)
    assert gmask.all() and mmask.all()
    q = np.zeros((R, 2, N, N), np.float32)
    q[4, 0, 0, 31] = 1.0  # empty table corner: allowed without masks
    d = a.select(q, height, 0)
    assert (d.action.row, d.action.col) == (0, 31)
    assert d.grasp_mask.all()
    empty = Heightmaps(np.zeros((N, N, 3), np.uint8), np.zeros((N, N), np.float32))
    assert a.decide(empty, 0) is None
    assert agent().decide(empty, 0) is None


def test_decide_runs_the_network_and_returns_a_complete_decision():
    height = scene_height()
    color = np.zeros((N, N, 3), np.uint8)
    color[height > 0] = (200, 100, 50)
    hm = Heightmaps(color, height)
    a = agent()
    d = a.decide(hm, 0)
    assert isinstance(d, Decision) and d.rule in RULES
    assert d.q_maps.shape == (R, 2, N, N) and d.q_maps.dtype == np.float32
    assert d.grasp_mask.dtype == np.uint8 and d.move_mask.shape == (N, N)
    with torch.no_grad():
        expected = q_maps(a.network, hm).numpy()
    assert np.array_equal(d.q_maps, expected)
    masked = masked_maps(expected, d.grasp_mask, d.move_mask)
    assert d.q_value == pytest.approx(float(np.max(masked)))


def test_posted_weights_are_picked_up_at_the_next_decision():
    a = agent()
    other = build_network("fast", R, seed=7)
    a.mailbox.post(build_network("fast", R, seed=6).state_dict(), version=1)
    a.mailbox.post(other.state_dict(), version=2)  # replaces the unread set
    height = scene_height()
    hm = Heightmaps(np.zeros((N, N, 3), np.uint8), height)
    a.decide(hm, 0)
    assert a.weights_version == 2
    for name, tensor in other.state_dict().items():
        assert torch.equal(a.network.state_dict()[name], tensor)
    assert a.maybe_swap_weights() is False  # nothing new


def test_the_three_compared_methods_map_to_network_and_masks():
    from flgd.learning.methods import METHODS, configure_method

    base = CellConfig()
    flg, dpen, rho = (configure_method(base, m) for m in METHODS)
    assert (flg.learning.network, flg.exploration.masks) == ("fast", True)
    assert (dpen.learning.network, dpen.exploration.masks) == ("fast", False)
    assert (rho.learning.network, rho.exploration.masks) == ("rho-fcn", True)
    dense = dataclasses.replace(base, learning=dataclasses.replace(base.learning, network="densenet121"))
    assert configure_method(dense, "DPEN").learning.network == "densenet121"
    with pytest.raises(ValueError, match="method"):
        configure_method(base, "VPG")
    with pytest.raises(ValueError, match="FLG head"):
        configure_method(rho, "FLG")


def test_grasp_only_never_moves_even_after_failures_or_exploration():
    height = scene_height()
    a = agent(config(grasp_only=True, epsilon_start=0.5, epsilon_end=0.5))
    q = np.zeros((R, 2, N, N), np.float32)
    q[3, 1, 16, 16] = 5.0  # a move that greedy would take
    grasp = Action("grasp", 10, 10, 0)
    rules = set()
    for step in range(200):
        a.record_outcome(grasp, False)  # failures keep coming: the two-failures rule must not fire
        d = a.select(q, height, step)
        rules.add(d.rule)
        assert d.action.primitive == "grasp", d
        a.previous = None
    assert "epsilon" in rules and "two-failures" not in rules
    # The same agent without grasp_only takes the move.
    b = agent(config())
    assert b.select(q, height, 0).action.is_move


def test_twin_grasps_act_on_the_mean_of_a_grasp_and_its_half_turn_and_leave_moves_alone():
    height = scene_height()
    q = np.zeros((R, 2, N, N), np.float32)
    # rotation 3 alone looks best at (10, 10), but its twin (11) says it is poor; rotation 5 and its twin 13
    # agree on a slightly lower value at (22, 20): only the mean sees that 5/13 is the better grasp
    q[3, 0, 10, 10], q[11, 0, 10, 10] = 1.0, 0.0
    q[5, 0, 22, 20], q[13, 0, 22, 20] = 0.8, 0.8
    q[2, 1, 10, 10], q[10, 1, 10, 10] = 0.3, -0.3   # moves are directional: no averaging
    plain = agent().select(q, height, 0)
    assert (plain.action.primitive, plain.action.rotation, plain.action.row) == ("grasp", 3, 10)

    twins = twin_grasp_maps(q)
    assert twins[3, 0, 10, 10] == twins[11, 0, 10, 10] == pytest.approx(0.5)
    assert np.array_equal(twins[:, 1], q[:, 1])
    assert np.array_equal(twin_grasp_maps(q[:15]), q[:15])  # an odd R has no twins
    chosen = agent().select(twins, height, 0)
    assert chosen.action.primitive == "grasp" and chosen.action.rotation % 8 == 5 and chosen.action.row == 22

    # decide() applies it to the network's maps when the option is on, and only then
    color = np.zeros((N, N, 3), np.uint8)
    color[height > 0] = (200, 100, 50)
    hm = Heightmaps(color, height)
    on = agent(config(twin_grasps=True))
    with torch.no_grad():
        raw = q_maps(on.network, hm).numpy()
    assert np.allclose(on.decide(hm, 0).q_maps, twin_grasp_maps(raw))
    assert np.array_equal(agent().decide(hm, 0).q_maps, raw)
