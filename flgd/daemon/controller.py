"""The daemon's orchestration: cell, agent, learner, store and state machine around the one cycle.

Threads: the run loop (the caller's thread, normally the main thread) is the
only one that touches the cell and the acting networks, so commands that need
them (reset, backend, a first snapshot, a policy load, the gate's overrides)
are queued to it and executed between cycles.  The learner trains in its own
thread and hands its weights over on a schedule: to the champion/challenger
gate (flgd/gate/keeper.py), which decides between cycles whether they act, or,
with the gate off, straight to the agent's mailbox; a decision never waits for it.

Learner settings: with a policy given the daemon fine-tunes it (the config's
``finetune`` section replaces ``learning``'s learning rate, updates per action,
BatchNorm mode, warm-up and double-DQN target; exploration continues from the policy's recorded
training steps, capped at ``finetune.max_epsilon``); without one it trains a fresh
network from scratch with ``learning`` as written.  Control connections have their own threads and
only read state, validate input and queue work; what each operator command does is in its handler
(flgd/daemon/commands.py), which ``handle`` looks up.

The run loop, faults, reset and shutdown share the state machine, the learning lock and the stop latch, and each
depends on the others' order of events (a stop during a reset, a fault during a checkpoint).  The steps of start-up
are in flgd/daemon/startup.py; the learning parts are built by flgd/learning_stack.py.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import os
import queue
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from flgd.memory import trim_heap
from flgd.calibration_watch import CalibrationWatch
from flgd.cell import Cell, CellFault, StopPending
from flgd.config import CellConfig, fine_tunes
from flgd.cycle import CycleRecord, CycleRunner
from flgd.cycle_record import CycleOutcome
from flgd.daemon import commands, startup
from flgd.daemon.notify import Notifier
from flgd.daemon.protocol import ProtocolError, Request
from flgd.daemon.startup import StartupError
from flgd.daemon.state import IllegalTransition, State, StateChange, StateMachine
from flgd.learning_stack import LEARNER_QUIET_TIMEOUT, CheckpointMeta, GateStart, Handover, LearningStack
from flgd.safety import PlanRefused
from flgd.store import CheckpointDir, Store, StoreError

if TYPE_CHECKING:
    from flgd.cell import Frame
    from flgd.learning.networks import QMapNetwork

__all__ = ["Controller", "StartupError"]

log = logging.getLogger("flgd")

COMMAND_TIMEOUT = 120.0  # seconds a control request waits for the run loop
# The cause of RUNNING -> PAUSED when a cell that cannot refill its own table finds nothing to grasp.
EMPTY_WORKSPACE_CAUSE = "workspace empty/nothing graspable: refill the table, then flgctl start"
ACCEPTING_COMMANDS = frozenset({State.IDLE, State.RUNNING, State.PAUSED, State.FAULT})


def _stack_field(name: str, doc: str) -> property:
    """A field the controller's learning stack keeps about its run (``Controller.learning``)."""
    return property(lambda self: getattr(self.learning, name), lambda self, value: setattr(self.learning, name, value),
                    doc=doc)


def _learning_part(name: str, doc: str) -> property:
    """A part of the controller's learning stack (``Controller.learning``), read-only: a part changes only by a
    rebuild of the stack."""
    return property(lambda self: getattr(self.learning, name) if self.learning.parts is not None else None, doc=doc)


