"""flgd run's signal handling (flgd/daemon/run.py): a stop signal halts the motion at once and leaves the state
change to the run loop, never deadlocks on a lock the interrupted code holds, and a second Ctrl-C exits."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from flgd.daemon.notify import Notifier
from flgd.daemon.state import State, StateMachine

REPO = Path(__file__).resolve().parents[1]
SIM = REPO / "cell_config" / "sim.yaml"

pytestmark = pytest.mark.usefixtures("one_torch_thread")


# --------------------------------------------------------------------------- the signal handler

class _FakeRunner:
    def __init__(self):
        self.halts = 0

    def request_stop(self):
        self.halts += 1


class _FakeController:
    """The parts of Controller the signal path touches, with the real (non-reentrant) locks."""

    def __init__(self):
        self.state = StateMachine(State.RUNNING)
        self.notifier = Notifier({})
        self.runner = _FakeRunner()
        self.state.add_listener(lambda change: self.notifier.send(f"STATUS={change.new.value}"))

    def request_stop(self, cause: str) -> None:  # what Controller.request_stop does
        self.state.transition(State.STOPPING, cause)
        if self.runner is not None:
            self.runner.request_stop()


def test_the_handler_halts_the_motion_but_leaves_the_state_change_to_the_loop():
    from flgd.daemon.run import _SignalStop

    ctl = _FakeController()
    stop = _SignalStop(ctl)
    assert stop.poll() is False
    stop.on_signal(signal.SIGTERM)
    assert ctl.runner.halts == 1 and ctl.state.state is State.RUNNING
    assert stop.poll() is True
    assert ctl.state.state is State.STOPPING and ctl.state.cause == "signal SIGTERM"
    assert stop.poll() is True and ctl.state.cause == "signal SIGTERM"  # polled again: no second transition


@pytest.mark.parametrize("lock", ["state", "notifier"])
def test_a_signal_while_the_main_thread_holds_a_lock_does_not_deadlock(lock):
    """A real SIGTERM delivered while this (the main) thread holds the lock, as in the daemon."""
    from flgd.daemon.run import _SignalStop

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals are delivered to the main thread only")
    ctl = _FakeController()
    stop = _SignalStop(ctl)
    held = ctl.state._lock if lock == "state" else ctl.notifier._lock

    def alarm(_s, _f):  # a deadlocked handler is interrupted here instead of hanging the test run
        raise TimeoutError("the signal handler deadlocked")

    prev_term = signal.signal(signal.SIGTERM, stop.on_signal)
    prev_alarm = signal.signal(signal.SIGALRM, alarm)
    try:
        signal.setitimer(signal.ITIMER_REAL, 5.0)
        with held:
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(100):  # the handler runs between bytecodes of this thread
                if stop.seen:
                    break
                time.sleep(0.01)
        signal.setitimer(signal.ITIMER_REAL, 0)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGTERM, prev_term)
        signal.signal(signal.SIGALRM, prev_alarm)
    assert stop.seen == [signal.SIGTERM] and ctl.runner.halts == 1
    assert stop.poll() and ctl.state.state is State.STOPPING


def test_a_failing_halt_never_raises_into_the_interrupted_code_and_is_logged_later(caplog):
    from flgd.daemon.run import _SignalStop

    ctl = _FakeController()
    calls = []

    def broken():  # the first halt (in the handler) fails; the loop's own stop later goes through
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("link gone")

    ctl.runner.request_stop = broken
    stop = _SignalStop(ctl)
    stop.on_signal(signal.SIGTERM)  # must not raise
    with caplog.at_level("ERROR"):
        assert stop.poll()
    assert "link gone" in caplog.text and ctl.state.state is State.STOPPING


def test_a_signal_during_setup_is_only_recorded():
    from flgd.daemon.run import _SignalStop

    ctl = _FakeController()
    ctl.runner = None
    stop = _SignalStop(ctl)
    stop.on_signal(signal.SIGINT)
    assert ctl.state.state is State.RUNNING and stop.poll() and ctl.state.cause == "signal SIGINT"


def test_a_second_ctrl_c_exits_at_once_with_130():
    code = ("import signal\n"
            "from flgd.daemon.run import _SignalStop\n"
            "class C:\n    runner = None\n"
            "s = _SignalStop(C())\n"
            "s.on_signal(signal.SIGINT)\n"
            "s.on_signal(signal.SIGINT)\n"
            "print('not reached')\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert p.returncode == 130 and "second interrupt" in p.stderr and "not reached" not in p.stdout


def test_run_docstring_no_longer_promises_the_motion_is_never_stopped():
    import flgd.daemon.run as run

    assert "never stopped mid-motion" not in run.__doc__ and "halts the motion in flight" in run.__doc__
