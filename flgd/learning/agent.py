"""The acting policy (paper III-D, IV-A): masked argmax over rho o Q plus FLG's exploration rules.

One decision, in this order:

1. ``two-failures``: after ``failed_grasps_trigger`` consecutive failed grasps
   the clutter is judged too dense and the action is the best move.
2. ``epsilon``: with probability epsilon (linear decay from epsilon_start to
   epsilon_end over epsilon_decay_steps) a random action: grasp or move with
   equal chance, then a rotation and a pixel drawn uniformly inside that
   primitive's mask.
3. ``greedy``: the best grasp and the best move under their masks; the higher
   Q wins (a tie goes to the grasp).
4. ``curriculum``: during the first ``curriculum_steps`` steps a chosen move
   (from rule 2 or 3) is kept only with probability
   ``curriculum_move_probability``; otherwise the best grasp is taken.
5. ``anti-repeat``: if a greedy choice (rule 1, 3 or 4) lands on the same
   primitive channel and pixel as the previous step, the action is drawn
   uniformly from the top ``top_m`` actions of that channel that are not at
   that pixel (the paper: "the action in the previous step will not be chosen";
   with the failure memory on, not within ``failure_radius`` of it).

Failure memory (``exploration.failure_memory``, flgd/learning/failure_memory.py):
the regions where a grasp failed or a move changed nothing in this scene are
-inf for rules 1, 3, 4 and 5, as the masks are, until the heightmap changes
there.  It is the escalation ladder's memory too:

* rung 1 -- after ``failed_grasps_trigger`` failed grasps, the best move (rule 1);
* rung 2 -- when rule 1 fires again before any grasp succeeded, the best move
  that starts near the newest failed grasp (``ladder-move``): a move that
  changes the region that keeps failing;
* rung 3 -- ``stuck_after`` actions without a successful grasp, or nothing left
  that is not suppressed: ``stuck_reason()`` says why, and the cycle declares the
  cell stuck instead of acting (flgd/cycle.py).

``Decision.greedy`` stays the masked argmax without the memory: it is the a' of
the learner's double-DQN target, and the memory is the episode's, not the
value function's.  ``exploration.failure_memory: false`` is the paper's rules
alone; the stuck count runs either way.

Masks are applied by setting Q to -inf outside them, not by the paper's literal
Hadamard product rho o Q: with a 0/1 mask a multiplication leaves 0 outside
the mask, and dueling Q-values are often negative inside it (Q = V + A -
mean(A) is centred), so the argmax would land on a masked-out pixel.  -inf
can never win and keeps ties inside the mask.

``exploration.masks = False`` is the DPEN ablation: both masks are all ones, less the geometric limits
(``exploration.grasp_in_view``, ``exploration.finger_clearance``), which hold in it too.
The returned ``Decision`` carries the masks that were applied.

Champion and challenger (flgd/gate/keeper.py): ``network`` is the champion; with a
``challenger`` set, each decision is made by the challenger with probability
``challenger_share`` (its own random stream, so the other draws are those of an
agent without one), and ``Decision.role`` / ``Decision.policy_id`` say which
network decided.  An epsilon-random action is credited to neither
(``policy_id`` None), nor is a move forced by the two-failures rule: the
streak behind it is shared by both networks' grasps.

Exploration of a trained policy continues where its training left it: epsilon is
taken at ``step + exploration_offset`` (the policy's recorded training steps) and
never above ``max_epsilon``.
"""

from __future__ import annotations

import copy
import dataclasses
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np
import torch

from flgd.actions import Action, Primitive, move_kind_at
from flgd.clutter import cell_action_masks, grasp_mask
from flgd.config import CellConfig
from flgd.perception import Heightmaps

from flgd.learning.failure_memory import FailureMemory
from flgd.learning.networks import QMapNetwork, q_maps, twin_grasp_maps

if TYPE_CHECKING:
    from flgd.config import ExplorationConfig

