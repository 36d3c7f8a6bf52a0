"""The operator's commands: one handler per protocol command, and the status they report.

``HANDLERS`` has exactly the names of ``protocol.COMMANDS`` (a test holds them equal), so a command cannot be
accepted by the protocol and missing here, or the other way round.  ``Controller.handle`` looks a request up
in it; what the handlers change they change through the controller, which keeps the run loop, faults,
recovery and shutdown.  Handlers run in the control connection's thread: whatever touches the cell or the
acting networks is queued to the run loop (``DaemonControl.run_on_loop``) and executed between cycles.  The
handlers see the controller only through ``flgd.daemon.control.DaemonControl``, its public face.
"""

from __future__ import annotations

import base64
import copy
import dataclasses
import datetime as _dt
import logging
import os
import time
from typing import TYPE_CHECKING, Any, Callable

from flgd.cell import CellFault, make_cell
from flgd.cycle import ToolInView
from flgd.daemon.metrics import compute_stats, status_summary
from flgd.daemon.protocol import ProtocolError, Request
from flgd.daemon.state import IllegalTransition, State
from flgd.store import StoreError

if TYPE_CHECKING:
    from flgd.daemon.control import DaemonControl
    from flgd.learning.policy_file import LoadedPolicy

__all__ = ["Command", "HANDLERS", "status", "status_text", "summary", "policy_load"]

log = logging.getLogger("flgd")


@dataclasses.dataclass(frozen=True)
class Command:
    """One operator command: what serves it, and whether it is served in every state (STOPPING included)."""

    run: Callable[["DaemonControl", Request], dict[str, Any]]
    any_state: bool = False


# ================================================================== status
def _fmt_pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.0f}%"


def summary(ctl: DaemonControl) -> dict[str, Any]:
    """Cycles, the rolling grasp success and picks per hour from the store (None where it cannot be read)."""
    if ctl.store is None:
        return {"cycles": 0, "grasp_success_last_50": None, "picks_per_hour": None}
    try:
        return status_summary(ctl.store)
    except StoreError:
        return {"cycles": None, "grasp_success_last_50": None, "picks_per_hour": None}


def status_text(ctl: DaemonControl) -> str:
    """The one-line status of systemd's STATUS= and the log."""
    s = summary(ctl)
    pph = "-" if s["picks_per_hour"] is None else f"{s['picks_per_hour']:.0f}"
    text = (f"{ctl.state.state.value} | cycles {s['cycles']} | grasp success {_fmt_pct(s['grasp_success_last_50'])}"
            f" (last 50) | picks/h {pph}")
    if ctl.state.state in (State.FAULT, State.PAUSED):
        text += f" | {ctl.state.cause}"
    if ctl.gate is not None and ctl.gate.champion is not None:
        text += f" | champion #{ctl.gate.champion.id}"
        if ctl.gate.challenger is not None:
            text += f", challenger #{ctl.gate.challenger.id} testing"
    if ctl.calibration_watch is not None and ctl.calibration_watch.drift:
        text += " | camera moved: flgd calibrate"
    return text


def status(ctl: DaemonControl) -> dict[str, Any]:
    """``flgctl status``: state, policy, learner, gate, store, last cycle, calibration and failure memory."""
    rec = ctl.last_record
    last = None
    if rec is not None:
        last = {"step": rec.step, "outcome": rec.outcome, "primitive": rec.primitive, "kind": rec.kind,
                "reward": rec.reward, "success": rec.success, "rule": rec.rule, "refused": rec.refused,
                "failure": rec.failure, "duration": rec.duration}
    stored = None
    if ctl.store is not None:
        try:
            stored = ctl.store.transition_count()
        except StoreError:
            stored = None
    return {
        "state": ctl.state.state.value,
        "cause": ctl.state.cause,
        "since": ctl.state.since,
        "pid": os.getpid(),
        "uptime": time.time() - ctl.started_at,
        "backend": ctl.backend,
        "config": ctl.config.source,
        "state_dir": str(ctl.state_dir),
        "policy": _acting_policy(ctl),
        "learner_from": ctl.policy_source,
        "step": ctl.runner.step if ctl.runner is not None else None,
        "cycle_in_flight": ctl.cycle_in_flight,
        "stored_transitions": stored,
        **ctl.learning.status(),
        "learning": "finetune" if ctl.fine_tune else "learning",
        "learning_why": ctl.learning_why,
        "store_problem": ctl.store_problem,
        "storage_budget_problem": ctl.store.budget_problem if ctl.store is not None else "",
        "last_cycle": last,
        "last_stuck": ctl.last_stuck,
        "calibration": ctl.calibration_watch.status() if ctl.calibration_watch is not None else None,
        "failure_memory": (ctl.agent.memory.status() if getattr(ctl.agent, "memory", None) is not None
                           else None),
        **{k: v for k, v in summary(ctl).items()},
    }


