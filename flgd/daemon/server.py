"""The control socket: accepts local connections, checks who is calling, serves protocol lines.

Why a thread per connection: requests are tiny and few, and a handler may
wait for the run loop (a backend swap); one slow client must not block
``flgctl status`` from another.  The number of connections is capped, every
connection has an idle timeout, and a line longer than the cap is answered
with ``too_long`` and skipped, so no client can exhaust the daemon.
"""

from __future__ import annotations

import dataclasses
import grp
import logging
import math
import os
import pwd
import socket
import stat
import struct
import threading
from pathlib import Path
from typing import Any, Callable

from flgd.daemon.protocol import (MAX_REQUEST_BYTES, ProtocolError, Request, encode, error_reply,
                                  ok_reply, parse_request)

__all__ = ["PeerPolicy", "ControlServer", "SocketInUse", "peer_credentials"]

log = logging.getLogger("flgd.control")

MAX_CONNECTIONS = 32
IDLE_TIMEOUT = 120.0
_SO_PEERCRED_FORMAT = "3i"  # struct ucred {pid_t pid; uid_t uid; gid_t gid;}


class SocketInUse(RuntimeError):
    """Another daemon already answers on the socket path."""


def peer_credentials(conn: socket.socket) -> tuple[int, int, int]:
    """(pid, uid, gid) of the process at the other end of a Unix socket."""
    raw = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize(_SO_PEERCRED_FORMAT))
    pid, uid, gid = struct.unpack(_SO_PEERCRED_FORMAT, raw)
    return pid, uid, gid


class PeerPolicy:
    """Who may command the daemon: root, the daemon's own uid, and members of one group."""

    def __init__(self, group: str | None = None):
        self.own_uid = os.getuid()
        self.group_name = group
        self.gid: int | None = None
        if group:
            try:
                self.gid = grp.getgrnam(group).gr_gid
            except KeyError:
                raise ValueError(f"control group {group!r} does not exist") from None

    def allows(self, uid: int, gid: int) -> bool:
        if uid in (0, self.own_uid):
            return True
        if self.gid is None:
            return False
        if gid == self.gid:
            return True
        try:
            user = pwd.getpwuid(uid)
        except KeyError:
            return False
        return self.gid in os.getgrouplist(user.pw_name, user.pw_gid)

    def describe(self) -> str:
        group = f", group {self.group_name}" if self.group_name else ""
        return f"root, uid {self.own_uid}{group}"


