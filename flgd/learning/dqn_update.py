"""One update of the learner: dueling double DQN on prioritized replay, with no thread of its own.

``DQNUpdate`` holds what an update changes (the online and target networks, Adam,
the anchor, the cached a') and makes one update at a time; ``flgd.learning.learner``
schedules its updates (a background thread or synchronous runs) and hands the
weights over.

One update (``update``):

* sample ``batch_size`` transitions with importance weights w from the replay;
* target y = r + gamma * Q_target(s', a') * (1 - done), where a' is the argmax
  of the *online* network over all rotations of s' under the masks of s' (the
  same masks the agent acts with; none for the DPEN ablation; no moves in
  grasp-only mode) and only a'`s rotation is forwarded through the target
  network (double DQN), one batch for the whole sample; with
  ``exploration.twin_grasps`` both use the mean of a grasp's two twin
  rotations, as the agent does;
* prediction: only the executed rotation i is forwarded through the online
  network, plus its twin (i + R/2) % R for a grasp, since the two-finger
  gripper closing along u or -u is the same grasp; both are trained towards y
  (with ``grasp_twins: one``, one of the two drawn at random);
  Q is read at the one trained pixel (``q_at_pixels``: the same value as the
  full Q-maps', without resizing and rotating them back);
* loss: Huber (delta = huber_delta) at the executed channel and pixel only,
  averaged over the transition's rotations, weighted by w, averaged over the
  batch; Adam with the configured learning rate and weight decay;
* priorities of the batch become |y - Q(s, a)| + epsilon (and are written back
  to the store through ``priority_sink``, so a restart keeps them);
* the target network copies the online one every ``target_update_every`` updates;
* with ``batchnorm: frozen`` the BatchNorm layers stay in eval mode during
  updates: they normalise with the loaded network's running statistics and
  never move them (their scale and shift still learn).  With the default
  ``batch`` each update normalises its own batch of 4-8 rotated images and
  moves the running statistics 10 % towards them, and those statistics are
  what the agent acts with: in a fine-tune they drift far faster than the
  weights (frozen statistics stopped the fine-tune's flood of moves, BENCHMARKS.md);
* an update whose loss, TD errors or gradients are not finite (NaN/Inf) is
  skipped before the optimizer step: the weights, BatchNorm statistics, Adam
  moments and priorities stay as they were, ``skipped_updates`` counts it and
  ``last_error`` says why (the daemon shows it in ``flgctl status``), so a
  diverging network is neither published to the agent nor checkpointed;
* with ``mirror_probability`` p > 0 each sampled transition is trained, with
  chance p, as its mirror image (``flgd.learning.augment``; same target);
* with ``anchor_weight`` a > 0 (L2-SP, Li et al. 2018) the loss adds
  a * sum((theta - theta_anchor)^2) over the trainable weights, where the anchor is
  the acting champion's weights (``set_anchor``: the gate calls it whenever the
  champion changes; until then the network the learner was built on).  Why the
  champion and not the first policy: it is the weights that proved themselves on
  this cell, and a restart restores it from the gate's records, so the anchor
  survives a power cut without any state of its own;
* with a ``prior`` sample and ``prior_share`` s > 0 (``finetune.prior_sample``,
  ``finetune.prior_share``), s * batch_size of each batch's transitions (the
  fraction rounded at random, so that the share holds on average; at least one
  transition always comes from the replay) are drawn uniformly from the sample of
  the cell the policy was trained in (``flgd.learning.prior_sample``).  They take
  the mean importance weight of the batch's replayed ones, and their TD errors set
  no priorities: only the replay's own transitions are prioritised.

Finding a' costs a forward pass over all 16 rotations of s', four times the
rest of an update on a CPU.  With ``next_argmax_max_age`` > 0 the learner
keeps a' per next state (by the replay's content key) and reuses it while it
is at most that many updates old; the agent's own decisions feed the cache
(``note_decision``: when it acted on s' it computed the same masked argmax
with the then-current weights), so most targets need no extra pass.  The
target network's value at a' is kept until the next target sync.  0 keeps the
exact double-DQN target (recomputed at every sampling).  With ``actor_argmax``
an a' never ages (as Ape-X's actors, the cell's decision on s' picks it): as
the replay grows, an age limit turns most targets into full passes again (hits
fell from 88 % to 45 % over 2,500 steps); the value Q_target(s', a') is still
the target network's of today, only the choice of a' is older.

The weights change only under ``_update_lock``, so a copy (``snapshot``) or a swap
(``replace_weights``) from another thread never sees half an update.
"""

