"""The learner: where the loss puts gradient, the double-DQN target, priorities and importance weights,
the target-network schedule, checkpoints, and the background thread publishing to the agent."""

from __future__ import annotations

import dataclasses
import os
import threading
import time

import numpy as np
import pytest
import torch

from flgd.actions import Action
from flgd.config import CellConfig
from flgd.learning.agent import Agent, WeightsMailbox, greedy_index, masked_maps
from flgd.learning.learner import Learner
from flgd.learning.networks import build_network, q_maps, rotated_inputs, twin_grasp_maps, unrotate_maps
from flgd.learning.replay import PrioritizedReplay, Transition, state_key
from flgd.perception import Heightmaps
from tests.fakes.learning import block_scene, learner_config

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def learner(cfg: CellConfig | None = None, replay: PrioritizedReplay | None = None, **kw) -> Learner:
    cfg = cfg or learner_config()
    return Learner(cfg, build_network("fast", 16, seed=0), replay or PrioritizedReplay.from_config(cfg.learning), **kw)


def test_the_loss_reads_the_executed_pixel_and_the_grasp_twin_as_the_full_q_maps_do():
    lrn = learner(learner_config(gamma=0.0))
    grasp = Transition(block_scene(1), Action("grasp", 9, 20, 3), 1.0, block_scene(2), False)
    push = Transition(block_scene(3), Action("push", 25, 4, 13), 0.5, None, True)
    edge = Transition(block_scene(4), Action("grasp", 31, 0, 6), 0.0, None, True)  # the border of the map
    terms = lrn.loss_terms([grasp, push, edge], np.array([1.0, 0.5, 1.0], np.float32))
    assert terms.owners == [0, 0, 1, 2, 2] and terms.rotations == [3, 11, 13, 6, 14]
    terms.predicted.sum().backward()
    pixel_grads = {n: p.grad.clone() for n, p in lrn.online.named_parameters()}
    lrn.online.zero_grad(set_to_none=True)
    # the same rows read from the full heightmap-frame Q-maps, forwarded as one batch like the loss's
    rows = [(grasp.state, 3, 0, 9, 20), (grasp.state, 11, 0, 9, 20), (push.state, 13, 1, 25, 4),
            (edge.state, 6, 0, 31, 0), (edge.state, 14, 0, 31, 0)]
    inputs = [rotated_inputs(s, [r], 16, lrn.online.stride) for s, r, *_ in rows]
    out = lrn.online(torch.cat([c for c, _ in inputs]), torch.cat([h for _, h in inputs]))
    maps = unrotate_maps(out, [r for _, r, *_ in rows], 16, 32, 32)
    full = torch.stack([maps[i, ch, row, col] for i, (_, _, ch, row, col) in enumerate(rows)])
    assert torch.allclose(terms.predicted.detach(), full.detach(), atol=1e-6)
    full.sum().backward()
    for name, p in lrn.online.named_parameters():
        assert torch.allclose(pixel_grads[name], p.grad, atol=1e-5, rtol=1e-4), name
    assert any(g.abs().sum() > 0 for g in pixel_grads.values())


def test_with_one_grasp_twin_a_grasp_trains_one_of_its_two_rotations_drawn_at_random():
    lrn = learner(learner_config(grasp_twins="one", gamma=0.0))
    grasp = Transition(block_scene(1), Action("grasp", 9, 20, 3), 1.0, None, True)
    push = Transition(block_scene(3), Action("push", 25, 4, 13), 0.5, None, True)
    drawn = []
    for _ in range(40):
        terms = lrn.loss_terms([grasp, push], np.ones(2, np.float32))
        assert terms.owners == [0, 1] and terms.rotations[1] == 13  # a move keeps its one rotation
        drawn.append(terms.rotations[0])
    assert set(drawn) == {3, 11} and 8 <= drawn.count(3) <= 32