__all__ = ["Decision", "Agent", "OutcomeState", "WeightsMailbox", "RULES", "epsilon_at", "masked_maps", "greedy_index"]

RULES: tuple[str, ...] = ("greedy", "epsilon", "anti-repeat", "two-failures", "ladder-move", "curriculum")
# how far beyond the failed region a rung-2 move may start (m): close enough that its push reaches the region
LADDER_REACH = 0.02


@dataclass(frozen=True)
class Decision:
    action: Action
    q_maps: np.ndarray  # float32 [R,2,H,W], heightmap frame
    grasp_mask: np.ndarray  # uint8 [H,W], or [R,H,W] where a limit is per rotation (flgd.clutter), as applied
    move_mask: np.ndarray
    q_value: float  # Q of the chosen action
    rule: str
    epsilon: float
    greedy: tuple[int, int, int, int] | None = None  # (rotation, channel, row, col) of the masked argmax
    role: str = "champion"  # which network's Q-maps these are: champion or challenger
    policy_id: int | None = None  # the gate's id of the policy credited with the outcome; None for epsilon
    weights_version: int = -1  # learner update count of the deciding network's weights (-1 unknown)
    suppressed: np.ndarray | None = None  # uint8 [H,W]: where the failure memory forbade actions (None: off)


class WeightsMailbox:
    """A one-slot mailbox: the learner posts whole weight sets, the actor takes the newest.

    Posting replaces an unread set, so the actor never copies more than one set
    per decision and never waits for training.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._weights: dict[str, torch.Tensor] | None = None
        self._version = 0
        self.posted = 0

    def post(self, state_dict: dict[str, torch.Tensor], version: int | None = None) -> None:
        """Publish a detached copy of ``state_dict`` (the caller may keep training its network)."""
        weights = {k: v.detach().to("cpu", copy=True) for k, v in state_dict.items()}
        with self._lock:
            self._weights = weights
            self.posted += 1
            self._version = self.posted if version is None else version

    @property
    def waiting(self) -> bool:
        """A posted set is waiting to be taken."""
        with self._lock:
            return self._weights is not None

    def take(self) -> tuple[dict[str, torch.Tensor], int] | None:
        """The newest unread set and its version, or None."""
        with self._lock:
            weights, self._weights = self._weights, None
            return None if weights is None else (weights, self._version)


def epsilon_at(step: int, exploration: ExplorationConfig) -> float:
    """Linear decay from epsilon_start to epsilon_end over epsilon_decay_steps, then constant."""
    frac = min(1.0, max(0, step) / exploration.epsilon_decay_steps)
    return float(exploration.epsilon_start + (exploration.epsilon_end - exploration.epsilon_start) * frac)


def masked_maps(q: np.ndarray, grasp: np.ndarray, move: np.ndarray) -> np.ndarray:
    """Q [R,2,H,W] with -inf outside the grasp mask (channel 0) and the move mask (channel 1), each [H,W] or
    per rotation [R,H,W]."""
    out = np.array(q, dtype=np.float32, copy=True)
    out[:, 0][np.broadcast_to(grasp, out.shape[:1] + out.shape[2:]) == 0] = -np.inf   # [H,W] or per rotation
    out[:, 1][np.broadcast_to(move, out.shape[:1] + out.shape[2:]) == 0] = -np.inf
    return out


def greedy_index(q: np.ndarray, grasp: np.ndarray, move: np.ndarray,
                 grasp_only: bool = False) -> tuple[int, int, int, int] | None:
    """(rotation, channel, row, col) of the best action under the masks, or None when nothing is allowed.

    The value the policy would act on greedily (rule 3), and so the a' of a
    double-DQN target; ``grasp_only`` leaves moves out, as the agent does.
    """
    masked = masked_maps(q, grasp, move)
    if grasp_only:
        masked[:, 1] = -np.inf
    return _argmax_allowed(masked)


def _argmax_allowed(masked: np.ndarray) -> tuple[int, int, int, int] | None:
    flat = int(np.argmax(masked))
    if not np.isfinite(masked.reshape(-1)[flat]):
        return None
    return tuple(int(v) for v in np.unravel_index(flat, masked.shape))  # type: ignore[return-value]


@dataclass(frozen=True)
class OutcomeState:
    """The agent's memory of outcomes in this scene, and its random streams (``Agent.outcome_state``)."""

    failed_grasps: int
    forced_moves: int
    previous: Action | None
    memory: FailureMemory
    rng: Mapping[str, Any]
    assign_rng: Mapping[str, Any]
    exhausted: str