class Controller:
    """Owns everything the daemon runs; ``setup`` then ``run_loop``; ``handle`` serves requests."""

    agent = _learning_part("agent", "the acting agent")
    learner = _learning_part("learner", "the background learner")
    replay = _learning_part("replay", "the learner's replay")
    prior = _stack_field("prior", "the fine-tune's prior sample (finetune.prior_sample), loaded in setup")
    gate = _learning_part("gate", "the Gatekeeper (None while the store is unusable)")
    gate_note = _learning_part("gate_note", "what the acting policy is, as the gate restored it")
    policy_source = _stack_field("source", "what the learner started from")
    resumed_from_updates = _stack_field("resumed_from_updates", "the update count the learner continued from")
    trainer_state = _stack_field("trainer_state", "what the learner's target network and Adam moments started from")
    last_checkpoint = _stack_field("last_checkpoint", "the newest checkpoint resumed from or written")

    def __init__(self, config: CellConfig, *, policy_path: str | None = None, autostart: bool = False,
                 notifier: Notifier | None = None, checkpoint_keep: int = 3,
                 learner_quiet_timeout: float = LEARNER_QUIET_TIMEOUT):
        self.config = config
        self.policy_arg = policy_path if policy_path is not None else (config.policy or None)
        self.fine_tune, self.learning_why = fine_tunes(dataclasses.replace(config, policy=self.policy_arg or ""))
        self.autostart = autostart
        self.notifier = notifier or Notifier({})
        self.state = StateMachine(State.IDLE)
        self.state.add_listener(self._on_state_change)
        self.state_dir = Path(config.state_dir)
        self.checkpoints = CheckpointDir(self.state_dir / "checkpoints", keep=checkpoint_keep)
        # replay, agent, learner, gate and prior sample (flgd/learning_stack.py), on the store once it is open
        self.learning = LearningStack(config, fine_tune=self.fine_tune, state_dir=self.state_dir,
                                      checkpoints=self.checkpoints, checkpoint_callback=self.write_checkpoint)
        self.store: Store | None = None
        self.store_problem = ""
        self.cell: Cell | None = None
        self.backend = config.backend
        self._start_network: QMapNetwork | None = None
        self.runner: CycleRunner | None = None
        self.last_record: CycleRecord | None = None
        self.last_stuck: dict[str, Any] | None = None  # the newest time the cell declared itself stuck
        cw = config.calibration_watch
        self.calibration_watch = (CalibrationWatch(cw, config.workspace, config.rewards, config.camera.depth_range)
                                  if cw.enabled else None)
        self._watched_frame: Frame | None = None  # the frame the calibration watch judged last
        self.cycle_in_flight = False
        self._learning_problem = ""
        self.learning_lock = threading.Lock()  # a policy load and a learner rebuild never interleave
        # how long a policy load or a learner restart waits for the learner's update in progress
        self.learner_quiet_timeout = learner_quiet_timeout
        self._inbox: "queue.Queue[tuple[Callable[[], dict[str, Any]], concurrent.futures.Future[dict[str, Any]]]]" = queue.Queue()
        self._wake = threading.Event()
        self._lock_fd: int | None = None
        self.started_at = time.time()

    # ================================================================== setup
    def setup(self) -> None:
        """Store, policy, learning stack, cell (``flgd.daemon.startup``).  Raises StartupError for what an operator
        must fix."""
        self._lock_fd = startup.lock_state_dir(self.state_dir)
        self._open_store()
        startup.remove_unfinished_files(self.checkpoints, self.state_dir)
        step = startup.start_step(self.store, self.state_dir)
        network = startup.start_network(self.learning, self.policy_arg)
        self._start_network = network
        startup.load_prior(self.learning, network.rotations)
        self._build_learning(network, step)
        startup.log_trainer_state(self.learning.restore_trainer_state(), self.state_dir, bool(self.last_checkpoint))
        self.cell = startup.connect_cell(self.cell_config_at(step))
        self.runner = CycleRunner(self.config, self.cell, self.agent, store=self.store, replay=self.replay,
                                  learner=self.learner, step=self._next_step(), backend=self.backend,
                                  on_phase=lambda _phase: self.notifier.watchdog())
        self.learner.start()
        if self.store_problem:
            self.state.transition(State.FAULT, self.store_problem)

    def cell_config_at(self, step: int) -> CellConfig:
        """The config a cell is built from at action ``step``: a restarted daemon's simulated cell deals new scenes
        (``flgd.wiring.continuing_config``), not the first ones of its run again."""
        from flgd.wiring import continuing_config

        return continuing_config(self.config, step)

    def _open_store(self) -> bool:
        self.store, self.store_problem = startup.open_store(self.config, self.state_dir)
        self.learning.store = self.store
        return self.store is not None

    def _next_step(self) -> int:
        return self.store.next_step() if self.store is not None else 0

    def _build_learning(self, network: QMapNetwork, step: int) -> None:
        """Replay, agent, learner and, on an open store, the gate, for a run at action ``step``: their random draws
        (exploration, replay sampling, mirroring) continue from seeds drawn for that action, not from the run's
        first ones.  The agent acts with the gate's champion (or the configured policy on a first start), and the
        learner hands its weights to the gate -- or, with the gate off, to the agent."""
        try:
            parts = self.learning.build(network, step, handover=Handover.GATE,
                                        gate=self._gate_start() if self.store is not None else None)
        except startup.gate_errors() as exc:
            raise StartupError(startup.gate_problem(exc, self.state_dir)) from exc
        if parts.replay_problem:
            self.store_problem = parts.replay_problem
        if parts.gate is not None:
            log.info("acting policy: %s; gate %s", parts.gate_note, "on" if parts.gate.enabled else "OFF")

    def _gate_start(self) -> GateStart:
        return GateStart(self._next_step(), self._configured_policy, self._fresh_policy, self._reset_learner_to)

    def _reset_learner_to(self, network: QMapNetwork) -> None:
        """Run loop (the gate, after a rollback or a drop as worse): the learner starts again from ``network``,
        under the learning lock, with an event either way."""
        from flgd.learning.learner import LearnerBusy

        try:
            with self.learning_lock:
                owed = self.learning.restart_learner_from(network, self.learner_quiet_timeout)
        except LearnerBusy as exc:
            self.record_event("learner", f"not reset to the champion: {exc}")
            raise
        self.record_event("learner", f"learner restarted from the champion ({owed} owed updates dropped)")

    def _configured_policy(self) -> tuple[Any, dict[str, Any], str] | None:
        from flgd.learning.policy_file import load_policy

        if not self.policy_arg:
            return None
        loaded = load_policy(self.policy_arg, expected_variant=self.config.learning.network)
        return loaded.network, loaded.metadata, f"policy {self.policy_arg}"

    def _fresh_policy(self) -> tuple[Any, dict[str, Any], str]:
        return self._start_network, {"training_steps": 0}, self.policy_source

    # ================================================================== checkpoints
    def write_checkpoint(self, network: QMapNetwork, updates: int) -> None:
        """Learner thread: write a checkpoint; a storage failure puts the daemon in FAULT."""
        step = self.runner.step if self.runner is not None else 0
        if self.learning.parts is not None:  # the policy's own count, not the daemon's
            step = self.learning.agent.policy_steps(step)
        meta = CheckpointMeta(step, self.config.name or self.backend, updates, self.policy_source)
        try:
            path = self.learning.write_checkpoint(network, updates, meta)
        except (StoreError, OSError) as exc:
            self._learning_problem = f"checkpoint failed: {exc}"
            self.wake()
            raise
        log.info("checkpoint %s", path)
        self._write_trainer_state()

    def _write_trainer_state(self) -> None:
        """Target network and Adam moments beside the checkpoint, so a restart keeps learning where it was.

        Called with the learner quiet (inside its update, or after it stopped).  Replay priorities are
        not in it: the store has them.  A failure here is logged, not a fault: the checkpoint holds
        what was learned, and a restart without this file only restarts the optimizer.
        """
        try:
            self.learning.write_trainer_state()
        except (OSError, RuntimeError) as exc:
            log.error("trainer state not saved (a restart will start Adam afresh): %s", exc)

    # ================================================================== the run loop
    def run_loop(self, stop_requested: Callable[[], bool] = lambda: False) -> None:
        """Run until STOPPING; cycles while RUNNING, commands between cycles."""
        self.notifier.ready(self.status_text())
        if self.autostart and self.state.state is State.IDLE:
            self.state.transition(State.RUNNING, "--autostart")
        while True:
            self.notifier.watchdog()
            if stop_requested() and self.state.state is not State.STOPPING:
                self.request_stop("signal")
            self._drain_inbox()
            if self._learning_problem and self.state.state in (State.RUNNING, State.IDLE, State.PAUSED):
                self.fault(self._learning_problem)
                self._learning_problem = ""
            st = self.state.state
            if st is State.STOPPING:
                return
            self._keep_learner_alive()
            if st is State.RUNNING:
                self._one_cycle()
            else:
                self._wake.wait(0.5)
                self._wake.clear()

    def _keep_learner_alive(self) -> None:
        """A learner thread that left its loop (it never should) is started again, with an event saying so."""
        lr = self.learner
        if lr is None or lr.running or self.store is None:
            return
        why = lr.stopped_why or "unknown"
        with self.learning_lock:
            if lr.running:
                return
            lr.start()
        log.warning("the learner thread was not running (%s): started again", why)
        self.record_event("learner", f"learner was not running ({why}): started again")

    def _one_cycle(self) -> None:
        # in flight until the gate has counted the cycle: a status that says no cycle is in flight agrees with
        # every count in it (a refill wait afterwards is not a cycle in flight)
        self.cycle_in_flight = True
        try:
            record = self._run_and_judge()
        finally:
            self.cycle_in_flight = False
        if record is None:
            return
        if record.outcome == CycleOutcome.EMPTY and record.refill_needed:
            self._wait_for_refill()
        elif record.outcome == CycleOutcome.EMPTY:
            self.record_event("scene", "workspace empty: new scene")
        elif record.outcome == CycleOutcome.DISCARDED:
            self.record_event("discarded", f"step {record.step}: {record.failure}")
        elif record.outcome == CycleOutcome.STUCK:
            self._on_stuck(record)
        self.notifier.status(self.status_text())
        trim_heap()  # what the cycle and the learner freed goes back to the system (flgd/memory.py)

    def _run_and_judge(self) -> CycleRecord | None:
        """One cycle and the gate's record of it; None when it ended in a fault (latched here)."""
        assert self.runner is not None
        try:
            record = self.runner.run_once()
        except CellFault as exc:
            self.fault(f"cell fault: {exc}")
            return None
        except StoreError as exc:
            self.fault(str(exc))
            return None
        except Exception as exc:  # a bug must stop the arm, not kill the service
            log.exception("cycle failed")
            self.fault(f"internal error in the cycle: {type(exc).__name__}: {exc}")
            return None
        self.last_record = record
        self._watch_calibration()
        if self.gate is not None:
            from flgd.learning.policy_file import PolicyFileError
            try:
                self.learning.after_cycle(record, self.runner)  # paced: this cycle's hand-over is taken now
            except (StoreError, OSError, PolicyFileError) as exc:
                self.fault(f"the gate could not record its decision: {exc}")
                return None
            except Exception as exc:  # a bug must stop the arm, not kill the service
                log.exception("the gate failed")
                self.fault(f"internal error in the gate: {type(exc).__name__}: {exc}")
                return None
        return record

    def _on_stuck(self, record: CycleRecord) -> None:
        """The agent gave up on this scene: say so (event, status, metric), and on a cell that cannot re-lay
        its own scene pause for a person unless ``exploration.stuck_action`` is ``continue``."""
        if record.relaid:
            what = "the scene was laid out anew"
        elif self.config.exploration.stuck_action == "pause":
            what = "paused: clear or rearrange the table, then flgctl start"
        else:
            what = "continuing with a clean failure memory (exploration.stuck_action: continue)"
        message = f"stuck after step {self.runner.step - 1 if self.runner else '?'}: {record.failure}; {what}"
        self.last_stuck = {"time": record.time, "reason": record.failure, "relaid": record.relaid, "action": what}
        log.warning("%s", message)
        self.record_event("stuck", message)
        if not record.relaid and self.config.exploration.stuck_action == "pause":
            try:
                self.state.transition(State.PAUSED, f"stuck: {record.failure}; flgctl start resumes",
                                      allowed_from=frozenset({State.RUNNING}))
            except IllegalTransition:
                pass  # paused or stopping meanwhile: either way no further cycle runs

    def _watch_calibration(self) -> None:
        """The cycle's newest frame to the calibration watch; a drift (or its end) is logged and recorded."""
        frame = self.runner.last_frame if self.runner is not None else None
        if self.calibration_watch is None or frame is None or frame is self._watched_frame:
            return
        self._watched_frame = frame
        try:
            event = self.calibration_watch.observe_frame(frame)
        except Exception:  # the watch is advice: a bug in it must not stop the cell
            log.exception("calibration watch failed on a frame")
            return
        if event is not None:
            (log.warning if event.kind == "calibration_drift" else log.info)("%s", event.message)
            self.record_event(event.kind, event.message)

    def _wait_for_refill(self) -> None:
        """PAUSED until the operator refilled the table: a real cell cannot do it, so cycling on would
        home the arm, capture and log an event forever.  The state change is the one event recorded."""
        try:
            self.state.transition(State.PAUSED, EMPTY_WORKSPACE_CAUSE, allowed_from=frozenset({State.RUNNING}))
        except IllegalTransition:
            pass  # paused or stopping meanwhile: either way no further cycle runs

    def fault(self, cause: str) -> None:
        """Latch FAULT with its cause (and record it): nothing moves until an operator's reset."""
        try:
            self.state.transition(State.FAULT, cause)
        except IllegalTransition:
            return
        self.record_event("fault", cause)

    def record_event(self, kind: str, message: str) -> None:
        """An event in the store's log; a store that cannot take it is a fault."""
        if self.store is None:
            return
        try:
            self.store.record_event(kind, message)
        except StoreError as exc:
            log.error("cannot record event %s (%s): %s", kind, message, exc)
            if kind != "fault" and self.state.state is not State.STOPPING:
                self.fault(str(exc))

    def _drain_inbox(self) -> None:
        while True:
            try:
                fn, fut = self._inbox.get_nowait()
            except queue.Empty:
                return
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                fut.set_result(fn())
            except BaseException as exc:
                fut.set_exception(exc)

    def swap_cell(self, cell: Cell, backend: str) -> str:
        """Run loop: act on ``cell`` from the next cycle; the old cell is closed.  Returns the old backend's name."""
        assert self.runner is not None
        old, old_name = self.cell, self.backend
        self.cell, self.backend = cell, backend
        self.runner.use_cell(cell, backend)
        self.agent.reset_episode()
        if old is not None:
            try:
                old.close()
            except Exception as exc:
                log.error("closing the %s cell failed: %s", old_name, exc)
        return old_name

    def wake(self) -> None:
        """Let the run loop look at its inbox and state now instead of at its next poll."""
        self._wake.set()

    def run_on_loop(self, fn: Callable[[], dict[str, Any]], timeout: float = COMMAND_TIMEOUT) -> dict[str, Any]:
        """Run ``fn`` on the run loop between cycles and return its result (ProtocolError "busy" if the loop does
        not take it within ``timeout``)."""
        fut: concurrent.futures.Future[dict[str, Any]] = concurrent.futures.Future[dict[str, Any]]()
        self._inbox.put((fn, fut))
        self.wake()
        try:
            return fut.result(timeout)
        except concurrent.futures.TimeoutError:
            if fut.cancel():
                raise ProtocolError("busy", f"the run loop did not take the command within {timeout:.0f} s")
            return fut.result()

    def request_stop(self, cause: str) -> None:
        """STOPPING: halt the motion in flight (the cell decelerates and holds), send nothing more.

        The cell is latched before the state changes, so no one who sees STOPPING can
        still get a move out of the cell (see ``clear_stop_latch`` for the other side).
        """
        if self.state.state is State.STOPPING:
            return
        if self.runner is not None:
            self.runner.request_stop()
        try:
            self.state.transition(State.STOPPING, cause)
        except IllegalTransition:
            return
        self.wake()

    def _on_state_change(self, change: StateChange) -> None:
        if change.new is State.STOPPING:
            self.notifier.stopping(f"stopping: {change.cause}")
        else:
            self.notifier.status(self.status_text())
        if change.new is not State.FAULT:  # faults are recorded with their own kind
            if self.store is not None:
                try:
                    self.store.record_event("state", f"{change.old.value} -> {change.new.value}: {change.cause}")
                except StoreError as exc:
                    log.error("cannot record the state change: %s", exc)

    # ================================================================== shutdown
    def shutdown(self) -> None:
        """After the loop: stop learning, save a final checkpoint, flush the store, release the cell."""
        if self.learner is not None:
            self.learner.stop(timeout=30.0, why="the daemon is stopping")
            if self.learning.owes_checkpoint() and self.store is not None:
                try:
                    self.write_checkpoint(self.learner.snapshot(), self.learner.updates)
                except Exception as exc:
                    log.error("final checkpoint failed: %s", exc)
        if self.store is not None:
            try:
                self.store.query("PRAGMA wal_checkpoint(TRUNCATE)")
            except StoreError as exc:
                log.error("store flush failed: %s", exc)
            self.store.close()
        if self.cell is not None:
            try:
                self.cell.close()
            except Exception as exc:
                log.error("closing the cell failed: %s", exc)
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    # ================================================================== status and commands
    def status_text(self) -> str:
        """The one-line status (systemd's STATUS=, ``flgd run``'s log), assembled in flgd/daemon/commands.py."""
        return commands.status_text(self)

    def status(self) -> dict[str, Any]:
        """What ``flgctl status`` shows, assembled in flgd/daemon/commands.py."""
        return commands.status(self)

    def handle(self, req: Request) -> dict[str, Any]:
        """Serve one validated request (control thread) from the command table; ProtocolError for error replies."""
        command = commands.HANDLERS.get(req.cmd)
        if command is None:
            raise ProtocolError("unknown_command", f"unknown command {req.cmd!r}")
        st = self.state.state
        if not command.any_state and st not in ACCEPTING_COMMANDS:
            raise ProtocolError("wrong_state", f"{req.cmd}: the daemon is {st.value}")
        return command.run(self, req)

    def _stop_pending(self) -> bool:
        """A stop was requested (the daemon is STOPPING, or the runner was told to stop)."""
        return self.state.state is State.STOPPING or bool(self.runner is not None and self.runner.stop_requested)

    def clear_stop_latch(self) -> bool:
        """Clear the cell's stop latch if, and only if, no stop is pending; False when one is.

        Why clear first and look after: ``request_stop`` marks the runner stopped
        before it latches the cell, so a stop not visible after the clear latches
        the cell later, and one that is visible is latched again here -- no stop is
        ever erased.
        """
        if self._stop_pending():
            return False
        if self.cell is None:
            return True
        self.cell.clear_stop()
        if self._stop_pending():
            self.cell.stop_motion()
            return False
        return True

    def _stopped_during_reset(self, when: str) -> ProtocolError:
        log.warning("reset interrupted by a stop %s; the arm was left where it is", when)
        return ProtocolError("failed", f"reset interrupted by a stop ({self.state.cause}) {when}: the arm was not "
                                       f"homed and the daemon is stopping; start flgd again, then flgctl reset")

    def reset(self) -> dict[str, Any]:
        """Run loop: clear a fault, home the arm (the cell's recovery does), new scene (simulation).

        A stop requested before, during or after the recovery wins: nothing more
        moves, the daemon goes on stopping and the client gets an error reply.
        """
        st = self.state.state
        if st not in (State.IDLE, State.PAUSED, State.FAULT):
            raise ProtocolError("wrong_state", f"reset: not allowed while {st.value}")
        if self._stop_pending():
            raise self._stopped_during_reset("before it started")
        assert self.runner is not None and self.cell is not None
        stale_problem = self._learning_problem  # from before the reset (a checkpoint that failed in FAULT)
        if self.store is None:
            if not self._open_store():
                self.fault(self.store_problem)
                raise ProtocolError("failed", f"reset: {self.store_problem}")
        if self.gate is None:  # the store came back (now or at an earlier reset whose gate failed)
            gate_problem = ""
            with self.learning_lock:  # the learner goes on from its weights; nothing handed over without a gate
                try:
                    self.learning.rebuild(self._next_step(), gate=self._gate_start())
                except startup.gate_errors() as exc:
                    gate_problem = startup.gate_problem(exc, self.state_dir)
                finally:  # whatever was built acts and learns from now on (an unexpected error is raised on)
                    if self.learning.parts is not None and self.learning.parts.replay_problem:
                        self.store_problem = self.learning.parts.replay_problem
                    self.learning.connect(self.runner)
                    self.runner.step = self._next_step()
            if gate_problem:
                self.fault(gate_problem)
                raise ProtocolError("failed", f"reset: {gate_problem}")
            assert self.gate is not None
            log.info("acting policy: %s; gate %s", self.gate_note, "on" if self.gate.enabled else "OFF")
        assert self.store is not None  # opened above, or it was open
        disk = self.store.space_problem()
        if disk:  # the recovery moves the arm, and nothing may move that cannot be recorded
            raise ProtocolError("failed", f"reset refused, still {st.value}: store {self.store.path}: {disk}")
        try:
            self.store.record_event("reset", f"reset requested in {st.value}")
        except StoreError as exc:
            self.fault(str(exc))
            raise ProtocolError("failed", f"reset: the store is still unusable: {exc}") from None
        if not self.clear_stop_latch():
            raise self._stopped_during_reset("before the recovery")
        try:
            self.cell.recover()  # homes the arm through a checked plan
            if self._stop_pending():
                raise StopPending("a stop arrived during the recovery")
            self.cell.reset_scene()
        except (CellFault, PlanRefused) as exc:
            if isinstance(exc, StopPending) or self._stop_pending():
                raise self._stopped_during_reset("during the recovery") from None
            self.fault(f"reset failed: {exc}")
            raise ProtocolError("failed", f"reset failed, still FAULT: {exc}") from None
        self.runner.forget_state()
        self.agent.reset_episode()
        cause = f"reset by operator (was {st.value})"
        cleared = bool(stale_problem) and self._learning_problem == stale_problem
        if cleared:
            self._learning_problem = ""
            cause += f"; cleared the earlier problem: {stale_problem}"
        try:
            self.state.transition(State.IDLE, cause)
        except IllegalTransition:
            if cleared:
                self._learning_problem = stale_problem
            if self._stop_pending():
                raise self._stopped_during_reset("after the recovery") from None
            raise
        return {"state": State.IDLE.value}
