"""When the reader of a command's output goes away (``flgd check-config FILE | head -1``), exit like Unix tools.

Why a module: ``flgd`` and ``flgctl`` both print to pipes; both must end quietly, without a traceback from the
interpreter's last flush of what is still buffered.
"""

from __future__ import annotations

import os
import sys

__all__ = ["stdout_to_devnull"]


def stdout_to_devnull() -> None:
    """Point stdout at /dev/null, so nothing still buffered can fail (and print a traceback) at exit."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass
