"""``flgd train``: headless training in sim_cell with the daemon's cycle, agent, learner and store.

The one training loop, for one cell or many: its collector (``flgd.training.collector``) runs the cells --
one here (``LocalCollector``) or N Ray workers (``flgd.training.ray_collector``), each running the daemon's
cycle (``CycleRunner.run_once``) -- and the loop keeps each cell's cycle as the daemon keeps one
(``flgd.cycle_commit``: store, replay, learner), lets that cell go on, then runs ``Learner.update_pending``:
the ``learning.updates_per_action`` updates the daemon's learner thread would run, but in this thread, so a
run does not depend on thread timing.  Network, replay, agent and learner are built by
``flgd.learning_stack`` exactly as the daemon builds them.

Run directory (``--out``), also the store's state directory:

* ``run.json``        -- settings, segments (one per start/resume), status;
* ``config.yaml``     -- the effective cell config of the run;
* ``flgd.sqlite``     -- the store: action log + replay transitions;
* ``checkpoints/``    -- policy files, every ``learning.checkpoint_every``
  updates and at exit (metadata: variant, method, steps, cell, rolling success);
* ``trainer-state.safetensors`` -- target network, Adam state, priorities;
* ``actions.csv``     -- one row per step (see flgd.training.actions_csv);
* ``curve.png``       -- rolling grasp success (last 50 and 200 grasps) and moves.

Resume = run the same command again (or ``flgd train --out DIR``).  Restored
exactly: the step counter, action log, replay contents and priorities, online
and target weights, Adam state and learner update count as of the last
checkpoint (one is written at every clean exit, including Ctrl-C).  Not
restored: the scene in flight (a new one is dropped), the RNG streams (the
sim, agent, replay and curriculum generators are re-seeded from (seed,
segment number), so a resumed run is reproducible but not bit-identical to an
uninterrupted one), the replay's beta annealing counter (restarts at
``priority_beta_start``), and after a kill -9 the updates since the last
checkpoint (their transitions are kept and replayed).

Ctrl-C / SIGTERM: the cycle in flight finishes (a worker's is dropped), a checkpoint and the trainer
state are written, exit code 130.  A second Ctrl-C exits at once; the store
(SQLite WAL) and the atomic checkpoints stay consistent.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import logging
import math
import os
import time
from collections import deque
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from flgd.atomic_file import write_atomically
from flgd.config import CellConfig, dump_config
from flgd.cycle_commit import commit_cycle
from flgd.cycle_record import CycleOutcome
from flgd.learning_stack import CheckpointMeta, LearningStack
from flgd.store import CheckpointDir
from flgd.training.actions_csv import ActionsCsv
from flgd.training.collector import Collector, CollectorStart, LocalCollector
from flgd.training.progress import BarProgress, LineProgress
from flgd.training.settings import (RUN_FILE, TRAIN_VARIANTS, TRUNK_NETWORKS, RunFileError, RunSettings,
                                    effective_config, portable_config, read_run_info, variant_network)
from flgd.wiring import resume_seed

if TYPE_CHECKING:
    from flgd.learning.agent import Agent
    from flgd.learning.learner import Learner, UpdateStats
    from flgd.learning.networks import QMapNetwork
    from flgd.learning.replay import PrioritizedReplay, Transition
    from flgd.perception import Heightmaps
    from flgd.store import Store
    from flgd.training.collected import CellReport, CollectedCycle

__all__ = ["TRAIN_VARIANTS", "TRUNK_NETWORKS", "variant_network", "RunSettings", "RunFileError", "TrainingRun",
           "TrainingCellError", "effective_config", "read_run_info", "next_scene_id", "EXIT_OK", "EXIT_ERROR",
           "EXIT_USAGE", "EXIT_INTERRUPTED"]

log = logging.getLogger("flgd.train")

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
CONFIG_FILE = "config.yaml"
LOG_FILE = "actions.csv"
CURVE_FILE = "curve.png"
POLL_SECONDS = 1.0    # how often the progress display is refreshed while waiting for a worker


class TrainingCellError(RuntimeError):
    """A cell's cycle raised ("N cell faults in a row", a full disk): the run stops after keeping what it sent.
    The message names the error's type."""


def rolling(outcomes: deque, window: int) -> float | None:
    """Success rate of the last ``window`` grasps, None until the window is full."""
    if len(outcomes) < window:
        return None
    recent = list(outcomes)[-window:]
    return sum(recent) / window



@dataclasses.dataclass(frozen=True)
class _Kept:
    """A cycle kept under the run's step, waiting for its updates and its actions.csv row."""

    cell: tuple[int, int]   # (worker index, incarnation)
    cycle: CollectedCycle
    row: dict[str, Any]
    seconds: float   # its commit


