"""A policy file's header, checked before its body is read.

Why: ``load_policy`` (``flgd/learning/policy_file.py``) reads the whole file, up to 512 MB, and only then
looks at the header.  ``flgctl policy load`` of a disk image, a zero-filled file or a renamed archive
would cost the daemon seconds and its size in memory before being refused.  Here only the first 8 bytes
and the header they announce are read: a file whose header length, JSON, flgd metadata or tensor extent
does not fit is refused in milliseconds, naming the file and the problem; the full check follows only
for a file that passes.
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path

from flgd.learning.policy_file import (MAX_HEADER_BYTES, PolicyFileError, PolicyFileUnreadable, _cannot_read,
                                       _check_metadata, _check_regular)

__all__ = ["check_policy_header"]


def check_policy_header(path: str | os.PathLike) -> None:
    """PolicyFileError unless ``path`` is a regular file whose safetensors header is an flgd policy's and whose
    tensors end exactly where the file does; reads the header only."""
    path = Path(path)
    try:
        st = os.stat(path)
    except OSError as exc:
        raise PolicyFileUnreadable(path, _cannot_read(path, exc), exc) from None
    _check_regular(path, st)  # a device, FIFO or oversized file is refused before it is opened
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
    except OSError as exc:
        raise PolicyFileUnreadable(path, _cannot_read(path, exc), exc) from None
    try:
        size = os.fstat(fd).st_size
        prefix = os.pread(fd, 8, 0)
        if len(prefix) < 8:
            raise PolicyFileError(path, f"truncated: {len(prefix)} bytes, too short for a safetensors header")
        (n,) = struct.unpack("<Q", prefix)
        if n == 0 or n > MAX_HEADER_BYTES or 8 + n > size:
            raise PolicyFileError(path, f"not a policy file: its first 8 bytes give a header length of {n}, which "
                                        f"does not fit the {size}-byte file (expected 1 to {MAX_HEADER_BYTES} "
                                        "bytes of JSON; a zero-filled, pickle or zip file renamed to a policy?)")
        raw = os.pread(fd, n, 8)
    except OSError as exc:
        raise PolicyFileUnreadable(path, f"cannot read: {exc.strerror or exc}", exc) from None
    finally:
        os.close(fd)
    try:
        header = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise PolicyFileError(path, f"corrupt header (not valid JSON: {exc})") from None
    if not isinstance(header, dict):
        raise PolicyFileError(path, "corrupt header (not a JSON object)")
    _check_metadata(path, header)
    body = size - 8 - n
    end = _tensor_extent(path, header)
    if end != body:
        raise PolicyFileError(path, f"the header's tensors take {end} bytes, the file holds {body} after the "
                                    "header (truncated, or not written by flgd)")


def _tensor_extent(path: Path, header: dict) -> int:
    """Where the last tensor's data ends, from the header's ``data_offsets``."""
    end = 0
    for name, entry in header.items():
        if name == "__metadata__":
            continue
        offsets = entry.get("data_offsets") if isinstance(entry, dict) else None
        if (not isinstance(offsets, list) or len(offsets) != 2
                or not all(isinstance(v, int) and v >= 0 for v in offsets) or offsets[0] > offsets[1]):
            raise PolicyFileError(path, f"corrupt header: tensor {name!r} has no valid data_offsets")
        end = max(end, offsets[1])
    return end
