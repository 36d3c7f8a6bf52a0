"""``flgd emulate``: the real cell's devices, emulated on the simulated cell, in the foreground (Ctrl-C stops it).

    flgd emulate --config cell_config/ur5e-emulated.yaml [--time-scale 1] [--faults PATH]
                 [--marker aruco|checkerboard --marker-offset X Y Z]
    flgd emulate --inject KIND [--during-motion] [--faults PATH]

The first runs the emulator (the devices and addresses: sim_cell/emulator/emulated_cell.py); the second sends a
fault to a running one (the kinds: sim_cell/emulator/faults.py).  Exit codes: 0 stopped by a signal, 1 it could
not start (a port taken, the simulator failed) or a fault was refused, 2 usage or config errors.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
from pathlib import Path

__all__ = ["main", "DEFAULT_FAULT_SOCKET"]

DEFAULT_FAULT_SOCKET = Path(os.environ.get("XDG_RUNTIME_DIR") or "/tmp") / "flgd-emulate.sock"


def _parser() -> argparse.ArgumentParser:
    from sim_cell.emulator.faults import KINDS

    p = argparse.ArgumentParser(prog="flgd emulate", description=__doc__.split("\n\n")[0])
    p.add_argument("--config", help="the cell config the daemon uses (backend ur5e, robot.host, "
                                    "gripper.xmlrpc_port, camera.emulator)")
    p.add_argument("--time-scale", type=float, default=1.0,
                   help="physics speed against real time (2 = twice as fast); default 1")
    p.add_argument("--faults", default=str(DEFAULT_FAULT_SOCKET),
                   help=f"the fault socket (default {DEFAULT_FAULT_SOCKET})")
    p.add_argument("--marker", choices=("aruco", "checkerboard"),
                   help="mount a calibration marker on the gripper, for flgd calibrate (its default tag or board)")
    p.add_argument("--marker-offset", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"),
                   help="the marker's centre in the tool frame, m (as flgd calibrate --marker-offset takes it)")
    p.add_argument("--inject", choices=KINDS, metavar="KIND",
                   help="send a fault to a running emulator: " + ", ".join(KINDS))
    p.add_argument("--during-motion", action="store_true",
                   help="with --inject: raise it at a random instant of the arm's next motion")
    return p


def _inject(args: argparse.Namespace) -> int:
    from sim_cell.emulator.faults import inject

    command = args.inject + (" --during-motion" if args.during_motion else "")
    try:
        reply = inject(args.faults, command)
    except OSError as exc:
        print(f"flgd emulate: no emulator answers on {args.faults} ({exc.strerror or exc}); "
              f"start one with flgd emulate --config FILE", file=sys.stderr)
        return 1
    print(json.dumps(reply))
    return 0 if reply.get("ok") else 1


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.inject:
        return _inject(args)
    if args.during_motion:
        print("flgd emulate: --during-motion goes with --inject KIND", file=sys.stderr)
        return 2
    if not args.config:
        print("flgd emulate: give --config FILE (the cell config the daemon uses), or --inject KIND",
              file=sys.stderr)
        return 2
    if not args.time_scale > 0:
        print(f"flgd emulate: --time-scale must be > 0, got {args.time_scale}", file=sys.stderr)
        return 2

    from flgd.config import ConfigError, load_config
    from sim_cell.emulator.emulated_cell import EmulatedCell, EmulatorConfigError

    logging.basicConfig(level=logging.INFO, format="%(asctime)s flgd-emulate %(levelname)s %(message)s")
    try:
        config = load_config(args.config)
        cell = EmulatedCell(config, time_scale=args.time_scale, fault_socket=args.faults, marker=args.marker,
                            marker_offset=tuple(args.marker_offset))
    except (ConfigError, EmulatorConfigError, ValueError) as exc:
        print(f"flgd emulate: {exc}", file=sys.stderr)
        return 2
    try:
        cell.start()
    except OSError as exc:
        print(f"flgd emulate: cannot start: {exc}", file=sys.stderr)
        return 1
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print("flgd emulate: ready\n" + cell.describe(), flush=True)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        cell.close()
    print("flgd emulate: stopped", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
