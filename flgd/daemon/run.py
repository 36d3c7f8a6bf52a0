"""``flgd run``: the cell-controller daemon (foreground; systemd runs it as ``Type=notify``).

Start-up order: config -> checks (state directory, named policy) -> control
socket claimed (answering ``busy`` until ready) and metrics port bound ->
state-directory lock and store -> policy -> cell -> READY=1.  A bad config,
policy, state directory, a socket or port in use, or a cell that fails is
reported with a clear message and exit code 1, before anything moves; a
daemon that exits early never removes a socket it did not create.  SIGTERM or Ctrl-C
halts the motion in flight at once (on the UR5e ``stopL``: the arm
decelerates and holds; nothing more is sent), the interrupted action is
logged and not learned from, then the daemon saves a checkpoint, flushes the
store and exits 0; a second Ctrl-C exits at once (the store stays consistent,
at most the action in flight is lost).

The signal handler itself only records the signal and calls the cell's
"stop motion now" entry point (``CycleRunner.request_stop``, which must stay
safe in a signal handler).  The state change to STOPPING, its listeners, the
systemd notification and the store write happen in the run loop, which polls
``_SignalStop.poll``: a handler runs in the main thread between two bytecodes,
and the state machine's and the notifier's locks are not reentrant, so doing
that work inside it would deadlock when the signal lands while the main thread
holds one of them.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any, Callable, TextIO

from flgd.config import ConfigError, load_config, parse_metrics_address
from flgd.log_limit import RepeatLimit
from flgd.daemon.notify import Notifier
from flgd.daemon.preflight import PreflightError, check_policy, check_state_dir, warn_if_policy_unused
from flgd.daemon.protocol import ProtocolError, Request
from flgd.daemon.state import State
from flgd.daemon.server import ControlServer, PeerPolicy, SocketInUse
from flgd.daemon.socket_path import default_socket_path, socket_candidates

if TYPE_CHECKING:
    from flgd.daemon.controller import Controller

__all__ = ["main", "default_socket_path", "socket_candidates"]

log = logging.getLogger("flgd")

EXIT_OK, EXIT_STARTUP = 0, 1


class _StatusLine(logging.Handler):
    """Log records on stderr that do not mangle the live status line of a terminal."""

    def __init__(self, stream: TextIO, live: bool):
        super().__init__()
        self.stream = stream
        self.live = live
        self.lock_ = threading.Lock()
        self.line = ""

    def emit(self, record: logging.LogRecord) -> None:
        msg = self.format(record)
        with self.lock_:
            if self.live:
                self.stream.write("\r\033[K" + msg + "\n" + self.line)
            else:
                self.stream.write(msg + "\n")
            self.stream.flush()

    def show(self, text: str) -> None:
        with self.lock_:
            width = max(20, _terminal_width() - 1)
            self.line = text[:width]
            self.stream.write("\r\033[K" + self.line)
            self.stream.flush()

    def finish(self) -> None:
        with self.lock_:
            if self.live and self.line:
                self.stream.write("\n")
                self.stream.flush()
            self.line = ""


def _terminal_width() -> int:
    try:
        columns = os.get_terminal_size(sys.stderr.fileno()).columns
    except OSError:
        columns = 0
    return columns if columns > 0 else 100


class _SignalStop:
    """SIGTERM/SIGINT: a flag and an immediate motion halt in the handler; the state change later, in the loop."""

    def __init__(self, controller: Controller) -> None:
        self.controller = controller
        self.seen: list[int] = []  # list.append is safe in a handler; read by the loop
        self.halt_errors: list[str] = []

    def on_signal(self, signum: int, _frame: FrameType | None = None) -> None:
        """The handler: nothing here may take a lock the interrupted main thread could hold (no logging, no
        state transition, no notifier, no store)."""
        self.seen.append(signum)
        if len(self.seen) > 1 and signum == signal.SIGINT:
            try:  # os.write, not sys.stderr/logging: both take locks the interrupted code may hold
                os.write(2, b"\nflgd: second interrupt, exiting now (the store is consistent)\n")
            except OSError:
                pass
            os._exit(130)
        runner = getattr(self.controller, "runner", None)
        if runner is not None:  # None during setup: nothing can be moving yet
            try:
                runner.request_stop()  # the cell's stop_motion: stopL on the UR5e; no more motion is sent
            except Exception as exc:  # never raise into whatever the main thread was doing
                self.halt_errors.append(f"{type(exc).__name__}: {exc}")

    def poll(self) -> bool:
        """Called by the run loop (normal context): move to STOPPING with the signal's name as the cause."""
        if not self.seen:
            return False
        for err in self.halt_errors:
            log.error("halting the motion on the signal failed: %s", err)
        self.halt_errors.clear()
        if self.controller.state.state is not State.STOPPING:
            self.controller.request_stop(f"signal {signal.Signals(self.seen[0]).name}")
        return True


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="flgd run", description="Run the flgd cell-controller daemon.")
    p.add_argument("--config", required=True, help="cell config YAML")
    p.add_argument("--policy", help="policy file to start from (default: the config's policy; a checkpoint "
                                    "in the state directory takes precedence, so learning resumes)")
    p.add_argument("--autostart", action="store_true", help="start cycling immediately (state RUNNING)")
    p.add_argument("--socket", help="control socket path (default: $RUNTIME_DIRECTORY/flgd.sock, else "
                                    "/run/flgd/flgd.sock)")
    p.add_argument("--control-group", help="group whose members may use flgctl (in addition to root and "
                                           "the daemon's user)")
    p.add_argument("--metrics", metavar="HOST:PORT",
                   help="serve Prometheus metrics at http://HOST:PORT/metrics (default: the config's metrics "
                        "key; off when neither is set; '' turns it off)")
    p.add_argument("--checkpoints-keep", type=int, default=3, help="checkpoints kept in the state directory")
    p.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    p.add_argument("--no-status-line", action="store_true", help="no live status line on a terminal")
    return p


