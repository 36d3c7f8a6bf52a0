"""The HTTP endpoint of the metrics: a fixed pool of workers, each connection with a deadline.

Why not ``prometheus_client.start_http_server``: it gives every connection a
thread and a descriptor, with no timeout and no cap.  On a plant network
without a login, a thousand half-sent requests then hold a thousand
descriptors; at systemd's default limit (1,024) the daemon has none left for
its control socket, and ``flgctl stop`` goes unanswered.  Here:

* at most ``workers`` connections are open at once -- each worker accepts one
  connection, serves it and closes it; further clients wait in the kernel's
  listen queue, which costs the daemon no descriptor;
* a connection gets ``deadline`` seconds in all (request, collection, reply);
  a client that trickles its request or does not read the reply is cut off;
* the page itself is prometheus_client's handler (``MetricsHandler``): content
  negotiation, gzip and ``name[]`` filtering are the library's.

So a flood of slow scrapes can delay other scrapes by at most about
``deadline`` each, and never touches the control plane.
"""

from __future__ import annotations

import logging
import socket
import socketserver
import threading
import time
from typing import cast

from prometheus_client.exposition import MetricsHandler
from prometheus_client.registry import CollectorRegistry

__all__ = ["MetricsHTTPServer", "WORKERS", "DEADLINE"]

log = logging.getLogger("flgd.metrics")

WORKERS = 4  # connections served at once; a scrape takes milliseconds, Prometheus scrapes one at a time
DEADLINE = 5.0  # seconds one connection may take from accept to close
LISTEN_BACKLOG = 16


class _HandlerServerInfo:
    """What ``BaseHTTPRequestHandler`` reads from its server (nothing but a name)."""

    def __init__(self, host: str, port: int):
        self.server_name = host
        self.server_port = port


class MetricsHTTPServer:
    """``/metrics`` of ``registry`` on ``host:port`` from ``workers`` threads; ``stop`` closes everything."""

    def __init__(self, registry: CollectorRegistry, host: str, port: int, *, workers: int = WORKERS,
                 deadline: float = DEADLINE):
        self.registry = registry
        self.host = host
        self.port = port
        self.workers = workers
        self.deadline = deadline
        self.handler_class: type[MetricsHandler] = MetricsHandler.factory(registry)
        self.handler_class.timeout = deadline  # no single read or write may wait longer than the whole deadline
        self._sock: socket.socket | None = None
        self._threads: list[threading.Thread] = []
        self._stopping = threading.Event()
        self._lock = threading.Lock()
        self._open: dict[int, tuple[socket.socket, float]] = {}  # worker index -> (connection, its deadline)
        self.served = 0
        self.cut_off = 0

    @property
    def server_port(self) -> int:
        return self.port

    def start(self) -> None:
        """Bind, listen and start the workers and the reaper; OSError if the address cannot be bound."""
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((self.host, self.port))
            sock.listen(LISTEN_BACKLOG)
            sock.settimeout(0.5)  # workers look at the stop flag between accepts
        except OSError:
            sock.close()
            raise
        self._sock = sock
        self.port = sock.getsockname()[1]
        self._threads = [threading.Thread(target=self._work, args=(i,), name=f"flgd-metrics-{i}", daemon=True)
                         for i in range(self.workers)]
        self._threads.append(threading.Thread(target=self._reap, name="flgd-metrics-reaper", daemon=True))
        for thread in self._threads:
            thread.start()

    def stop(self) -> None:
        self._stopping.set()
        with self._lock:
            for conn, _ in self._open.values():
                _shutdown(conn)
        for thread in self._threads:
            thread.join(timeout=2.0)
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def open_connections(self) -> int:
        with self._lock:
            return len(self._open)

    # ------------------------------------------------------------------ workers
    def _work(self, index: int) -> None:
        assert self._sock is not None
        while not self._stopping.is_set():
            try:
                conn, address = self._sock.accept()
            except socket.timeout:
                continue
            except OSError as exc:
                if self._stopping.is_set():
                    return
                log.warning("metrics: accept failed: %s", exc)  # out of descriptors, most likely: wait
                self._stopping.wait(1.0)
                continue
            with self._lock:
                self._open[index] = (conn, time.monotonic() + self.deadline)
            try:
                conn.settimeout(self.deadline)
                # the handler reads only the server's name and port: a stand-in, not a socketserver
                self.handler_class(conn, address, cast(socketserver.BaseServer, _HandlerServerInfo(self.host, self.port)))
                self.served += 1
            except Exception as exc:  # a client that went away, a collector error: the next one is served
                log.warning("metrics: a request failed: %s: %s", type(exc).__name__, exc)
            finally:
                with self._lock:
                    self._open.pop(index, None)
                conn.close()

    def _reap(self) -> None:
        """Cut off every connection past its deadline (its worker's blocked read or write then returns)."""
        while not self._stopping.wait(0.25):
            now = time.monotonic()
            with self._lock:
                late = [conn for conn, deadline in self._open.values() if now > deadline]
            for conn in late:
                self.cut_off += 1
                _shutdown(conn)


def _shutdown(conn: socket.socket) -> None:
    try:
        conn.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