def _acting_policy(ctl: DaemonControl) -> str:
    """The gate's champion; with no store (and so no gate), what will act after a reset."""
    if ctl.gate is not None and ctl.gate.champion is not None:
        return f"champion #{ctl.gate.champion.id}: {ctl.gate.champion.origin}"
    if ctl.store is None:
        from flgd.daemon.acting_policy import acting_after_reset

        return acting_after_reset(ctl.state_dir, ctl.policy_arg)
    return ctl.policy_source


# ================================================================== state changes
def change_state(ctl: DaemonControl, new: State, cause: str, allowed: set[State], cmd: str) -> dict[str, Any]:
    """The operator's state change, refused with the states it is allowed in."""
    try:
        ctl.state.transition(new, cause, allowed_from=frozenset(allowed))
    except IllegalTransition:
        names = ", ".join(sorted(s.value for s in allowed))
        hint = " (reset first)" if ctl.state.state is State.FAULT else ""
        raise ProtocolError("wrong_state", f"{cmd}: not allowed while {ctl.state.state.value}; "
                                           f"allowed in {names}{hint}") from None
    ctl.wake()
    return {"state": new.value}


def _start(ctl: DaemonControl, req: Request) -> dict[str, Any]:
    if not ctl.clear_stop_latch():
        raise ProtocolError("wrong_state", f"start: the daemon is stopping ({ctl.state.cause})")
    return change_state(ctl, State.RUNNING, "start by operator", {State.IDLE, State.PAUSED}, req.cmd)


def _pause(ctl: DaemonControl, req: Request) -> dict[str, Any]:
    return change_state(ctl, State.PAUSED, "pause by operator", {State.RUNNING}, req.cmd)


def _stop(ctl: DaemonControl, req: Request) -> dict[str, Any]:
    ctl.request_stop("stop by operator")
    return {"stopping": True}


def _reset(ctl: DaemonControl, req: Request) -> dict[str, Any]:
    st = ctl.state.state
    if st not in (State.IDLE, State.PAUSED, State.FAULT):
        raise ProtocolError("wrong_state", f"reset: not allowed while {st.value}; pause first")
    return ctl.run_on_loop(ctl.reset)


# ================================================================== what the store says
def _stats(ctl: DaemonControl, req: Request) -> dict[str, Any]:
    if ctl.store is None:
        raise ProtocolError("failed", f"no statistics: {ctl.store_problem}")
    try:
        return compute_stats(ctl.store)
    except StoreError as exc:
        raise ProtocolError("failed", str(exc)) from None


def _policy_history(ctl: DaemonControl, req: Request) -> dict[str, Any]:
    limit = req.args.get("limit", 50)
    if isinstance(limit, bool) or not 1 <= limit <= 10000:
        raise ProtocolError("bad_request", f"policy_history: limit must be 1..10000, got {limit!r}")
    if ctl.gate is None:
        raise ProtocolError("failed", f"no policy history: {ctl.store_problem or 'no store'}")
    try:
        return {"events": ctl.gate.history(limit)}
    except StoreError as exc:
        raise ProtocolError("failed", str(exc)) from None


# ================================================================== policies, backend, snapshot
def policy_load(ctl: DaemonControl, path: str, who: str = "") -> dict[str, Any]:
    """Validate the file here, then make it the champion between cycles (see ``swap_in_policy``); a refusal is
    logged and recorded as an event with its reason."""
    try:
        return _load_policy(ctl, path, who)
    except ProtocolError as exc:
        log.warning("policy load of %s by %s refused: %s", path, who or "operator", exc.message)
        ctl.record_event("policy", f"load of {path} by {who or 'operator'} refused: {exc.message}")
        raise


