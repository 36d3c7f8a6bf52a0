"""The flgd control protocol: one JSON object per line over a Unix stream socket.

Socket: ``$RUNTIME_DIRECTORY/flgd.sock`` under systemd, else ``/run/flgd/flgd.sock``
(``flgd run --socket PATH`` and ``flgctl --socket PATH`` override it).  The
socket file has mode 0660; the daemon also checks the peer's credentials
(SO_PEERCRED): root, the daemon's own uid, or a member of the control group
may talk to it.  Anyone else gets one ``forbidden`` error line and is
disconnected.

Request (UTF-8, at most ``MAX_REQUEST_BYTES`` bytes including the newline)::

    {"cmd": "status"}
    {"cmd": "policy_load", "args": {"path": "/var/lib/flgd/good.flgp"}, "id": 7}

``cmd`` is a string; ``args`` (optional) an object whose keys the command
accepts (unknown keys are errors); ``id`` (optional) any JSON scalar echoed in
the reply.  A connection may send any number of requests; each line gets
exactly one reply line, in order.

Reply::

    {"ok": true,  "id": 7, "state": "IDLE", "result": {...}}
    {"ok": false, "id": 7, "state": "IDLE", "error": {"code": "wrong_state", "message": "..."}}

Error codes: ``bad_request`` (not JSON, not an object, wrong types, unknown
args, not UTF-8, empty line, a key given twice, a NUL character in a string
arg, an integer of 2**63 or more, an ``id`` string over 200 characters), ``too_long`` (line over the cap; the rest of that
line is discarded), ``unknown_command``, ``wrong_state`` (the command is not
allowed in the current state), ``failed`` (the command was valid but did not
succeed; the daemon's state is unchanged unless the message says otherwise),
``busy`` (the run loop did not take the command in time), ``forbidden``.

Commands (args in brackets; states in which the command is accepted):

=============  =====================  ======================================================
cmd            args                   effect
=============  =====================  ======================================================
ping           --                     any state; ``{"pong": true, "pid": ...}``
status         --                     any state; state, cause, cycles, backend, policy, ...
stats          --                     any state; the metrics of ``flgctl stats``
start          --                     IDLE, PAUSED -> RUNNING
pause          --                     RUNNING -> PAUSED (the cycle in flight completes)
reset          --                     IDLE, PAUSED, FAULT: clear a fault (cell.recover),
                                      home the arm, new scene in sim -> IDLE
stop           --                     any state but STOPPING: halt the motion in flight and stop,
                                      flush the store and exit
policy_load    path: str              any state but STOPPING: validate the policy file, then
                                      swap it in between cycles; on failure nothing changes
policy_save    path: str (optional)   any state but STOPPING: write the acting policy (the
                                      path must lie inside the state directory; default
                                      <state_dir>/policies/policy-<time>-u<updates>.safetensors)
policy_history limit: int (optional)  any state; the gate's events (promotions, drops, rollbacks,
                                      loads, overrides) with their evidence, newest last
policy_promote --                     any state but STOPPING: the challenger becomes the champion now
policy_reject  --                     any state but STOPPING: drop the challenger now
policy_rollback --                    any state but STOPPING: the champion's predecessor acts again
backend        name: str              any state but STOPPING: connect the new cell between
                                      cycles; if it fails, the old cell stays
snapshot       --                     any state but STOPPING: PNG (base64) of the last
                                      decision's heightmap, Q-maps, masks and action
=============  =====================  ======================================================

Paths are read and written by the daemon, so they must be absolute and
accessible to the daemon's user; the daemon writes only inside its state
directory (``flgctl policy save FILE`` lets the daemon save there and copies
the file out with the caller's own permissions).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "MAX_REQUEST_BYTES",
    "COMMANDS",
    "ProtocolError",
    "Request",
    "parse_request",
    "ok_reply",
    "error_reply",
    "encode",
]

MAX_REQUEST_BYTES = 64 * 1024

# cmd -> {arg name: (type, required)}
COMMANDS: dict[str, dict[str, tuple[type, bool]]] = {
    "ping": {},
    "status": {},
    "stats": {},
    "start": {},
    "pause": {},
    "reset": {},
    "stop": {},
    "policy_load": {"path": (str, True)},
    "policy_save": {"path": (str, False)},
    "policy_history": {"limit": (int, False)},
    "policy_promote": {},
    "policy_reject": {},
    "policy_rollback": {},
    "backend": {"name": (str, True)},
    "snapshot": {},
}

ERROR_CODES = ("bad_request", "too_long", "unknown_command", "wrong_state", "failed", "busy", "forbidden")


class ProtocolError(Exception):
    """A request that cannot be served; ``code`` is one of ERROR_CODES."""

    def __init__(self, code: str, message: str, request_id: Any = None):
        assert code in ERROR_CODES, code
        self.code = code
        self.message = message
        self.request_id = request_id
        super().__init__(f"{code}: {message}")


@dataclass(frozen=True)
class Request:
    cmd: str
    args: dict[str, Any] = field(default_factory=dict[str, Any])
    id: Any = None
    peer: str = ""  # who sent it ("uid U pid P", from SO_PEERCRED; set by the server), for the gate's records


MAX_ID_CHARS = 200
_INT_LIMIT = 2 ** 63  # integers are counts and ids: anything longer is a mistake or an attack


def _scalar(v: Any) -> bool:
    return v is None or isinstance(v, (str, int, float, bool))


def _described(v: Any) -> str:
    """A value for an error message, never quoted back whole when it is huge."""
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) >= _INT_LIMIT:
        return f"a {len(str(abs(v)))}-digit number"
    if isinstance(v, str) and len(v) > 80:
        return f"a string of {len(v)} characters"
    return repr(v)


class _DuplicateKey(ValueError):
    def __init__(self, key: str):
        super().__init__(key)
        self.key = key


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """json's object hook: a key given twice is refused, not silently resolved to its last value."""
    obj: dict[str, Any] = {}
    for key, value in pairs:
        if key in obj:
            raise _DuplicateKey(key)
        obj[key] = value
    return obj


