"""The urgent lane: connections over the control socket's caps, read by the accept loop itself for a stop or pause.

Why in the accept loop and not a thread per connection: a client that opens
connections and holds them must not be able to take what the operator's
``flgctl stop`` needs.  A thread per waiting connection would need a cap, and a
cap can be filled.  Here a waiting connection costs one descriptor and one
entry; the loop that accepts a connection also reads its first line, without
blocking, in the same pass of its selector.  When the lane is full the
connection that has waited longest is let go (``busy``): a connection that has
sent nothing since it was accepted is the likeliest to be a held one, and a
client that sends its request at once -- flgctl -- is read long before
``capacity`` newer connections can push it out.

A line that names ``stop`` or ``pause`` is handed to ``answer`` (which serves
it on a thread of its own); anything else, a line not complete within
``timeout`` of the accept, or a closed connection is answered ``busy`` or
dropped here.
"""

from __future__ import annotations

import collections
import selectors
import socket
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol

from flgd.daemon.protocol import MAX_REQUEST_BYTES

__all__ = ["UrgentLane", "Peer"]

Peer = tuple[int, int, int]  # (pid, uid, gid) of the client


class _Refuser(Protocol):
    def __call__(self, conn: socket.socket, peer: Peer, line: bytes | None) -> None: ...


@dataclass
class _Waiting:
    conn: socket.socket
    fd: int
    peer: Peer
    deadline: float
    received: bytearray = field(default_factory=bytearray)


class UrgentLane:
    """Over-cap connections waiting for their first request line, read without blocking by one selector.

    ``answer(conn, peer, line)`` takes a complete first line (the caller decides what to serve);
    ``refuse(conn, peer, line)`` takes a connection let go (``line`` is None when none arrived);
    both own the connection from then on.
    """

    def __init__(self, selector: selectors.BaseSelector, *, capacity: int, timeout: float,
                 answer: Callable[[socket.socket, Peer, bytes], None], refuse: _Refuser,
                 clock: Callable[[], float] = time.monotonic):
        self.selector = selector
        self.capacity = capacity
        self.timeout = timeout
        self.answer = answer
        self.refuse = refuse
        self.clock = clock
        self._waiting: "collections.OrderedDict[int, _Waiting]" = collections.OrderedDict()  # oldest first
        self.evicted = 0

    def __len__(self) -> int:
        return len(self._waiting)

    def add(self, conn: socket.socket, peer: Peer) -> None:
        """Wait for ``conn``'s first line; the longest-waiting connection makes room when the lane is full."""
        while len(self._waiting) >= self.capacity:
            oldest = next(iter(self._waiting.values()))
            self._leave(oldest)
            self.evicted += 1
            self.refuse(oldest.conn, oldest.peer, None)
        conn.setblocking(False)
        waiting = _Waiting(conn, conn.fileno(), peer, self.clock() + self.timeout)
        self.selector.register(waiting.fd, selectors.EVENT_READ, waiting)
        self._waiting[waiting.fd] = waiting

    def owns(self, data: object) -> bool:
        """Whether a selector key's data is one of this lane's connections."""
        return isinstance(data, _Waiting)

    def readable(self, data: object) -> None:
        """Read what ``data``'s connection has sent; hand it on once its first line is whole."""
        assert isinstance(data, _Waiting)
        waiting = data
        if self._waiting.get(waiting.fd) is not waiting:  # let go earlier in the same pass of the selector
            return
        try:
            chunk = waiting.conn.recv(MAX_REQUEST_BYTES)
        except BlockingIOError:
            return
        except OSError:
            chunk = b""
        if not chunk:  # the client went away
            self._leave(waiting)
            self.refuse(waiting.conn, waiting.peer, None)
            return
        waiting.received += chunk
        end = waiting.received.find(b"\n")
        if end < 0:
            if len(waiting.received) >= MAX_REQUEST_BYTES:
                self._leave(waiting)
                self.refuse(waiting.conn, waiting.peer, bytes(waiting.received))
            return
        self._leave(waiting)
        self.answer(waiting.conn, waiting.peer, bytes(waiting.received[:end]))

    def expire(self) -> None:
        """Let go of every connection whose line did not come within ``timeout``."""
        now = self.clock()
        while self._waiting:
            oldest = next(iter(self._waiting.values()))
            if oldest.deadline > now:
                return
            self._leave(oldest)
            self.refuse(oldest.conn, oldest.peer, None)

    def seconds_to_next_deadline(self, at_most: float) -> float:
        if not self._waiting:
            return at_most
        oldest = next(iter(self._waiting.values()))
        return max(0.0, min(at_most, oldest.deadline - self.clock()))

    def close_all(self) -> None:
        while self._waiting:
            waiting = next(iter(self._waiting.values()))
            self._leave(waiting)
            self.refuse(waiting.conn, waiting.peer, None)

    def _leave(self, waiting: _Waiting) -> None:
        """Out of the lane and the selector (before its connection is closed, so its descriptor is still its own)."""
        del self._waiting[waiting.fd]
        self.selector.unregister(waiting.fd)
