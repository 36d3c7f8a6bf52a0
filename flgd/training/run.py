"""``flgd train``: headless training in sim_cell with the daemon's cycle, agent, learner and store.

Nothing here is a second training loop: each step is ``CycleRunner.run_once``
(the daemon's cycle) followed by ``Learner.update_pending`` -- the
``learning.updates_per_action`` updates the daemon's learner thread would run,
but in this thread, so a run does not depend on thread timing.  Network,
replay, agent and learner are built by ``flgd.learning_stack`` exactly as the
daemon builds them.

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

Ctrl-C / SIGTERM: the cycle in flight finishes, a checkpoint and the trainer
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

from flgd.atomic_file import write_atomically
from flgd.config import CellConfig, dump_config
from flgd.cycle_record import CycleOutcome
from flgd.learning_stack import CheckpointMeta, Handover, LearningStack
from flgd.store import CheckpointDir
from flgd.training.actions_csv import ActionsCsv
from flgd.training.progress import BarProgress, LineProgress
from flgd.training.settings import (RUN_FILE, TRAIN_VARIANTS, TRUNK_NETWORKS, RunFileError, RunSettings,
                                    effective_config, read_run_info, variant_network)
from flgd.wiring import resume_seed

if TYPE_CHECKING:
    from flgd.cell import Cell
    from flgd.cycle import CycleRunner
    from flgd.learning.agent import Agent
    from flgd.learning.learner import Learner
    from flgd.learning.networks import QMapNetwork
    from flgd.learning.replay import PrioritizedReplay
    from flgd.store import Store
    from flgd.training.cell_loop import TrainingCell

__all__ = ["TRAIN_VARIANTS", "TRUNK_NETWORKS", "variant_network", "RunSettings", "RunFileError", "TrainingRun",
           "effective_config", "read_run_info", "next_scene_id", "EXIT_OK", "EXIT_ERROR", "EXIT_USAGE",
           "EXIT_INTERRUPTED"]

log = logging.getLogger("flgd.train")

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
CONFIG_FILE = "config.yaml"
LOG_FILE = "actions.csv"
CURVE_FILE = "curve.png"


def rolling(outcomes: deque, window: int) -> float | None:
    """Success rate of the last ``window`` grasps, None until the window is full."""
    if len(outcomes) < window:
        return None
    recent = list(outcomes)[-window:]
    return sum(recent) / window




class TrainingRun:
    """One run directory: set up (fresh or resumed), train to ``settings.steps``, stop cleanly."""

    # no gate in a training run: the learner's weights act as they are handed over
    learner_hands_to: Handover = Handover.AGENT

    def __init__(self, out: Path, settings: RunSettings, base_config: CellConfig,
                 progress: LineProgress | BarProgress,
                 threads: int | None = None):
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
        self.cell_loop: TrainingCell | None = None  # its cell and cycle runner below
        self.cell: Cell | None = None
        self.runner: CycleRunner | None = None

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
            segments[-1].update(self._segment_run_info())
        if self.learner is not None:  # how the double-DQN a' of the targets was found (this segment)
            info["next_argmax"] = {"reused": self.learner.argmax_reused, "computed": self.learner.argmax_computed}
        self.run_info = info
        write_atomically(self.out / RUN_FILE, (json.dumps(info, indent=2) + "\n").encode(), mode=0o644)

    def _segment_run_info(self) -> dict[str, Any]:
        """What a kind of run adds to its segment in run.json (the multi-worker run: its workers), so that a
        resumed run keeps every segment's record."""
        return {}

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
        parts = learning.build(network, handover=self.learner_hands_to,
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

        step = self.store.next_step()
        self._setup_cell(step)
        self._begin_segment(step)

    def _setup_cell(self, step: int) -> None:
        """The run's own simulated cell and cycle runner (``TrainingCell``), storing into the run's store."""
        from flgd.training.cell_loop import TrainingCell

        self.cell_loop = TrainingCell(self.config, self.settings, self.agent, step=step,
                                      scene=next_scene_id(self.actions.rows),
                                      curriculum_seed=resume_seed(self.settings.seed, self.segment, 5),
                                      note=self._note, store=self.store, replay=self.replay, learner=self.learner)
        self.cell, self.runner = self.cell_loop.cell, self.cell_loop.runner

    def _note(self, kind: str, event: str, message: str) -> None:
        """A fault or a give-up: said to the operator and kept in the store's events."""
        self.progress.message(f"flgd train: {message}")
        if event:
            self.store.record_event(kind, event)

    @property
    def step(self) -> int:
        """Actions taken so far (the next action's step)."""
        return self.runner.step if self.runner is not None else int(self.run_info.get("step", 0))

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
                                     "depth_noise": sim.depth_noise}})
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
        data = dump_config(self.config).encode()
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
        start_step, t0 = self.runner.step, time.monotonic()
        target = self.settings.steps
        if start_step >= target:
            self.progress.message(f"flgd train: already at step {start_step} >= --steps {target}; nothing to do")
        self.progress.start(start_step, target)
        while self.runner.step < target and not self.stop_signals:
            cycle = self.cell_loop.cycle()
            if cycle is None:
                continue
            record = cycle.record
            t_update = time.perf_counter()
            updates = self.learner.update_pending()
            t_update = time.perf_counter() - t_update
            self._log_step(record, cycle, updates, t_update, record.timings.get("store"))
            done = self.runner.step - start_step
            rate = done / max(1e-9, time.monotonic() - t0)
            eta = (target - self.runner.step) / rate if rate > 0 else math.inf
            self.progress.show(self.runner.step, self._status(rate, eta))
        interrupted = bool(self.stop_signals) and self.runner.step < target
        self.progress.show(self.runner.step, self._status(None, None), force=True)
        self.progress.finish()
        self.final_checkpoint()
        self._write_run_info("interrupted" if interrupted else "finished")
        self.progress.message(f"flgd train: {'interrupted' if interrupted else 'finished'} at step "
                              f"{self.runner.step}, {self.learner.updates} updates; log {self.out / LOG_FILE}, "
                              f"curve {self.out / CURVE_FILE}")
        return EXIT_INTERRUPTED if interrupted else EXIT_OK

    def _log_step(self, record: Any, cycle: Any, updates: list, t_update: float, t_store: float | None) -> None:
        """One step's row in actions.csv and its grasp in the rolling success."""
        if record.outcome == CycleOutcome.EXECUTED and record.primitive == "grasp" and record.success is not None:
            self.grasps.append(int(record.success))
        row = {k: v for k, v in record.row().items() if k in _LOG_KEYS}
        row.update({"objects_left": cycle.objects_left, "scene": cycle.scene, "scene_kind": cycle.scene_kind,
                    "updates": self.learner.updates, "loss": updates[-1].loss if updates else None,
                    "t_update": t_update, "t_store": t_store})
        self.actions.append(row)

    def _status(self, rate: float | None, eta: float | None, objects: str | None = None) -> dict[str, str]:
        """The progress fields: rolling grasp success, objects on the table, learner updates, actions/s, ETA."""
        r50, r200 = rolling(self.grasps, 50), rolling(self.grasps, 200)
        pct = lambda v: "-" if v is None else f"{100 * v:.0f}%"  # noqa: E731
        fields = {"grasp success": f"{pct(r50)} (last 50) {pct(r200)} (last 200)",
                  "objects": str(self.cell.object_count if objects is None else objects),
                  "updates": str(self.learner.updates)}
        if rate is not None:
            fields["actions/s"] = f"{rate:.2f}"
        if eta is not None and math.isfinite(eta):
            fields["ETA"] = _duration(eta)
        return fields

    def close(self) -> None:
        for closer in (self.cell_loop, self.store):
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