def test_double_dqn_target_uses_online_argmax_under_masks_and_target_value():
    cfg = learner_config(gamma=0.5)
    lrn = learner(cfg)
    lrn.target.load_state_dict(build_network("fast", 16, seed=5).state_dict())  # make them differ
    s2 = block_scene(4)
    t = Transition(block_scene(3), Action("grasp", 5, 5, 0), 0.25, s2, False)
    done = Transition(block_scene(3), Action("grasp", 5, 5, 0), 1.0, s2, True)
    agent = Agent(cfg, lrn.online)
    gmask, mmask = agent.masks(s2.height)
    lrn.online.eval()
    with torch.no_grad():
        online = q_maps(lrn.online, s2).numpy()
        target = q_maps(lrn.target, s2).numpy()
    lrn.online.train()
    rot, ch, row, col = np.unravel_index(np.argmax(masked_maps(online, gmask, mmask)), online.shape)
    assert gmask[row, col] if ch == 0 else mmask[row, col]
    ys = lrn.targets([t, done])
    assert ys[0] == pytest.approx(0.25 + 0.5 * target[rot, ch, row, col], abs=1e-5)
    assert ys[1] == 1.0
    # The target's own argmax is generally elsewhere: the value is not max(target).
    assert target[rot, ch, row, col] != pytest.approx(target.max())


def test_grasp_only_targets_ignore_the_move_channel():
    cfg = learner_config(gamma=0.5)
    cfg = dataclasses.replace(cfg, exploration=dataclasses.replace(cfg.exploration, grasp_only=True))
    lrn = learner(cfg)
    s2 = block_scene(4)
    with torch.no_grad():
        lrn.online.eval()
        online = q_maps(lrn.online, s2).numpy()
        target = q_maps(lrn.target, s2).numpy()
    gmask, mmask = Agent(cfg, lrn.online).masks(s2.height)
    masked = masked_maps(online, gmask, mmask)
    masked[:, 1] = -np.inf
    rot, ch, row, col = np.unravel_index(np.argmax(masked), masked.shape)
    assert ch == 0
    y = lrn.targets([Transition(block_scene(3), Action("grasp", 5, 5, 0), 0.0, s2, False)])[0]
    assert y == pytest.approx(0.5 * target[rot, 0, row, col], abs=1e-5)


def _replayed(replay: PrioritizedReplay, transition: Transition) -> Transition:
    return replay.get(replay.add(transition))


def test_replayed_transitions_carry_the_content_key_of_their_next_state():
    replay = PrioritizedReplay(8, seed=0)
    s2 = block_scene(4)
    got = _replayed(replay, Transition(block_scene(3), Action("grasp", 5, 5, 0), 0.0, s2, False))
    assert got.next_key == state_key(s2)
    assert got.next_key != state_key(block_scene(3))
    assert _replayed(replay, Transition(block_scene(3), Action("push", 5, 5, 0), 0.0, None, True)).next_key is None


def test_cached_next_argmax_from_the_agent_gives_the_exact_target_without_a_forward_pass():
    cfg = learner_config(gamma=0.5, next_argmax_max_age=10, target_update_every=1000)
    replay = PrioritizedReplay(8, seed=0)
    lrn = learner(cfg, replay)
    lrn.target.load_state_dict(build_network("fast", 16, seed=5).state_dict())
    s2 = block_scene(4)
    t = _replayed(replay, Transition(block_scene(3), Action("grasp", 5, 5, 0), 0.25, s2, False))
    exact = learner(learner_config(gamma=0.5), PrioritizedReplay(8, seed=0))
    exact.target.load_state_dict(lrn.target.state_dict())
    expected = exact.targets([t])[0]

    agent = Agent(cfg, lrn.online)
    decision = agent.decide(s2, step=10_000)
    # the decision carries the masked argmax it already computed: the one the learner would compute
    assert decision.greedy == greedy_index(decision.q_maps, decision.grasp_mask, decision.move_mask)
    lrn.note_decision(s2, decision, weights_version=0)
    assert lrn.targets([t])[0] == pytest.approx(expected, abs=1e-6)
    assert (lrn.argmax_reused, lrn.argmax_computed) == (1, 0)


