"""The control socket: accepts local connections, checks who is calling, serves protocol lines.

Why a thread per connection: requests are tiny and few, and a handler may
wait for the run loop (a backend swap); one slow client must not block
``flgctl status`` from another.  A line longer than the cap is answered with
``too_long`` and skipped, so no client can exhaust the daemon's memory.

Why the operator can always stop the cell: connections are capped in all
(``MAX_CONNECTIONS``) and per uid (``MAX_CONNECTIONS_PER_UID``, so one account's
runaway script cannot take the slots of the others), and a request line must
arrive whole within ``REQUEST_TIMEOUT`` of its first byte (a client trickling
a byte at a time is cut off).  A connection over either cap is not refused
outright: it goes to the urgent lane (``flgd/daemon/urgent_lane.py``), where
the accept loop itself reads its first line within ``URGENT_TIMEOUT`` and
serves it only if it is ``stop`` or ``pause`` (both are answered at once,
without the run loop).  The lane never fills up against a newcomer: the
connection that has waited longest makes room, so clients that open
connections and hold them -- idle, trickling or by the hundred, from any
number of threads -- cannot keep stop and pause from being read and answered.

Why the operator can still stop the cell when the process is out of file
descriptors (a leak, or a flood of connections elsewhere): the server holds one
spare descriptor; when ``accept`` fails for want of descriptors it closes the
spare, takes the waiting connection on it and reopens the spare when that
connection closes -- one control connection at a time, never a tight loop, one
log line per episode rather than one per failure.

Who owns the socket path: the daemon holds an exclusive lock on ``PATH.lock``
(beside the socket) from before it binds until it exits, and removes only the
socket file it created itself (same inode), never one another daemon made.
A socket file found while holding the lock is a dead daemon's, and is replaced.
"""

from __future__ import annotations

import dataclasses
import errno
import fcntl
import grp
import logging
import math
import os
import pwd
import resource
import selectors
import socket
import stat
import struct
import threading
import time
from pathlib import Path
from typing import Any, Callable

from flgd.daemon.protocol import (MAX_REQUEST_BYTES, ProtocolError, Request, encode, error_reply,
                                  ok_reply, parse_request)
from flgd.daemon.peer_access import unreadable_path_arg
from flgd.daemon.urgent_lane import Peer, UrgentLane

__all__ = ["PeerPolicy", "ControlServer", "ConnectionSlots", "SocketInUse", "peer_credentials",
           "URGENT_COMMANDS"]

log = logging.getLogger("flgd.control")

MAX_CONNECTIONS = 32
MAX_CONNECTIONS_PER_UID = 16
IDLE_TIMEOUT = 120.0  # seconds a connection may wait between two requests
REQUEST_TIMEOUT = 10.0  # seconds from a request line's first byte to its newline
# The urgent lane, for connections over the caps: one request, read within URGENT_TIMEOUT.
URGENT_COMMANDS = frozenset({"stop", "pause"})
URGENT_WAITING = 64  # connections waiting in the lane for their first line (the oldest makes room)
MAX_URGENT = 16  # stop and pause requests being answered at once
MAX_URGENT_PER_UID = 8
URGENT_TIMEOUT = 2.0
ACCEPT_BATCH = 16  # accepts per pass of the loop: what waits in the lane is read in between
_SO_PEERCRED_FORMAT = "3i"  # struct ucred {pid_t pid; uid_t uid; gid_t gid;}


def _descriptor_limit() -> str:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    return f"{soft} soft, {hard} hard"


class SocketInUse(RuntimeError):
    """Another daemon already answers on the socket path."""