from __future__ import annotations

import copy
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from flgd.clutter import cell_action_masks
from flgd.actions import Action
from flgd.config import CellConfig, ConfigError
from flgd.perception import Heightmaps

from flgd.learning.augment import mirror_action, mirror_heightmaps
from flgd.learning.agent import Decision, greedy_index
from flgd.learning.networks import QMapNetwork, q_at_pixels, q_maps, rotated_inputs, twin_grasp_maps
from flgd.learning.prior_sample import PriorSample
from flgd.learning.replay import PrioritizedReplay, Transition, state_key

__all__ = ["DQNUpdate", "UpdateStats", "LossTerms", "resolve_device"]

log = logging.getLogger("flgd.learning.learner")  # the learner's messages keep the logger they always had

CheckpointCallback = Callable[[QMapNetwork, int], None]
PrioritySink = Callable[[list[tuple[int, float]]], None]  # (store transition id, raw priority) pairs


@dataclass(frozen=True)
class UpdateStats:
    update: int  # number of this update (1-based)
    loss: float
    mean_abs_td: float
    batch_size: int
    beta: float
    seconds: float
    indices: tuple[int, ...] = ()  # replay slots of the batch
    td_errors: tuple[float, ...] = ()  # y - Q(s, a) per slot, before the step
    anchor_penalty: float = 0.0  # the L2-SP term included in ``loss`` (0 with ``anchor_weight`` 0)
    prior_transitions: int = 0  # of ``batch_size``, drawn from the prior sample (after the replayed ones)


@dataclass
class LossTerms:
    """Everything one loss evaluation produced (exposed so tests can inspect the gradient path)."""

    loss: torch.Tensor
    td_errors: np.ndarray  # per transition, y - Q(s, a) at the executed rotation
    targets: np.ndarray  # y per transition
    predicted: torch.Tensor  # [N] Q(s, a) of each forwarded rotation at the trained channel and pixel
    owners: list[int]  # transition index of each row of predicted
    rotations: list[int]  # rotation index of each row of predicted
    actions: list[Action]  # the action trained per transition (mirrored when the transition was)


def resolve_device(device: str | torch.device | None, source: str = "<config>") -> torch.device:
    """The torch device for ``learning.device``; ConfigError (naming ``source``) for a device this machine lacks.

    ConfigError, not a bare ValueError, so that ``flgd run`` reports it as a config problem and exits 1
    instead of a traceback (``load_config`` normally catches it first).
    """
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(device)
    except (RuntimeError, TypeError, ValueError) as exc:
        raise ConfigError(source, [f"learning.device: got {str(device)!r}, expected one of 'cpu', 'cuda', 'auto' "
                                   f"({exc})"]) from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(source, [f"learning.device: got {str(device)!r}, but torch finds no CUDA device on this "
                                   "machine (CPU-only torch build, or no usable NVIDIA driver); expected 'cpu' or "
                                   "'auto'"])
    return device