def test_a_cached_argmax_older_than_the_limit_is_recomputed_with_the_current_network():
    cfg = learner_config(gamma=0.5, next_argmax_max_age=3, target_update_every=1000)
    replay = PrioritizedReplay(8, seed=0)
    lrn = learner(cfg, replay)
    s2 = block_scene(4)
    t = _replayed(replay, Transition(block_scene(3), Action("grasp", 5, 5, 0), 0.25, s2, False))
    gmask, _ = Agent(cfg, lrn.online).masks(s2.height)
    rows, cols = np.nonzero(gmask == 0)  # a (deliberately wrong) cached a' off the objects
    stale = (0, 0, int(rows[0]), int(cols[0]))
    lrn._next_argmax[t.next_key] = (0, stale)
    with torch.no_grad():
        q_stale = q_maps(lrn.target, s2, rotation_indices=[0])[0, 0, stale[2], stale[3]].item()
    assert lrn.targets([t])[0] == pytest.approx(0.25 + 0.5 * q_stale, abs=1e-6)  # fresh enough: used as is
    lrn.updates = 4  # now 4 updates old > 3
    exact = learner(learner_config(gamma=0.5), PrioritizedReplay(8, seed=0))
    exact.online.load_state_dict(lrn.online.state_dict())
    exact.target.load_state_dict(lrn.target.state_dict())
    assert lrn.targets([t])[0] == pytest.approx(exact.targets([t])[0], abs=1e-6)
    assert lrn.argmax_computed == 1 and lrn._next_argmax[t.next_key][0] == 4


def test_with_actor_argmax_the_deciding_weights_a_prime_is_used_however_many_updates_later():
    # the exact target while the weights are those that decided; thousands of updates later the cell's a' still
    # picks the rotation and pixel, and only Q_target(s', a') is computed (one rotation of the target network)
    cfg = learner_config(gamma=0.5, actor_argmax=True, target_update_every=1000)
    replay = PrioritizedReplay(8, seed=0)
    lrn = learner(cfg, replay)
    s2 = block_scene(4)
    t = _replayed(replay, Transition(block_scene(3), Action("grasp", 5, 5, 0), 0.25, s2, False))
    exact = learner(learner_config(gamma=0.5), PrioritizedReplay(8, seed=0))
    exact.online.load_state_dict(lrn.online.state_dict())
    exact.target.load_state_dict(lrn.target.state_dict())
    decision = Agent(cfg, lrn.online).decide(s2, step=10_000)
    lrn.note_decision(s2, decision, weights_version=0)
    assert lrn.targets([t])[0] == pytest.approx(exact.targets([t])[0], abs=1e-6)
    lrn.updates = 5000
    lrn._next_value.clear()  # a target sync: the value is recomputed, the choice of a' is not
    rot, ch, row, col = decision.greedy
    with torch.no_grad():
        q_t = q_maps(lrn.target, s2, rotation_indices=[rot])[0, ch, row, col].item()
    assert lrn.targets([t])[0] == pytest.approx(0.25 + 0.5 * q_t, abs=1e-6)
    assert (lrn.argmax_reused, lrn.argmax_computed) == (2, 0)
    # a decision of weights ahead of this learner's line is still refused
    lrn._next_argmax.clear()
    lrn.note_decision(s2, decision, weights_version=6000)
    assert lrn._next_argmax == {}


def test_decisions_of_old_weights_are_not_cached_and_nothing_is_cached_with_age_zero():
    s2 = block_scene(4)
    for max_age, version, updates in ((0, 0, 0), (3, 0, 5), (3, -1, 0)):
        lrn = learner(learner_config(next_argmax_max_age=max_age))
        lrn.updates = updates
        lrn.note_decision(s2, Agent(lrn.config, lrn.online).decide(s2, step=10_000), weights_version=version)
        assert lrn._next_argmax == {}


def test_importance_weights_scale_the_loss_and_priorities_become_td_plus_epsilon():
    lrn = learner()
    batch = [Transition(block_scene(i), Action("shift", 10, 10 + i, i), 0.5, None, True) for i in range(2)]
    lrn.online.eval()  # same BN statistics for both evaluations
    one = lrn.loss_terms(batch, np.array([1.0, 1.0], np.float32))
    weighted = lrn.loss_terms(batch, np.array([0.2, 0.6], np.float32))
    per = [lrn.loss_terms([b], np.array([1.0], np.float32)).loss.item() for b in batch]
    assert weighted.loss.item() == pytest.approx((0.2 * per[0] + 0.6 * per[1]) / 2, rel=1e-5)
    assert one.loss.item() == pytest.approx((per[0] + per[1]) / 2, rel=1e-5)

    replay = PrioritizedReplay(8, epsilon=0.01, seed=0)
    for b in batch:
        replay.add(b)
    lrn = learner(replay=replay)
    lrn.online.eval()
    with torch.no_grad():
        expected_td = {i: 0.5 - float(q_maps(lrn.online, b.state)[i, 1, 10, 10 + i]) for i, b in enumerate(batch)}
    terms = lrn.loss_terms(batch, np.ones(2, np.float32))
    assert np.allclose(terms.td_errors, [expected_td[0], expected_td[1]], atol=1e-5)
    lrn.online.train()
    stats = lrn.update()
    assert stats.update == 1 and stats.batch_size == 2
    latest = dict(zip(stats.indices, stats.td_errors))  # a slot drawn twice keeps its last TD error
    for i, td in latest.items():
        assert replay.priority(i) == pytest.approx(abs(td) + 0.01)


