"""The metrics endpoint's limits on a small server object (flgd/daemon/metrics_http.py): at most ``workers``
connections served at once, each cut off at its deadline however it trickles, and the next one served after."""

from __future__ import annotations

import socket
import time

import pytest
from prometheus_client import CollectorRegistry, Gauge

from flgd.daemon.metrics_http import MetricsHTTPServer

REQUEST = b"GET /metrics HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"


@pytest.fixture
def registry() -> CollectorRegistry:
    reg = CollectorRegistry()
    Gauge("flgd_test_value", "a value to serve", registry=reg).set(7)
    return reg


def _serve(registry, **kw) -> MetricsHTTPServer:
    srv = MetricsHTTPServer(registry, "127.0.0.1", 0, **kw)
    srv.start()
    return srv


def _connect(srv: MetricsHTTPServer) -> socket.socket:
    return socket.create_connection(("127.0.0.1", srv.port), timeout=10)


def _page(conn: socket.socket) -> bytes:
    conn.settimeout(10)
    out = b""
    while True:
        chunk = conn.recv(65536)
        if not chunk:
            return out
        out += chunk


def test_a_request_trickled_past_the_deadline_is_cut_off_although_no_single_read_times_out(registry):
    """One byte every 0.1 s keeps every read shorter than the deadline: only the deadline of the whole
    connection ends it, long before the request is complete."""
    srv = _serve(registry, deadline=0.5)
    try:
        with _connect(srv) as conn:
            sent = 0
            cut = False
            for byte in REQUEST[:-1] + b" " * 40:  # never a complete request: 3 s of trickling at most
                try:
                    conn.sendall(bytes([byte]))
                except OSError:
                    cut = True
                    break
                sent += 1
                conn.settimeout(0.1)
                try:
                    if conn.recv(65536) == b"":  # closed by the server
                        cut = True
                        break
                except socket.timeout:
                    pass
                except OSError:
                    cut = True
                    break
            assert cut, f"a client trickling {sent} bytes was never cut off"
        assert srv.cut_off == 1
        with _connect(srv) as conn:  # the worker is free again: the next scrape is served
            conn.sendall(REQUEST)
            assert b"flgd_test_value 7.0" in _page(conn)
    finally:
        srv.stop()


def test_at_most_workers_connections_are_served_at_once_and_the_next_waits_its_turn(registry):
    srv = _serve(registry, workers=2, deadline=60.0)
    held = [_connect(srv) for _ in range(2)]  # silent: each holds a worker until its deadline
    try:
        deadline = time.monotonic() + 10
        while srv.open_connections() < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert srv.open_connections() == 2
        with _connect(srv) as waiting:
            waiting.sendall(REQUEST)
            waiting.settimeout(0.5)
            with pytest.raises(socket.timeout):
                waiting.recv(65536)  # in the listen queue: no worker is free, no descriptor spent on it
            assert srv.open_connections() == 2 and srv.served == 0
            held.pop().close()  # a worker frees: the waiting scrape is served
            assert b"flgd_test_value 7.0" in _page(waiting)
        assert srv.cut_off == 0
    finally:
        for conn in held:
            conn.close()
        srv.stop()