class DQNUpdate:
    """The learner's networks and optimizer, and one update on a prioritized batch (see the module docstring)."""

    def __init__(self, config: CellConfig, network: QMapNetwork, replay: PrioritizedReplay,
                 device: str | torch.device | None = None, checkpoint_callback: CheckpointCallback | None = None,
                 priority_sink: PrioritySink | None = None, prior: PriorSample | None = None,
                 prior_share: float = 0.0, updates: int = 0) -> None:
        lc = config.learning
        if updates < 0:
            raise ValueError(f"updates: got {updates!r}, expected the update count to go on from (>= 0)")
        if not 0.0 <= prior_share < 1.0:
            raise ValueError(f"prior_share: got {prior_share!r}, expected 0 <= share < 1")
        if prior_share > 0.0 and prior is None:
            raise ValueError(f"prior_share {prior_share!r} needs a prior sample")
        if lc.threads > 0:
            torch.set_num_threads(lc.threads)
        self.config = config
        self.replay = replay
        self.device = resolve_device(device if device is not None else lc.device, config.source)
        self.rotations = network.rotations
        self.online = copy.deepcopy(network).to(self.device)
        self._training_mode()
        self.target = copy.deepcopy(network).to(self.device).eval()
        for p in self.target.parameters():
            p.requires_grad_(False)
        self.optimizer = torch.optim.Adam(self.online.parameters(), lr=lc.learning_rate,
                                          weight_decay=lc.weight_decay)
        self._mirror_rng = np.random.default_rng([lc.seed, 0x6D69])  # its own stream: other draws unchanged
        self._twin_rng = np.random.default_rng([lc.seed, 0x7477])  # which twin a grasp trains (grasp_twins "one")
        self.prior = prior if prior_share > 0.0 else None
        self.prior_share = prior_share if prior is not None else 0.0
        self._prior_rng = np.random.default_rng([lc.seed, 0x7072])  # its own stream, like mirroring's
        self.prior_drawn = 0  # transitions drawn from the prior sample into updates so far
        self.checkpoint_callback = checkpoint_callback
        self.priority_sink = priority_sink
        self.updates = int(updates)  # a resumed learner counts on from its checkpoint's update
        self.skipped_updates = 0  # updates not applied because the loss, TD errors or gradients were not finite
        self.last_error: str | None = None
        self.last_stats: UpdateStats | None = None
        self._update_lock = threading.RLock()  # re-entered by the learner's load_weights inside paused
        # next-state key -> (update count when a' was found, a' or None); and -> (a', Q_target(s', a'))
        self._argmax_lock = threading.Lock()
        self._next_argmax: dict[bytes, tuple[int, tuple[int, int, int, int] | None]] = {}
        self._next_value: dict[bytes, tuple[tuple[int, int, int, int], float]] = {}
        self.argmax_reused = 0
        self.argmax_computed = 0
        self._anchor: dict[str, torch.Tensor] = {}
        self.set_anchor(network)

    @property
    def network(self) -> QMapNetwork:
        """The online (trained) network; read it only from the learner thread or via ``snapshot``."""
        return self.online

    def _training_mode(self) -> None:
        """Online network in training mode; its BatchNorm layers in eval mode when ``batchnorm`` is frozen."""
        self.online.train()
        if self.config.learning.batchnorm == "frozen":
            for m in self.online.modules():
                if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                    m.eval()

    def _masks(self, height: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return cell_action_masks(height, self.config, self.rotations)

    def _argmax_age_ok(self, found_at: int) -> bool:
        """Whether an a' found with the weights of update ``found_at`` may serve as the target's argmax now."""
        lc = self.config.learning
        if found_at < 0 or found_at > self.updates:
            return False  # unknown, or of a line of weights ahead of this learner's (resumed from older)
        return lc.actor_argmax or self.updates - found_at <= lc.next_argmax_max_age

    def _caching(self) -> bool:
        lc = self.config.learning
        return lc.actor_argmax or lc.next_argmax_max_age > 0

    def note_decision(self, state: Heightmaps, decision: Decision, weights_version: int) -> None:
        """Remember the greedy a' the agent found on ``state`` with weights ``weights_version`` (an update count).

        Used when ``next_argmax_max_age`` > 0 or ``actor_argmax`` is on; the decision's Q-maps and
        masks are the ones the learner would compute for ``state`` as s'.
        """
        if not self._caching() or not self._argmax_age_ok(weights_version):
            return
        index = decision.greedy
        if index is None:   # a Decision built without it (older callers): the same argmax, computed here
            index = greedy_index(decision.q_maps, decision.grasp_mask, decision.move_mask,
                                 self.config.exploration.grasp_only)
        self.note_greedy(state_key(state), weights_version, index)

    def note_greedy(self, key: bytes, weights_version: int, index: tuple[int, int, int, int] | None) -> None:
        """``note_decision`` for a decision made elsewhere (a worker of ``flgd train --workers``): the state's
        replay key (``state_key``), the update count of the weights that decided, and their greedy a'."""
        if not self._caching() or not self._argmax_age_ok(weights_version):
            return
        with self._argmax_lock:
            self._next_argmax[key] = (int(weights_version), None if index is None else
                                      (int(index[0]), int(index[1]), int(index[2]), int(index[3])))

    def remembered_argmax(self) -> list[tuple[bytes, int, tuple[int, int, int, int] | None]]:
        """Every remembered a' as (state key, update count of the weights that found it, index or None): what a
        trainer state keeps, so that a resumed learner does not search the next states again."""
        with self._argmax_lock:
            return [(key, version, index) for key, (version, index) in self._next_argmax.items()]

    def remember_argmax(self, entries: Sequence[tuple[bytes, int, tuple[int, int, int, int] | None]]) -> int:
        """Take back a' saved by ``remembered_argmax`` (entries found with weights newer than this learner's are
        never used, as in ``note_greedy``); how many were taken."""
        taken = 0
        for key, version, index in entries:
            if self._caching() and self._argmax_age_ok(int(version)):
                self.note_greedy(bytes(key), int(version), index)
                taken += 1
        return taken

    def _greedy_next(self, t: Transition) -> tuple[int, int, int, int] | None:
        """a' for ``t.next_state``: from the cache while fresh enough, else from the online network."""
        caching = self._caching()
        key = t.next_key
        if caching and key is not None:
            with self._argmax_lock:
                hit = self._next_argmax.get(key)
            if hit is not None and self._argmax_age_ok(hit[0]):
                self.argmax_reused += 1
                return hit[1]
        assert t.next_state is not None, "a' is searched only for a transition with a next state"
        height = np.nan_to_num(np.asarray(t.next_state.height, dtype=np.float32), nan=0.0)
        gmask, mmask = self._masks(height)
        q_next = q_maps(self.online, t.next_state, self.rotations).cpu().numpy()
        if self.config.exploration.twin_grasps:
            q_next = twin_grasp_maps(q_next)  # a' as the agent would choose it
        index = greedy_index(q_next, gmask, mmask, self.config.exploration.grasp_only)
        self.argmax_computed += 1
        if caching and key is not None:
            with self._argmax_lock:
                self._next_argmax[key] = (self.updates, index)
                if len(self._next_argmax) > 2 * self.config.learning.replay_capacity:
                    self._forget_old_argmax()
        return index

    def _forget_old_argmax(self) -> None:
        """Drop entries too old to be used, or with ``actor_argmax`` the oldest half (states that left the
        replay end up here; one still replayed then has its a' found again)."""
        if self.config.learning.actor_argmax:
            newest = sorted(self._next_argmax.items(), key=lambda kv: kv[1][0])
            self._next_argmax = dict(newest[len(newest) // 2:])
        else:
            self._next_argmax = {k: v for k, v in self._next_argmax.items() if self._argmax_age_ok(v[0])}
        self._next_value = {k: v for k, v in self._next_value.items() if k in self._next_argmax}

    def _target_values(self, wanted: list[tuple[Transition, tuple[int, int, int, int]]]) -> list[float]:
        """Q_target(s', a') for each (transition, a'), from the value cache or one batched target-network pass
        (in eval mode each input is independent of the others, so batching changes no value)."""
        values: list[float | None] = [None] * len(wanted)
        twins = self.config.exploration.twin_grasps and self.rotations % 2 == 0
        misses: dict[tuple[int, int], list[int]] = {}
        for k, (t, index) in enumerate(wanted):
            cached = self._next_value.get(t.next_key) if t.next_key is not None else None
            if cached is not None and cached[0] == index:
                values[k] = cached[1]
            else:
                assert t.next_state is not None, "a target value is read only for a transition with a next state"
                misses.setdefault(tuple(np.asarray(t.next_state.height).shape), []).append(k)
        for (h_px, w_px), ks in misses.items():
            colors, heights, rots, owners = [], [], [], []
            for k in ks:
                rot = wanted[k][1][0]
                these = [rot, (rot + self.rotations // 2) % self.rotations] if wanted[k][1][1] == 0 and twins else [rot]
                next_state = wanted[k][0].next_state
                assert next_state is not None  # listed as a miss above only with one
                c, h = rotated_inputs(next_state, these, self.rotations, self.target.stride, self.device)
                colors.append(c)
                heights.append(h)
                rots += these
                owners += [k] * len(these)
            q = q_at_pixels(self.target, torch.cat(colors), torch.cat(heights), rots,
                            [wanted[k][1][1] for k in owners], [wanted[k][1][2] for k in owners],
                            [wanted[k][1][3] for k in owners], h_px, w_px).cpu().numpy()
            for k in ks:
                value = float(np.mean([q[i] for i, o in enumerate(owners) if o == k]))
                values[k] = value
                t, index = wanted[k]
                if t.next_key is not None and self._caching():
                    self._next_value[t.next_key] = (index, value)
        found = [v for v in values if v is not None]
        assert len(found) == len(wanted), "every wanted value was cached or computed"
        return found

    @torch.no_grad()
    def targets(self, transitions: Sequence[Transition]) -> np.ndarray:
        """y = r + gamma * Q_target(s', argmax_a' online(s')) * (1 - done) for each transition."""
        gamma = self.config.learning.gamma
        ys = np.array([t.reward for t in transitions], dtype=np.float64)
        was_training = self.online.training
        self.online.eval()
        try:
            wanted: list[tuple[Transition, tuple[int, int, int, int]]] = []
            rows: list[int] = []
            for k, t in enumerate(transitions):
                if t.done or t.next_state is None or gamma == 0.0:
                    continue
                index = self._greedy_next(t)
                if index is None:
                    continue  # nothing left to act on in s': no future value
                wanted.append((t, index))
                rows.append(k)
            for k, value in zip(rows, self._target_values(wanted)):
                ys[k] += gamma * value
        finally:
            if was_training:
                self._training_mode()
        return ys

    def loss_terms(self, transitions: Sequence[Transition], weights: np.ndarray) -> LossTerms:
        """The weighted Huber loss at the executed pixels (see module doc), with its intermediate values."""
        ys = self.targets(transitions)
        p_mirror = self.config.learning.mirror_probability
        colors, heights, owners, rots, actions = [], [], [], [], []
        for k, t in enumerate(transitions):
            a = t.action
            if a.rotations != self.rotations:
                raise ValueError(f"transition {k}: action has {a.rotations} rotations, network {self.rotations}")
            rows_px, cols_px = np.asarray(t.state.height).shape
            if not (0 <= a.row < rows_px and 0 <= a.col < cols_px):
                raise ValueError(f"transition {k}: pixel ({a.row}, {a.col}) is outside the {rows_px}x{cols_px} "
                                 "heightmap")
            state = t.state
            if p_mirror > 0 and self._mirror_rng.random() < p_mirror:
                state, a = mirror_heightmaps(state), mirror_action(a, cols_px)
            actions.append(a)
            these = [a.rotation]
            if not a.is_move:
                twin = (a.rotation + self.rotations // 2) % self.rotations
                if self.config.learning.grasp_twins == "both":
                    these.append(twin)
                elif self._twin_rng.random() < 0.5:
                    these = [twin]
            c, h = rotated_inputs(state, these, self.rotations, self.online.stride, self.device)
            colors.append(c)
            heights.append(h)
            owners += [k] * len(these)
            rots += these
        shapes = {tuple(np.asarray(t.state.height).shape) for t in transitions}
        if len(shapes) != 1:
            raise ValueError(f"transitions in one batch have different heightmap sizes: {sorted(shapes)}")
        (h_px, w_px), = shapes
        predicted = q_at_pixels(self.online, torch.cat(colors), torch.cat(heights), rots,
                                [actions[k].channel for k in owners], [actions[k].row for k in owners],
                                [actions[k].col for k in owners], h_px, w_px)
        y = torch.tensor(ys[owners], dtype=predicted.dtype, device=self.device)
        per_row = F.huber_loss(predicted, y, reduction="none", delta=self.config.learning.huber_delta)
        owner_t = torch.tensor(owners, device=self.device)
        per_transition = torch.zeros(len(transitions), dtype=per_row.dtype, device=self.device)
        per_transition = per_transition.index_add(0, owner_t, per_row)
        counts = torch.bincount(owner_t, minlength=len(transitions)).to(per_row.dtype)
        w = torch.as_tensor(np.asarray(weights, dtype=np.float32), device=self.device)
        loss = (w * per_transition / counts).mean()
        first = [owners.index(k) for k in range(len(transitions))]  # the executed rotation's row (or its twin's)
        td = (y[first] - predicted[first]).detach().cpu().numpy().astype(np.float64)
        return LossTerms(loss=loss, td_errors=td, targets=ys, predicted=predicted, owners=owners, rotations=rots,
                         actions=actions)

    def set_anchor(self, network: QMapNetwork) -> None:
        """Pull the trained weights toward ``network``'s from the next update on (``anchor_weight``).

        Safe from any thread: the copy is made here and swapped in whole, so an update in progress keeps the
        anchor it started with.  A network whose parameters do not match the learner's raises ValueError.
        """
        mine = dict(self.online.named_parameters())
        theirs = dict(network.named_parameters())
        if set(theirs) != set(mine) or any(theirs[k].shape != mine[k].shape for k in mine):
            raise ValueError("anchor network: its parameters do not match the learner's network")
        if self.config.learning.anchor_weight > 0.0:  # off: no copy of the weights kept
            self._anchor = {k: v.detach().to(self.device, copy=True) for k, v in theirs.items()}

    def anchor_penalty(self) -> torch.Tensor | None:
        """anchor_weight * sum((theta - anchor)^2) over the trainable weights; None when off."""
        a = self.config.learning.anchor_weight
        anchor = self._anchor
        if a <= 0.0 or not anchor:
            return None
        total = torch.stack([((p - anchor[k]) ** 2).sum() for k, p in self.online.named_parameters()
                             if p.requires_grad]).sum()
        return a * total

    def _prior_count(self, batch_size: int) -> int:
        """How many of this batch come from the prior sample: share * size, its fraction rounded at random."""
        if self.prior is None or batch_size < 2:
            return 0
        expected = self.prior_share * batch_size
        count = int(expected) + int(self._prior_rng.random() < expected - int(expected))
        return min(count, batch_size - 1)

    def _not_finite(self, terms: LossTerms) -> str | None:
        """Why this update must not be applied (loss, TD errors or a gradient not finite), else None."""
        loss = float(terms.loss.detach())
        if not math.isfinite(loss):
            return f"loss is {loss}"
        if not np.all(np.isfinite(terms.td_errors)):
            return "a TD error is not finite"
        for name, p in self.online.named_parameters():
            if p.grad is not None and not bool(torch.isfinite(p.grad).all()):
                return f"the gradient of {name} is not finite (loss {loss:.6g})"
        return None

    def update(self) -> UpdateStats | None:
        """One gradient step on a prioritized batch; None while the replay is empty or when the update was
        skipped because it was not finite (see the module docstring)."""
        if len(self.replay) == 0:
            return None
        with self._update_lock:
            start = time.perf_counter()
            beta = self.replay.beta
            size = self.config.learning.batch_size
            from_prior = self._prior_count(size)
            indices, transitions, weights = self.replay.sample(size - from_prior)
            if from_prior:
                assert self.prior is not None, "_prior_count draws from a prior sample only when there is one"
                transitions = transitions + self.prior.draw(from_prior, self._prior_rng)
                self.prior_drawn += from_prior
                weights = np.concatenate([weights, np.full(from_prior, weights.mean(), dtype=np.float32)])
            # the training-mode forward moves BatchNorm's running statistics: kept to undo a skipped update
            buffers = {name: b.detach().clone() for name, b in self.online.named_buffers()}
            terms = self.loss_terms(transitions, weights)
            penalty = self.anchor_penalty()
            if penalty is not None:
                terms.loss = terms.loss + penalty
            self.optimizer.zero_grad(set_to_none=True)
            terms.loss.backward()  # type: ignore[no-untyped-call]  # torch leaves Tensor.backward unannotated
            why = self._not_finite(terms)
            if why is not None:
                # Applying it would turn the weights into NaN for good (and the next checkpoint with them).
                self.optimizer.zero_grad(set_to_none=True)
                with torch.no_grad():
                    for name, b in self.online.named_buffers():
                        b.copy_(buffers[name])
                self.skipped_updates += 1
                self.last_error = (f"update {self.updates + 1} skipped: {why} (weights unchanged; "
                                   f"{self.skipped_updates} non-finite updates skipped so far)")
                log.warning("learner: %s", self.last_error)
                return None
            self.optimizer.step()
            tagged = self.replay.update_priorities(indices, np.abs(terms.td_errors[:len(indices)]))
            if self.priority_sink is not None and tagged:
                try:
                    self.priority_sink(tagged)
                except Exception as exc:  # a full disk must not stop learning; the priorities are a hint
                    log.exception("writing replay priorities failed at update %d", self.updates + 1)
                    self.last_error = f"saving priorities at update {self.updates + 1}: {exc}"
            self.updates += 1
            if self.updates % self.config.learning.target_update_every == 0:
                self.target.load_state_dict(self.online.state_dict())
                self._next_value.clear()
            stats = UpdateStats(update=self.updates, loss=float(terms.loss.detach()),
                                mean_abs_td=float(np.mean(np.abs(terms.td_errors))),
                                batch_size=len(transitions), beta=beta, seconds=time.perf_counter() - start,
                                indices=tuple(int(i) for i in indices),
                                td_errors=tuple(float(v) for v in terms.td_errors[:len(indices)]),
                                anchor_penalty=0.0 if penalty is None else float(penalty.detach()),
                                prior_transitions=from_prior)
            self.last_stats = stats
            if self.checkpoint_callback is not None and self.updates % self.config.learning.checkpoint_every == 0:
                try:
                    self.checkpoint_callback(self.online, self.updates)
                except Exception as exc:  # a failed checkpoint must not stop learning
                    log.exception("checkpoint callback failed at update %d", self.updates)
                    self.last_error = f"checkpoint at update {self.updates}: {exc}"
        return stats

    def snapshot(self) -> QMapNetwork:
        """A consistent copy of the online network (safe from any thread), e.g. to save a policy."""
        with self._update_lock:
            net = copy.deepcopy(self.online)
        return net.to("cpu").eval()

    def replace_weights(self, network: QMapNetwork) -> None:
        """Online and target weights become ``network``'s (a policy loaded at run time); the cached a' go."""
        with self._update_lock:
            self.online.load_state_dict(network.state_dict())
            self.target.load_state_dict(network.state_dict())
            with self._argmax_lock:
                self._next_argmax.clear()
            self._next_value.clear()

    def reset_trainer_state(self) -> None:
        """Target = online weights and fresh Adam moments: what a learner built on the network starts with."""
        with self._update_lock:
            self.target.load_state_dict(self.online.state_dict())
            self.optimizer.state.clear()
            self._next_value.clear()