def _load_policy(ctl: DaemonControl, path: str, who: str) -> dict[str, Any]:
    from flgd.learning.policy_file import PolicyFileError, load_policy
    from flgd.policy_header import check_policy_header

    if not os.path.isabs(path):
        raise ProtocolError("bad_request", f"policy_load: path must be absolute, got {path!r}")
    try:
        check_policy_header(path)  # a file that is no policy is refused before its body is read
        running = ctl.agent.network.architecture() if ctl.agent is not None else None
        loaded = load_policy(path, expected_variant=ctl.config.learning.network, expected_architecture=running)
    except PolicyFileError as exc:
        raise ProtocolError("failed", f"policy not loaded, the running policy stays: {exc}") from None
    return ctl.run_on_loop(lambda: swap_in_policy(ctl, path, loaded, who or "operator"))


def swap_in_policy(ctl: DaemonControl, path: str, loaded: LoadedPolicy, who: str) -> dict[str, Any]:
    """Run loop: the loaded policy becomes the champion and the learner's weights, checkpointed at once.

    Why a checkpoint: a restart resumes learning from the newest checkpoint, which would otherwise
    still hold the weights from before the load.  The learner is held between two updates meanwhile
    (``Learner.paused``: its thread lives on), its owed updates are dropped and counted, and its Adam
    moments, which belong to the old weights, are reset.
    """
    from flgd.learning.learner import LearnerBusy
    from flgd.learning.policy_file import PolicyFileError

    lr = ctl.learner
    step = ctl.runner.step if ctl.runner else 0
    checkpoint_error = ""
    with ctl.learning_lock:
        try:
            with lr.paused(ctl.learner_quiet_timeout):
                before = {k: v.detach().clone() for k, v in lr.online.state_dict().items()}
                try:
                    lr.online.load_state_dict(loaded.network.state_dict())  # fits the running network?
                except (RuntimeError, ValueError) as exc:
                    lr.online.load_state_dict(before)
                    raise ProtocolError("failed", f"policy not loaded, the running policy stays: {path}: "
                                                  f"weights do not fit the running network: {exc}") from None
                if ctl.gate is not None:
                    try:
                        ctl.gate.load_champion(loaded.network, loaded.metadata, f"policy {path}", step, who)
                    except (StoreError, OSError, PolicyFileError) as exc:
                        lr.online.load_state_dict(before)
                        raise ProtocolError("failed", f"policy not loaded, the running policy stays: the "
                                                      f"gate could not record it: {exc}") from None
                else:
                    ctl.agent.network.load_state_dict(loaded.network.state_dict())
                    lr.set_anchor(loaded.network)  # with a gate its champion change does this
                lr.load_weights(loaded.network, publish=False)
                lr.reset_trainer_state()
                owed = lr.drop_backlog()
                if owed:
                    log.info("policy load: %d owed learner updates dropped", owed)
                offset = int(loaded.metadata.get("training_steps", 0)) - step  # ε goes on from its steps
                ctl.agent.continue_exploration_from(offset)
                ctl.policy_source = f"policy {path} (loaded at step {step} by {who})"
                try:
                    if ctl.store is not None:
                        ctl.store.set_counter("exploration_offset", offset)
                    ctl.write_checkpoint(lr.snapshot(), lr.updates)
                except (StoreError, OSError, PolicyFileError) as exc:  # storage errors also mean FAULT
                    checkpoint_error = str(exc)
        except LearnerBusy as exc:
            raise ProtocolError("busy", f"policy not loaded, the running policy stays: {exc} (the learner "
                                        f"keeps running; try again)") from None
    ctl.record_event("policy", f"loaded {path} by {who}")
    if checkpoint_error:
        raise ProtocolError("failed", f"policy {path} is loaded and acting, but its checkpoint could not be "
                                      f"written ({checkpoint_error}), so a restart would resume learning from "
                                      f"the previous one; fix the state directory {ctl.state_dir}, flgctl "
                                      f"reset, then load the policy again")
    return {"loaded": path, "checkpoint": ctl.last_checkpoint, "dropped_updates": owed,
            "champion": None if ctl.gate is None or ctl.gate.champion is None else ctl.gate.champion.id,
            "metadata": {k: v for k, v in loaded.metadata.items()
                         if isinstance(v, (str, int, float, bool, type(None)))}}