def main(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    live = sys.stderr.isatty() and not args.no_status_line
    handler = _StatusLine(sys.stderr, live)
    journal = bool(os.environ.get("JOURNAL_STREAM"))
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s" if journal else
                                           "%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S"))
    handler.addFilter(RepeatLimit())  # no condition that fails on every try can flood the journal
    limit_learner_log()
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(args.log_level)

    try:
        config = load_config(args.config)
    except ConfigError as exc:
        print(f"flgd run: {exc}", file=sys.stderr)
        return EXIT_STARTUP
    if args.checkpoints_keep < 1:
        print(f"flgd run: --checkpoints-keep: got {args.checkpoints_keep}, expected >= 1", file=sys.stderr)
        return EXIT_STARTUP
    try:
        peers = PeerPolicy(args.control_group)
    except ValueError as exc:
        print(f"flgd run: --control-group: {exc}", file=sys.stderr)
        return EXIT_STARTUP
    metrics_address = config.metrics if args.metrics is None else args.metrics
    try:
        metrics_bind = parse_metrics_address(metrics_address) if metrics_address else None
    except ValueError as exc:
        where = "--metrics" if args.metrics is not None else f"config {config.source}: metrics"
        print(f"flgd run: {where}: {exc}", file=sys.stderr)
        return EXIT_STARTUP
    # Everything an operator must fix is found before the socket is claimed or the cell touched.
    try:
        check_state_dir(config)
        policy = check_policy(config, args.policy)
    except PreflightError as exc:
        print(f"flgd run: {exc}", file=sys.stderr)
        return EXIT_STARTUP

    from flgd.daemon.controller import Controller, StartupError

    notifier = Notifier()
    controller = Controller(config, policy_path=args.policy, autostart=args.autostart, notifier=notifier,
                            checkpoint_keep=args.checkpoints_keep)
    stop = _SignalStop(controller)
    previous = {sig: signal.signal(sig, stop.on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}

    sock_path = Path(args.socket) if args.socket else default_socket_path()
    ready = threading.Event()
    state_name = lambda: controller.state.state.value if ready.is_set() else "STARTING"  # noqa: E731
    server = ControlServer(sock_path, _until_ready(controller.handle, ready), state_name, peers)
    metrics = None
    status_stop = threading.Event()
    try:
        server.bind()  # before the cell: a second daemon on this socket stops here, touching nothing
        if metrics_bind is not None:
            from flgd.daemon.prometheus import MetricsServer

            metrics = MetricsServer(controller, *metrics_bind, state_name=state_name)
            metrics.start()
        server.start()  # answers "busy: starting" until the setup is done
        notifier.status("starting: loading policy and connecting the cell")
        controller.setup()
        warn_if_policy_unused(policy, controller.status()["policy"], controller.policy_source, str(config.state_dir))
        if live:
            threading.Thread(target=_status_loop, args=(controller, handler, status_stop), daemon=True,
                             name="flgd-status").start()
        log.info("ready: %s, %s, state dir %s, socket %s", controller.backend, controller.policy_source,
                 config.state_dir, sock_path)
        ready.set()  # after the start-up lines: a client that got an answer finds them in the log
        controller.run_loop(stop_requested=stop.poll)
    except (StartupError, ConfigError, SocketInUse, OSError) as exc:
        handler.finish()
        print(f"flgd run: {exc}", file=sys.stderr)
        notifier.status(f"failed to start: {exc}")
        controller.shutdown()
        for sig, previous_handler in previous.items():
            signal.signal(sig, previous_handler)
        return EXIT_STARTUP
    finally:
        status_stop.set()
        server.stop()  # removes only the socket file this daemon created
        if metrics is not None:
            metrics.stop()
    handler.finish()
    log.info("stopping: %s", controller.state.cause)
    controller.shutdown()
    log.info("stopped")
    notifier.close()
    for sig, previous_handler in previous.items():  # run in-process (tests): leave no handler behind
        signal.signal(sig, previous_handler)
    return EXIT_OK


LEARNER_LOGGER = "flgd.learning.learner"
LEARNER_BURST = 3  # records of one learner message per minute


def limit_learner_log() -> RepeatLimit:
    """The learner fails once per update when the disk is full, each message with its update number: at most
    ``LEARNER_BURST`` of each a minute, tracebacks of storage errors as one line (installed once)."""
    from flgd.store.errors import StoreError

    learner = logging.getLogger(LEARNER_LOGGER)
    for existing in learner.filters:
        if isinstance(existing, RepeatLimit):
            return existing
    limit = RepeatLimit(burst=LEARNER_BURST, by_template=True, quiet=(OSError, StoreError))
    learner.addFilter(limit)
    return limit


def _until_ready(handle: Callable[[Request], dict[str, Any]], ready: threading.Event) -> Callable[[Request], dict[str, Any]]:
    """The control handler, answering ``busy`` while the daemon is still setting up."""

    def serve(request: Request) -> dict[str, Any]:
        if not ready.is_set():
            raise ProtocolError("busy", "flgd is starting (loading the policy, connecting the cell); try again "
                                        "in a moment")
        return handle(request)

    return serve


def _status_loop(controller: Controller, handler: _StatusLine, stop: threading.Event) -> None:
    while not stop.wait(1.0):
        handler.show("flgd " + controller.status_text())
