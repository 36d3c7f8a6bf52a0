"""Running a policy on scenes in the simulated cell, run by run, through the one cycle (CycleRunner).

Each run: put the scene into the cell (load the file, or drop new random
clutter), forget the agent's episode state, then cycle until the run ends:

* ``cleared``           -- the workspace is empty;
* ``nothing-graspable`` -- objects are left but none shows in the grasp mask;
* ``failures``          -- more than ``failure_limit`` consecutive failed actions
  (VPG's test rule; see ``flgd.evaluation.metrics``);
* ``stuck``             -- the cell declared itself stuck (the agent's escalation
  ladder, ``exploration.stuck_after``): counted, not completed -- the daemon's
  simulated cell would re-lay the scene here;
* ``action-limit``      -- ``max_actions`` actions (default: 10 per object, at least 30;
  a safety net for policies that keep moving the clutter around);
* ``unstable`` / ``fault`` -- the simulator gave up (not counted in the rates).

Frozen evaluation (the default) acts greedily: epsilon = 0 and no curriculum,
while the anti-repeat and two-failures rules stay on -- they are part of the
policy.  With ``learn`` the agent explores and learns online exactly as the
daemon does when it is given a policy: the ``finetune`` learner settings, epsilon
continuing from the policy's training steps (capped at ``finetune.max_epsilon``),
no few-moves curriculum phase, a background ``Learner`` handing its weights over
every ``gate.handover_every`` updates to the champion/challenger gate (or, with the
gate off, to the agent), all built by the daemon's own ``flgd.learning_stack`` on
a store in a temporary directory.  Nothing is written to the config's state directory.

The cycle resets the scene when the workspace is empty; here that only marks
the end of the run (``EpisodeCell``), so that the next run's scene is exactly
the one asked for.

Reproducibility: a frozen evaluation (``learn`` off, ``--no-learn``) gives the
same runs for the same command line, config and policy file: one simulated cell
per object set, seeded with ``seed``, scenes in order, and weights that never
change.  With ``learn`` it does not: a background Learner thread trains while
the cell runs and new weights reach the agent whenever an update happens to
finish, so which action sees which weights depends on thread timing (and on the
machine's load); only the scenes of the first run are the same.

Runs are numbered from 1 within each scene (``RunLog.run``, the progress line,
the JSON's ``run_logs[].run``, the ``--save-qmaps`` folder ``run01`` and the
picture captions).  Finished runs are kept in ``Evaluator.results`` as they end,
so a caller can save them when a later run fails or the evaluation is
interrupted; an exception in a run ends the evaluation as an EvaluationError
naming the scene and the run, since the simulator may be left broken.
"""

from __future__ import annotations

import dataclasses
import re
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from flgd.cell import CellFault, WrappedCell
from flgd.config import CellConfig
from flgd.cycle import CycleRecord, CycleRunner
from flgd.cycle_record import CycleOutcome
from flgd.evaluation.metrics import FAILURE_LIMIT, ActionEntry, RunLog
from flgd.evaluation.scene_sets import SceneSpec

if TYPE_CHECKING:
    from sim_cell.cell import SimCell
    from flgd.learning.networks import QMapNetwork
    from flgd.learning_stack import LearningStack

__all__ = ["EvalOptions", "EvaluationError", "EpisodeCell", "Evaluator", "evaluation_config",
           "DEFAULT_ACTIONS_PER_OBJECT", "MIN_DEFAULT_ACTIONS"]

DEFAULT_ACTIONS_PER_OBJECT = 10
MIN_DEFAULT_ACTIONS = 30  # so VPG's failure rule (11 in a row) can always end a run first
PACKED_CELL = "<packed arrangements>"   # key of the cell that lays packed scenes


class EvaluationError(RuntimeError):
    """The evaluation cannot go on (the simulated cell cannot be created or recovered)."""