def test_target_network_follows_its_schedule_and_checkpoints_are_called():
    cfg = learner_config(target_update_every=3, checkpoint_every=2, learning_rate=1e-3)
    calls = []
    lrn = learner(cfg, checkpoint_callback=lambda net, n: calls.append((n, net.variant)))
    for i in range(3):
        lrn.replay.add(Transition(block_scene(i), Action("grasp", 12, 12, i), float(i % 2), None, True))

    def same() -> bool:
        o, t = lrn.online.state_dict(), lrn.target.state_dict()
        return all(torch.equal(o[k], t[k]) for k in o)

    assert same()
    lrn.update()
    assert not same()
    lrn.update()
    assert not same()
    lrn.update()
    assert same()
    lrn.update()
    assert calls == [(2, "fast"), (4, "fast")]
    assert lrn.updates == 4


def test_background_learner_publishes_weights_that_the_agent_picks_up():
    cfg = learner_config(updates_per_action=2, checkpoint_every=1)
    cfg = dataclasses.replace(cfg, gate=dataclasses.replace(cfg.gate, handover_every=3))
    replay = PrioritizedReplay.from_config(cfg.learning)
    agent = Agent(cfg, build_network("fast", 16, seed=0))
    niceness = []  # of the thread running the updates, seen from the checkpoint callback

    def record_niceness(net, n):
        niceness.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))

    lrn = Learner(cfg, agent.network, replay, mailbox=agent.mailbox, checkpoint_callback=record_niceness,
                  thread_nice=5)
    assert lrn.online is not agent.network  # the learner trains its own copy
    lrn.start()
    try:
        hm = block_scene(0)
        for step in range(3):
            d = agent.decide(hm, step)
            replay.add(Transition(hm, d.action, 0.0, block_scene(step + 1), False))
            lrn.notify_new_transition()
            assert lrn.wait_idle(timeout=120)
            hm = block_scene(step + 1)
        assert lrn.updates == 6 and lrn.failed_updates == 0
        main_nice = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        assert niceness == [min(19, main_nice + 5)] * 6  # training yields the CPU to decisions
        assert agent.mailbox.posted == 2 and lrn.handovers == 2  # after updates 3 and 6
        agent.decide(hm, 3)
        assert agent.weights_version == 6
        trained = lrn.snapshot().state_dict()
        for name, tensor in agent.network.state_dict().items():
            assert torch.equal(tensor, trained[name]), name
    finally:
        lrn.stop(timeout=60)
    assert not lrn.running


def test_a_failing_update_is_reported_and_the_thread_keeps_running():
    cfg = learner_config(updates_per_action=1)
    replay = PrioritizedReplay.from_config(cfg.learning)
    # An action built for 8 rotations cannot be trained by a 16-rotation network.
    replay.add(Transition(block_scene(0), Action("grasp", 3, 3, 1, rotations=8), 0.0, None, True))
    lrn = learner(cfg, replay=replay)
    lrn.start()
    try:
        lrn.notify_new_transition()
        assert lrn.wait_idle(timeout=60)
        assert lrn.failed_updates == 1 and "rotations" in lrn.last_error
        assert lrn.running
    finally:
        lrn.stop(timeout=60)


