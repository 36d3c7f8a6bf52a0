"""Prioritized replay: sum-tree sampling in proportion to priority, importance weights, ring buffer,
compact shared states and the rebuild path used after a restart."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from flgd.actions import Action
from flgd.learning.replay import PrioritizedReplay, SumTree, Transition, pack_heightmaps, unpack_heightmaps
from flgd.perception import Heightmaps

REPO = Path(__file__).resolve().parents[1]

# chi-square critical values at p = 0.001
CHI2_999 = {7: 24.322, 15: 37.697}


def hm(seed: int, n: int = 16) -> Heightmaps:
    rng = np.random.default_rng(seed)
    return Heightmaps(rng.integers(0, 255, (n, n, 3), dtype=np.uint8), (rng.random((n, n)) * 0.1).astype(np.float32))


def transition(i: int, next_state: Heightmaps | None = None, state: Heightmaps | None = None) -> Transition:
    s = state if state is not None else hm(i)
    return Transition(s, Action("grasp", i % 16, 0, i % 16), float(i), next_state if next_state is not None else hm(1000 + i), False)


def test_sum_tree_sums_and_finds_the_leaf_under_a_cumulative_value():
    tree = SumTree(5)
    values = [1.0, 0.0, 2.5, 0.5, 3.0]
    for i, v in enumerate(values):
        tree.update(i, v)
    assert tree.total == pytest.approx(7.0)
    edges = np.cumsum(values)
    for x in np.linspace(0, 6.999, 200):
        expected = int(np.searchsorted(edges, x, side="right"))
        assert tree.find(x) == expected
    tree.update(2, 0.0)
    assert tree.total == pytest.approx(4.5)
    with pytest.raises(ValueError):
        tree.update(0, float("nan"))
    with pytest.raises(IndexError):
        tree.update(5, 1.0)


def test_sampling_follows_the_priorities_chi_square():
    replay = PrioritizedReplay(16, alpha=1.0, beta_start=0.4, beta_steps=100, epsilon=0.01, seed=3)
    state = hm(0)
    for i in range(8):
        replay.add(Transition(state, Action("grasp", 0, 0, 0), 0.0, state, False))
    td = np.array([0.1, 0.5, 1.0, 2.0, 0.2, 4.0, 0.05, 1.5])
    replay.update_priorities(range(8), td)
    draws = np.concatenate([replay.sample(32)[0] for _ in range(500)])
    observed = np.bincount(draws, minlength=8)
    p = (td + 0.01) / (td + 0.01).sum()
    expected = p * len(draws)
    chi2 = float(((observed - expected) ** 2 / expected).sum())
    assert chi2 < CHI2_999[7], (observed, expected)
    # The exponent alpha flattens the distribution: alpha = 0 is uniform.
    flat = PrioritizedReplay(16, alpha=0.0, seed=4)
    for i in range(8):
        flat.add(Transition(state, Action("grasp", 0, 0, 0), 0.0, state, False))
    flat.update_priorities(range(8), td)
    observed = np.bincount(np.concatenate([flat.sample(32)[0] for _ in range(250)]), minlength=8)
    chi2 = float(((observed - 1000) ** 2 / 1000).sum())
    assert chi2 < CHI2_999[7]


def test_importance_weights_follow_the_formula_and_beta_anneals_to_one():
    replay = PrioritizedReplay(8, alpha=0.5, beta_start=0.4, beta_steps=10, epsilon=0.01, seed=0)
    for i in range(4):
        replay.add(transition(i))
    td = np.array([0.09, 0.99, 3.99, 0.24])
    replay.update_priorities(range(4), td)
    pri = (td + 0.01) ** 0.5
    probs = pri / pri.sum()
    for call in range(12):
        beta = min(1.0, 0.4 + 0.6 * call / 10)
        assert replay.beta == pytest.approx(beta)
        idx, _, w = replay.sample(4)
        expected = (4 * probs[idx]) ** -beta / (4 * probs.min()) ** -beta
        assert np.allclose(w, expected, rtol=1e-5)
        assert w.max() <= 1.0 + 1e-6
    assert replay.beta == 1.0


def test_new_transitions_get_the_current_max_priority_and_the_ring_overwrites_the_oldest():
    replay = PrioritizedReplay(3, seed=0)
    assert replay.add(transition(0)) == 0
    assert replay.priority(0) == 1.0  # empty replay: 1
    replay.update_priorities([0], [4.99])
    assert replay.add(transition(1)) == 1
    assert replay.priority(1) == pytest.approx(5.0)
    replay.update_priorities([0, 1], [0.19, 0.49])
    replay.add(transition(2))
    assert replay.priority(2) == pytest.approx(0.5)  # max of what is stored now, not of the past
    assert replay.add(transition(3)) == 0  # full: the oldest slot is reused
    assert len(replay) == 3
    assert replay.get(0).reward == 3.0 and replay.get(1).reward == 1.0
    with pytest.raises(ValueError, match="done=True"):
        replay.add(Transition(hm(0), Action("grasp", 0, 0, 0), 0.0, None, False))
    with pytest.raises(ValueError, match="priority"):
        replay.add(transition(4), priority=-1.0)


def test_states_are_stored_once_compactly_and_come_back_at_the_stored_precision():
    states = [hm(i, 64) for i in range(6)]
    replay = PrioritizedReplay(4, seed=0)
    for i in range(5):  # a chain s0->s1->...->s5: each state is the next one's previous
        replay.add(Transition(states[i], Action("push", 1, 2, 3), 0.5, states[i + 1], False))
    assert replay.stored_states == 5  # s1..s5 (s0 left with the overwritten slot), not 8
    back = replay.get(1)
    assert np.array_equal(back.state.color, states[1].color)
    assert np.abs(back.state.height - states[1].height).max() <= 1e-4  # float16 near 0.1 m
    assert np.array_equal(back.next_state.color, states[2].color)
    assert back.action == Action("push", 1, 2, 3) and back.reward == 0.5
    done = Transition(states[0], Action("grasp", 0, 0, 0), 1.0, None, True)
    idx = replay.add(done)
    assert replay.get(idx).next_state is None and replay.get(idx).done


def test_a_realistic_224_state_packs_to_a_fraction_of_its_raw_size():
    """The footprint claim of the module doc: a noisy textured 224 x 224 scene, 20 blocks."""
    rng = np.random.default_rng(0)
    n = 224
    height = np.zeros((n, n), np.float32)
    color = np.clip(rng.normal(120, 6, (n, n, 3)), 0, 255).astype(np.uint8)  # table texture + noise
    for _ in range(20):
        r, c = rng.integers(0, n - 20, 2)
        height[r:r + 20, c:c + 20] = rng.uniform(0.02, 0.06)
        color[r:r + 20, c:c + 20] = rng.integers(0, 255, 3)
    height += rng.normal(0, 0.001, height.shape).astype(np.float32) * (height > 0)
    blob = pack_heightmaps(Heightmaps(color, height))
    raw_float32 = n * n * 4 * 4
    assert len(blob) < 0.25 * raw_float32  # < 200 KiB; 20,000 states < 4 GB
    back = unpack_heightmaps(blob)
    assert np.array_equal(back.color, color) and np.abs(back.height - height).max() < 1e-4


def test_rebuild_from_stored_transitions_restores_the_same_sampling():
    original = PrioritizedReplay(10, seed=9)
    for i in range(6):
        original.add(transition(i))
    original.update_priorities(range(6), [0.1, 2.0, 0.3, 0.0, 1.0, 5.0])
    stored = [(original.get(i), original.priority(i)) for i in range(6)]
    rebuilt = PrioritizedReplay(10, seed=9)
    assert rebuilt.extend(stored) == list(range(6))
    for i in range(6):
        assert rebuilt.priority(i) == original.priority(i)
    a, _, wa = original.sample(6)
    b, _, wb = rebuilt.sample(6)
    assert np.array_equal(a, b) and np.array_equal(wa, wb)


def test_concurrent_adds_and_samples_keep_the_tree_consistent():
    replay = PrioritizedReplay(50, seed=0)
    replay.add(transition(0))
    errors: list[BaseException] = []

    def sampler():
        try:
            for _ in range(200):
                idx, batch, w = replay.sample(4)
                replay.update_priorities(idx, np.ones(len(idx)))
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    t = threading.Thread(target=sampler)
    t.start()
    for i in range(1, 120):
        replay.add(transition(i))
    t.join()
    assert not errors
    leaves = np.array([replay.priority(i) for i in range(len(replay))]) ** replay.alpha
    assert len(replay) == 50
    tree_total = replay._tree.total
    assert tree_total == pytest.approx(leaves.sum())


def test_tagged_slots_report_their_new_priorities_for_the_store():
    replay = PrioritizedReplay(3, epsilon=0.01, seed=0)
    replay.add(transition(0), tag=40)
    replay.add(transition(1))  # untagged (no store): never reported
    replay.add(transition(2), tag=42)
    assert (replay.tag(0), replay.tag(1), replay.tag(2)) == (40, None, 42)
    assert replay.update_priorities([0, 1, 2], [0.5, -2.0, 0.25]) == [(40, 0.51), (42, 0.26)]
    replay.add(transition(3), tag=43)  # overwrites slot 0: its tag goes with it
    assert replay.tag(0) == 43 and replay.update_priorities([0], [1.0]) == [(43, 1.01)]
    with pytest.raises(ValueError, match="tag"):
        replay.add(transition(4), tag=-3)


def test_a_bad_td_error_changes_no_priority_of_the_batch():
    replay = PrioritizedReplay(4, seed=0)
    for i in range(3):
        replay.add(transition(i), tag=i)
    before = [replay.priority(i) for i in range(3)]
    with pytest.raises(ValueError, match="slot 2"):
        replay.update_priorities([0, 1, 2], [0.3, 0.2, float("nan")])
    assert [replay.priority(i) for i in range(3)] == before


def test_a_resumed_learner_continues_the_beta_schedule():
    """beta anneals over sampled batches, one per update; a resumed run must not restart at beta_start."""
    from flgd.config import load_config
    from flgd.learning.networks import build_network
    from flgd.learning_stack import Handover, LearningStack

    cfg = load_config(REPO / "cell_config" / "sim.yaml")
    lc = cfg.learning
    replay = PrioritizedReplay.from_config(lc)
    assert replay.beta == pytest.approx(lc.priority_beta_start)
    half = lc.priority_beta_steps // 2
    stack = LearningStack(cfg, fine_tune=False, state_dir=REPO)
    parts = stack.build(build_network(lc.network, rotations=16, seed=0), handover=Handover.AGENT, updates=half)
    replay = parts.replay
    assert parts.learner.updates == half  # and the learner counts on from there
    assert replay.beta == pytest.approx(lc.priority_beta_start + (1 - lc.priority_beta_start) * half / lc.priority_beta_steps)
    replay.resume_annealing(10 * lc.priority_beta_steps)
    assert replay.beta == pytest.approx(1.0)
    with pytest.raises(ValueError, match="samples drawn"):
        replay.resume_annealing(-1)