class TrainingRun:
    """One run directory: set up (fresh or resumed), train to ``settings.steps``, stop cleanly."""

    def __init__(self, out: Path, settings: RunSettings, base_config: CellConfig,
                 progress: LineProgress | BarProgress,
                 threads: int | None = None, collector: Collector | None = None):
        """``collector``: where the cycles come from (default: one simulated cell in this process)."""
        self.out = out
        self.settings = settings
        self.progress = progress
        self.run_info = self._load_run_info()
        self.segment = len(self.run_info.get("segments", []))
        self.config = effective_config(base_config, settings, out, self.segment)
        if threads is not None:
            self.config = dataclasses.replace(self.config, learning=dataclasses.replace(
                self.config.learning, threads=threads))
        self.stop_signals: list[int] = []
        self._cpu_at_start = time.process_time()
        self.grasps: deque = deque(maxlen=200)
        self._lock_fd: int | None = None
        self.collector: Collector = collector if collector is not None else LocalCollector()
        self._next_step = int(self.run_info.get("step", 0))   # until setup reads the store
        self._next_scene = 0
        # per cell (worker index, incarnation): (its own scene number, the run's) it acts on; its newest kept
        # next state
        self._scene_of: dict[tuple[int, int], tuple[int, int]] = {}
        self._last_states: dict[tuple[int, int], Heightmaps] = {}
        # the daemon's learning stack; the priorities live in the trainer state (written with each checkpoint)
        self.learning = LearningStack(self.config, fine_tune=False, state_dir=out, few_moves=True,
                                      checkpoints=CheckpointDir(out / "checkpoints", keep=1_000_000),
                                      checkpoint_callback=self._checkpoint, priorities_in_store=False)
        # built by ``setup``
        self.store: Store | None = None
        self.replay: PrioritizedReplay | None = None
        self.agent: Agent | None = None
        self.learner: Learner | None = None
        self.actions: ActionsCsv | None = None  # actions.csv

    # ------------------------------------------------------------------ setup
    def _load_run_info(self) -> dict:
        return read_run_info(self.out) or {}

    def _write_run_info(self, status: str) -> None:
        info = dict(self.run_info)
        info.update({"settings": dataclasses.asdict(self.settings), "status": status,
                     "step": self.step,
                     "updates": self.learner.updates if self.learner is not None else info.get("updates", 0),
                     "rolling_success_50": rolling(self.grasps, 50),
                     "rolling_success_200": rolling(self.grasps, 200),
                     "updated": _now()})
        segments = info.get("segments")
        _move_old_worker_record(info)
        if segments and isinstance(segments[-1], dict) and self.learner is not None:
            # this process's CPU seconds in this segment: the learner's, and in one process the cell's too
            segments[-1]["process_cpu_seconds"] = round(time.process_time() - self._cpu_at_start, 1)
            segments[-1].update(self.collector.stats())
        if self.learner is not None:  # how the double-DQN a' of the targets was found (this segment)
            info["next_argmax"] = {"reused": self.learner.argmax_reused, "computed": self.learner.argmax_computed}
        self.run_info = info
        write_atomically(self.out / RUN_FILE, (json.dumps(info, indent=2) + "\n").encode(), mode=0o644)

    def _take_lock(self) -> None:
        """The state directory's one lock (``flgd.state_dir_lock``): a daemon or another run there refuses us."""
        from flgd.state_dir_lock import StateDirBusy, lock_state_dir

        try:
            self._lock_fd = lock_state_dir(self.out, create=True)
        except StateDirBusy as exc:
            raise RuntimeError(str(exc)) from None

    def setup(self) -> None:
        import torch

        from flgd.store import Store
        from flgd.training.state import remove_temporary as remove_trainer_state_temporaries

        self.collector.prepare()   # before the run directory is touched: a cluster that cannot be joined leaves it
        self.out.mkdir(parents=True, exist_ok=True)
        self._take_lock()
        if self.config.learning.threads > 0:
            torch.set_num_threads(self.config.learning.threads)
        self._write_config()
        self.store = self.learning.store = Store(self.out, keep_transitions=self.config.learning.replay_capacity)
        self.learning.checkpoints.remove_temporary()
        remove_trainer_state_temporaries(self.out)
        learning = self.learning
        network = learning.start_from(self.settings.init_policy or None)
        parts = learning.build(network, handover=self.collector.handover,
                               replay_seed=resume_seed(self.settings.seed, self.segment, 3),
                               agent_seed=resume_seed(self.settings.seed, self.segment, 4))
        if parts.replay_problem:
            raise RuntimeError(parts.replay_problem)
        self.replay, self.agent, self.learner = parts.replay, parts.agent, parts.learner
        self._restore_trainer_state()

        self.actions = ActionsCsv(self.out / LOG_FILE)
        self.actions.reconcile(self.store.action_log())
        for r in self.actions.rows:
            if r.get("primitive") == "grasp" and r.get("success") not in ("", None) \
                    and r.get("outcome", "executed") == "executed":
                self.grasps.append(int(float(r["success"])))

        self.store.remember_states = self.collector.cells   # each cell's last next state, their cycles interleaved
        self._next_step = step = self.store.next_step()
        self._next_scene = next_scene_id(self.actions.rows)
        self.collector.start(CollectorStart(self.config, self.settings, self.segment, step, self.agent, self.learner,
                                            self.store, self.progress.message, self.store.record_event))
        self._begin_segment(step)

    @property
    def step(self) -> int:
        """Actions kept so far (the next action's step)."""
        return self._next_step

    def _begin_segment(self, step: int) -> None:
        """A segment in run.json (one per start or resume) and the run's first lines."""
        learning = self.learning
        segments = list(self.run_info.get("segments", []))
        # the learning, exploration and object settings in force, so that a run whose config.yaml was
        # edited between segments (more updates per action, another object set) says so
        sim = self.config.sim
        segments.append({"started": _now(), "from_step": step, "from_updates": self.learner.updates,
                         "source": learning.source, "code": _code_version(),
                         "learning": dataclasses.asdict(self.config.learning),
                         "exploration": dataclasses.asdict(self.config.exploration),
                         "objects": {"object_set": sim.object_set, "domain_randomization": sim.domain_randomization,
                                     "depth_noise": sim.depth_noise}, **self.collector.segment_info()})
        self.run_info["segments"] = segments
        self.run_info.setdefault("created", _now())
        self.run_info["config_source"] = self.config.source
        self._write_run_info("running")
        self.store.record_event("train", f"segment {self.segment} from step {step}: {self.settings.describe()}")
        self.progress.message(f"flgd train: {self.settings.describe()} -> {self.out} "
                              f"({'resumed at step ' + str(step) if self.segment else 'new run'}; {learning.source})")

    def _restore_trainer_state(self) -> None:
        """The resumed learner's target network, Adam moments and priorities (``LearningStack``); what else, said."""
        outcome = self.learning.restore_trainer_state()
        if outcome.problem:
            self.progress.message(f"flgd train: trainer state not used ({outcome.problem}); fresh optimizer state")
        elif outcome.other_update is not None:
            self.progress.message(f"flgd train: trainer state is of update {outcome.other_update}, the checkpoint of "
                                  f"{self.learning.resumed_from_updates}: fresh optimizer state, default priorities")

    def _write_config(self) -> None:
        """config.yaml, atomically (a kill mid-write must not leave a file the resume cannot load), and
        only when it changed."""
        path = self.out / CONFIG_FILE
        data = dump_config(portable_config(self.config, self.out.resolve())).encode()
        try:
            if path.read_bytes() == data:
                return
        except OSError:
            pass
        write_atomically(path, data, mode=0o644)

    # ------------------------------------------------------------------ checkpoints
    def _checkpoint(self, network: QMapNetwork, updates: int) -> None:
        """Learner callback (inside an update): policy file + trainer state + curve."""
        r50, r200 = rolling(self.grasps, 50), rolling(self.grasps, 200)
        run = {"rolling_success": r200 if r200 is not None else r50,
               "rolling_success_50": r50, "rolling_success_200": r200,
               "method": TRAIN_VARIANTS[self.settings.variant][2], "train_variant": self.settings.variant,
               "seed": self.settings.seed, "curriculum": self.settings.curriculum, "objects": self.settings.objects,
               "grasp_only": self.settings.grasp_only}
        meta = CheckpointMeta(int(self.step), self.config.name or self.config.backend, updates,
                              f"flgd train {self.out.name}", run)
        self.learning.write_checkpoint(network, updates, meta)
        self.learning.write_trainer_state()
        self.write_curve()

    def record_failure(self) -> None:
        """After an error: the last checkpoint and run.json saying "failed", where the run got far enough to
        have them."""
        if self.learner is not None and self.actions is not None:
            self.final_checkpoint()
            self._write_run_info("failed")

    def final_checkpoint(self) -> None:
        if self.learning.owes_checkpoint():
            self._checkpoint(self.learner.online, self.learner.updates)
        else:
            self.write_curve()

    def write_curve(self) -> None:
        from flgd.training.curve import plot_curves

        try:
            plot_curves(self.out / CURVE_FILE, {self.settings.variant: self.actions.rows},
                        title=f"flgd train: {self.settings.describe()}")
        except Exception as exc:  # a plot must never cost a training run
            log.warning("learning curve not written: %s", exc)

    # ------------------------------------------------------------------ the loop
    def train(self) -> int:
        """Train until ``settings.steps`` or a stop signal; returns the exit code."""
        start_step, t0 = self._next_step, time.monotonic()
        target = self.settings.steps
        if start_step >= target:
            self.progress.message(f"flgd train: already at step {start_step} >= --steps {target}; nothing to do")
        self.progress.start(start_step, target)
        while self._next_step < target and not self.stop_signals:
            report = self.collector.next_report(POLL_SECONDS)
            if report is None:
                self._show(start_step, t0)
                continue
            kept = self._keep(report)
            if self._next_step < target:
                # the cell's next cycle starts before this one is learned from: with workers, the learner's
                # updates and the cycle run side by side (the worker acts with weights one action older)
                self.collector.go_on(report.cell, self._next_step)
            self._learn(kept)
            self._show(start_step, t0)
        interrupted = bool(self.stop_signals) and self._next_step < target
        self._show(start_step, t0, force=True)
        self.progress.finish()
        self.final_checkpoint()
        self._write_run_info("interrupted" if interrupted else "finished")
        dropped = self.collector.in_flight if interrupted else 0
        self.progress.message(f"flgd train: {'interrupted' if interrupted else 'finished'} at step "
                              f"{self._next_step}, {self.learner.updates} updates"
                              + (f", {workers} workers" if (workers := self.collector.segment_info().get("workers"))
                                 else "")
                              + (f" ({dropped} cycles in flight dropped)" if dropped else "")
                              + f"; log {self.out / LOG_FILE}, curve {self.out / CURVE_FILE}")
        return EXIT_INTERRUPTED if interrupted else EXIT_OK

    def _keep(self, report: CellReport) -> list[_Kept]:
        """Keep a cell's cycles under the run's next steps (``_learn`` learns from them and logs them); a cycle
        that raised in the cell stops the run after its rows are kept and learned from."""
        where = self.collector.where(report.cell)
        for key, version, index in report.decisions:  # the double-DQN a' the cell found, for the learner
            self.learner.note_greedy(key, version, index)
        for kind, event, message in report.notes:
            self.progress.message(f"flgd train: {where}{message}")
            if event:
                self.store.record_event(kind, f"{where}{event}")
        kept = []
        cell = (report.cell, report.incarnation)
        for cycle in report.cycles:
            if self._next_step >= self.settings.steps:
                break  # a cycle beyond --steps (several workers were in flight): not kept
            kept.append(self._commit(cell, cycle))
        if report.open_intent is not None and report.open_intent >= self._next_step:
            self._next_step = report.open_intent + 1   # used up by an intent that stays open (CellReport)
        if report.error:
            self._learn(kept)
            raise TrainingCellError(f"{where}{report.error}")
        return kept

    def _commit(self, cell: tuple[int, int], cycle: CollectedCycle) -> _Kept:
        """One collected cycle under the run's next step, kept as the daemon keeps a cycle; its transition
        schedules the learner's updates, which ``_learn`` runs."""
        row = dict(cycle.row, step=self._next_step)
        transition = self._relinked(cell, cycle.transition)
        committed = commit_cycle(row, transition, store=self.store, replay=self.replay, learner=self.learner)
        if transition is not None:
            if transition.next_state is None:
                self._last_states.pop(cell, None)
            else:
                self._last_states[cell] = transition.next_state
        self._next_step += 1
        return _Kept(cell, cycle, row, committed.seconds)

    def _relinked(self, cell: tuple[int, int], transition: Transition | None) -> Transition | None:
        """The transition with its state replaced by the very object kept as this cell's last next state, when
        it is that state (same pixels): the store, which remembers one recent next state per cell, then keeps
        it once instead of a second copy per action -- also when other cells' cycles were kept in between, and
        when the state came back from a worker as a copy."""
        previous = self._last_states.get(cell)
        if transition is None or previous is None:
            return transition
        state = transition.state
        if state is previous:
            return transition
        if previous.height.shape == state.height.shape and np.array_equal(previous.height, state.height) \
                and np.array_equal(previous.color, state.color):
            same = transition.next_state is transition.state
            return dataclasses.replace(transition, state=previous, next_state=previous if same
                                       else transition.next_state)
        return transition

    def _learn(self, kept: list[_Kept]) -> None:
        """The updates the kept cycles scheduled (``learning.updates_per_action`` each), then their rows in
        actions.csv (a fault's row stays in the store's action log only)."""
        t_update = time.perf_counter()
        updates = self.learner.update_pending()
        t_update = time.perf_counter() - t_update
        for k in kept:
            if k.cycle.outcome == CycleOutcome.FAULT:
                self._scene_of.pop(k.cell, None)
                continue
            scene = self._scene_of.get(k.cell)
            if scene is None or scene[0] != k.cycle.scene:  # a new scene of this cell: a new run-wide id
                scene = self._scene_of[k.cell] = (k.cycle.scene, self._next_scene)
                self._next_scene += 1
            self._log_step(k, scene[1], updates, t_update)

    def _log_step(self, kept: _Kept, scene: int, updates: list[UpdateStats], t_update: float) -> None:
        """One step's row in actions.csv and its grasp in the rolling success."""
        cycle = kept.cycle
        if cycle.outcome == CycleOutcome.EXECUTED and cycle.primitive == "grasp" and cycle.success is not None:
            self.grasps.append(int(cycle.success))
        row = {k: v for k, v in kept.row.items() if k in _LOG_KEYS}
        row.update({"objects_left": cycle.objects_left, "scene": scene, "scene_kind": cycle.scene_kind,
                    "updates": self.learner.updates, "loss": updates[-1].loss if updates else None,
                    "t_update": t_update, "t_store": kept.seconds})
        self.actions.append(row)

    def _show(self, start_step: int, t0: float, force: bool = False) -> None:
        done = self._next_step - start_step
        rate = done / max(1e-9, time.monotonic() - t0)
        eta = (self.settings.steps - self._next_step) / rate if rate > 0 else math.inf
        self.progress.show(self._next_step, self._status(rate if done else None, eta if done else None), force=force)

    def _status(self, rate: float | None, eta: float | None) -> dict[str, str]:
        """The progress fields: rolling grasp success, objects on the tables, learner updates, actions/s, ETA,
        workers alive."""
        r50, r200 = rolling(self.grasps, 50), rolling(self.grasps, 200)
        pct = lambda v: "-" if v is None else f"{100 * v:.0f}%"  # noqa: E731
        cells = self.collector.status()
        fields = {"grasp success": f"{pct(r50)} (last 50) {pct(r200)} (last 200)",
                  "objects": cells.pop("objects", "-"), "updates": str(self.learner.updates)}
        if rate is not None:
            fields["actions/s"] = f"{rate:.2f}"
        if eta is not None and math.isfinite(eta):
            fields["ETA"] = _duration(eta)
        fields.update(cells)
        return fields

    def close(self) -> None:
        for closer in (self.collector, self.store):
            if closer is not None:
                try:
                    closer.close()
                except Exception as exc:
                    log.error("close failed: %s", exc)
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None