@dataclass(frozen=True)
class EvalOptions:
    runs: int = 3
    seed: int = 0
    learn: bool = False
    grasp_only: bool = False
    max_actions: int | None = None        # per run; None = 10 per object, at least 30
    failure_limit: int = FAILURE_LIMIT
    save_qmaps: Path | None = None        # directory for one Q-map picture per action


def evaluation_config(config: CellConfig, options: EvalOptions) -> CellConfig:
    """``config`` as evaluated: greedy unless learning, grasp-only if asked, seeded, no scene of its own."""
    ex = config.exploration
    if not options.learn:
        ex = dataclasses.replace(ex, epsilon_start=0.0, epsilon_end=0.0, curriculum_steps=0)
    if options.grasp_only:
        ex = dataclasses.replace(ex, grasp_only=True)
    sim = dataclasses.replace(config.sim, seed=options.seed, scene="", objects=0)
    learning = dataclasses.replace(config.learning, seed=options.seed)
    return dataclasses.replace(config, exploration=ex, sim=sim, learning=learning)


class EpisodeCell(WrappedCell):
    """A simulated cell whose ``reset_scene`` ends the run instead of making new clutter.

    Everything else is the wrapped cell's; ``use`` switches the wrapped cell
    (one per object set) under one CycleRunner.
    """

    name = "sim"

    def __init__(self, config: CellConfig, inner: SimCell) -> None:
        super().__init__(inner, config)
        self.scene_ended = False

    def use(self, inner: SimCell) -> None:
        self.inner = inner
        self.scene_ended = False

    def reset_scene(self) -> None:
        self.scene_ended = True

    def can_reset_scene(self) -> bool:
        return True   # a run ends where the scene would be reset: nobody needs to refill the table

    def close(self) -> None:
        """The wrapped cells belong to the Evaluator, which closes them."""


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or "scene"


def _describe(exc: BaseException) -> str:
    """``pybullet.error: ...`` / ``OSError: ...``: the type tells which layer failed."""
    kind = type(exc)
    name = kind.__qualname__ if kind.__module__ == "builtins" else f"{kind.__module__}.{kind.__qualname__}"
    return f"{name}: {exc}"


def _result_text(record: CycleRecord) -> str:
    if record.outcome == CycleOutcome.REFUSED:
        return f"refused ({record.refused})"
    if record.kind == "grasp":
        return "held an object" if record.success else "missed"
    return (f"moved the clutter (r {record.reward:g}, mu {record.mu}, eta {record.eta})" if record.reward
            else f"no change (mu {record.mu}, eta {record.eta})")


