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
from enum import StrEnum
from typing import TYPE_CHECKING, Any, Callable

from flgd.config import CellConfig, learner_settings
from flgd.store import CheckpointDir, Store

if TYPE_CHECKING:
    from flgd.cycle import CycleRunner
    from flgd.cycle_record import CycleRecord
    from flgd.gate.keeper import Gatekeeper
    from flgd.learning.agent import Agent
    from flgd.learning.learner import Learner
    from flgd.learning.networks import QMapNetwork
    from flgd.learning.prior_sample import PriorSample
    from flgd.learning.replay import PrioritizedReplay

__all__ = ["LearningStack", "LearningParts", "GateStart", "Handover", "CheckpointMeta", "TrainerStateRestore",
           "learning_config", "LEARNER_QUIET_TIMEOUT"]

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


class Handover(StrEnum):
    """Where the learner hands its weights: what acts on them decides how they are vetted."""

    GATE = "gate"      # the daemon and ``flgd eval --learn``: the champion/challenger gate tests them first
    AGENT = "agent"    # ``flgd train`` in one process: they act as they are handed over
    NOBODY = "nobody"  # ``flgd train --workers``: nobody acts in this process, the workers get them otherwise


@dataclass(frozen=True)
class GateStart:
    """What the gate restores its champion from on a build with a gate (``flgd.gate.keeper.Gatekeeper.restore``):
    the configured policy, else a fresh network; ``reset_learner`` is what the gate calls after a rollback or a
    drop as worse (None: ``LearningStack.restart_learner_from``; the daemon wraps that with its lock and an event).
    """

    step: int
    configured: Callable[[], tuple[QMapNetwork, dict, str] | None]
    fresh: Callable[[], tuple[QMapNetwork, dict, str]]
    reset_learner: Callable[[QMapNetwork], object] | None = None


@dataclass(frozen=True)
class LearningParts:
    """The fully built learning of one run, as ``LearningStack.build`` made it; a rebuild makes a new record.

    ``gate`` is None without a store, or in a run whose learner hands its weights to the agent or to nobody;
    ``replay_problem`` is the store error that stopped the replay's rebuild part-way ('' when none)."""

    replay: PrioritizedReplay
    agent: Agent
    learner: Learner
    gate: Gatekeeper | None = None
    gate_note: str = ""
    replay_problem: str = ""


