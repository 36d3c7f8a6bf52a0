"""Where the control socket is: the daemon binds the first usable candidate, flgctl tries each.

Why a module of its own: flgctl needs these few lines and nothing of the daemon's start-up (the config
schema alone costs it a sixth of a second, more on a loaded machine), and the operator's ``flgctl stop``
should start fast.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["default_socket_path", "socket_candidates"]


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