def test_learning_is_deterministic_for_a_fixed_seed():
    def run() -> dict[str, torch.Tensor]:
        cfg = learner_config(learning_rate=1e-3, seed=3)
        replay = PrioritizedReplay.from_config(cfg.learning)
        for i in range(4):
            replay.add(Transition(block_scene(i), Action("grasp", 8 + i, 12, i), float(i % 2), block_scene(i + 1), False))
        lrn = Learner(cfg, build_network("fast", 16, seed=3), replay)
        for _ in range(3):
            lrn.update()
        return lrn.snapshot().state_dict()

    a, b = run(), run()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_the_backlog_is_capped_and_the_dropped_updates_are_counted():
    """A learner slower than the cell owes at most max_backlog updates (never less than one action's)."""
    capped = learner(learner_config(updates_per_action=3, max_backlog=7))
    for _ in range(10):
        capped.notify_new_transition()
    assert capped.pending == 7 and capped.dropped_updates == 23
    tight = learner(learner_config(updates_per_action=3, max_backlog=2))
    tight.notify_new_transition()
    tight.notify_new_transition()
    assert tight.pending == 3 and tight.dropped_updates == 3
    unlimited = learner(learner_config(updates_per_action=3, max_backlog=0))
    for _ in range(10):
        unlimited.notify_new_transition()
    assert unlimited.pending == 30 and unlimited.dropped_updates == 0
    # what is owed is still run: the synchronous mode drains the capped backlog exactly
    capped.replay.add(Transition(block_scene(1), Action("grasp", 9, 20, 3), 1.0, None, True))
    assert len(capped.update_pending()) == 7 and capped.pending == 0 and capped.updates == 7


def test_a_stop_whose_join_timed_out_never_leaves_two_learner_threads():
    """Fault injection: an update that blocks (a slow disk, a stuck device) outlasts ``stop``'s timeout."""
    cfg = learner_config(updates_per_action=1)
    replay = PrioritizedReplay.from_config(cfg.learning)
    replay.add(Transition(block_scene(0), Action("grasp", 8, 12, 0), 1.0, None, True))
    lrn = learner(cfg, replay=replay)
    release, entered = threading.Event(), threading.Event()
    real_update = lrn.update

    def blocking_update():
        entered.set()
        release.wait(30)
        return real_update()

    lrn.update = blocking_update
    lrn.start()
    try:
        lrn.notify_new_transition()
        assert entered.wait(30)
        lrn.stop(timeout=0.05)           # the join times out: the thread is still inside its update
        assert lrn.running
        lrn.start()                      # the stop is withdrawn: the same thread carries on
        alive = [t for t in threading.enumerate() if t.name == "flgd-learner"]
        assert len(alive) == 1
        release.set()
        assert lrn.wait_idle(timeout=60) and lrn.updates == 1
        lrn.notify_new_transition()      # and it still takes new work
        assert lrn.wait_idle(timeout=60) and lrn.updates == 2
    finally:
        release.set()
        lrn.stop(timeout=60)
    assert not lrn.running
    assert not [t for t in threading.enumerate() if t.name == "flgd-learner"]


def _bn_stats(net: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in net.state_dict().items() if "running_" in k or "num_batches" in k}


@pytest.mark.parametrize("mode", ["batch", "frozen"])
def test_frozen_batchnorm_keeps_the_running_statistics_while_the_weights_learn(mode):
    lrn = learner(learner_config(batchnorm=mode, learning_rate=1e-3))
    for i in range(3):
        lrn.replay.add(Transition(block_scene(i), Action("grasp", 12, 12, i), float(i % 2), block_scene(i + 5), False))
    stats_before = _bn_stats(lrn.online)
    conv_before = lrn.online.enc1[0].weight.detach().clone()
    bn_scale_before = lrn.online.enc1[1].weight.detach().clone()
    for _ in range(3):
        assert lrn.update() is not None
    stats_after = _bn_stats(lrn.online)
    moved = [k for k in stats_before if not torch.equal(stats_before[k], stats_after[k])]
    assert not torch.equal(conv_before, lrn.online.enc1[0].weight)
    assert not torch.equal(bn_scale_before, lrn.online.enc1[1].weight)  # BN's scale learns in both modes
    if mode == "frozen":
        assert moved == []
        # the training forward normalised with the running statistics: it matches the eval-mode output
        t = Transition(block_scene(1), Action("grasp", 12, 12, 1), 1.0, None, True)
        train_pred = lrn.loss_terms([t], np.ones(1, np.float32)).predicted.detach()
        lrn.online.eval()
        with torch.no_grad():
            eval_pred = lrn.loss_terms([t], np.ones(1, np.float32)).predicted
        assert torch.allclose(train_pred, eval_pred, atol=1e-5)
    else:
        assert any("running_mean" in k for k in moved) and any("running_var" in k for k in moved)


