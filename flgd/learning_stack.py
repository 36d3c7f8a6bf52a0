"""One run's learning stack: replay, agent, learner, gate and prior sample, with its checkpoints and trainer state.

The daemon (start-up and reset), ``flgd eval --learn``, ``flgd train`` and the
benches (which run the daemon's Controller or the Evaluator) all build their
learning here, from the parts ``flgd.wiring`` makes, so that what an evaluation
or a bench measures is what the daemon does: the same learner settings and
curriculum rule (``learning_config``), the same start network and resume seeds,
one trainer-state restore, one checkpoint-metadata type (``CheckpointMeta``).
What stays the caller's: its store, its cell and cycle runner, and what it does
with a problem (the daemon faults, ``flgd train`` stops, the evaluation ends).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from flgd.config import CellConfig, learner_settings
from flgd.store import CheckpointDir, Store

__all__ = ["LearningStack", "CheckpointMeta", "TrainerStateRestore", "learning_config", "LEARNER_QUIET_TIMEOUT"]

LEARNER_QUIET_TIMEOUT = 60.0  # seconds a restart of the learner (or a policy load) waits for its update in progress


def learning_config(config: CellConfig, fine_tune: bool, *, few_moves: bool = False) -> CellConfig:
    """What the agent and the learner run with: ``config`` with the ``finetune`` learner settings when
    ``fine_tune`` (``flgd.config.learner_settings``), and without the curriculum's few-moves phase, which is
    ``flgd train --curriculum``'s alone (``few_moves`` keeps it)."""
    tuned = learner_settings(config, fine_tune)
    if few_moves:
        return tuned
    return dataclasses.replace(tuned, exploration=dataclasses.replace(tuned.exploration, curriculum_steps=0))


@dataclass(frozen=True)
class CheckpointMeta:
    """What a checkpoint's policy file records of the learning that wrote it (the daemon and ``flgd train``).

    ``training_steps`` is the policy's own count of actions (exploration goes on from it when it is loaded);
    ``run`` holds what a training run adds (its settings and rolling success)."""

    training_steps: int
    cell: str
    learner_updates: int
    source: str
    run: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {"training_steps": max(0, int(self.training_steps)), "cell": self.cell,
                "learner_updates": int(self.learner_updates), "source": self.source, **self.run}


@dataclass(frozen=True)
class TrainerStateRestore:
    """What a resumed learner got back: its trainer state, or why it starts with fresh Adam moments.

    ``other_update`` is the update count of a trainer state written with another checkpoint; ``problem`` what
    is wrong with one that cannot be used."""

    restored: bool
    why: str
    other_update: int | None = None
    problem: str = ""

    def describe(self) -> str:
        """The daemon's status words: ``restored at update N`` or ``fresh (why)``."""
        return self.why if self.restored else f"fresh ({self.why})"