class Evaluator:
    """Runs ``options.runs`` runs of each scene with one policy; ``close`` releases the cells and learner."""

    def __init__(self, config: CellConfig, network: QMapNetwork, options: EvalOptions, *, training_steps: int = 0,
                 progress: Callable[[SceneSpec, RunLog], None] | None = None) -> None:
        import torch

        from flgd.learning.agent import Agent

        if config.backend != "sim":
            raise EvaluationError(f"{config.source}: backend {config.backend!r}: flgd eval runs in the simulated "
                                  "cell; use a config with backend: sim (e.g. cell_config/sim.yaml)")
        if options.runs < 1:
            raise ValueError(f"runs: got {options.runs}, expected >= 1")
        if options.max_actions is not None and options.max_actions < 1:
            raise ValueError(f"max_actions: got {options.max_actions}, expected >= 1")
        self.config = evaluation_config(config, options)
        self.options = options
        self.progress = progress
        if self.config.learning.threads > 0:
            torch.set_num_threads(self.config.learning.threads)
        self.replay = self.learner = self.gate = self.store = None
        self.learning: LearningStack | None = None  # with ``learn``
        self._learn_dir: tempfile.TemporaryDirectory | None = None
        if options.learn:
            self._start_learning(network, training_steps)
        else:
            self.agent = Agent(self.config, network, seed=options.seed)
        self._cells: dict[str, Any] = {}
        self.results: list[tuple[SceneSpec, list[RunLog]]] = []
        self.episode = EpisodeCell(self.config, None)
        self.runner = CycleRunner(self.config, self.episode, self.agent, replay=self.replay, learner=self.learner,
                                  store=self.store, step=0, backend="sim",
                                  decide_while_placing=False)   # the harness every earlier result was measured on

    def _start_learning(self, network: QMapNetwork, training_steps: int) -> None:
        """The daemon's learning stack for a given policy (flgd.learning_stack, its learner settings and curriculum
        rule included), on a store in a temporary directory."""
        from flgd.learning_stack import GateStart, Handover, LearningStack
        from flgd.store import Store

        self._learn_dir = tempfile.TemporaryDirectory(prefix="flgd-eval-learn-")
        stack = LearningStack(self.config, fine_tune=True, state_dir=self._learn_dir.name)
        self.config = stack.config
        self.store = stack.store = Store(self._learn_dir.name, keep_transitions=self.config.learning.replay_capacity)
        stack.load_prior(network.rotations)
        policy = (network, {"training_steps": int(training_steps)}, "the evaluated policy")
        parts = stack.build(network, handover=Handover.GATE, agent_seed=self.options.seed,
                            gate=GateStart(0, configured=lambda: policy, fresh=lambda: policy))
        self.learning = stack
        self.replay, self.agent, self.learner, self.gate = parts.replay, parts.agent, parts.learner, parts.gate
        self.learner.start()

    # ------------------------------------------------------------------ cells
    def _cell_for(self, spec: SceneSpec) -> Any:
        """One simulated cell per object set (scene files share the config's; packed scenes have their own,
        so that the arrangements a seed gives do not depend on what else is evaluated)."""
        key = spec.objects if spec.is_clutter else PACKED_CELL if spec.packed else ""
        if key not in self._cells:
            from sim_cell.cell import SimCell

            cfg = self.config
            if spec.is_clutter:
                cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, object_set=key))
            try:
                self._cells[key] = SimCell(cfg)
            except (ValueError, CellFault) as exc:
                raise EvaluationError(f"cannot create the simulated cell: {exc}") from None
        return self._cells[key]

    def close(self) -> None:
        if self.learner is not None:
            self.learner.stop(timeout=30.0)
            self.learner = None
        if self.store is not None:
            self.store.close()
            self.store = None
        if self._learn_dir is not None:
            self._learn_dir.cleanup()
            self._learn_dir = None
        for cell in self._cells.values():
            cell.close()
        self._cells.clear()

    def __enter__(self) -> "Evaluator":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ running
    def evaluate(self, scenes: list[SceneSpec]) -> list[tuple[SceneSpec, list[RunLog]]]:
        """All runs of all scenes, in order (also in ``self.results``, which grows run by run).

        Why the growing list: when a run fails or Ctrl-C arrives, the runs already finished are still
        there for the caller to report.  Any exception in a run becomes an EvaluationError naming the
        scene and run; the evaluation stops there rather than go on with a simulator that may be broken.
        """
        self.results = []
        runs = self.options.runs
        for spec in scenes:
            logs: list[RunLog] = []
            self.results.append((spec, logs))
            for number in range(1, runs + 1):
                try:
                    log = self.run(spec, number)
                except Exception as exc:
                    what = str(exc) if isinstance(exc, EvaluationError) else _describe(exc)
                    raise EvaluationError(f"scene {spec.name} ({spec.describe()}), run {number} of {runs}: {what}; "
                                          "the evaluation stopped there (the simulated cell may be broken)") from exc
                logs.append(log)
                if self.progress is not None:
                    self.progress(spec, log)
        return self.results

    def _set_scene(self, cell: SimCell, spec: SceneSpec) -> int:
        from sim_cell.scenes import SceneError

        if spec.packed:
            return cell.make_packed()
        if spec.is_clutter:
            return cell.make_clutter(spec.count)
        try:
            return cell.load_scene(spec.path, vpg_meshes=spec.vpg_meshes)
        except SceneError as exc:
            raise EvaluationError(str(exc)) from None

    def run(self, spec: SceneSpec, number: int) -> RunLog:
        """Run number ``number`` (from 1) of ``spec``; see the module doc for when it ends."""
        if isinstance(number, bool) or not isinstance(number, int) or number < 1:
            raise ValueError(f"run number: got {number!r}, expected an integer >= 1 (runs count from 1)")
        t0 = time.perf_counter()
        cell = self._cell_for(spec)
        self.episode.use(cell)
        objects = self._set_scene(cell, spec)
        grasped_before, dropped_before = cell.stats["grasped_out"], cell.stats["dropped"]
        limit = self.options.max_actions or max(MIN_DEFAULT_ACTIONS, DEFAULT_ACTIONS_PER_OBJECT * objects)
        self.agent.reset_episode()
        self.runner.forget_state()
        actions: list[ActionEntry] = []
        streak = 0
        end, note = "", ""
        while not end:
            try:
                record = self.runner.run_once()
                if self.learning is not None:  # paced: this cycle's hand-over is taken now, not by timing
                    self.learning.after_cycle(record, self.runner)
            except CellFault as exc:
                end, note = "fault", str(exc)
                try:
                    cell.recover()
                except CellFault as exc2:
                    raise EvaluationError(f"the simulated cell cannot recover from a fault: {exc2}") from None
                break
            if record.outcome in (CycleOutcome.EXECUTED, CycleOutcome.REFUSED):
                entry = ActionEntry(kind=record.kind or record.primitive or "grasp",
                                    success=bool(record.reward and record.reward > 0),
                                    refused=record.outcome == CycleOutcome.REFUSED)
                actions.append(entry)
                streak = 0 if entry.success else streak + 1
                if self.options.save_qmaps is not None:
                    self._save_qmap(spec, number, len(actions), record)
            if record.outcome == CycleOutcome.STUCK:
                end, note = "stuck", record.failure
            elif record.outcome == CycleOutcome.DISCARDED:
                end, note = "unstable", record.failure
            elif record.outcome == CycleOutcome.STOPPED:
                end, note = "fault", record.failure
            elif record.outcome == CycleOutcome.EMPTY or record.done or self.episode.scene_ended:
                end = "cleared" if cell.object_count == 0 else "nothing-graspable"
            elif streak > self.options.failure_limit:
                end = "failures"
            elif len(actions) >= limit:
                end = "action-limit"
        return RunLog(scene=spec.name, run=number, objects=objects, actions=tuple(actions),
                      objects_left=cell.object_count if end not in ("unstable", "fault") else objects,
                      objects_grasped=cell.stats["grasped_out"] - grasped_before, end=end,
                      seconds=time.perf_counter() - t0, note=note,
                      objects_dropped=cell.stats["dropped"] - dropped_before)

    def _save_qmap(self, spec: SceneSpec, run: int, number: int, record: CycleRecord) -> None:
        from flgd.visualize import ActionGlyph, qmap_picture, write_png

        last = self.runner.last_decided
        if last is None or last[2] != record.step:
            return
        hm, decision, step = last
        folder = Path(self.options.save_qmaps) / _slug(spec.group or "scenes") / _slug(spec.name) / f"run{run:02d}"
        folder.mkdir(parents=True, exist_ok=True)
        caption = (f"{spec.name} run {run} action {number}: {record.kind} -> {_result_text(record)}"
                   f"   | rule {decision.rule}, eps {decision.epsilon:.2f}")
        image = qmap_picture(hm.color, hm.height, decision.q_maps, decision.grasp_mask, decision.move_mask,
                             decision.action, caption=caption, glyph=ActionGlyph.from_config(self.config),
                             unknown=hm.unknown, suppressed=decision.suppressed)
        write_png(folder / f"action{number:03d}-{record.kind}.png", image)