def parse_request(line: bytes) -> Request:
    """Validate one request line (without its newline); raise ProtocolError if it is not a request."""
    if len(line) + 1 > MAX_REQUEST_BYTES:
        raise ProtocolError("too_long", f"request of {len(line) + 1} bytes is over the "
                                        f"{MAX_REQUEST_BYTES}-byte limit")
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ProtocolError("bad_request", f"request is not UTF-8 ({exc.reason} at byte {exc.start})") from None
    if not text.strip():
        raise ProtocolError("bad_request", "empty request; expected a JSON object such as "
                                           '{"cmd": "status"}')
    try:
        data = json.loads(text, object_pairs_hook=_no_duplicates)
    except _DuplicateKey as exc:
        raise ProtocolError("bad_request", f"key {exc.key[:80]!r} appears twice in the request; give each key "
                                           "once") from None
    except (json.JSONDecodeError, RecursionError) as exc:
        where = f" at column {exc.colno}" if isinstance(exc, json.JSONDecodeError) else ""
        raise ProtocolError("bad_request", f"request is not valid JSON{where}") from None
    except ValueError:  # an integer of more digits than Python converts (sys.get_int_max_str_digits)
        raise ProtocolError("bad_request", "request holds a number too long to read (more than "
                                           f"{sys.get_int_max_str_digits()} digits)") from None
    if not isinstance(data, dict):
        raise ProtocolError("bad_request", f"request is a JSON {type(data).__name__}, expected an object "
                                           'such as {"cmd": "status"}')
    rid = data.get("id")
    if not _scalar(rid):
        raise ProtocolError("bad_request", "'id' must be a JSON scalar (string, number, bool or null)")
    if (isinstance(rid, int) and abs(rid) >= _INT_LIMIT) or (isinstance(rid, str) and len(rid) > MAX_ID_CHARS):
        raise ProtocolError("bad_request", f"'id' is {_described(rid)}; expected a number below 2**63 or a "
                                           f"string of at most {MAX_ID_CHARS} characters")
    extra = set(data) - {"cmd", "args", "id"}
    if extra:
        raise ProtocolError("bad_request", f"unknown request keys {sorted(extra)}; expected cmd, args, id",
                            rid)
    cmd = data.get("cmd")
    if not isinstance(cmd, str):
        raise ProtocolError("bad_request", f"'cmd' must be a string, got {type(cmd).__name__}", rid)
    if cmd not in COMMANDS:
        raise ProtocolError("unknown_command", f"unknown command {cmd[:80]!r}; known: "
                                               f"{', '.join(COMMANDS)}", rid)
    args = data.get("args", {})
    if args is None:
        args = {}
    if not isinstance(args, dict):
        raise ProtocolError("bad_request", f"'args' must be an object, got {type(args).__name__}", rid)
    spec = COMMANDS[cmd]
    unknown = set(args) - set(spec)
    if unknown:
        names = ", ".join(spec) or "none"
        raise ProtocolError("bad_request", f"{cmd}: unknown args {sorted(map(str, unknown))[:5]}; "
                                           f"accepted: {names}", rid)
    for name, (tp, required) in spec.items():
        if name not in args:
            if required:
                raise ProtocolError("bad_request", f"{cmd}: missing arg {name!r} ({tp.__name__})", rid)
            continue
        value = args[name]
        if not isinstance(value, tp) or isinstance(value, bool) and tp is not bool:
            raise ProtocolError("bad_request", f"{cmd}: arg {name!r} must be a {tp.__name__}, got "
                                               f"{type(value).__name__}", rid)
        if isinstance(value, int) and abs(value) >= _INT_LIMIT:
            raise ProtocolError("bad_request", f"{cmd}: arg {name!r} is {_described(value)}; expected a number "
                                               "below 2**63", rid)
        if isinstance(value, str) and "\x00" in value:
            raise ProtocolError("bad_request", f"{cmd}: arg {name!r} contains a NUL character (\\x00); "
                                               "expected a file path or name without one", rid)
    return Request(cmd=cmd, args=dict(args), id=rid)


def encode(obj: dict[str, Any]) -> bytes:
    return (json.dumps(obj, separators=(",", ":"), allow_nan=False, default=str) + "\n").encode("utf-8")


def ok_reply(request_id: Any, state: str, result: dict[str, Any]) -> dict[str, Any]:
    return {"ok": True, "id": request_id, "state": state, "result": result}


def error_reply(request_id: Any, state: str, code: str, message: str) -> dict[str, Any]:
    return {"ok": False, "id": request_id, "state": state, "error": {"code": code, "message": message}}
