"""ur_rtde in a process of its own, so that the library failing cannot take the daemon down with it.

ur_rtde is C++ behind pybind11.  Against a dropped RTDE link, version 1.6.5's control interface reconnects
from its own receive thread; seen against ``flgd emulate`` that thread can loop for ever holding Python's lock,
or end the process with a segmentation fault.  In the daemon's process either would stop the control socket,
the learner and the store with it, and systemd's restart would be the only recovery.

``IsolatedRTDEFactory`` builds the four interfaces inside one child process and hands ``URArm`` proxies with
the same methods.  Every call crosses a pipe (tens of microseconds) and has a deadline; a child that dies or
stops answering is killed and every call after that raises :class:`RTDEProcessLost`, which ``URArm`` turns
into a latched fault like any other failed call.  ``URArm.recover`` then opens fresh interfaces through the
factory, which starts a new child: the controller sees a new client, as after a restart of the service.
"""

from __future__ import annotations

import multiprocessing
import signal
import threading
from multiprocessing.connection import Connection
from typing import Any, Protocol

__all__ = ["RTDEFactory", "IsolatedRTDEFactory", "RemoteInterface", "RTDEProcessLost", "RTDECallInProgress", "Snapshot",
           "CALL_TIMEOUT", "OPEN_TIMEOUT"]

CALL_TIMEOUT = 20.0   # s a call may take (the dashboard's own timeout is 2 s; asynchronous moves return at once)
OPEN_TIMEOUT = 30.0   # s to open an interface (the control interface uploads its script and waits for it); well
                      # under the service's WatchdogSec, so a hung open is a latched fault, not a killed daemon
_PR_SET_PDEATHSIG = 1
_CLASSES = {"control": ("rtde_control", "RTDEControlInterface"), "receive": ("rtde_receive", "RTDEReceiveInterface"),
            "io": ("rtde_io", "RTDEIOInterface"), "dashboard": ("dashboard_client", "DashboardClient")}


class RTDEFactory(Protocol):
    """Builds the four ur_rtde interfaces (``rtde_process.IsolatedRTDEFactory``: in a child process); tests pass a
    fake with the same methods."""

    def control(self, host: str) -> Any: ...

    def receive(self, host: str) -> Any: ...

    def io(self, host: str) -> Any: ...

    def dashboard(self, host: str) -> Any: ...


class RTDEProcessLost(RuntimeError):
    """The process that holds the ur_rtde interfaces ended or stopped answering."""


class RTDECallInProgress(RuntimeError):
    """A call from the thread that is already waiting on the pipe (a signal handler's stopL during a move): not
    sent; the interrupted call returns first and its caller sees the stop request."""


