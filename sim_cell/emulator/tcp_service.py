"""A threaded TCP listener for the emulator's servers: bind, accept, one thread per client, close, drop.

Each emulated controller port (RTDE, dashboard, script ports) is one
``TCPService`` with a handler for a connected socket.  A port that is taken
fails with an error naming host:port; a handler's exception (a malformed
packet) is logged and closes that connection only, never the server.
"""

from __future__ import annotations

import logging
import socket
import threading
from typing import Callable

__all__ = ["TCPService", "PortTaken", "start_all"]

log = logging.getLogger(__name__)

Handler = Callable[[socket.socket], None]


class PortTaken(OSError):
    """The emulator cannot listen on host:port (another emulator or a real controller's software?)."""


class TCPService:
    """Listens on ``host:port`` and runs ``handler(sock)`` in a thread per client."""

    def __init__(self, name: str, host: str, port: int, handler: Handler):
        self.name = name
        self.host = host
        self.port = port
        self._handler = handler
        self._listener: socket.socket | None = None
        self._accept_thread: threading.Thread | None = None
        self._clients: dict[socket.socket, threading.Thread] = {}
        self._lock = threading.Lock()
        self._closing = threading.Event()

    def start(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((self.host, self.port))
        except OSError as exc:
            sock.close()
            raise PortTaken(f"{self.name}: cannot listen on {self.host}:{self.port}: {exc.strerror or exc}") from exc
        sock.listen(8)
        sock.settimeout(0.2)
        self._listener = sock
        self._closing.clear()
        self._accept_thread = threading.Thread(target=self._accept, name=f"{self.name}-accept", daemon=True)
        self._accept_thread.start()

    def _accept(self) -> None:
        while not self._closing.is_set():
            try:
                conn, _ = self._listener.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            thread = threading.Thread(target=self._serve, args=(conn,), name=f"{self.name}-client", daemon=True)
            with self._lock:
                self._clients[conn] = thread
            thread.start()

    def _serve(self, conn: socket.socket) -> None:
        try:
            self._handler(conn)
        except (ConnectionError, OSError):
            pass  # the client went away, or drop_clients closed it
        except Exception:
            log.exception("%s: a client's request failed; its connection is closed", self.name)
        finally:
            with self._lock:
                self._clients.pop(conn, None)
            try:
                conn.close()
            except OSError:
                pass

    @property
    def client_count(self) -> int:
        with self._lock:
            return len(self._clients)

    def drop_clients(self) -> None:
        """Close every client connection (a dropped link); the server keeps listening."""
        with self._lock:
            conns = list(self._clients)
        for conn in conns:
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    @property
    def closing(self) -> bool:
        return self._closing.is_set()

    def close(self) -> None:
        """Stop listening, drop the clients and join the threads; safe to call twice."""
        self._closing.set()
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        self.drop_clients()
        if self._accept_thread is not None:
            self._accept_thread.join(timeout=2.0)
            self._accept_thread = None
        with self._lock:
            threads = list(self._clients.values())
        for t in threads:
            t.join(timeout=2.0)


def start_all(parts) -> None:
    """``start()`` each of ``parts`` in order; on a failure close those already started and raise."""
    started = []
    try:
        for part in parts:
            part.start()
            started.append(part)
    except Exception:
        for part in reversed(started):
            part.close()
        raise


def read_exact(conn: socket.socket, n: int) -> bytes:
    """``n`` bytes from ``conn``; ConnectionError when the peer closed it first."""
    chunks = bytearray()
    while len(chunks) < n:
        data = conn.recv(n - len(chunks))
        if not data:
            raise ConnectionError("peer closed the connection")
        chunks += data
    return bytes(chunks)


def read_line(conn: socket.socket, limit: int = 65536) -> bytes:
    """Bytes from ``conn`` up to and including the first newline, or all there is when the peer closes first or
    ``limit`` bytes came without one."""
    data = b""
    while b"\n" not in data and len(data) < limit:
        chunk = conn.recv(limit)
        if not chunk:
            break
        data += chunk
    return data
