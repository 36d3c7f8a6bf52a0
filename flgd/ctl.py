"""``flgctl``: command a running flgd over its control socket (protocol: ``flgd.daemon.protocol``).

Human-readable output by default, ``--json`` prints the daemon's reply object
for scripts.  Exit codes: 0 success, 1 the daemon refused or the command
failed, 2 usage error, 3 the daemon is not running (or not reachable),
4 permission denied.
"""

from __future__ import annotations

import argparse
import base64
import datetime as _dt
import json
import math
import os
import shutil
import socket
import sys
import time
from pathlib import Path
from typing import Any, TextIO

__all__ = ["main", "Client", "call", "DaemonUnreachable", "EXIT_OK", "EXIT_FAILED", "EXIT_USAGE", "EXIT_NOT_RUNNING",
           "EXIT_FORBIDDEN"]

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_NOT_RUNNING, EXIT_FORBIDDEN = 0, 1, 2, 3, 4


class DaemonUnreachable(RuntimeError):
    def __init__(self, message: str, code: int = EXIT_NOT_RUNNING):
        super().__init__(message)
        self.code = code


class Client:
    """One connection to the daemon; ``call`` sends a request and returns the reply object."""

    def __init__(self, path: str | os.PathLike, timeout: float = 150.0):
        self.path = Path(path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(timeout)
        try:
            self._connect(time.monotonic() + timeout)
        except FileNotFoundError:
            self.sock.close()
            raise DaemonUnreachable(f"flgd is not running (no control socket at {self.path})") from None
        except ConnectionRefusedError:
            self.sock.close()
            raise DaemonUnreachable(f"flgd is not running (nothing listens on {self.path})") from None
        except PermissionError:
            self.sock.close()
            raise DaemonUnreachable(f"permission denied on {self.path}: ask to be added to the flgd group",
                                    EXIT_FORBIDDEN) from None
        except OSError as exc:
            self.sock.close()
            raise DaemonUnreachable(f"cannot connect to {self.path}: {exc}") from None
        self._buf = b""

    def _connect(self, deadline: float) -> None:
        """Connect; a full listen queue (EAGAIN: a Unix socket with a timeout does not wait) is tried again."""
        while True:
            try:
                self.sock.connect(str(self.path))
                return
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise
                time.sleep(0.05)

    def call(self, cmd: str, **args: Any) -> dict:
        req: dict[str, Any] = {"cmd": cmd}
        if args:
            req["args"] = args
        try:
            self.sock.sendall((json.dumps(req) + "\n").encode("utf-8"))
        except OSError as exc:
            # A refused peer is disconnected after its error line; that line is the better message.
            try:
                return self._read_reply()
            except DaemonUnreachable:
                raise DaemonUnreachable(f"connection to {self.path} lost: {exc}") from None
        return self._read_reply()

    def _read_reply(self) -> dict:
        while b"\n" not in self._buf:
            try:
                chunk = self.sock.recv(1 << 20)
            except socket.timeout:
                raise DaemonUnreachable(f"no reply from flgd on {self.path} (timed out)") from None
            except OSError as exc:
                raise DaemonUnreachable(f"connection to {self.path} lost: {exc}") from None
            if not chunk:
                raise DaemonUnreachable(f"flgd closed the connection on {self.path} without a reply")
            self._buf += chunk
        line, _, self._buf = self._buf.partition(b"\n")
        try:
            reply = json.loads(line)
        except ValueError:  # JSONDecodeError, or UnicodeDecodeError for bytes that are not UTF-8
            raise DaemonUnreachable(f"unreadable reply from {self.path}: {line[:200]!r}", EXIT_FAILED) from None
        if not isinstance(reply, dict) or "ok" not in reply:
            raise DaemonUnreachable(f"unexpected reply from {self.path}: {line[:200]!r}", EXIT_FAILED)
        return reply

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# For the commands the daemon serves even when all its connection slots are taken (URGENT_COMMANDS of
# flgd/daemon/server.py), a ``busy`` reply means "the urgent lane is full for a moment": flgctl tries again.
URGENT_RETRY_SECONDS = 10.0


def call(socket_path: str | os.PathLike, cmd: str, args: dict[str, Any] | None = None,
         timeout: float = 150.0) -> dict:
    """One request on a new connection; ``stop`` and ``pause`` are retried on ``busy`` for a few seconds."""
    from flgd.daemon.server import URGENT_COMMANDS

    deadline = time.monotonic() + min(timeout, URGENT_RETRY_SECONDS)
    while True:
        with Client(socket_path, timeout=timeout) as client:
            reply = client.call(cmd, **(args or {}))
        busy = not reply.get("ok") and reply.get("error", {}).get("code") == "busy"
        if not (busy and cmd in URGENT_COMMANDS and time.monotonic() < deadline):
            return reply
        time.sleep(0.2)


def _find_socket(explicit: str | None) -> Path:
    from flgd.daemon.socket_path import socket_candidates

    if explicit:
        return Path(explicit)
    cands = socket_candidates()
    for p in cands:
        if p.exists():
            return p
    return cands[0]


def _timeout(text: str) -> float:
    """argparse type: seconds > 0 (0 would make the socket non-blocking, NaN/inf/negative crash settimeout)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and 0 < value <= 86400):
        raise argparse.ArgumentTypeError(f"got {text!r}, expected seconds, a number > 0 and <= 86400")
    return value


def _parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--json", action="store_true", default=argparse.SUPPRESS,
                        help="print the daemon's reply as JSON")
    common.add_argument("--socket", default=argparse.SUPPRESS, help="control socket path")
    common.add_argument("--timeout", type=_timeout, default=argparse.SUPPRESS,
                        help="seconds to wait for a reply (default 150)")
    p = argparse.ArgumentParser(prog="flgctl", parents=[common],
                                description="Command a running flgd daemon over its control socket.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, help_ in (("start", "start cycling (IDLE/PAUSED -> RUNNING)"),
                        ("pause", "pause after the cycle in flight (RUNNING -> PAUSED)"),
                        ("reset", "clear a fault, home the arm, new scene in sim (-> IDLE)"),
                        ("status", "state, cause, cycles, policy, learner"),
                        ("stats", "grasp success, picks per hour, moves, faults, cycle-time split"),
                        ("stop", "halt the motion in flight and stop the daemon"),
                        ("ping", "check that the daemon answers")):
        sub.add_parser(name, parents=[common], help=help_)
    pol = sub.add_parser("policy", parents=[common], help="the acting policy and the champion/challenger gate")
    polsub = pol.add_subparsers(dest="policy_command", required=True,
                                metavar="load|save|history|promote|reject|rollback")
    load = polsub.add_parser("load", parents=[common], help="validate a policy file, then make it the champion")
    load.add_argument("file")
    save = polsub.add_parser("save", parents=[common], help="write the acting policy, the champion (default: state dir)")
    save.add_argument("file", nargs="?")
    hist = polsub.add_parser("history", parents=[common],
                             help="every promotion, drop, rollback, load and override, with its evidence")
    hist.add_argument("--limit", type=int, default=50, help="newest N events (default 50)")
    for name, help_ in (("promote", "make the challenger the champion now (logged with who asked)"),
                        ("reject", "drop the challenger now (logged with who asked)"),
                        ("rollback", "let the champion's predecessor act again (logged with who asked)")):
        polsub.add_parser(name, parents=[common], help=help_)
    be = sub.add_parser("backend", parents=[common], help="swap the cell between cycles (sim, ur5e, ...)")
    be.add_argument("name")
    snap = sub.add_parser("snapshot", parents=[common], help="PNG of the heightmap, Q-maps and chosen action")
    snap.add_argument("file")
    return p


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.1f}%"


def _human(command: str, reply: dict, extra: dict) -> str:
    r = reply.get("result", {})
    if command == "status":
        since = _dt.datetime.fromtimestamp(r["since"]).strftime("%Y-%m-%d %H:%M:%S")
        lines = [f"state         {r['state']} since {since} ({r['cause']})",
                 f"cycles        {r['cycles']}  (grasp success last 50: {_pct(r.get('grasp_success_last_50'))}, "
                 f"picks/h: {'-' if r.get('picks_per_hour') is None else format(r['picks_per_hour'], '.0f')})",
                 f"backend       {r['backend']}   config {r['config']}",
                 f"policy        {r['policy']}",
                 f"learner       {r['learner_updates']} updates ({r.get('learner_backlog', 0)} waiting, "
                 f"{r.get('learner_dropped', 0)} dropped), "
                 f"replay {r['replay_size']} "
                 f"(stored {r['stored_transitions']}), from {r.get('learner_from') or '-'}, "
                 f"last checkpoint {r['last_checkpoint'] or '-'}, "
                 f"optimizer {r.get('trainer_state', '-')}",
                 *([f"prior sample  {p['path']}: {p['transitions']} transitions, {100 * p['share']:.0f} % of each "
                    f"batch, {p['drawn']} drawn so far"] if (p := r.get('learner_prior')) else []),
                 f"state dir     {r['state_dir']}   pid {r['pid']}"]
        if not r.get("learner_running", True):
            lines.append(f"learner       NOT RUNNING ({r.get('learner_stopped_why') or 'reason unknown'})")
        if r.get("learning"):
            lines.append(f"learning      {r['learning']} settings: {r.get('learning_why', '')}")
        lines += _gate_lines(r.get("gate"))
        if r.get("learner_error"):
            lines.append(f"learner error {r['learner_error']}")
        if r.get("store_problem"):
            lines.append(f"store problem {r['store_problem']}")
        if r.get("storage_budget_problem"):
            lines.append(f"disk budget   {r['storage_budget_problem']}")
        last = r.get("last_cycle")
        if last:
            lines.append(f"last cycle    step {last['step']} {last['outcome']} {last['kind'] or ''} "
                         f"reward {last['reward']} ({last['duration']:.2f} s)")
        memory = r.get("failure_memory")
        if memory:
            lines.append(f"this scene    {memory['actions_since_success']} actions since the last successful grasp, "
                         f"{memory['suppressed_regions']} failed regions avoided")
        stuck = r.get("last_stuck")
        if stuck:
            when = _dt.datetime.fromtimestamp(stuck["time"]).strftime("%Y-%m-%d %H:%M:%S")
            lines.append(f"last stuck    {when}: {stuck['reason']}; {stuck['action']}")
        lines += _calibration_lines(r.get("calibration"))
        return "\n".join(lines)
    if command == "stats":
        from flgd.daemon.metrics import format_stats
        return format_stats(r)
    if command == "snapshot":
        act = r.get("action")
        what = "no action (empty workspace)" if not act else \
            f"{act['primitive']} at row {act['row']} col {act['col']} rotation {act['rotation']}"
        return f"wrote {extra['file']} ({r.get('source')}: {what})"
    if command == "policy load":
        champion = f" (champion #{r['champion']})" if r.get("champion") is not None else ""
        return f"policy loaded: {r['loaded']}{champion}"
    if command == "policy history":
        return _history_lines(r.get("events", []))
    if command in ("policy promote", "policy rollback"):
        return f"{command}: champion is now #{r['champion']} ({r.get('reason', '')})"
    if command == "policy reject":
        return f"policy reject: challenger #{r['rejected']} dropped"
    if command == "policy save":
        where = f"{r['copied_to']} (copy of {r['saved']})" if r.get("copied_to") else r["saved"]
        champion = f"champion #{r['champion']}, " if r.get("champion") is not None else ""
        return f"policy saved: {where} ({champion}{r['learner_updates']} learner updates)"
    if command == "backend":
        return f"backend {r['previous']} -> {r['backend']}"
    if command == "stop":
        # The reply only says the request was accepted; the protocol has no later confirmation.
        return ("stop requested: flgd halts the motion in flight, then saves a checkpoint, flushes the store "
                "and exits (its log, or `systemctl status flgd`, shows when it has stopped)")
    if command == "ping":
        return f"flgd answers (pid {r['pid']}, {reply['state']})"
    return f"{command}: ok, state {reply['state']}"


def _tally_text(t: dict | None) -> str:
    if not t:
        return "-"
    rate = "-" if t.get("per_action") is None else f"{t['per_action']:.3f}"
    return (f"{t['successes']}/{t['actions']} actions = {rate} picks/action, grasp success "
            f"{_pct(t.get('grasp_success'))}")


def _calibration_lines(c: dict | None) -> list[str]:
    """The calibration watch's estimate of the table plane, and its verdict (nothing when the watch is off)."""
    if not c:
        return []
    if c.get("table_tilt_degrees") is None:
        return [f"calibration   no frame judged yet ({c.get('unjudged_frames', 0)} with too little table)"]
    seen = (f"table tilt {c['table_tilt_degrees']:.2f} deg (limit {c['max_tilt_degrees']:g}), offset "
            f"{1000 * c['table_offset_m']:+.1f} mm (limit {c['max_offset_mm']:g}), median of {c['window']} frames")
    if c.get("drift"):
        when = _dt.datetime.fromtimestamp(c["since"]).strftime("%Y-%m-%d %H:%M:%S")
        return [f"calibration   CAMERA MOVED since {when}: {seen}; run {c.get('remedy', 'flgd calibrate')}"]
    return [f"calibration   ok: {seen}"]


def _gate_lines(g: dict | None) -> list[str]:
    if not g:
        return []
    lines = []
    ch = g.get("champion")
    if ch:
        lines.append(f"champion      #{ch['id']} {ch['origin']} (since step {ch['since_step']}): "
                     f"{_tally_text(ch.get('live'))}")
    if not g.get("enabled"):
        lines.append("gate          OFF: the learner's weights act as soon as they are handed over (unvetted)")
        return lines
    cl = g.get("challenger")
    if cl:
        lines.append(f"challenger    #{cl['id']} {cl['origin']} acting on {100 * g['share']:.0f}% of decisions: "
                     f"{_tally_text(cl.get('tally'))}; champion meanwhile {_tally_text(cl.get('champion_during_test'))}")
    else:
        lines.append("challenger    none (the learner's next hand-over becomes one)")
    v = g.get("verdict")
    if v:
        lines.append(f"gate          {v['kind']}: {v['reason']}")
    return lines


def _history_lines(events: list[dict]) -> str:
    if not events:
        return "no gate events yet"
    out = []
    for e in events:
        when = _dt.datetime.fromtimestamp(e["time"]).strftime("%Y-%m-%d %H:%M:%S")
        out.append(f"{when}  step {e['step']:>6}  {e['kind']:<15} #{e['policy']}  {e['message']}  [{e['who']}]")
    return "\n".join(out)


def _local_failure(as_json: bool, reply: dict, message: str) -> int:
    """The daemon succeeded but flgctl's own step failed: say so on stderr, and with --json also as a
    ``{"ok": false}`` object on stdout, so a script never reads an empty output as success."""
    _say(f"flgctl: {message}", sys.stderr)
    if as_json:
        _say(json.dumps({"ok": False, "id": reply.get("id"), "state": reply.get("state"),
                          "error": {"code": "local", "message": message}, "daemon_result": reply.get("result")},
                         indent=2))
    return EXIT_FAILED


class _OutputFailed(Exception):
    """stdout could not be written (a closed pipe, a full disk)."""

    def __init__(self, error: OSError):
        super().__init__(str(error))
        self.error = error


def _say(text: str, stream: TextIO | None = None) -> None:
    """Write one line and flush it, so a write error shows here rather than in a traceback at exit.

    A failed write to stdout raises _OutputFailed; one to stderr is dropped (there is nowhere left to say it).
    """
    stream = sys.stdout if stream is None else stream
    try:
        stream.write(text + "\n")
        stream.flush()
    except OSError as exc:
        if stream is sys.stderr:
            return
        raise _OutputFailed(exc) from None


def _output_failed(exc: _OutputFailed) -> int:
    """Like Unix tools: silent on a reader that went away (``| head -1``), one line on any other write error.

    stdout then points at /dev/null, so the interpreter's final flush of what is still buffered cannot
    print a traceback either.
    """
    from flgd.closed_pipe import stdout_to_devnull

    stdout_to_devnull()
    if not isinstance(exc.error, BrokenPipeError):
        _say(f"flgctl: cannot write the output: {exc.error.strerror or exc.error}", sys.stderr)
    return EXIT_FAILED


def main(argv: list[str] | None = None) -> int:
    """The command line; the exit codes of the module docstring (1 also when the output cannot be written)."""
    try:
        return _run(argv)
    except _OutputFailed as exc:
        return _output_failed(exc)


def _run(argv: list[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return EXIT_USAGE if exc.code not in (0, None) else EXIT_OK
    as_json = getattr(args, "json", False)
    timeout = getattr(args, "timeout", 150.0)
    path = _find_socket(getattr(args, "socket", None))

    command = args.command
    call_args: dict[str, Any] = {}
    extra: dict[str, Any] = {}
    cmd = command
    if command == "policy":
        command = f"policy {args.policy_command}"
        cmd = f"policy_{args.policy_command}"
        if args.policy_command == "load":
            call_args["path"] = os.path.abspath(args.file)
        elif args.policy_command == "history":
            call_args["limit"] = args.limit
    elif command == "backend":
        call_args["name"] = args.name
    elif command == "snapshot":
        extra["file"] = args.file

    try:
        reply = call(path, cmd, call_args, timeout=timeout)
    except DaemonUnreachable as exc:
        if as_json:
            _say(json.dumps({"ok": False, "error": {"code": "not_running" if exc.code == EXIT_NOT_RUNNING
                                                    else "unreachable", "message": str(exc)}}))
        else:
            _say(f"flgctl: {exc}", sys.stderr)
        return exc.code

    if reply.get("ok") and command == "policy save" and args.file is not None:
        # the daemon saved inside its state directory; copy it out with this user's permissions
        try:
            shutil.copyfile(reply["result"]["saved"], args.file)
            reply["result"]["copied_to"] = os.path.abspath(args.file)
        except OSError as exc:
            hint = ""
            if isinstance(exc, PermissionError) and exc.filename == reply["result"]["saved"]:
                hint = (" (reading it needs group access to the daemon's state directory: be a member of "
                        "group flgd, or copy it as root)")
            return _local_failure(as_json, reply, f"the daemon saved {reply['result']['saved']}, but copying it "
                                                  f"to {args.file} failed: {exc}{hint}")

    if reply.get("ok") and command == "snapshot":
        try:
            png = base64.b64decode(reply["result"].pop("png_base64"), validate=True)
            Path(args.file).write_bytes(png)
            reply["result"]["file"] = os.path.abspath(args.file)
            reply["result"]["bytes"] = len(png)
        except (OSError, ValueError, KeyError) as exc:
            return _local_failure(as_json, reply, f"cannot write {args.file}: {exc}")

    if as_json:
        _say(json.dumps(reply, indent=2))
    elif reply.get("ok"):
        _say(_human(command, reply, extra))
    else:
        err = reply.get("error", {})
        _say(f"flgctl {command}: {err.get('message', 'failed')} [{err.get('code')}; state "
             f"{reply.get('state')}]", sys.stderr)
    if reply.get("ok"):
        return EXIT_OK
    return EXIT_FORBIDDEN if reply.get("error", {}).get("code") == "forbidden" else EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