def _serve(conn: Connection) -> None:
    """The child: open interfaces and run their methods, one request at a time, until told to exit."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # Ctrl-C is the daemon's to handle; it closes us in order
    _die_with_parent()
    from flgd.hardware import hardware_library

    interfaces: dict[int, Any] = {}
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        kind = request[0]
        try:
            if kind == "open":
                _, handle, name, host = request
                module, cls = _CLASSES[name]
                interfaces[handle] = getattr(hardware_library(module), cls)(host)
                reply: tuple = ("ok", None)
            elif kind == "call":
                _, handle, method, args = request
                reply = ("ok", _portable(getattr(interfaces[handle], method)(*args)))
            elif kind == "exit":
                conn.send(("ok", None))
                return
            else:
                reply = ("error", "ValueError", f"unknown request {kind!r}")
        except Exception as exc:  # ur_rtde raises RuntimeError and friends from C++: the caller decides
            reply = ("error", type(exc).__name__, str(exc))
        try:
            conn.send(reply)
        except (BrokenPipeError, OSError):
            return


def _die_with_parent() -> None:
    """Linux: be killed when the daemon dies, even while ur_rtde holds this process in a loop (it would never
    read the pipe's end-of-file) and might go on talking to the controller for a daemon started after it."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):
        pass  # not Linux: the pipe's end-of-file still ends an idle child


class Snapshot:
    """A ur_rtde result object that cannot cross the pipe (``AsyncOperationStatus``), as the values its getters
    returned in the child: ``status.isAsyncOperationRunning()`` works on this side as on the original."""

    def __init__(self, type_name: str, values: dict[str, Any]) -> None:
        self.type_name = type_name
        self.values = values

    def __getattr__(self, name: str) -> Any:
        values = self.__dict__.get("values", {})
        if name not in values:
            raise AttributeError(f"{self.__dict__.get('type_name', '?')}.{name} was not captured")
        return lambda: values[name]


def _portable(value: Any) -> Any:
    """``value`` if it is plain data (what ur_rtde returns but for status objects), else a Snapshot of its
    argument-free getters."""
    if value is None or isinstance(value, (bool, int, float, str, list, tuple, dict)):
        return value
    values = {}
    for name in dir(value):
        if name.startswith("_"):
            continue
        attr = getattr(value, name, None)
        if callable(attr):
            try:
                values[name] = attr()
            except TypeError:
                continue  # needs arguments: not a getter
    return Snapshot(type(value).__name__, values)


class _Child:
    """One child process and its pipe; calls are serialised (one request in flight)."""

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("spawn")   # never fork a process with threads and a torch pool
        self._conn, child_end = ctx.Pipe()
        self.process = ctx.Process(target=_serve, args=(child_end,), name="flgd-ur_rtde", daemon=True)
        self.process.start()
        child_end.close()
        self._lock = threading.Lock()
        self._owner: int | None = None   # the thread waiting on the pipe now
        self.lost: str | None = None
        self._next_handle = 0

    def request(self, message: tuple, timeout: float, what: str) -> Any:
        if self._owner == threading.get_ident():
            raise RTDECallInProgress(f"{what}: not sent, this thread is waiting for another call's reply")
        with self._lock:
            self._owner = threading.get_ident()
            try:
                if self.lost is not None:
                    raise RTDEProcessLost(self.lost)
                try:
                    self._conn.send(message)
                    if not self._conn.poll(timeout):
                        self._lose(f"{what} did not return within {timeout:.0f} s")
                    reply = self._conn.recv()
                except (EOFError, OSError):
                    self.process.join(1.0)
                    self._lose(f"{what}: the process ended")
                except RTDEProcessLost:
                    raise
                except BaseException:  # e.g. KeyboardInterrupt between send and reply: the pipe is out of step
                    self._abandon(f"{what} was interrupted")
                    raise
            finally:
                self._owner = None
        if reply[0] == "ok":
            return reply[1]
        raise _remote_error(reply[1], reply[2])

    def new_handle(self) -> int:
        self._next_handle += 1
        return self._next_handle

    def _abandon(self, why: str) -> None:
        """Kill the child and mark it lost without raising (the caller re-raises what interrupted it)."""
        try:
            self._lose(why)
        except RTDEProcessLost:
            pass

    def _lose(self, why: str) -> None:
        code = self.process.exitcode
        if code is None:
            self.process.kill()
            self.process.join(5.0)
            ended = "it was stopped"
        elif code < 0:
            ended = f"it ended on signal {signal.Signals(-code).name}"
        else:
            ended = f"it exited with code {code}"
        self.lost = f"ur_rtde's process: {why}; {ended}"
        raise RTDEProcessLost(self.lost)

    def close(self) -> None:
        if self.lost is None and self.process.is_alive():
            try:
                self.request(("exit",), 5.0, "exit")
            except (RTDEProcessLost, RuntimeError):
                pass
        self.lost = self.lost or "closed"
        self.process.join(5.0)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(5.0)
        self._conn.close()


def _remote_error(type_name: str, message: str) -> Exception:
    """The child's exception, as a RuntimeError named after its type (ur_rtde's are RuntimeError mostly)."""
    return RuntimeError(message) if type_name == "RuntimeError" else RuntimeError(f"{type_name}: {message}")


class RemoteInterface:
    """A ur_rtde interface living in the child: ``iface.moveL(...)`` runs there and returns its result."""

    def __init__(self, child: _Child, name: str, host: str) -> None:
        self._child = child
        self._name = name
        self._handle = child.new_handle()
        child.request(("open", self._handle, name, host), OPEN_TIMEOUT, f"opening the {name} interface")

    @property
    def process_alive(self) -> bool:
        """False once the child ended or was stopped: every call would raise RTDEProcessLost."""
        return self._child.lost is None

    def __getattr__(self, method: str) -> Any:
        if method.startswith("_"):
            raise AttributeError(method)

        def call(*args: Any) -> Any:
            return self._child.request(("call", self._handle, method, args), CALL_TIMEOUT,
                                       f"{self._name}.{method}")

        call.__name__ = method
        return call


class IsolatedRTDEFactory:
    """``RTDEFactory`` for URArm: the four interfaces in one child process, a new child once the last one is lost.

    ``URArm.close`` disconnects the interfaces, then calls :meth:`close`, which ends the child.
    """

    def __init__(self) -> None:
        self._child: _Child | None = None
        self._lock = threading.Lock()

    def _live_child(self) -> _Child:
        with self._lock:
            if self._child is None or self._child.lost is not None:
                if self._child is not None:
                    self._child.close()
                self._child = _Child()
            return self._child

    def control(self, host: str) -> RemoteInterface:
        return RemoteInterface(self._live_child(), "control", host)

    def receive(self, host: str) -> RemoteInterface:
        return RemoteInterface(self._live_child(), "receive", host)

    def io(self, host: str) -> RemoteInterface:
        return RemoteInterface(self._live_child(), "io", host)

    def dashboard(self, host: str) -> RemoteInterface:
        return RemoteInterface(self._live_child(), "dashboard", host)

    def restart(self) -> None:
        """End the child now (its interfaces are dropped); the next interface opened starts a fresh one."""
        with self._lock:
            if self._child is not None:
                self._child.close()
                self._child = None

    def close(self) -> None:
        self.restart()