class Agent:
    """Chooses actions from Q-maps; holds the exploration state (failure streak, previous action)."""

    def __init__(self, config: CellConfig, network: QMapNetwork, seed: int = 0, *, max_epsilon: float = 1.0,
                 exploration_offset: int = 0) -> None:
        if not 0.0 <= max_epsilon <= 1.0:
            raise ValueError(f"max_epsilon: got {max_epsilon!r}, expected 0..1")
        self.config = config
        self.network = network
        self.rotations = network.rotations
        self.rng = np.random.default_rng(seed)
        self.mailbox = WeightsMailbox()
        self.weights_version = 0
        self.failed_grasps = 0
        self.previous: Action | None = None
        self.network.eval()
        self.champion_id: int | None = None
        self.challenger: QMapNetwork | None = None
        self.challenger_id: int | None = None
        self.challenger_version = -1
        self.challenger_share = 0.0
        self._assign_rng = np.random.default_rng([int(seed), 0x6761])
        self.exploration_offset = int(exploration_offset)
        self.max_epsilon = float(max_epsilon)
        ex = config.exploration
        self.memory = FailureMemory(self.rotations, ex.failure_radius / config.workspace.resolution,
                                    ex.failure_rotations, config.rewards.delta, ex.failure_retries)
        self.forced_moves = 0       # two-failures moves since the last successful grasp (the ladder's rung)
        self._exhausted = ""        # why the last decision found nothing left to try

    # ------------------------------------------------------------------ weights

    def maybe_swap_weights(self) -> bool:
        """Load the newest weights posted by the learner, if any; True when swapped."""
        posted = self.mailbox.take()
        if posted is None:
            return False
        weights, version = posted
        self.network.load_state_dict(weights)
        self.network.eval()
        self.weights_version = version
        return True

    def act_with(self, weights: Mapping[str, torch.Tensor], policy_id: int | None, version: int) -> None:
        """Decide with ``weights`` from the next decision on: the acting policy ``policy_id`` (None: not one the
        gate keeps), whose learner update count is ``version`` (-1 unknown; the cached double-DQN a' needs it)."""
        self.network.load_state_dict(dict(weights))
        self.network.eval()
        self.champion_id = policy_id
        self.weights_version = int(version)

    def set_challenger_share(self, share: float) -> None:
        """The share of greedy decisions the challenger makes, as the gate's evidence earned it."""
        if not 0.0 <= share <= 1.0:
            raise ValueError(f"challenger share: got {share!r}, expected 0..1")
        self.challenger_share = float(share) if self.challenger is not None else 0.0

    def set_challenger(self, network: QMapNetwork | None, policy_id: int | None = None, version: int = -1,
                       share: float = 0.0) -> None:
        """The network that makes a ``share`` of the greedy decisions (None: the champion makes them all)."""
        if network is not None:
            network.eval()
        self.challenger, self.challenger_id = network, (policy_id if network is not None else None)
        self.challenger_version = version if network is not None else -1
        self.challenger_share = float(share) if network is not None else 0.0

    def continue_exploration_from(self, offset: int) -> None:
        """Exploration goes on at ``step + offset`` from now: a loaded policy's recorded training steps less the
        step it starts acting at, so that a trained policy does not explore like a fresh one."""
        self.exploration_offset = int(offset)

    def policy_steps(self, step: int) -> int:
        """The acting policy's own count of actions when this cell is at ``step`` (what its policy file records,
        and what exploration continues from when it is loaded again): the one place the two counts meet."""
        return max(0, int(step) + self.exploration_offset)

    def epsilon(self, step: int) -> float:
        """Exploration rate at ``step``: the schedule at ``step + exploration_offset``, capped at ``max_epsilon``."""
        return min(self.max_epsilon, epsilon_at(step + self.exploration_offset, self.config.exploration))

    # ------------------------------------------------------------------ deciding

    def masks(self, height: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rho_g, rho_m) for ``height``; all ones for the DPEN ablation (object presence still checked)."""
        return cell_action_masks(height, self.config, self.rotations)

    def stuck_reason(self) -> str:
        """Why the cell should stop trying in this scene ('' = it should not): ``stuck_after`` actions without
        a successful grasp, or a last decision that found every allowed action suppressed."""
        ex = self.config.exploration
        mem = self.memory
        if ex.stuck_after > 0 and mem.since_success >= ex.stuck_after:
            return (f"{mem.since_success} actions without a successful grasp (exploration.stuck_after "
                    f"{ex.stuck_after}); {len(mem.enforced)} failed regions suppressed")
        return self._exhausted

    def q_maps(self, heightmaps: Heightmaps, network: QMapNetwork | None = None) -> np.ndarray:
        """All-rotation Q-maps [R,2,H,W] float32 of ``network`` (default: the champion; grasp twins averaged
        when ``exploration.twin_grasps``)."""
        with torch.inference_mode():
            maps = q_maps(self.network if network is None else network, heightmaps, self.rotations)
        q = maps.float().cpu().numpy()
        return twin_grasp_maps(q) if self.config.exploration.twin_grasps else q

    def decide(self, heightmaps: Heightmaps, step: int) -> Decision | None:
        """The next action for ``heightmaps`` at training step ``step``; None when nothing is on the table."""
        self.maybe_swap_weights()
        height = np.nan_to_num(np.asarray(heightmaps.height, dtype=np.float32), nan=0.0)
        if not grasp_mask(height, self.config.rewards, self.config.workspace.resolution).any():
            return None
        challenger = self.challenger
        by_challenger = challenger is not None and self._assign_rng.random() < self.challenger_share
        network = challenger if by_challenger else self.network
        decision = self.select(self.q_maps(heightmaps, network), height, step)
        if decision is None:
            return None
        role = "challenger" if by_challenger else "champion"
        policy = self.challenger_id if by_challenger else self.champion_id
        credited = decision.rule not in ("epsilon", "two-failures", "ladder-move")
        return dataclasses.replace(decision, role=role, policy_id=policy if credited else None,
                                   weights_version=self.challenger_version if by_challenger
                                   else self.weights_version)

    def select(self, q: np.ndarray, height: np.ndarray, step: int) -> Decision | None:
        """The decision rules on given Q-maps [R,2,H,W] (``decide`` without the network)."""
        ex = self.config.exploration
        q = np.asarray(q, dtype=np.float32)
        if q.ndim != 4 or q.shape[0] != self.rotations or q.shape[1] != 2 or q.shape[2:] != height.shape:
            raise ValueError(f"q-maps: expected [{self.rotations},2,{height.shape[0]},{height.shape[1]}], "
                             f"got {list(q.shape)}")
        gmask, mmask = self.masks(height)
        self._exhausted = ""
        if not gmask.any() and (ex.grasp_only or not mmask.any()):
            if grasp_mask(height, self.config.rewards, self.config.workspace.resolution).any():
                self._exhausted = ("what the camera sees lies at the heightmap's border, where every grasp and push "
                                   "would bring the gripper down beyond its edge onto what it cannot see "
                                   "(exploration.grasp_in_view): clear the table's border")
            return None
        masked = masked_maps(q, gmask, mmask)
        if ex.grasp_only:
            masked[:, 1] = -np.inf
        greedy = _argmax_allowed(masked)
        suppressed = None
        if ex.failure_memory:
            self.memory.release_changed(height)
            if self.memory.enforced:
                masked[self.memory.suppressed()] = -np.inf
                if not np.isfinite(masked).any():
                    self._exhausted = (f"every allowed action lies in one of the {len(self.memory.enforced)} "
                                       "regions where an action failed in this scene")
                    return None
            suppressed = self.memory.footprint()
        eps = self.epsilon(step)
        greedy_choice = True
        has_grasp = bool(np.isfinite(masked[:, 0]).any())
        has_move = bool(np.isfinite(masked[:, 1]).any())

        if (self.failed_grasps >= ex.failed_grasps_trigger or not has_grasp) and not ex.grasp_only and has_move:
            channel, rule = 1, ("two-failures" if has_grasp else "ladder-move")
            index = self._best(masked, 1)
            target = self.memory.last_failed_grasp if ex.failure_memory else None
            if self.forced_moves >= 1 and target is not None:
                reach = (ex.failure_radius + LADDER_REACH) / self.config.workspace.resolution
                near = np.where(self.memory.near(target.row, target.col, reach, height.shape)[None], masked[:, 1],
                                -np.inf)
                if np.isfinite(near).any():
                    n_rot, n_row, n_col = np.unravel_index(int(np.argmax(near)), near.shape)
                    index, rule = (int(n_rot), 1, int(n_row), int(n_col)), "ladder-move"
            self.forced_moves += 1
        elif not has_grasp:  # grasp-only and every grasp suppressed
            self._exhausted = "every grasp lies in a region where a grasp failed in this scene (grasp-only)"
            return None
        elif self.rng.random() < eps:
            channel, rule = (0 if ex.grasp_only or not mmask.any() else int(self.rng.integers(2))), "epsilon"
            index = self._random_inside(gmask if channel == 0 else mmask, channel)
            greedy_choice = False
        else:
            best_grasp, best_move = self._best(masked, 0), self._best(masked, 1)
            channel = 1 if masked[best_move] > masked[best_grasp] else 0
            index = best_move if channel else best_grasp
            rule = "greedy"

        if channel == 1 and rule not in ("two-failures", "ladder-move") and step < ex.curriculum_steps \
                and has_grasp and self.rng.random() >= ex.curriculum_move_probability:
            channel, rule, index = 0, "curriculum", self._best(masked, 0)
            greedy_choice = True

        if greedy_choice and self._repeats(channel, index):
            index = self._top_m_excluding(masked, channel, (index[2], index[3]))
            rule = "anti-repeat"
        if not np.isfinite(masked[index]):  # epsilon drew a suppressed pixel: the best allowed action instead
            channel = channel if (has_grasp, has_move)[channel] else 1 - channel
            index = self._best(masked, channel)

        rot, _, row, col = (int(v) for v in index)
        primitive: Primitive = "grasp" if channel == 0 else self._move_kind(float(height[row, col]))
        action = Action(primitive, row, col, rot, self.rotations)
        self.previous = action
        return Decision(action=action, q_maps=q, grasp_mask=gmask, move_mask=mmask,
                        q_value=float(q[rot, channel, row, col]), rule=rule, epsilon=eps,
                        greedy=greedy, suppressed=suppressed)

    def record_outcome(self, action: Action, grasp_success: bool | None, *, move_changed: bool | None = None,
                       height_after: np.ndarray | None = None, kind: str | None = None) -> None:
        """Feed the executed action's result: grasp streaks for rule 1, location for rule 5, the failure memory.

        ``grasp_success`` is None for moves (and for a grasp whose result is
        unknown, which leaves the streak unchanged).  A move ends the streak.
        ``move_changed`` (a move's reward > 0) and ``height_after`` (the
        heightmap the outcome was judged on) feed the failure memory; without
        ``height_after`` a failure is counted but no region is suppressed.
        """
        self.previous = action
        if action.is_move:
            self.failed_grasps = 0
        elif grasp_success is True:
            self.failed_grasps = 0
            self.forced_moves = 0
        elif grasp_success is False:
            self.failed_grasps += 1
        if action.is_move:
            success = bool(move_changed)
        elif grasp_success is None:
            return
        else:
            success = bool(grasp_success)
        self.memory.record(action, kind or action.primitive, success,
                           height_after if self.config.exploration.failure_memory else None)

    def outcome_state(self) -> "OutcomeState":
        """What ``record_outcome`` changes, copied: a provisional outcome can be taken back (``restore_outcome_state``).

        Why: while the arm carries a picked object to the place the next decision is already made, on the outcome
        measured at home; should the object slip out on the way, that outcome is taken back and the failure
        recorded instead, so the agent ends as if it had waited."""
        return OutcomeState(self.failed_grasps, self.forced_moves, self.previous, copy.deepcopy(self.memory),
                            self.rng.bit_generator.state, self._assign_rng.bit_generator.state, self._exhausted)

    def restore_outcome_state(self, state: object) -> None:
        """Back to what ``outcome_state`` copied (the cycle keeps it without looking inside)."""
        if not isinstance(state, OutcomeState):
            raise TypeError(f"restore_outcome_state: expected what outcome_state() returned, got {type(state).__name__}")
        self.failed_grasps, self.forced_moves, self.previous = state.failed_grasps, state.forced_moves, state.previous
        self.memory = copy.deepcopy(state.memory)
        self.rng.bit_generator.state = state.rng
        self._assign_rng.bit_generator.state = state.assign_rng
        self._exhausted = state.exhausted

    def reset_episode(self) -> None:
        """Forget the streak, the previous location and the failure memory (new scene)."""
        self.failed_grasps = 0
        self.forced_moves = 0
        self.previous = None
        self.memory.clear()
        self._exhausted = ""

    # ------------------------------------------------------------------ helpers

    def _move_kind(self, height_at_point: float) -> Primitive:
        return move_kind_at(height_at_point, self.config.rewards.shift_height)

    @staticmethod
    def _best(masked: np.ndarray, channel: int) -> tuple[int, int, int, int]:
        flat = int(np.argmax(masked[:, channel]))
        rot, row, col = np.unravel_index(flat, masked[:, channel].shape)
        return int(rot), channel, int(row), int(col)

    def _random_inside(self, mask: np.ndarray, channel: int) -> tuple[int, int, int, int]:
        if mask.ndim == 3:   # a grasp mask per rotation
            rots, rows, cols = np.nonzero(mask)
            k = int(self.rng.integers(len(rows)))
            return int(rots[k]), channel, int(rows[k]), int(cols[k])
        rows, cols = np.nonzero(mask)
        k = int(self.rng.integers(len(rows)))
        return int(self.rng.integers(self.rotations)), channel, int(rows[k]), int(cols[k])

    def _repeats(self, channel: int, index: tuple[int, int, int, int]) -> bool:
        prev = self.previous
        return prev is not None and prev.channel == channel and (prev.row, prev.col) == (index[2], index[3])

    def _top_m_excluding(self, masked: np.ndarray, channel: int, pixel: tuple[int, int]) -> tuple[int, int, int, int]:
        values = masked[:, channel].copy()
        if self.config.exploration.failure_memory:  # not the same action a few millimetres away either
            values[:, self.memory.near(pixel[0], pixel[1], self.memory.radius_px, values.shape[1:])] = -np.inf
        else:
            values[:, pixel[0], pixel[1]] = -np.inf
        flat = values.reshape(-1)
        finite = int(np.count_nonzero(np.isfinite(flat)))
        if finite == 0:  # the previous pixel is the only candidate left: keep it
            return self._best(masked, channel)
        m = min(self.config.exploration.top_m, finite)
        top = np.argpartition(-flat, m - 1)[:m]
        rot, row, col = np.unravel_index(int(top[self.rng.integers(m)]), values.shape)
        return int(rot), channel, int(row), int(col)