_LOG_KEYS = frozenset({"step", "time", "outcome", "primitive", "kind", "row", "col", "rotation", "reward",
                       "success", "rule", "epsilon",
                       "q_value", "mu", "eta", "refused", "failure", "contact_stop_mm", "t_capture", "t_perceive", "t_decide",
                       "t_plan", "t_execute", "t_judge", "duration"})


def _move_old_worker_record(info: dict[str, Any]) -> None:
    """A run started before run.json kept workers per segment had one top-level ``workers`` list (its last
    multi-worker segment's): it moves into that segment, so that resuming keeps it."""
    old = info.pop("workers", None)
    if not isinstance(old, list):
        return
    for segment in reversed(info.get("segments") or []):
        if isinstance(segment, dict) and "workers" in segment and "worker_stats" not in segment:
            segment["worker_stats"] = old
            return


def next_scene_id(rows: list[dict[str, str]]) -> int:
    """The scene id a (re)started segment begins with: one past the last logged, since a new cell starts a
    new scene (ids stay unique across segments)."""
    ids = []
    for r in rows:
        try:
            ids.append(int(float(r.get("scene") or "")))
        except (ValueError, OverflowError):
            continue
    return max(ids) + 1 if ids else 0


def _code_version() -> str:
    """The git commit of the code a segment ran (runs that span sim changes must say so), '+dirty' if edited."""
    import subprocess

    repo = Path(__file__).resolve().parents[2]
    try:
        head = subprocess.run(["git", "-C", str(repo), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no", "flgd",
                                "sim_cell"], capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (head or "unknown") + ("+dirty" if dirty else "")


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _duration(seconds: float) -> str:
    seconds = int(seconds)
    h, rem = divmod(seconds, 3600)
    return f"{h}h{rem // 60:02d}m" if h else f"{rem // 60}m{rem % 60:02d}s"