def gate_command(ctl: DaemonControl, cmd: str, who: str) -> dict[str, Any]:
    """Run loop: a manual promote, reject or rollback, recorded with who asked."""
    from flgd.gate.keeper import GateError
    from flgd.learning.policy_file import PolicyFileError

    if ctl.gate is None:
        raise ProtocolError("failed", f"{cmd}: the gate is not available ({ctl.store_problem or 'no store'})")
    step = ctl.runner.step if ctl.runner else 0
    try:
        if cmd == "policy_promote":
            out = ctl.gate.promote(step, who, f"promoted by {who}")
        elif cmd == "policy_reject":
            out = ctl.gate.reject(step, who)
        else:
            out = ctl.gate.rollback(step, who, f"rolled back by {who}")
    except GateError as exc:
        raise ProtocolError("failed", f"{cmd.replace('_', ' ')}: {exc}") from None
    except (StoreError, OSError, PolicyFileError) as exc:
        raise ProtocolError("failed", f"{cmd.replace('_', ' ')}: the gate could not record it: {exc}") from None
    ctl.record_event("policy", f"{cmd.replace('_', ' ')} by {who}: {out}")
    return out


def policy_save(ctl: DaemonControl, path: str | None) -> dict[str, Any]:
    from flgd.learning.policy_file import PolicyFileError, save_policy

    # The daemon writes only inside its state directory: a client of another uid must not be able
    # to make it overwrite arbitrary files.  flgctl copies a saved policy out with the user's rights.
    if path is None:
        stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")
        path = str(ctl.state_dir / "policies" / f"policy-{stamp}-u{ctl.learner.updates}.safetensors")
    elif not os.path.isabs(path):
        raise ProtocolError("bad_request", f"policy_save: path must be absolute, got {path!r}")
    else:
        real, root = os.path.realpath(path), os.path.realpath(ctl.state_dir)
        if os.path.commonpath([real, root]) != root or real == root:
            raise ProtocolError("bad_request", f"policy_save: {path} is outside the state directory {root}; "
                                               "omit the path (flgctl policy save FILE copies the file out)")
    stats = summary(ctl)
    # the acting policy (the champion), copied between decisions; the learner's own weights are in checkpoints
    acting = ctl.run_on_loop(lambda: {"network": copy.deepcopy(ctl.agent.network)})["network"]
    champion = ctl.gate.champion if ctl.gate is not None else None
    meta = {"training_steps": ctl.agent.policy_steps(ctl.runner.step if ctl.runner else 0),
            "cell": ctl.config.name or ctl.backend,
            "rolling_success": stats.get("grasp_success_last_50"),
            "learner_updates": int(ctl.learner.updates),
            "source": champion.origin if champion is not None else ctl.policy_source,
            "gate_policy": None if champion is None else champion.id}
    try:
        save_policy(path, acting, meta)
    except (PolicyFileError, OSError) as exc:
        raise ProtocolError("failed", f"policy not saved to {path}: {exc}") from None
    ctl.record_event("policy", f"saved {path}")
    return {"saved": path, "learner_updates": int(ctl.learner.updates),
            "champion": None if champion is None else champion.id}


def swap_backend(ctl: DaemonControl, name: str) -> dict[str, Any]:
    """Run loop: connect the new cell first; keep the old one if that fails."""
    assert ctl.runner is not None
    try:
        new = make_cell(ctl.cell_config_at(ctl.runner.step), backend=name)
    except Exception as exc:
        raise ProtocolError("failed", f"backend {name!r} did not connect; still on {ctl.backend!r}: "
                                      f"{type(exc).__name__}: {exc}") from None
    old_name = ctl.swap_cell(new, name)
    ctl.record_event("backend", f"{old_name} -> {name}")
    # A new cell never starts moving on its own: the operator looks at it, then starts it.
    try:
        ctl.state.transition(State.PAUSED, f"backend swapped {old_name} -> {name}: flgctl start to run on it",
                             allowed_from=frozenset({State.RUNNING}))
    except IllegalTransition:
        pass  # not running (idle, paused, in fault): the state stays as it was
    return {"backend": name, "previous": old_name}


