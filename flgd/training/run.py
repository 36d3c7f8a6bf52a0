"""``flgd train``: headless training in sim_cell with the daemon's cycle, agent, learner and store.

Nothing here is a second training loop: each step is ``CycleRunner.run_once``
(the daemon's cycle) followed by ``Learner.update_pending`` -- the
``learning.updates_per_action`` updates the daemon's learner thread would run,
but in this thread, so a run does not depend on thread timing.  Network,
replay, agent and learner are built by ``flgd.wiring`` exactly as the daemon
builds them.

Run directory (``--out``), also the store's state directory:

* ``run.json``        -- settings, segments (one per start/resume), status;
* ``config.yaml``     -- the effective cell config of the run;
* ``flgd.sqlite``     -- the store: action log + replay transitions;
* ``checkpoints/``    -- policy files, every ``learning.checkpoint_every``
  updates and at exit (metadata: variant, method, steps, cell, rolling success);
* ``trainer-state.safetensors`` -- target network, Adam state, priorities;
* ``actions.csv``     -- one row per step (see flgd.training.actionlog);
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

import argparse
import dataclasses
import datetime as _dt
import fcntl
import json
import logging
import math
import os
import signal
import sys
import time
import traceback
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from flgd.atomic_file import write_atomically
from flgd.config import CellConfig, ConfigError, dump_config, load_sim_config

__all__ = ["TRAIN_VARIANTS", "TRUNK_NETWORKS", "variant_network", "RunSettings", "RunFileError", "TrainingRun", "effective_config", "read_run_info",
           "main", "EXIT_INTERRUPTED"]

log = logging.getLogger("flgd.train")

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
RUN_FILE = "run.json"
CONFIG_FILE = "config.yaml"
LOG_FILE = "actions.csv"
CURVE_FILE = "curve.png"
MAX_CONSECUTIVE_FAULTS = 5

# variant -> (network on the fast trunk, masks, paper method).  The variant picks the head and the masks;
# the config's learning.network picks the trunk (TRUNK_NETWORKS), so the paper's DenseNet-121 trains too.
TRAIN_VARIANTS: dict[str, tuple[str, bool, str]] = {
    "flg": ("fast", True, "FLG"),
    "dpen": ("fast", False, "DPEN"),
    "rho-fcn": ("rho-fcn-fast", True, "rho-FCN"),
}
# trunk -> variant -> learning.network.  Each learning.network names one trunk (rho-fcn is the VPG head on the
# DenseNet-121, rho-fcn-fast the same head on the fast trunk).
TRUNK_NETWORKS: dict[str, dict[str, str]] = {
    "fast": {"flg": "fast", "dpen": "fast", "rho-fcn": "rho-fcn-fast"},
    "densenet121": {"flg": "densenet121", "dpen": "densenet121", "rho-fcn": "rho-fcn"},
}
_TRUNK_OF = {net: trunk for trunk, nets in TRUNK_NETWORKS.items() for net in nets.values()}


def variant_network(variant: str, network: str) -> str:
    """The learning.network that trains ``variant`` on the trunk of the config's ``network``
    (fast or densenet121; its head, FLG or VPG, is the variant's)."""
    if variant not in TRAIN_VARIANTS:
        raise ValueError(f"variant: got {variant!r}, expected one of {', '.join(sorted(TRAIN_VARIANTS))}")
    if network not in _TRUNK_OF:
        raise ValueError(f"learning.network: got {network!r}, expected one of {', '.join(sorted(_TRUNK_OF))}")
    return TRUNK_NETWORKS[_TRUNK_OF[network]][variant]


@dataclass(frozen=True)
class RunSettings:
    variant: str = "flg"
    objects: int = 10
    steps: int = 1000
    seed: int = 0
    curriculum: bool = False
    grasp_only: bool = False
    init_policy: str = ""  # a new run starts from this policy file's weights (fresh replay and optimizer)
    give_up_after: int = 0  # new scene after this many actions in a row without a successful grasp (0 = never)

    def describe(self) -> str:
        scene = "curriculum 10->20 objects + presets" if self.curriculum else f"{self.objects} objects"
        mode = ", grasp only" if self.grasp_only else ""
        start = f", from {self.init_policy}" if self.init_policy else ""
        give_up = f", new scene after {self.give_up_after} actions without a grasp" if self.give_up_after else ""
        return f"{self.variant} ({TRAIN_VARIANTS[self.variant][2]}), {scene}{mode}, seed {self.seed}{start}{give_up}"


class RunFileError(ValueError):
    """A run directory's run.json that cannot be used; the message names the file, the problem and what to do."""


def read_run_info(out: Path) -> dict | None:
    """The run.json of run directory ``out``, None if it has none; a damaged one is a ``RunFileError``.

    Never guess: a run.json that does not parse or is not a run's record must not be taken for "no run"
    (a new run would be started over the old one's store and checkpoints)."""
    path = Path(out) / RUN_FILE
    if not path.exists():
        return None
    fix = (f"the run in {path.parent} was not changed; restore {RUN_FILE} (its settings are also in "
           f"the policy metadata of checkpoints/) or start the run in another directory")
    from flgd.training.records import read_json_record

    try:
        info = read_json_record(path, fix)
    except ValueError as exc:
        raise RunFileError(str(exc)) from None
    if not isinstance(info, dict):
        raise RunFileError(f"{path}: expected a JSON object (settings, segments, status), got "
                           f"{type(info).__name__}; {fix}")
    settings = info.get("settings")
    if not isinstance(settings, dict):
        raise RunFileError(f"{path}: key 'settings': expected an object of the run's settings, got "
                           f"{'nothing' if settings is None else type(settings).__name__}; {fix}")
    defaults = dataclasses.asdict(RunSettings())
    for key, value in settings.items():
        if key not in defaults:
            continue
        want = type(defaults[key])
        ok = isinstance(value, want) and (want is bool or not isinstance(value, bool))
        if key == "variant" and ok and value not in TRAIN_VARIANTS:
            raise RunFileError(f"{path}: settings.variant: got {value!r}, expected one of "
                               f"{sorted(TRAIN_VARIANTS)}; {fix}")
        if not ok:
            raise RunFileError(f"{path}: settings.{key}: got {value!r}, expected {want.__name__}; {fix}")
    if not isinstance(info.get("segments", []), list):
        raise RunFileError(f"{path}: key 'segments': expected a list, got {type(info['segments']).__name__}; "
                           f"{fix}")
    return info


def _derived_seed(seed: int, segment: int, stream: int) -> int:
    """Segment 0 uses ``seed`` itself; a resumed segment gets fresh, reproducible streams."""
    if segment == 0:
        return seed
    return int(np.random.SeedSequence([seed, segment, stream]).generate_state(1)[0])


def effective_config(base: CellConfig, settings: RunSettings, out: Path, segment: int = 0) -> CellConfig:
    """The cell config of a run: variant, objects, seeds, curriculum and the run directory as state dir.
    The variant sets the head and the masks, ``base.learning.network`` the trunk (``variant_network``)."""
    from flgd.curriculum import Curriculum

    _, masks, _ = TRAIN_VARIANTS[settings.variant]
    network = variant_network(settings.variant, base.learning.network)
    cfg = dataclasses.replace(
        base,
        state_dir=str(out),
        policy="",
        learning=dataclasses.replace(base.learning, network=network, seed=_derived_seed(settings.seed, segment, 1)),
        exploration=dataclasses.replace(base.exploration, masks=masks, grasp_only=settings.grasp_only),
        sim=dataclasses.replace(base.sim, objects=settings.objects, seed=_derived_seed(settings.seed, segment, 2),
                                scene=""))
    if settings.curriculum:
        cfg = Curriculum().apply_to_config(cfg)
    return cfg


def rolling(outcomes: deque, window: int) -> float | None:
    """Success rate of the last ``window`` grasps, None until the window is full."""
    if len(outcomes) < window:
        return None
    recent = list(outcomes)[-window:]
    return sum(recent) / window


class _Progress:
    """A one-line live display on a terminal, periodic plain lines otherwise."""

    def __init__(self, stream, live: bool, every_steps: int = 25, every_seconds: float = 60.0):
        self.stream, self.live = stream, live
        self.every_steps, self.every_seconds = every_steps, every_seconds
        self.last_print = 0.0
        self.last_step = -1

    def show(self, step: int, text: str, force: bool = False) -> None:
        now = time.monotonic()
        if self.live:
            try:
                width = os.get_terminal_size(self.stream.fileno()).columns - 1
            except OSError:
                width = 120
            self.stream.write("\r\033[K" + text[:max(20, width)])
            self.stream.flush()
        elif force or step - self.last_step >= self.every_steps or now - self.last_print >= self.every_seconds:
            self.stream.write(text + "\n")
            self.stream.flush()
            self.last_print, self.last_step = now, step

    def message(self, text: str) -> None:
        self.stream.write(("\r\033[K" if self.live else "") + text + "\n")
        self.stream.flush()

    def finish(self) -> None:
        if self.live:
            self.stream.write("\n")
            self.stream.flush()


class TrainingRun:
    """One run directory: set up (fresh or resumed), train to ``settings.steps``, stop cleanly."""

    def __init__(self, out: Path, settings: RunSettings, base_config: CellConfig, progress: _Progress,
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
        self.grasps: deque = deque(maxlen=200)
        self.scene_count = 0
        # (objects, scene kind) of the scene the current cycle acts on, noted before the runner resets it
        self._cycle_scene: tuple[int | None, str] = (None, "")
        self.last_checkpoint_updates = -1
        self.consecutive_faults = 0
        self.actions_without_grasp = 0  # in the current scene (give_up_after)
        self._lock_fd: int | None = None

    # ------------------------------------------------------------------ setup
    def _load_run_info(self) -> dict:
        return read_run_info(self.out) or {}

    def _write_run_info(self, status: str) -> None:
        info = dict(self.run_info)
        info.update({"settings": dataclasses.asdict(self.settings), "status": status,
                     "step": self.runner.step if hasattr(self, "runner") else info.get("step", 0),
                     "updates": self.learner.updates if hasattr(self, "learner") else info.get("updates", 0),
                     "rolling_success_50": rolling(self.grasps, 50),
                     "rolling_success_200": rolling(self.grasps, 200),
                     "updated": _now()})
        if hasattr(self, "learner"):  # how the double-DQN a' of the targets was found (this segment)
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

        from flgd.cell import make_cell
        from flgd.cycle import CycleRunner
        from flgd.store import CheckpointDir, Store
        from flgd.training.actionlog import ActionLog
        from flgd.wiring import build_agent_and_learner, rebuild_replay, starting_network

        self.out.mkdir(parents=True, exist_ok=True)
        self._take_lock()
        if self.config.learning.threads > 0:
            torch.set_num_threads(self.config.learning.threads)
        self._write_config()
        self.store = Store(self.out, keep_transitions=self.config.learning.replay_capacity)
        self.checkpoints = CheckpointDir(self.out / "checkpoints", keep=1_000_000)
        self.checkpoints.remove_temporary()
        from flgd.training.state import remove_temporary as remove_trainer_state_temporaries

        remove_trainer_state_temporaries(self.out)
        start = starting_network(self.config, self.checkpoints, self.settings.init_policy or None)
        self.last_checkpoint_updates = start.resumed_from_updates if start.checkpoint else -1
        replay_seed = _derived_seed(self.settings.seed, self.segment, 3)
        self.replay, problem = rebuild_replay(self.config, self.store, seed=replay_seed)
        if problem:
            raise RuntimeError(problem)
        self.agent, self.learner = build_agent_and_learner(
            self.config, start.network, self.replay, checkpoint_callback=self._checkpoint,
            updates=start.resumed_from_updates, agent_seed=_derived_seed(self.settings.seed, self.segment, 4))
        self._restore_trainer_state(start.resumed_from_updates if start.checkpoint else None)

        self.actions = ActionLog(self.out / LOG_FILE)
        self.actions.reconcile(self.store.action_log())
        for r in self.actions.rows:
            if r.get("primitive") == "grasp" and r.get("success") not in ("", None) \
                    and r.get("outcome", "executed") == "executed":
                self.grasps.append(int(float(r["success"])))

        step = self.store.next_step()
        cell = make_cell(self.config)
        self.scene_count = _next_scene_id(self.actions.rows)
        if self.settings.curriculum:
            from flgd.curriculum import Curriculum, CurriculumCell
            from sim_cell.cell import preset_scenes

            curriculum = Curriculum()
            cell.set_object_count(curriculum.object_count(step))
            cell.reset_scene()
            rng = np.random.default_rng(_derived_seed(self.settings.seed, self.segment, 5))
            cell = CurriculumCell(cell, curriculum, lambda: self.runner.step, preset_scenes(), rng)
            cell.scene_kind = f"random {curriculum.object_count(step)}"
        self.cell = cell
        self.runner = CycleRunner(self.config, cell, self.agent, store=self.store, replay=self.replay,
                                  learner=self.learner, step=step, backend=self.config.backend,
                                  on_phase=self._on_phase)
        segments = list(self.run_info.get("segments", []))
        # the learning, exploration and object settings in force, so that a run whose config.yaml was
        # edited between segments (more updates per action, another object set) says so
        sim = self.config.sim
        segments.append({"started": _now(), "from_step": step, "from_updates": self.learner.updates,
                         "source": start.source, "code": _code_version(),
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
                              f"({'resumed at step ' + str(step) if self.segment else 'new run'}; {start.source})")

    def _restore_trainer_state(self, checkpoint_updates: int | None) -> None:
        from flgd.training.state import TRAINER_STATE, load_trainer_state, restore_learner

        path = self.out / TRAINER_STATE
        if checkpoint_updates is None or not path.exists():
            return
        try:
            state = load_trainer_state(path)
        except (OSError, ValueError, RuntimeError) as exc:
            self.progress.message(f"flgd train: trainer state not used ({exc}); fresh optimizer state")
            return
        if state.updates != checkpoint_updates:
            self.progress.message(f"flgd train: trainer state is of update {state.updates}, the checkpoint of "
                                  f"{checkpoint_updates}: fresh optimizer state, default priorities")
            return
        restore_learner(self.learner, state)
        saved = dict(zip(state.priority_ids.tolist(), state.priorities.tolist()))
        eps = self.config.learning.priority_epsilon
        for slot, tid in enumerate(self._slot_tags()):
            if tid in saved:
                self.replay.update_priorities([slot], [max(0.0, saved[tid] - eps)])

    def _slot_tags(self) -> list[int | None]:
        """The store's transition id in each replay slot, read from the replay itself.

        Not counted alongside: a cycle that raises after its transition was added (a scene reset
        failing, say) would shift such a count and attach saved priorities to other transitions."""
        return [self.replay.tag(i) for i in range(len(self.replay))]

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
    def _checkpoint(self, network: Any, updates: int) -> None:
        """Learner callback (inside an update): policy file + trainer state + curve."""
        from flgd.learning.policy_file import save_policy
        from flgd.training.state import TRAINER_STATE, save_trainer_state

        r50, r200 = rolling(self.grasps, 50), rolling(self.grasps, 200)
        meta = {"training_steps": int(self.runner.step), "cell": self.config.name or self.config.backend,
                "rolling_success": r200 if r200 is not None else r50,
                "rolling_success_50": r50, "rolling_success_200": r200,
                "method": TRAIN_VARIANTS[self.settings.variant][2], "train_variant": self.settings.variant,
                "learner_updates": int(updates), "seed": self.settings.seed,
                "curriculum": self.settings.curriculum, "objects": self.settings.objects,
                "grasp_only": self.settings.grasp_only, "source": f"flgd train {self.out.name}"}
        self.checkpoints.write(lambda p: save_policy(p, network, meta), updates)
        tagged = [(slot, tid) for slot, tid in enumerate(self._slot_tags()) if tid is not None]
        save_trainer_state(self.out / TRAINER_STATE, self.learner,
                           np.array([tid for _, tid in tagged], dtype=np.int64),
                           np.array([self.replay.priority(slot) for slot, _ in tagged], dtype=np.float64))
        self.store.set_counter("learner_updates", updates)
        self.last_checkpoint_updates = updates
        self.write_curve()

    def final_checkpoint(self) -> None:
        if self.learner.updates > max(0, self.last_checkpoint_updates):
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
    def _on_phase(self, name: str) -> None:
        """Note the scene an action acts on while it is still there: a cycle that ends its scene resets it
        before returning, so reading the cell afterwards would describe the next scene."""
        if name in ("plan", "judge"):
            cell = self.cell
            kind = getattr(cell, "scene_kind", f"random {self.settings.objects}") if name == "plan" \
                else self._cycle_scene[1]
            self._cycle_scene = (cell.object_count, kind)

    def _handle_fault(self, exc: Exception) -> None:
        """A cell fault or a simulator error inside a cycle: recover, new scene; give up after several in a row."""
        from flgd.cell import CellFault

        self.consecutive_faults += 1
        what = str(exc) if isinstance(exc, CellFault) else f"{type(exc).__name__}: {exc}"
        self.progress.message(f"flgd train: cell fault at step {self.runner.step}: {what}; recovering")
        self.store.record_event("fault", what)
        while True:
            if self.consecutive_faults >= MAX_CONSECUTIVE_FAULTS:
                raise RuntimeError(f"{self.consecutive_faults} cell faults in a row; last: {what}")
            try:
                self.cell.recover()
                self.cell.reset_scene()
                break
            except Exception as again:  # recovering failed too: count it and try again
                self.consecutive_faults += 1
                what = f"recovery: {type(again).__name__}: {again}"
                self.progress.message(f"flgd train: {what}")
        self.runner.forget_state()
        self.agent.reset_episode()
        self.actions_without_grasp = 0

    def train(self) -> int:
        """Train until ``settings.steps`` or a stop signal; returns the exit code."""
        from flgd.cell import CellFault
        from flgd.store import StoreError

        start_step, t0 = self.runner.step, time.monotonic()
        target = self.settings.steps
        if start_step >= target:
            self.progress.message(f"flgd train: already at step {start_step} >= --steps {target}; nothing to do")
        while self.runner.step < target and not self.stop_signals:
            try:
                record = self.runner.run_once()
            except CellFault as exc:
                self._handle_fault(exc)
                self.scene_count += 1
                continue
            except StoreError:
                raise  # disk full, read-only ...: stop with a checkpoint rather than lose steps
            except Exception as exc:  # the simulator failing inside a cycle: log it, new scene, go on
                traceback.print_exc(file=sys.stderr)
                self._handle_fault(exc)
                self.scene_count += 1
                continue
            self.consecutive_faults = 0
            if record.outcome == "empty" or record.step is None:
                self.scene_count += 1
                continue
            t_update = time.perf_counter()
            updates = self.learner.update_pending()
            t_update = time.perf_counter() - t_update
            if record.outcome == "executed" and record.primitive == "grasp" and record.success is not None:
                self.grasps.append(int(record.success))
            objects, kind = self._cycle_scene
            row = {k: v for k, v in record.row().items() if k in _LOG_KEYS}
            # a discarded action's scene blew up and was replaced: its object count means nothing
            row.update({"objects_left": None if record.outcome == "discarded" else objects,
                        "scene": self.scene_count,
                        "scene_kind": kind,
                        "updates": self.learner.updates,
                        "loss": updates[-1].loss if updates else None, "t_update": t_update,
                        "t_store": record.timings.get("store")})
            self.actions.append(row)
            if record.done or record.outcome == "discarded":  # the runner has started a new scene
                self.scene_count += 1
                self.actions_without_grasp = 0
            elif record.outcome == "executed":
                self._maybe_give_up(record)
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

    def _maybe_give_up(self, record) -> None:
        """A new scene after ``give_up_after`` actions in a row without a successful grasp.

        Why: a scene the policy cannot clear is otherwise kept for ever, and
        the move reward pays for shuffling its last objects about (each shift
        changes the heightmap by more than tau1): a fine-tune collapsed that
        way on a single block (BENCHMARKS.md, "Fine-tuning the shipped policy").
        """
        if record.primitive == "grasp" and record.success:
            self.actions_without_grasp = 0
            return
        self.actions_without_grasp += 1
        limit = self.settings.give_up_after
        if limit <= 0 or self.actions_without_grasp < limit:
            return
        what = (f"{self.actions_without_grasp} actions without a successful grasp at step {self.runner.step}, "
                f"{self.cell.object_count} objects left: new scene")
        self.progress.message(f"flgd train: {what}")
        self.store.record_event("give-up", what)
        self.scene_count += 1
        self.actions_without_grasp = 0
        try:
            self.cell.reset_scene()
        except Exception as exc:  # the simulator failing to lay out the new scene: recover as from a fault
            self._handle_fault(exc)
            return
        self.runner.forget_state()
        self.agent.reset_episode()

    def _status(self, rate: float | None, eta: float | None) -> str:
        r50, r200 = rolling(self.grasps, 50), rolling(self.grasps, 200)
        pct = lambda v: "-" if v is None else f"{100 * v:.0f}%"  # noqa: E731
        text = (f"step {self.runner.step}/{self.settings.steps} | grasp success {pct(r50)} (last 50) "
                f"{pct(r200)} (last 200) | objects {self.cell.object_count}")
        if rate is not None:
            text += f" | {rate:.2f} actions/s"
        if eta is not None and math.isfinite(eta):
            text += f" | ETA {_duration(eta)}"
        return text

    def close(self) -> None:
        for closer in (getattr(self, "cell", None), getattr(self, "store", None)):
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


def _next_scene_id(rows: list[dict[str, str]]) -> int:
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


# ---------------------------------------------------------------------- command line

def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="flgd train", description="Train a policy headless in sim_cell (the daemon's cycle, agent and "
                                       "learner; synchronous updates).  Run again with the same --out to resume.")
    p.add_argument("--config", help="cell config YAML (backend sim); optional when resuming --out")
    p.add_argument("--variant", choices=sorted(TRAIN_VARIANTS),
                   help="flg (default), dpen (no masks), rho-fcn (VPG head); the trunk is the config's "
                        "learning.network (fast or densenet121, the paper's)")
    p.add_argument("--objects", type=int, help="objects per random scene (default 10; not with --curriculum)")
    p.add_argument("--steps", type=int, help="train until this many steps (actions) in total (default 1000)")
    p.add_argument("--seed", type=int, help="seed of the sim, network, agent and replay (default 0)")
    p.add_argument("--out", required=True, help="run directory (created; resumed if it holds a run)")
    p.add_argument("--curriculum", action="store_true", default=None,
                   help="paper IV-A curriculum: few moves for 500 steps, 10 -> 20 objects from step 400, "
                        "preset piles after 1500 steps")
    p.add_argument("--grasp-only", action="store_true", default=None, help="never move (paper's Grasping-only)")
    p.add_argument("--init-policy", metavar="FILE",
                   help="start a new run from this policy file (e.g. to fine-tune the shipped policy on other "
                        "objects) instead of a fresh network; the replay and optimizer start empty")
    p.add_argument("--give-up-after", type=int, metavar="N",
                   help="start a new scene after N actions in a row without a successful grasp (default 0: never; "
                        "a run started without it keeps never)")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: learning.threads of the config)")
    p.add_argument("--log-every", type=int, default=25, help="steps between plain progress lines (no terminal)")
    return p


def _settings(args: argparse.Namespace, previous: dict | None) -> RunSettings:
    """Settings from the command line, checked against a run being resumed."""
    given = {"variant": args.variant, "objects": args.objects, "steps": args.steps, "seed": args.seed,
             "curriculum": args.curriculum, "grasp_only": args.grasp_only,
             "init_policy": None if args.init_policy is None else str(Path(args.init_policy).resolve()),
             "give_up_after": args.give_up_after}
    if previous:
        for key, value in given.items():
            before = previous.get(key, getattr(RunSettings(), key))  # a key newer than the run: its default
            if key != "steps" and value is not None and value != before:
                raise ValueError(f"--{key.replace('_', '-')}: got {value!r}, but the run in --out was started "
                                 f"with {before!r}; use another --out for other settings")
        merged = {**dataclasses.asdict(RunSettings()), **previous, **{k: v for k, v in given.items() if v is not None}}
        return RunSettings(**{f.name: merged[f.name] for f in dataclasses.fields(RunSettings)})
    defaults = RunSettings()
    s = RunSettings(**{k: (getattr(defaults, k) if v is None else v) for k, v in given.items()})
    if s.curriculum and args.objects is not None:
        raise ValueError("--objects: the curriculum sets the object count (10 -> 20); drop one of the two")
    if s.curriculum:
        s = dataclasses.replace(s, objects=10)
    return s


def main(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    out = Path(args.out).resolve()
    try:
        previous_info = read_run_info(out)
    except RunFileError as exc:
        print(f"flgd train: {exc}", file=sys.stderr)
        return EXIT_USAGE
    try:
        settings = _settings(args, previous_info.get("settings") if previous_info else None)
        for name in ("objects", "steps", "seed", "give_up_after"):
            v = getattr(settings, name)
            if v < 0 or (name == "objects" and not 1 <= v <= 60):
                raise ValueError(f"--{name.replace('_', '-')}: got {v!r}, expected "
                                 + ("1..60" if name == "objects" else ">= 0"))
        if args.threads is not None and args.threads < 0:
            raise ValueError(f"--threads: got {args.threads!r}, expected >= 0")
    except ValueError as exc:
        print(f"flgd train: {exc}", file=sys.stderr)
        return EXIT_USAGE
    config_path = args.config or (str(out / CONFIG_FILE) if previous_info else None)
    if config_path is None:
        print("flgd train: --config is required for a new run", file=sys.stderr)
        return EXIT_USAGE
    try:
        base = load_sim_config(config_path, "training runs in sim_cell; fine-tune on a real cell with `flgd run`")
    except ConfigError as exc:
        print(f"flgd train: {exc}", file=sys.stderr)
        return EXIT_USAGE
    try:
        network = variant_network(settings.variant, base.learning.network)
        if settings.init_policy and not previous_info:
            from flgd.learning.policy_file import PolicyFileError, load_policy
            try:
                load_policy(settings.init_policy, expected_variant=network)
            except PolicyFileError as exc:
                raise ValueError(f"--init-policy: {exc}") from None
    except ValueError as exc:
        print(f"flgd train: {config_path}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if base.learning.init_trunk and not previous_info and not settings.init_policy:
        from flgd.learning.trunk import TrunkFileError
        from flgd.wiring import fresh_network
        try:  # a new run would start from it: refuse a trunk that does not fit before anything starts
            fresh_network(effective_config(base, settings, out), None)
        except TrunkFileError as exc:
            print(f"flgd train: {config_path}: learning.init_trunk: {exc}", file=sys.stderr)
            return EXIT_USAGE

    live = sys.stderr.isatty()
    progress = _Progress(sys.stderr, live, every_steps=max(1, args.log_every))
    run = TrainingRun(out, settings, base, progress, threads=args.threads)

    def on_signal(signum, _frame) -> None:
        run.stop_signals.append(signum)
        if len(run.stop_signals) > 1:
            sys.stderr.write("\nflgd train: second interrupt, exiting now (the store and checkpoints are "
                             "consistent; the updates since the last checkpoint are lost)\n")
            sys.stderr.flush()
            os._exit(EXIT_INTERRUPTED)
        progress.message("flgd train: stopping after the current step (Ctrl-C again to exit at once)")

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        run.setup()
        return run.train()
    except Exception as exc:
        progress.finish()
        print(f"flgd train: {type(exc).__name__}: {exc}", file=sys.stderr)
        if hasattr(run, "learner") and hasattr(run, "runner"):
            try:
                run.final_checkpoint()
                run._write_run_info("failed")
            except Exception as exc2:
                print(f"flgd train: final checkpoint failed: {exc2}", file=sys.stderr)
        return EXIT_ERROR
    finally:
        run.close()
        for sig, handler in previous.items():  # called in-process (tests, scripts): leave no handler behind
            signal.signal(sig, handler)