def _json_safe(obj: Any) -> Any:
    """NaN/inf are not JSON: report them as null."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


Handler = Callable[[Request], dict]
StateName = Callable[[], str]


class ControlServer:
    """Serves ``handler(request) -> result dict`` on a Unix socket; handler errors become replies."""

    def __init__(self, path: str | os.PathLike, handler: Handler, state_name: StateName,
                 policy: PeerPolicy, mode: int = 0o660):
        self.path = Path(path)
        self.handler = handler
        self.state_name = state_name
        self.policy = policy
        self.mode = mode
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._slots = threading.BoundedSemaphore(MAX_CONNECTIONS)
        self.requests_served = 0
        self.refused_peers = 0

    # ------------------------------------------------------------------ life cycle
    def start(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._remove_stale_socket()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old_umask = os.umask(0o117)  # the socket file is never world-accessible, even briefly
        try:
            sock.bind(str(self.path))
        finally:
            os.umask(old_umask)
        os.chmod(self.path, self.mode)
        if self.policy.gid is not None:
            try:
                os.chown(self.path, -1, self.policy.gid)
            except PermissionError:
                log.warning("cannot give the control socket to group %s; only uid %d and root may use it",
                            self.policy.group_name, os.getuid())
        sock.listen(16)
        sock.settimeout(0.5)
        self._sock = sock
        self._thread = threading.Thread(target=self._accept_loop, name="flgd-control", daemon=True)
        self._thread.start()
        log.info("control socket %s (mode %o; allowed: %s)", self.path, self.mode, self.policy.describe())

    def _remove_stale_socket(self) -> None:
        try:
            st = self.path.lstat()
        except FileNotFoundError:
            return
        if not stat.S_ISSOCK(st.st_mode):
            raise SocketInUse(f"{self.path} exists and is not a socket; refusing to replace it")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        probe.settimeout(1.0)
        try:
            probe.connect(str(self.path))
        except (ConnectionRefusedError, FileNotFoundError):
            self.path.unlink(missing_ok=True)  # left behind by a daemon that died
            return
        except OSError:
            pass
        finally:
            probe.close()
        raise SocketInUse(f"another flgd answers on {self.path}; stop it first or use --socket")

    def stop(self) -> None:
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass

    # ------------------------------------------------------------------ serving
    def _accept_loop(self) -> None:
        assert self._sock is not None
        while not self._stopping.is_set():
            try:
                conn, _ = self._sock.accept()
            except socket.timeout:
                continue
            except OSError:
                if self._stopping.is_set():
                    return
                log.exception("control socket accept failed")
                continue
            if not self._slots.acquire(blocking=False):
                self._send_and_close(conn, error_reply(None, self.state_name(), "busy",
                                                       f"too many connections (max {MAX_CONNECTIONS})"))
                continue
            threading.Thread(target=self._serve_connection, args=(conn,), name="flgd-client",
                             daemon=True).start()

    def _send_and_close(self, conn: socket.socket, reply: dict) -> None:
        try:
            conn.settimeout(2.0)
            conn.sendall(encode(reply))
        except OSError:
            pass
        finally:
            conn.close()

    def _serve_connection(self, conn: socket.socket) -> None:
        try:
            try:
                pid, uid, gid = peer_credentials(conn)
            except OSError as exc:
                log.warning("cannot read peer credentials: %s", exc)
                self._send_and_close(conn, error_reply(None, self.state_name(), "forbidden",
                                                       "peer credentials unavailable"))
                return
            if not self.policy.allows(uid, gid):
                self.refused_peers += 1
                log.warning("refused control connection from pid %d uid %d gid %d (allowed: %s)",
                            pid, uid, gid, self.policy.describe())
                self._send_and_close(conn, error_reply(
                    None, self.state_name(), "forbidden",
                    f"uid {uid} is not allowed to control flgd (allowed: {self.policy.describe()})"))
                return
            conn.settimeout(IDLE_TIMEOUT)
            self._serve_lines(conn, f"uid {uid} pid {pid}")
        finally:
            try:
                conn.close()
            finally:
                self._slots.release()

    def _serve_lines(self, conn: socket.socket, peer: str = "") -> None:
        buf = bytearray()
        skipping = False  # inside an over-long line whose too_long reply was already sent
        while not self._stopping.is_set():
            try:
                chunk = conn.recv(65536)
            except (socket.timeout, OSError):
                return
            if not chunk:
                return
            buf += chunk
            while True:
                nl = buf.find(b"\n")
                if nl < 0:
                    if not skipping and len(buf) >= MAX_REQUEST_BYTES:
                        self._reply(conn, error_reply(None, self.state_name(), "too_long",
                                                      f"request line is over the {MAX_REQUEST_BYTES}-byte "
                                                      f"limit; the rest of the line is ignored"))
                        skipping = True
                    if skipping:
                        buf.clear()
                    break
                line = bytes(buf[:nl])
                del buf[:nl + 1]
                if skipping:
                    skipping = False
                    continue
                if not self._reply(conn, self._answer(line, peer)):
                    return

    def _answer(self, line: bytes, peer: str = "") -> dict:
        if line.endswith(b"\r"):
            line = line[:-1]
        try:
            request = dataclasses.replace(parse_request(line), peer=peer)
        except ProtocolError as exc:
            return error_reply(exc.request_id, self.state_name(), exc.code, exc.message)
        try:
            result = self.handler(request)
        except ProtocolError as exc:
            return error_reply(request.id, self.state_name(), exc.code, exc.message)
        except Exception as exc:  # a handler bug must not take the daemon down
            log.exception("control command %s failed", request.cmd)
            return error_reply(request.id, self.state_name(), "failed",
                               f"{request.cmd}: internal error: {type(exc).__name__}: {exc}")
        self.requests_served += 1
        return ok_reply(request.id, self.state_name(), _json_safe(result))

    def _reply(self, conn: socket.socket, reply: dict) -> bool:
        try:
            conn.sendall(encode(_json_safe(reply)))
            return True
        except OSError:
            return False