def test_no_update_is_scheduled_until_the_replay_holds_min_replay_transitions():
    lrn = learner(learner_config(min_replay=3, updates_per_action=2))
    for i in range(2):
        lrn.replay.add(Transition(block_scene(i), Action("grasp", 12, 12, i), 1.0, None, True))
        lrn.notify_new_transition()
        assert lrn.pending == 0
    assert lrn.update_pending() == [] and lrn.updates == 0
    lrn.replay.add(Transition(block_scene(2), Action("grasp", 12, 12, 2), 0.0, None, True))
    lrn.notify_new_transition()
    assert lrn.pending == 2
    assert [s.update for s in lrn.update_pending()] == [1, 2]   # the two skipped actions are not made up


def test_twin_grasps_targets_take_a_prime_and_its_value_from_twin_means():
    cfg = learner_config(gamma=0.5)
    cfg = dataclasses.replace(cfg, exploration=dataclasses.replace(cfg.exploration, twin_grasps=True,
                                                                   grasp_only=True))
    lrn = learner(cfg)
    lrn.target.load_state_dict(build_network("fast", 16, seed=5).state_dict())
    s2 = block_scene(4)
    t = Transition(block_scene(3), Action("grasp", 5, 5, 0), 0.25, s2, False)
    gmask, mmask = Agent(cfg, lrn.online).masks(s2.height)
    lrn.online.eval()
    with torch.no_grad():
        online = q_maps(lrn.online, s2).numpy()
        target = q_maps(lrn.target, s2).numpy()
    lrn.online.train()
    rot, ch, row, col = greedy_index(twin_grasp_maps(online), gmask, mmask, grasp_only=True)
    assert ch == 0
    expected = 0.25 + 0.5 * (target[rot, 0, row, col] + target[(rot + 8) % 16, 0, row, col]) / 2
    assert lrn.targets([t])[0] == pytest.approx(expected, abs=1e-5)
    # and that is not what the plain rule gives (the twins' values differ)
    assert target[rot, 0, row, col] != pytest.approx(target[(rot + 8) % 16, 0, row, col], abs=1e-4)


class _RecordingMailbox(WeightsMailbox):
    """Notes the learner's backlog at each hand-over."""

    def __init__(self, learner_ref: list) -> None:
        super().__init__()
        self.learner_ref = learner_ref
        self.backlogs: list[int] = []

    def post(self, state_dict, version=None) -> None:
        self.backlogs.append(self.learner_ref[0].pending)
        super().post(state_dict, version)


def test_weights_are_handed_over_on_schedule_while_the_learner_has_a_backlog():
    cfg = learner_config(updates_per_action=3)
    cfg = dataclasses.replace(cfg, gate=dataclasses.replace(cfg.gate, handover_every=2))
    replay = PrioritizedReplay.from_config(cfg.learning)
    ref: list = []
    mailbox = _RecordingMailbox(ref)
    lrn = Learner(cfg, build_network("fast", 16, seed=0), replay, mailbox=mailbox)
    ref.append(lrn)
    for k in range(4):  # 12 updates owed before the thread runs one: a cell that outruns its learner
        replay.add(Transition(block_scene(k), Action("grasp", 5, 5, 0), 1.0, block_scene(k + 1), False))
        lrn.notify_new_transition()
    lrn.start()
    try:
        assert lrn.wait_idle(timeout=300)
    finally:
        lrn.stop(timeout=60)
    assert lrn.updates == 12 and lrn.handovers == 6
    assert mailbox.backlogs[:5] == [10, 8, 6, 4, 2]  # handed over with updates still owed
    assert mailbox.take()[1] == 12


def test_wait_idle_returns_when_the_thread_has_left_even_with_updates_scheduled_after():
    cfg = learner_config(updates_per_action=1)
    replay = PrioritizedReplay.from_config(cfg.learning)
    replay.add(Transition(block_scene(0), Action("grasp", 5, 5, 0), 1.0, block_scene(1), False))
    lrn = Learner(cfg, build_network("fast", 16, seed=0), replay)
    lrn.start()
    lrn.stop(timeout=60, why="test")
    lrn.notify_new_transition()  # a cycle that schedules an update after the stop
    assert lrn.pending == 1 and not lrn.running and lrn.stopped_why == "test"
    assert lrn.wait_idle(timeout=20)  # nothing would ever run it: waiting would hang the caller