def snapshot(ctl: DaemonControl) -> dict[str, Any]:
    from flgd.visualize import ActionGlyph, encode_png, qmap_picture

    runner = ctl.runner
    assert runner is not None
    last = runner.last_decided
    note = "last decision"
    if last is None:
        if ctl.state.state is State.FAULT:
            raise ProtocolError("failed", "snapshot: no decision yet and the cell is in FAULT")
        return ctl.run_on_loop(lambda: fresh_snapshot(ctl))
    hm, decision, step = last
    image = qmap_picture(hm.color, hm.height, decision.q_maps, decision.grasp_mask, decision.move_mask,
                         decision.action, caption=f"{note}: step {step}, rule {decision.rule}, "
                                              f"Q {decision.q_value:.3f}",
                         glyph=ActionGlyph.from_config(ctl.config), unknown=hm.unknown,
                         suppressed=decision.suppressed)
    return {"png_base64": base64.b64encode(encode_png(image)).decode("ascii"), "source": note, "step": step,
            "action": dataclasses.asdict(decision.action), "q_value": decision.q_value}


def fresh_snapshot(ctl: DaemonControl) -> dict[str, Any]:
    """Run loop: capture and evaluate the network without acting (no decision state changes)."""
    from flgd.visualize import ActionGlyph, encode_png, greedy_action, qmap_picture

    assert ctl.runner is not None
    try:
        hm = ctl.runner.perceive_now()
    except ToolInView as exc:   # the arm stands where a picture shows it: nothing wrong with the cell
        raise ProtocolError("failed", f"snapshot: {exc}") from None
    except CellFault as exc:
        ctl.fault(f"cell fault during snapshot capture: {exc}")
        raise ProtocolError("failed", f"snapshot: capture failed: {exc}") from None
    ctl.agent.maybe_swap_weights()
    q = ctl.agent.q_maps(hm)
    gmask, mmask = ctl.agent.masks(hm.height)
    action = None
    if gmask.any() or mmask.any():   # a move alone may be allowed (grasps on a sliver at the border are not)
        action = greedy_action(q, gmask, mmask, hm.height, ctl.config.rewards.shift_height)
    note = "fresh capture, greedy action (not executed)"
    image = qmap_picture(hm.color, hm.height, q, gmask, mmask, action, caption=note,
                         glyph=ActionGlyph.from_config(ctl.config), unknown=hm.unknown,
                         suppressed=ctl.agent.memory.footprint() if ctl.agent.memory.enforced else None)
    return {"png_base64": base64.b64encode(encode_png(image)).decode("ascii"), "source": note,
            "action": None if action is None else dataclasses.asdict(action),
            "q_value": None if action is None else float(q[action.rotation, action.channel, action.row,
                                                           action.col])}


# ================================================================== the table
def _gate_override(ctl: DaemonControl, req: Request) -> dict[str, Any]:
    return ctl.run_on_loop(lambda: gate_command(ctl, req.cmd, req.peer or "operator"))


HANDLERS: dict[str, Command] = {
    "ping": Command(lambda ctl, req: {"pong": True, "pid": os.getpid()}, any_state=True),
    "status": Command(lambda ctl, req: status(ctl), any_state=True),
    "stats": Command(_stats, any_state=True),
    "start": Command(_start),
    "pause": Command(_pause),
    "reset": Command(_reset),
    "stop": Command(_stop),
    "policy_load": Command(lambda ctl, req: policy_load(ctl, req.args["path"], req.peer)),
    "policy_save": Command(lambda ctl, req: policy_save(ctl, req.args.get("path"))),
    "policy_history": Command(_policy_history, any_state=True),
    "policy_promote": Command(_gate_override),
    "policy_reject": Command(_gate_override),
    "policy_rollback": Command(_gate_override),
    "backend": Command(lambda ctl, req: ctl.run_on_loop(lambda: swap_backend(ctl, req.args["name"]))),
    "snapshot": Command(lambda ctl, req: snapshot(ctl)),
}
