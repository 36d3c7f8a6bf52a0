"""Memory the daemon frees goes back to the system, so a cell PC's RAM is not held at a heap's high-water mark.

Why: every decision and every learner update allocates and frees tensors of megabytes (16 rotations of
224 x 224 feature maps).  glibc keeps freed heap pages for reuse, and raises its ``mmap`` threshold after the
first large free, so that such blocks come from the heap too: the daemon on the shipped sim config settled at
about 1 GB of resident memory (``flgd bench soak``) while it needs far less at any instant.  The daemon calls
``trim_heap`` after each cycle: the free pages go back (about 20 ms), and the next cycle faults its pages in
again (about 50 ms more per decision; resident memory 0.62x).  Keeping large blocks on ``mmap`` instead (``return_freed_memory``) saves a little more but made every
allocation a fresh mapping: it doubled the decision and update times, so the daemon does not use it.  Both are
measured by ``flgd bench memory`` (BENCHMARKS.md).  On a C library without these calls (not glibc) nothing
changes.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
from typing import Callable

__all__ = ["return_freed_memory", "trim_heap", "MMAP_THRESHOLD"]

log = logging.getLogger("flgd")

M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter (malloc.h); setting it also stops the dynamic adjustment
MMAP_THRESHOLD = 128 * 1024  # glibc's own starting value, kept fixed


def _libc(name: str, argtypes: tuple, restype: type) -> Callable[..., int] | None:
    """The C library's function ``name``, typed; None where there is none (not glibc)."""
    library = ctypes.util.find_library("c")
    if not library:
        return None
    try:
        function = getattr(ctypes.CDLL(library), name)
    except (OSError, AttributeError):
        return None
    function.argtypes = argtypes
    function.restype = restype
    return function


def return_freed_memory(threshold: int = MMAP_THRESHOLD) -> bool:
    """Keep blocks of ``threshold`` bytes or more on ``mmap`` for the rest of the process; True if it took."""
    mallopt = _libc("mallopt", (ctypes.c_int, ctypes.c_int), ctypes.c_int)
    return mallopt is not None and bool(mallopt(M_MMAP_THRESHOLD, int(threshold)))


def trim_heap() -> bool:
    """Give the heap's free pages back now (glibc ``malloc_trim``); True if any were returned."""
    malloc_trim = _libc("malloc_trim", (ctypes.c_size_t,), ctypes.c_int)
    return malloc_trim is not None and bool(malloc_trim(0))