def test_paused_holds_the_thread_between_updates_and_it_resumes_after():
    cfg = learner_config(updates_per_action=1)
    replay = PrioritizedReplay.from_config(cfg.learning)
    replay.add(Transition(block_scene(0), Action("grasp", 5, 5, 0), 1.0, block_scene(1), False))
    lrn = Learner(cfg, build_network("fast", 16, seed=0), replay)
    lrn.start()
    try:
        with lrn.paused(timeout=60):
            lrn.notify_new_transition()
            lrn.notify_new_transition()
            time.sleep(0.5)
            assert lrn.updates == 0  # held
            assert lrn.drop_backlog() >= 1
        lrn.notify_new_transition()
        assert lrn.wait_idle(timeout=120)
        assert lrn.running and lrn.updates >= 1  # the same thread carries on
    finally:
        lrn.stop(timeout=60)


def _distance(net: torch.nn.Module, ref: torch.nn.Module) -> float:
    theirs = dict(ref.named_parameters())
    return float(sum(((p.detach() - theirs[k].detach()) ** 2).sum() for k, p in net.named_parameters()))


def _anchored_run(anchor_weight: float) -> tuple[Learner, list]:
    cfg = learner_config(learning_rate=1e-3, seed=3, anchor_weight=anchor_weight)
    replay = PrioritizedReplay.from_config(cfg.learning)
    for i in range(6):
        replay.add(Transition(block_scene(i), Action("grasp", 8 + i, 12, i), float(i % 2), block_scene(i + 1), False))
    lrn = Learner(cfg, build_network("fast", 16, seed=3), replay)
    return lrn, [lrn.update() for _ in range(8)]


def test_the_anchor_weight_holds_the_trained_weights_near_the_weights_they_started_from():
    start = build_network("fast", 16, seed=3)
    free, free_stats = _anchored_run(0.0)
    held, held_stats = _anchored_run(50.0)
    assert all(s.anchor_penalty == 0.0 for s in free_stats)
    assert held_stats[0].anchor_penalty == 0.0 < held_stats[-1].anchor_penalty  # it grows as the weights move
    assert held_stats[-1].loss >= held_stats[-1].anchor_penalty  # and it is part of the loss that was minimised
    assert 0.0 < _distance(held.online, start) < 0.5 * _distance(free.online, start)


def test_set_anchor_moves_the_pull_to_other_weights_and_refuses_a_network_that_does_not_fit():
    lrn, _ = _anchored_run(50.0)
    before = float(lrn.anchor_penalty().detach())
    other = build_network("fast", 16, seed=11)
    lrn.set_anchor(other)
    assert float(lrn.anchor_penalty().detach()) == pytest.approx(50.0 * _distance(lrn.online, other), rel=1e-5)
    assert float(lrn.anchor_penalty().detach()) > 10 * before
    with pytest.raises(ValueError, match="anchor network"):
        lrn.set_anchor(torch.nn.Linear(2, 2))
    assert float(lrn.anchor_penalty().detach()) == pytest.approx(50.0 * _distance(lrn.online, other), rel=1e-5)


def _prior_of(transitions: list[Transition]):
    from flgd.learning.prior_sample import PriorSample

    return PriorSample("prior.npz", tuple(transitions), {})


def _q_at(lrn: Learner, state: Heightmaps, action: Action) -> float:
    with torch.no_grad():
        q = q_maps(lrn.online.eval(), state, lrn.rotations).cpu().numpy()
    lrn._training_mode()
    return float(q[action.rotation, action.channel, action.row, action.col])


def test_a_prior_share_trains_on_the_prior_sample_beside_the_replay_and_sets_no_priority_for_it():
    cfg = learner_config(batch_size=4, gamma=0.0, learning_rate=1e-3, mirror_probability=0.0)
    own = Transition(block_scene(1), Action("grasp", 9, 20, 3), 0.0, None, True)
    old = Transition(block_scene(2), Action("grasp", 14, 11, 5), 1.0, None, True)

    def run(prior_share: float) -> tuple[Learner, list]:
        replay = PrioritizedReplay.from_config(cfg.learning)
        replay.add(own, tag=7)
        lrn = learner(cfg, replay, prior=_prior_of([old]) if prior_share else None, prior_share=prior_share)
        stats = [lrn.update() for _ in range(30)]
        return lrn, stats

    before = _q_at(learner(cfg), old.state, old.action)
    with_prior, stats = run(0.5)
    without, _ = run(0.0)
    # two of each batch of 4 come from the prior sample; only the replay's two slots are prioritised
    assert {s.prior_transitions for s in stats} == {2}
    assert all(len(s.indices) == 2 and len(s.td_errors) == 2 for s in stats)
    # the prior's reward of 1 is learned at its pixel; without the sample nothing pulls it there
    assert abs(_q_at(with_prior, old.state, old.action) - 1.0) < 0.5 * abs(before - 1.0)
    assert abs(_q_at(without, old.state, old.action) - 1.0) > 0.8 * abs(before - 1.0)