class LearningStack:
    """Replay, agent, learner, gate and prior sample of one run, built the one way (module doc).

    Build order: ``start_from`` (the start network), ``load_prior``, ``build``, ``restore_trainer_state``, then
    ``attach_gate`` where there is a store.  ``config`` is what agent and learner run with (``learning_config``);
    ``priorities_in_store`` says where the replay priorities live across a restart: the store (the daemon,
    written as they are set) or the trainer state (``flgd train``, written with each checkpoint).
    """

    def __init__(self, config: CellConfig, *, fine_tune: bool, state_dir: str | Path, store: Store | None = None,
                 checkpoints: CheckpointDir | None = None,
                 checkpoint_callback: Callable[[Any, int], None] | None = None,
                 few_moves: bool = False, priorities_in_store: bool = True) -> None:
        self.config = learning_config(config, fine_tune, few_moves=few_moves)
        self.fine_tune = fine_tune
        self.state_dir = Path(state_dir)
        self.store = store
        self.checkpoints = checkpoints
        self.checkpoint_callback = checkpoint_callback
        self.priorities_in_store = priorities_in_store
        self.prior: Any = None  # the fine-tune's prior sample (finetune.prior_sample), loaded once
        self.replay: Any = None
        self.agent: Any = None
        self.learner: Any = None
        self.gate: Any = None  # the Gatekeeper, once attached
        self.gate_note = ""
        self.source = ""  # what the learner started from (status lines, checkpoint metadata)
        self.resumed_from_updates = 0
        self.last_checkpoint = ""  # the newest checkpoint resumed from or written
        self.trainer_state = "fresh"  # what the learner's target network and Adam moments started from

    # ------------------------------------------------------------------ building
    def start_from(self, policy: str | None) -> Any:
        """The start network: the newest readable checkpoint, else ``policy``, else a fresh one
        (``flgd.wiring.starting_network``; PolicyFileError / TrunkFileError for a file that cannot be used)."""
        from flgd.wiring import starting_network

        assert self.checkpoints is not None, "a run that resumes has a checkpoint directory"
        start = starting_network(self.config, self.checkpoints, policy)
        self.resumed_from_updates = start.resumed_from_updates
        self.source = start.source
        if start.checkpoint is not None:
            self.last_checkpoint = str(start.checkpoint)
        return start.network

    def load_prior(self, rotations: int) -> None:
        """The fine-tune's prior sample, for every learner built (PriorSampleError naming the file)."""
        from flgd.wiring import configured_prior

        self.prior = configured_prior(self.config, rotations, self.fine_tune)

    def build(self, network: Any, step: int = 0, *, replay_seed: int | None = None,
              agent_seed: int | None = None) -> str:
        """Replay (from the store), agent and learner for a run at action ``step``; the store's problem or ''.

        Their random draws continue from seeds drawn for that action (``flgd.wiring.continuing_config``); a
        caller with seeds of its own (``flgd train``'s segments) gives ``replay_seed`` and ``agent_seed``.  The
        learner hands nothing over before a gate is attached (``attach_gate``) or, in a run without one,
        ``hand_to_agent``."""
        from flgd.wiring import build_agent_and_learner, continuing_config, rebuild_replay

        config = continuing_config(self.config, step)
        self.replay, problem = rebuild_replay(config, self.store, seed=replay_seed)
        self.agent, self.learner = build_agent_and_learner(
            config, network, self.replay, checkpoint_callback=self.checkpoint_callback,
            updates=self.resumed_from_updates, agent_seed=agent_seed,
            store=self.store if self.priorities_in_store else None, fine_tune=self.fine_tune, prior=self.prior)
        self.learner.mailbox = None
        return problem

    def hand_to_agent(self) -> None:
        """No gate (``flgd train``): the learner's weights go straight to the agent as they are handed over."""
        self.learner.mailbox = self.agent.mailbox

    def rebuild(self, step: int) -> str:
        """Replay, agent and learner built again on the store (after it came back): the learner goes on from its
        own weights and update count, and is started; it hands nothing over until a gate is attached."""
        old = self.learner
        old.stop(timeout=30.0, why="rebuilt after the store was reopened")
        problem = self.build(old.snapshot(), step)
        self.learner.updates = old.updates  # checkpoints keep counting on
        self.gate = None
        self.learner.start()
        return problem

    def connect(self, runner: Any) -> None:
        """Point a cycle runner at this stack's agent, store, replay and learner (after ``rebuild``)."""
        runner.agent, runner.store, runner.replay, runner.learner = self.agent, self.store, self.replay, self.learner

    def attach_gate(self, step: int, *, configured: Callable[[], tuple[Any, dict, str] | None],
                    fresh: Callable[[], tuple[Any, dict, str]]) -> None:
        """The champion/challenger gate on the store (``flgd.wiring.attach_gate``): GateError / PolicyFileError
        when there is no policy to act with, StoreError / OSError on storage."""
        from flgd.wiring import attach_gate

        assert self.store is not None, "the gate keeps its records in the store"
        self.gate, self.gate_note = attach_gate(self.config, self.store, self.agent, self.learner, self.state_dir,
                                                step, fine_tune=self.fine_tune, configured=configured, fresh=fresh)
        self.gate.reset_learner = self.restart_learner_from  # the daemon wraps it with its lock and an event

    def restart_learner_from(self, network: Any, quiet_timeout: float = LEARNER_QUIET_TIMEOUT) -> int:
        """The gate, after a rollback or a drop as worse: the learner starts again from ``network`` (its weights,
        a fresh trainer state, the owed updates dropped; their number returned).  LearnerBusy when the update in
        progress does not end within ``quiet_timeout`` seconds."""
        with self.learner.paused(quiet_timeout):
            self.learner.load_weights(network, publish=False)
            self.learner.reset_trainer_state()
            return self.learner.drop_backlog()

    # ------------------------------------------------------------------ running
    def after_cycle(self, record: Any, runner: Any) -> None:
        """Between cycles: the gate takes the hand-over this cycle's updates made (paced runs wait for them,
        ``CycleRunner.wait_for_learner``) and judges champion and challenger."""
        if self.gate is None:
            return
        runner.wait_for_learner()
        self.gate.after_cycle(record)

    def status(self) -> dict[str, Any]:
        """What the daemon's status shows of its learning: the learner's own (``Learner.status()``), the replay,
        the gate, and what the learner resumed from."""
        from flgd.learning.learner import no_learner_status

        return {"replay_size": len(self.replay) if self.replay is not None else 0,
                **(self.learner.status() if self.learner is not None else no_learner_status()),
                "gate": None if self.gate is None else self.gate.status(),
                "resumed_from_updates": self.resumed_from_updates, "trainer_state": self.trainer_state,
                "last_checkpoint": self.last_checkpoint}

    # ------------------------------------------------------------------ checkpoints
    def checkpointed_updates(self) -> int:
        """The update count of the newest checkpoint resumed from or written; -1 without one."""
        return CheckpointDir.updates_of(Path(self.last_checkpoint)) if self.last_checkpoint else -1

    def owes_checkpoint(self) -> bool:
        """The learner ran updates since the newest checkpoint (a clean exit writes one)."""
        return self.learner is not None and self.learner.updates > max(0, self.checkpointed_updates())

    def write_checkpoint(self, network: Any, updates: int, meta: CheckpointMeta) -> Path:
        """The policy file of update ``updates`` (StoreError / OSError), and the store's count of updates."""
        from flgd.learning.policy_file import save_policy

        assert self.checkpoints is not None, "checkpoints are written to the run's checkpoint directory"
        path = self.checkpoints.write(lambda p: save_policy(p, network, meta.as_dict()), updates)
        if self.store is not None:
            self.store.set_counter("learner_updates", updates)
        self.last_checkpoint = str(path)
        return path

    def write_trainer_state(self) -> None:
        """Target network and Adam moments beside the checkpoint (and the replay priorities, where the store does
        not keep them), so a resumed learner goes on where it was.  Call with the learner quiet."""
        import numpy as np

        from flgd.training.state import TRAINER_STATE, save_trainer_state

        tagged = [] if self.priorities_in_store else [(slot, tid) for slot, tid in enumerate(self._slot_tags())
                                                      if tid is not None]
        save_trainer_state(self.state_dir / TRAINER_STATE, self.learner,
                           np.array([tid for _, tid in tagged], dtype=np.int64),
                           np.array([self.replay.priority(slot) for slot, _ in tagged], dtype=np.float64))

    def restore_trainer_state(self) -> TrainerStateRestore:
        """Give a resumed learner back its target network, Adam moments and priorities, saved with its checkpoint.

        Only a trainer state written with the very checkpoint the run resumed from is used; anything else
        (none, another update count, unreadable, not fitting the network) leaves the learner as built, target
        = the checkpoint's weights and fresh moments.  What happened is returned and kept in ``trainer_state``.
        """
        from flgd.training.state import TRAINER_STATE, load_trainer_state, restore_learner

        path = self.state_dir / TRAINER_STATE
        if not self.last_checkpoint:
            outcome = TrainerStateRestore(False, "no checkpoint to resume")
        elif not path.exists():
            outcome = TrainerStateRestore(False, f"{path.name} not found")
        else:
            try:
                state = load_trainer_state(path)
                if state.updates != self.resumed_from_updates:
                    outcome = TrainerStateRestore(False, f"{path.name} is of update {state.updates}, the checkpoint "
                                                         f"of {self.resumed_from_updates}", other_update=state.updates)
                else:
                    restore_learner(self.learner, state)
                    self._restore_priorities(dict(zip(state.priority_ids.tolist(), state.priorities.tolist())))
                    outcome = TrainerStateRestore(True, f"restored at update {state.updates}")
            except (OSError, ValueError, RuntimeError, KeyError) as exc:
                self.learner.reset_trainer_state()
                outcome = TrainerStateRestore(False, f"{path}: {exc}", problem=str(exc))
        self.trainer_state = outcome.describe()
        return outcome

    def _restore_priorities(self, saved: dict[int, float]) -> None:
        """Each replay slot's saved priority, found by the store id the slot holds (raw, less the epsilon the
        replay adds back)."""
        if not saved:
            return
        eps = self.config.learning.priority_epsilon
        for slot, tid in enumerate(self._slot_tags()):
            if tid in saved:
                self.replay.update_priorities([slot], [max(0.0, saved[tid] - eps)])

    def _slot_tags(self) -> list[int | None]:
        """The store's transition id in each replay slot, read from the replay itself.

        Not counted alongside: a cycle that raises after its transition was added (a scene reset
        failing, say) would shift such a count and attach saved priorities to other transitions."""
        return [self.replay.tag(i) for i in range(len(self.replay))]