class ConnectionSlots:
    """At most ``total`` connections at once, and at most ``per_uid`` of them from one uid."""

    def __init__(self, total: int, per_uid: int):
        self.total = total
        self.per_uid = per_uid
        self._lock = threading.Lock()
        self._by_uid: dict[int, int] = {}

    def acquire(self, uid: int) -> bool:
        with self._lock:
            if sum(self._by_uid.values()) >= self.total or self._by_uid.get(uid, 0) >= self.per_uid:
                return False
            self._by_uid[uid] = self._by_uid.get(uid, 0) + 1
            return True

    def release(self, uid: int) -> None:
        with self._lock:
            left = self._by_uid.get(uid, 0) - 1
            if left > 0:
                self._by_uid[uid] = left
            else:
                self._by_uid.pop(uid, None)

    def held(self, uid: int | None = None) -> int:
        with self._lock:
            return sum(self._by_uid.values()) if uid is None else self._by_uid.get(uid, 0)


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


Handler = Callable[[Request], dict[str, Any]]
StateName = Callable[[], str]


class ControlServer:
    """Serves ``handler(request) -> result dict`` on a Unix socket; handler errors become replies.

    ``bind`` claims the path (lock, stale-socket check, bind, listen) and is
    cheap, so the daemon calls it before anything touches the cell; ``start``
    binds if needed and begins serving.
    """

    def __init__(self, path: str | os.PathLike[str], handler: Handler, state_name: StateName,
                 policy: PeerPolicy, mode: int = 0o660, *, request_timeout: float = REQUEST_TIMEOUT,
                 idle_timeout: float = IDLE_TIMEOUT, urgent_timeout: float = URGENT_TIMEOUT):
        self.path = Path(path)
        self.lock_path = self.path.with_name(self.path.name + ".lock")
        self.handler = handler
        self.state_name = state_name
        self.policy = policy
        self.mode = mode
        self.request_timeout = request_timeout
        self.idle_timeout = idle_timeout
        self.urgent_timeout = urgent_timeout
        self._sock: socket.socket | None = None
        self._lock_fd: int | None = None
        self._created: tuple[int, int] | None = None  # (st_dev, st_ino) of the socket file this server made
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._slots = ConnectionSlots(MAX_CONNECTIONS, MAX_CONNECTIONS_PER_UID)
        self._urgent = ConnectionSlots(MAX_URGENT, MAX_URGENT_PER_UID)
        self.requests_served = 0
        self.refused_peers = 0
        self._reserve_fd: int | None = None  # a spare descriptor for when the process has run out
        self._closers: dict[int, Callable[[], None]] = {}
        self._exhausted_since = 0.0  # monotonic time accepts began to fail (0: they do not)
        self._exhausted_failures = 0
        self._lane: UrgentLane | None = None  # set while the accept loop runs

    # ------------------------------------------------------------------ life cycle
    def bind(self) -> None:
        """Claim the socket path; SocketInUse if another daemon has it (nothing of theirs is touched)."""
        if self._sock is not None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._take_path_lock()
        try:
            self._remove_stale_socket()
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            old_umask = os.umask(0o117)  # the socket file is never world-accessible, even briefly
            try:
                sock.bind(str(self.path))
            except OSError:
                sock.close()
                raise
            finally:
                os.umask(old_umask)
            st = os.lstat(self.path)
            self._created = (st.st_dev, st.st_ino)
            os.chmod(self.path, self.mode)
            if self.policy.gid is not None:
                try:
                    os.chown(self.path, -1, self.policy.gid)
                except PermissionError:
                    log.warning("cannot give the control socket to group %s; only uid %d and root may use it",
                                self.policy.group_name, os.getuid())
            sock.listen(128)  # a burst of connections waits here instead of failing
            sock.settimeout(0.5)
            self._sock = sock
        except BaseException:
            self._remove_own_socket()
            self._release_path_lock()
            raise

    def start(self) -> None:
        self.bind()
        self._thread = threading.Thread(target=self._accept_loop, name="flgd-control", daemon=True)
        self._thread.start()
        log.info("control socket %s (mode %o; allowed: %s)", self.path, self.mode, self.policy.describe())

    def _take_path_lock(self) -> None:
        fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise SocketInUse(f"another flgd is running or starting on {self.path} (it holds {self.lock_path}); "
                              "stop it first or use --socket") from None
        self._lock_fd = fd

    def _release_path_lock(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # the lock file stays: removing it would let two daemons lock two files
            self._lock_fd = None

    def _remove_stale_socket(self) -> None:
        """With the path lock held: a socket file there is a dead daemon's, unless something answers on it."""
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

    def _remove_own_socket(self) -> None:
        """Unlink the socket file only if it is still the one this server created."""
        if self._created is None:
            return
        try:
            st = os.lstat(self.path)
            if (st.st_dev, st.st_ino) == self._created:
                self.path.unlink()
        except FileNotFoundError:
            pass
        self._created = None

    def stop(self) -> None:
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        self._remove_own_socket()
        self._release_path_lock()
        if self._reserve_fd is not None:
            os.close(self._reserve_fd)
            self._reserve_fd = None

    # ------------------------------------------------------------------ serving
    def _accept_loop(self) -> None:
        """Accept connections and read the urgent lane's, in one selector loop that never blocks on a client."""
        assert self._sock is not None
        self._open_reserve()
        self._sock.setblocking(False)
        with selectors.DefaultSelector() as selector:
            selector.register(self._sock, selectors.EVENT_READ, None)
            self._lane = UrgentLane(selector, capacity=URGENT_WAITING, timeout=self.urgent_timeout,
                                    answer=self._answer_from_lane, refuse=self._refuse_from_lane)
            try:
                while not self._stopping.is_set():
                    for key, _ in selector.select(self._lane.seconds_to_next_deadline(0.5)):
                        try:
                            if key.data is None:
                                self._accept_batch()
                            elif self._lane.owns(key.data):
                                self._lane.readable(key.data)
                        except Exception:  # never let one connection end the accept loop
                            log.exception("control socket: serving a connection failed")
                    self._lane.expire()
            finally:
                self._lane.close_all()
                self._lane = None

    def _accept_batch(self) -> None:
        """Up to ``ACCEPT_BATCH`` waiting connections; the loop reads the lane before taking more."""
        for _ in range(ACCEPT_BATCH):
            try:
                conn, _ = self._sock.accept()  # type: ignore[union-attr]
            except BlockingIOError:
                return
            except OSError as exc:
                if self._stopping.is_set():
                    return
                if exc.errno in (errno.EMFILE, errno.ENFILE):
                    self._accept_with_reserve(exc)
                else:
                    self._accept_failed(exc)
                return
            conn.setblocking(True)
            if self._reserve_fd is None:
                self._open_reserve()
            if self._reserve_fd is None:
                # took the descriptor a lent connection just gave back: still exhausted, and this connection
                # is the lent one now (the reserve is reopened when it closes); the episode goes on
                self._admit_safely(conn, on_close=self._open_reserve)
                continue
            self._accept_recovered()
            self._admit_safely(conn)

    def _admit_safely(self, conn: socket.socket, on_close: Callable[[], None] | None = None) -> None:
        try:
            self._admit(conn, on_close)
        except Exception:  # never let one connection end the accept loop
            log.exception("control connection setup failed")
            self._close(conn)

    # ------------------------------------------------------------------ out of descriptors
    def _open_reserve(self) -> None:
        """Hold one spare descriptor, so a control connection can be taken when the process has none left."""
        if self._reserve_fd is None:
            try:
                self._reserve_fd = os.open(os.devnull, os.O_RDONLY | os.O_CLOEXEC)
            except OSError:
                self._reserve_fd = None  # still exhausted: retried when the next lent connection closes

    def _accept_with_reserve(self, exc: OSError) -> None:
        """Out of descriptors: give the spare one to the waiting connection, or back off until one frees."""
        if not self._exhausted_since:
            self._exhausted_since = time.monotonic()
            log.error("control socket: out of file descriptors (%s; limit %s); control connections are taken "
                      "one at a time through a reserve descriptor until some are closed (this is logged once "
                      "per episode)", exc.strerror or exc, _descriptor_limit())
        self._exhausted_failures += 1
        if self._reserve_fd is None:
            self._stopping.wait(0.05)  # the lent descriptor is still in use: no tight loop
            return
        os.close(self._reserve_fd)
        self._reserve_fd = None
        try:
            conn, _ = self._sock.accept()  # type: ignore[union-attr]
        except OSError:
            self._open_reserve()
            self._stopping.wait(0.05)
            return
        conn.setblocking(True)
        self._admit_safely(conn, on_close=self._open_reserve)

    def _accept_failed(self, exc: OSError) -> None:
        """Any other accept error: logged once per episode, retried after a short back-off."""
        self._exhausted_failures += 1
        if not self._exhausted_since:
            self._exhausted_since = time.monotonic()
            log.error("control socket: accept failed: %s (logged once until an accept succeeds again)", exc)
        self._stopping.wait(0.05)

    def _accept_recovered(self) -> None:
        if self._exhausted_since:
            log.warning("control socket: accepting again after %.0f s (%d accepts failed meanwhile)",
                        time.monotonic() - self._exhausted_since, self._exhausted_failures)
            self._exhausted_since = 0.0
            self._exhausted_failures = 0

    def _admit(self, conn: socket.socket, on_close: Callable[[], None] | None = None) -> None:
        """Check the caller, then give the connection a slot or a place in the urgent lane.

        ``on_close`` runs once the connection is closed (the reserve descriptor is taken back then).
        """
        if on_close is not None:
            self._closers[id(conn)] = on_close
        try:
            pid, uid, gid = peer_credentials(conn)
        except OSError as exc:
            log.warning("cannot read peer credentials: %s", exc)
            self._refuse(conn, "forbidden", "peer credentials unavailable")
            return
        if not self.policy.allows(uid, gid):
            self.refused_peers += 1
            log.warning("refused control connection from pid %d uid %d gid %d (allowed: %s)",
                        pid, uid, gid, self.policy.describe())
            self._refuse(conn, "forbidden",
                         f"uid {uid} is not allowed to control flgd (allowed: {self.policy.describe()})")
            return
        peer = (pid, uid, gid)
        if self._slots.acquire(uid):
            threading.Thread(target=self._serve_connection, args=(conn, peer), name="flgd-client",
                             daemon=True).start()
        elif self._lane is not None:
            self._lane.add(conn, peer)
        else:
            self._refuse(conn, "busy", self._busy_message(uid))

    def _busy_message(self, uid: int) -> str:
        return (f"too many connections ({self._slots.held(uid)} of uid {uid}, at most {MAX_CONNECTIONS_PER_UID} "
                f"per uid and {MAX_CONNECTIONS} in all); close some and try again (stop and pause are still "
                "served, and flgctl retries them)")

    def _refuse(self, conn: socket.socket, code: str, message: str) -> None:
        """One error line without waiting for the peer (the accept loop must never block), then close."""
        self._send_and_close(conn, error_reply(None, self.state_name(), code, message))

    def _close(self, conn: socket.socket) -> None:
        """Close a connection, then run what waits for its descriptor (see ``_admit``)."""
        on_close = self._closers.pop(id(conn), None)
        conn.close()
        if on_close is not None:
            on_close()

    def _serve_connection(self, conn: socket.socket, peer: tuple[int, int, int]) -> None:
        try:
            self._serve_lines(conn, peer)
        finally:
            try:
                self._close(conn)
            finally:
                self._slots.release(peer[1])

    def _answer_from_lane(self, conn: socket.socket, peer: Peer, line: bytes) -> None:
        """A first line read in the urgent lane: stop and pause are served on a thread; the rest get ``busy``."""
        try:
            request = parse_request(line.rstrip(b"\r"))
        except ProtocolError as exc:
            self._send_and_close(conn, error_reply(exc.request_id, self.state_name(), exc.code, exc.message))
            return
        if request.cmd not in URGENT_COMMANDS:
            self._send_and_close(conn, error_reply(request.id, self.state_name(), "busy",
                                                   self._busy_message(peer[1])))
        elif not self._urgent.acquire(peer[1]):
            self._send_and_close(conn, error_reply(request.id, self.state_name(), "busy",
                                                   f"{MAX_URGENT} stop and pause requests are being answered; "
                                                   "try again (flgctl does)"))
        else:
            threading.Thread(target=self._serve_urgent, args=(conn, peer, line), name="flgd-urgent",
                             daemon=True).start()

    def _refuse_from_lane(self, conn: socket.socket, peer: Peer, line: bytes | None) -> None:
        if line is None:
            self._refuse(conn, "busy", self._busy_message(peer[1]))
        else:
            self._refuse(conn, "too_long", f"request line is over the {MAX_REQUEST_BYTES}-byte limit")

    def _send_and_close(self, conn: socket.socket, reply: dict[str, Any]) -> None:
        """One reply line without waiting for the peer (the accept loop must never block), then close."""
        try:
            conn.setblocking(False)
            conn.send(encode(_json_safe(reply)))
        except OSError:
            pass
        finally:
            self._close(conn)

    def _serve_urgent(self, conn: socket.socket, peer: Peer, line: bytes) -> None:
        """Answer a stop or pause read in the urgent lane, then close."""
        try:
            conn.setblocking(True)
            self._reply(conn, self._answer(line, peer))
        finally:
            try:
                self._close(conn)
            finally:
                self._urgent.release(peer[1])

    def _serve_lines(self, conn: socket.socket, peer: tuple[int, int, int]) -> None:
        buf = bytearray()
        skipping = False  # inside an over-long line whose too_long reply was already sent
        line_deadline: float | None = None  # when the line being received must be complete
        while not self._stopping.is_set():
            if line_deadline is None:
                timeout = self.idle_timeout
            else:
                timeout = line_deadline - time.monotonic()
                if timeout <= 0:
                    self._reply_timeout(conn)
                    return
            try:
                conn.settimeout(timeout)
                chunk = conn.recv(65536)
            except socket.timeout:
                if line_deadline is not None:
                    self._reply_timeout(conn)
                return
            except OSError:
                return
            if not chunk:
                return
            if line_deadline is None:
                line_deadline = time.monotonic() + self.request_timeout
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
                # the next line's clock starts with its first byte, already here or still to come
                line_deadline = time.monotonic() + self.request_timeout if buf else None
                if skipping:
                    skipping = False
                    continue
                if not self._reply(conn, self._answer(line, peer)):
                    return

    def _reply_timeout(self, conn: socket.socket) -> None:
        self._reply(conn, error_reply(None, self.state_name(), "bad_request",
                                      f"request line not complete within {self.request_timeout:g} s of its first "
                                      "byte (send each request as one line); connection closed"))

    def _answer(self, line: bytes, peer: tuple[int, int, int]) -> dict[str, Any]:
        if line.endswith(b"\r"):
            line = line[:-1]
        try:
            request = dataclasses.replace(parse_request(line), peer=f"uid {peer[1]} pid {peer[0]}")
        except ProtocolError as exc:
            return error_reply(exc.request_id, self.state_name(), exc.code, exc.message)
        refusal = unreadable_path_arg(request, peer[1], peer[2], own_uid=self.policy.own_uid)
        if refusal:
            log.warning("refused %s from uid %d: %s", request.cmd, peer[1], refusal)
            return error_reply(request.id, self.state_name(), "forbidden", refusal)
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

    def _reply(self, conn: socket.socket, reply: dict[str, Any]) -> bool:
        try:
            conn.settimeout(self.request_timeout)  # a client that does not read its reply is let go too
            conn.sendall(encode(_json_safe(reply)))
            return True
        except OSError:
            return False