def test_a_fractional_prior_share_holds_on_average_and_one_replayed_transition_always_stays():
    cfg = learner_config(batch_size=4)
    prior = _prior_of([Transition(block_scene(2), Action("grasp", 14, 11, 5), 1.0, None, True)])
    lrn = learner(cfg, prior=prior, prior_share=0.3)
    counts = [lrn._prior_count(4) for _ in range(4000)]
    assert set(counts) == {1, 2}
    assert abs(np.mean(counts) - 1.2) < 0.05
    assert learner(cfg, prior=prior, prior_share=0.9)._prior_count(4) == 3
    with pytest.raises(ValueError, match="needs a prior sample"):
        learner(cfg, prior_share=0.25)


# --------------------------------------------------------------------------- the learner's NaN guard

N = 32


def scene(seed: int) -> Heightmaps:
    rng = np.random.default_rng(seed)
    h = np.zeros((N, N), np.float32)
    r, c = rng.integers(2, N - 8, 2)
    h[r:r + 6, c:c + 6] = 0.03
    color = np.full((N, N, 3), 90, np.uint8)
    return Heightmaps(color, h)


def make_learner(calls: list) -> Learner:
    cfg = CellConfig()
    cfg = dataclasses.replace(cfg, learning=dataclasses.replace(cfg.learning, batch_size=2, device="cpu",
                                                                checkpoint_every=1))
    replay = PrioritizedReplay.from_config(cfg.learning)
    for i in range(3):
        replay.add(Transition(scene(i), Action("grasp", 10, 12, i), 1.0, scene(i + 1), False))
    return Learner(cfg, build_network("fast", 16, seed=0).eval(), replay, checkpoint_callback=lambda net, n: calls.append(n))


class _InfGrad(torch.autograd.Function):
    """Identity forward, infinite gradient backward: a finite loss whose step would still wreck the weights."""

    @staticmethod
    def forward(ctx, x):
        return x.clone()

    @staticmethod
    def backward(ctx, grad):
        return grad * float("inf")


@pytest.mark.parametrize("poison", ["nan_loss", "inf_gradient"])
def test_a_non_finite_update_is_skipped_counted_and_reported_and_nothing_is_checkpointed(poison):
    calls: list[int] = []
    lrn = make_learner(calls)
    real = lrn.loss_terms

    def diverging(transitions, weights):
        terms = real(transitions, weights)
        terms.loss = terms.loss * float("nan") if poison == "nan_loss" else _InfGrad.apply(terms.loss)
        return terms

    before = {k: v.clone() for k, v in lrn.online.state_dict().items()}
    priorities = [lrn.replay.priority(i) for i in range(3)]
    lrn.loss_terms = diverging
    assert lrn.update() is None
    after = lrn.online.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before), "a non-finite update changed the weights"
    assert lrn.optimizer.state == {} and lrn.updates == 0 and calls == []
    assert [lrn.replay.priority(i) for i in range(3)] == priorities
    assert lrn.skipped_updates == 1 and "update 1 skipped" in lrn.last_error
    assert ("loss is nan" if poison == "nan_loss" else "gradient of") in lrn.last_error, lrn.last_error
    # learning goes on once the updates are finite again
    lrn.loss_terms = real
    stats = lrn.update()
    assert stats is not None and lrn.updates == 1 and calls == [1] and lrn.skipped_updates == 1
    assert all(torch.isfinite(v).all() for v in lrn.online.state_dict().values() if v.is_floating_point())


def test_the_background_learner_reports_skipped_updates_through_last_error():
    calls: list[int] = []
    lrn = make_learner(calls)
    real = lrn.loss_terms

    def nan_loss(transitions, weights):
        terms = real(transitions, weights)
        terms.loss = terms.loss * float("nan")
        return terms

    lrn.loss_terms = nan_loss
    lrn.start()
    try:
        lrn.notify_new_transition()
        assert lrn.wait_idle(120)
    finally:
        lrn.stop(30)
    assert lrn.skipped_updates >= 1 and lrn.failed_updates == 0 and lrn.updates == 0
    assert lrn.last_error and "skipped" in lrn.last_error
