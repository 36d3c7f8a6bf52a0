"""``flgd run``: the cell-controller daemon (foreground; systemd runs it as ``Type=notify``).

Start-up order: config -> state directory and store -> policy -> cell ->
control socket -> READY=1.  A bad config, policy or cell is reported with a
clear message and exit code 1, before anything moves.  SIGTERM or Ctrl-C
lets the cycle in flight finish (the arm is never stopped mid-motion by the
daemon itself), then saves a checkpoint, flushes the store and exits 0; a
second Ctrl-C exits at once (the store stays consistent, at most the action
in flight is lost).
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from pathlib import Path

from flgd.config import ConfigError, load_config
from flgd.daemon.notify import Notifier
from flgd.daemon.server import ControlServer, PeerPolicy, SocketInUse

__all__ = ["main", "default_socket_path", "socket_candidates"]

log = logging.getLogger("flgd")

EXIT_OK, EXIT_STARTUP = 0, 1


def socket_candidates(environ: dict[str, str] | None = None) -> list[Path]:
    """Where the control socket is looked for, in order (flgctl tries each)."""
    env = os.environ if environ is None else environ
    out = []
    if env.get("FLGD_SOCKET"):
        out.append(Path(env["FLGD_SOCKET"]))
    if env.get("RUNTIME_DIRECTORY"):
        out.append(Path(env["RUNTIME_DIRECTORY"].split(":")[0]) / "flgd.sock")
    out.append(Path("/run/flgd/flgd.sock"))
    if env.get("XDG_RUNTIME_DIR"):
        out.append(Path(env["XDG_RUNTIME_DIR"]) / "flgd" / "flgd.sock")
    return out


def default_socket_path(environ: dict[str, str] | None = None) -> Path:
    """The daemon's socket: $FLGD_SOCKET, $RUNTIME_DIRECTORY/flgd.sock, /run/flgd/flgd.sock if writable,
    else $XDG_RUNTIME_DIR/flgd/flgd.sock."""
    cands = socket_candidates(environ)
    for p in cands:
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(p.parent, os.W_OK):
            return p
    return cands[0]


class _StatusLine(logging.Handler):
    """Log records on stderr that do not mangle the live status line of a terminal."""

    def __init__(self, stream, live: bool):
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

    from flgd.daemon.controller import Controller, StartupError

    notifier = Notifier()
    controller = Controller(config, policy_path=args.policy, autostart=args.autostart, notifier=notifier,
                            checkpoint_keep=args.checkpoints_keep)
    signals_seen: list[int] = []

    def on_signal(signum, _frame) -> None:
        signals_seen.append(signum)
        if len(signals_seen) > 1 and signum == signal.SIGINT:
            handler.finish()
            sys.stderr.write("flgd: second interrupt, exiting now (the store is consistent)\n")
            sys.stderr.flush()
            os._exit(130)
        controller.request_stop(f"signal {signal.Signals(signum).name}")

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}

    server = None
    status_stop = threading.Event()
    try:
        notifier.status("starting: loading policy and connecting the cell")
        controller.setup()
        sock_path = Path(args.socket) if args.socket else default_socket_path()
        server = ControlServer(sock_path, controller.handle, lambda: controller.state.state.value, peers)
        server.start()
        if live:
            threading.Thread(target=_status_loop, args=(controller, handler, status_stop), daemon=True,
                             name="flgd-status").start()
        log.info("ready: %s, %s, state dir %s, socket %s", controller.backend, controller.policy_source,
                 config.state_dir, sock_path)
        controller.run_loop(stop_requested=lambda: bool(signals_seen))
    except (StartupError, SocketInUse, OSError) as exc:
        handler.finish()
        print(f"flgd run: {exc}", file=sys.stderr)
        notifier.status(f"failed to start: {exc}")
        controller.shutdown()
        for sig, previous_handler in previous.items():
            signal.signal(sig, previous_handler)
        return EXIT_STARTUP
    finally:
        status_stop.set()
        if server is not None:
            server.stop()
    handler.finish()
    log.info("stopping: %s", controller.state.cause)
    controller.shutdown()
    log.info("stopped")
    notifier.close()
    for sig, previous_handler in previous.items():  # run in-process (tests): leave no handler behind
        signal.signal(sig, previous_handler)
    return EXIT_OK


def _status_loop(controller, handler: _StatusLine, stop: threading.Event) -> None:
    while not stop.wait(1.0):
        handler.show("flgd " + controller.status_text())