class LearningStack:
    """The learning of one run, built the one way (module doc): ``start_from`` (the start network),
    ``load_prior``, ``build`` (replay, agent, learner and gate, a ``LearningParts``), ``restore_trainer_state``.

    ``config`` is what agent and learner run with (``learning_config``); ``priorities_in_store`` says where the
    replay priorities live across a restart: the store (the daemon, written as they are set) or the trainer
    state (``flgd train``, written with each checkpoint).
    """

    def __init__(self, config: CellConfig, *, fine_tune: bool, state_dir: str | Path, store: Store | None = None,
                 checkpoints: CheckpointDir | None = None,
                 checkpoint_callback: Callable[[QMapNetwork, int], None] | None = None,
                 few_moves: bool = False, priorities_in_store: bool = True) -> None:
        self.config = learning_config(config, fine_tune, few_moves=few_moves)
        self.fine_tune = fine_tune
        self.state_dir = Path(state_dir)
        self.store = store
        self.checkpoints = checkpoints
        self.checkpoint_callback = checkpoint_callback
        self.priorities_in_store = priorities_in_store
        self.prior: PriorSample | None = None  # the fine-tune's prior sample (finetune.prior_sample), loaded once
        self.parts: LearningParts | None = None
        self.source = ""  # what the learner started from (status lines, checkpoint metadata)
        self.resumed_from_updates = 0
        self.last_checkpoint = ""  # the newest checkpoint resumed from or written
        self.trainer_state = "fresh"  # what the learner's target network and Adam moments started from

    # ------------------------------------------------------------------ the parts
    def _built(self) -> LearningParts:
        if self.parts is None:
            raise RuntimeError("the learning stack is not built yet (LearningStack.build)")
        return self.parts

    @property
    def agent(self) -> Agent:
        return self._built().agent

    @property
    def learner(self) -> Learner:
        return self._built().learner

    @property
    def replay(self) -> PrioritizedReplay:
        return self._built().replay

    @property
    def gate(self) -> Gatekeeper | None:
        return None if self.parts is None else self.parts.gate

    @property
    def gate_note(self) -> str:
        return "" if self.parts is None else self.parts.gate_note

    # ------------------------------------------------------------------ building
    def start_from(self, policy: str | None) -> QMapNetwork:
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

    def build(self, network: QMapNetwork, step: int = 0, *, handover: Handover, gate: GateStart | None = None,
              updates: int | None = None, replay_seed: int | None = None,
              agent_seed: int | None = None) -> LearningParts:
        """Replay (from the store), agent, learner and -- with ``gate`` and a store -- the gate, for a run at
        action ``step``, each constructed whole; the record is kept in ``parts`` and returned.

        Their random draws continue from seeds drawn for that action (``flgd.wiring.continuing_config``); a
        caller with seeds of its own (``flgd train``'s segments) gives ``replay_seed`` and ``agent_seed``.  The
        learner counts on from ``updates`` (default: the checkpoint resumed from).  With ``handover`` GATE and no
        gate built, the learner hands nothing over: nothing acts before a gate has vetted it.  The
        gate raises GateError / PolicyFileError when there is no policy to act with, StoreError / OSError on
        storage; then nothing is kept.
        """
        from flgd.gate.keeper import Gatekeeper
        from flgd.learning.agent import WeightsMailbox
        from flgd.learning.learner import Learner
        from flgd.wiring import continuing_config, make_agent, rebuild_replay

        config = continuing_config(self.config, step)
        updates = self.resumed_from_updates if updates is None else int(updates)
        replay, problem = rebuild_replay(config, self.store, seed=replay_seed)
        agent = make_agent(config, network, config.learning.seed if agent_seed is None else agent_seed,
                           self.fine_tune)
        with_gate = gate is not None and self.store is not None
        if with_gate and handover != Handover.GATE:
            raise ValueError(f"a gate vets the learner's weights: handover must be gate, got {handover}")
        handovers = WeightsMailbox()
        mailbox: WeightsMailbox | None = None  # GATE without a gate: nothing is handed over until one is built
        if handover == Handover.GATE and with_gate:  # with gate.enabled false they act as handed over
            mailbox = handovers if self.config.gate.enabled else agent.mailbox
        elif handover == Handover.AGENT:
            mailbox = agent.mailbox
        store = self.store if self.priorities_in_store else None
        learner = Learner(config, network, replay, mailbox=mailbox, checkpoint_callback=self.checkpoint_callback,
                          priority_sink=None if store is None else store.save_priorities, prior=self.prior,
                          prior_share=config.finetune.prior_share if self.prior is not None else 0.0,
                          updates=updates)
        replay.resume_annealing(updates)  # one batch per update: beta goes on where the run left it
        keeper: Gatekeeper | None = None
        note = ""
        if gate is not None and self.store is not None:
            keeper = Gatekeeper(self.config, self.store, agent, self.state_dir, handovers=handovers,
                                on_champion=learner.set_anchor,   # the learner's L2-SP anchor is what acts
                                reset_learner=gate.reset_learner or self.restart_learner_from)
            note = keeper.restore(gate.step, gate.configured, gate.fresh)
            agent.continue_exploration_from(self._exploration_offset(keeper, gate.step))
        self.parts = LearningParts(replay, agent, learner, keeper, note, problem)
        return self.parts

    def _exploration_offset(self, gate: Gatekeeper, step: int) -> int:
        """The stored offset; on a first start, fine-tuning, the champion's recorded training steps less ``step``
        (exploration continues from them), else 0 -- then stored."""
        assert self.store is not None and gate.champion is not None
        offset = self.store.counter("exploration_offset", -1)
        if offset < 0:
            offset = gate.champion.training_steps - step if self.fine_tune else 0
            self.store.set_counter("exploration_offset", offset)
        return offset

    def rebuild(self, step: int, gate: GateStart | None = None) -> LearningParts:
        """Everything built again on the store (after it came back, or to attach a gate): the learner goes on from
        its own weights and update count, and is started.  When the gate cannot be built, the parts are built
        without one (the learner hands nothing over) and the gate's error is raised."""
        old = self.learner
        old.stop(timeout=30.0, why="rebuilt on the store")
        updates = old.updates
        try:  # each build gets its own copy: a gate that fails part-way has loaded its champion into the agent's
            parts = self.build(old.snapshot(), step, handover=Handover.GATE, gate=gate, updates=updates)
        except BaseException:
            self.build(old.snapshot(), step, handover=Handover.GATE, updates=updates)
            self.learner.start()
            raise
        self.learner.start()
        return parts

    def connect(self, runner: CycleRunner) -> None:
        """Point a cycle runner at this stack's agent, store, replay and learner (after ``rebuild``)."""
        runner.use_learning(self.agent, self.store, self.replay, self.learner)

    def restart_learner_from(self, network: QMapNetwork, quiet_timeout: float = LEARNER_QUIET_TIMEOUT) -> int:
        """The gate, after a rollback or a drop as worse: the learner starts again from ``network`` (its weights,
        a fresh trainer state, the owed updates dropped; their number returned).  LearnerBusy when the update in
        progress does not end within ``quiet_timeout`` seconds."""
        with self.learner.paused(quiet_timeout):
            self.learner.load_weights(network, publish=False)
            self.learner.reset_trainer_state()
            return self.learner.drop_backlog()

    # ------------------------------------------------------------------ running
    def after_cycle(self, record: CycleRecord, runner: CycleRunner) -> None:
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

        parts = self.parts
        return {"replay_size": len(parts.replay) if parts is not None else 0,
                **(parts.learner.status() if parts is not None else no_learner_status()),
                "gate": None if self.gate is None else self.gate.status(),
                "resumed_from_updates": self.resumed_from_updates, "trainer_state": self.trainer_state,
                "last_checkpoint": self.last_checkpoint}

    # ------------------------------------------------------------------ checkpoints
    def checkpointed_updates(self) -> int:
        """The update count of the newest checkpoint resumed from or written; -1 without one."""
        return CheckpointDir.updates_of(Path(self.last_checkpoint)) if self.last_checkpoint else -1

    def owes_checkpoint(self) -> bool:
        """The learner ran updates since the newest checkpoint (a clean exit writes one)."""
        return self.parts is not None and self.parts.learner.updates > max(0, self.checkpointed_updates())

    def write_checkpoint(self, network: QMapNetwork, updates: int, meta: CheckpointMeta) -> Path:
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
