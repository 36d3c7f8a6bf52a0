"""Policy files: one safetensors file holding a network's weights and its metadata.

Why safetensors: its loader parses a JSON header and copies raw tensor bytes,
so loading a file can never execute code (unlike pickle, which torch.save
uses).  On top of the container's own checks, loading refuses a file unless

* the first 8 bytes give a header length that fits the file, and the header is
  a JSON object (a pickle or zip renamed to the policy suffix fails here,
  before any other parser sees it);
* ``__metadata__`` has ``format = flgd-policy`` and a known ``format_version``;
* the variant (and ``expected_variant``, if given) and architecture are known,
  and every tensor name, dtype and shape equals the rebuilt network's;
* ``weights_sha256`` matches the tensors, and ``metadata_sha256`` matches the
  other metadata, so a flipped bit anywhere in the file is caught;
* every floating-point tensor is finite: a network that diverged to NaN or Inf
  would act on garbage Q-maps, so it is refused (naming the first bad tensor)
  both when loading and when saving.

Before a byte is read, the path must be a regular file of at most
``MAX_POLICY_BYTES``: ``flgctl policy load /dev/zero`` would otherwise grow the
daemon until the OOM killer stops it, and a FIFO would block it forever.
A read the operating system refuses (permissions, an I/O error, a missing
path) raises ``PolicyFileUnreadable``, a ``PolicyFileError`` that proves
nothing about the content.

Metadata fields: format, format_version, variant, architecture (JSON),
shapes (JSON name -> shape), training_steps, cell, rolling_success, created
(UTC ISO 8601), weights_sha256, metadata_sha256, and ``extra`` (JSON of any
other caller-supplied keys).

Saving is atomic: the bytes go to a temporary file in the target directory,
which is fsynced, renamed over the target and the directory fsynced, so a
crash leaves either the old or the new file, never a torn one.  Saved files
are mode 0640 (``POLICY_MODE``), not the temporary file's 0600: the daemon
saves into its state directory as user flgd, and operators in group flgd must
be able to read (copy out) what ``flgctl policy save FILE`` asked for.
"""

from __future__ import annotations

from typing import Any

import datetime as _dt
import hashlib
import json
import math
import os
import stat
import struct
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load as _st_load
from safetensors.torch import save as _st_save

from flgd.atomic_file import write_atomically
from flgd.learning.networks import VARIANTS, QMapNetwork, build_network

__all__ = ["FORMAT", "FORMAT_VERSION", "POLICY_SUFFIX", "MAX_POLICY_BYTES", "POLICY_MODE", "PolicyFileError",
           "PolicyFileUnreadable", "first_non_finite", "LoadedPolicy", "save_policy", "load_policy", "read_metadata", "check_fits"]

FORMAT = "flgd-policy"
FORMAT_VERSION = 1
POLICY_SUFFIX = ".safetensors"
MAX_HEADER_BYTES = 16 * 1024 * 1024
# The shipped fast policy is ~0.3 MB and a DenseNet-121 policy ~30 MB; 512 MB leaves an order of
# magnitude of room for bigger networks while a mistaken path (a disk image, /dev/zero) is refused
# before the daemon tries to hold it in memory.
MAX_POLICY_BYTES = 512 * 1024 * 1024
# Group-readable, not world-readable: see "Saving" in the module docstring.
POLICY_MODE = 0o640
# Paths a systemd unit with ProtectHome=yes / PrivateTmp=yes (systemd/flgd.service) cannot see.
_SANDBOX_HIDDEN = ("/home", "/root", "/run/user", "/tmp", "/var/tmp")
SANDBOX_HINT = ("if flgd runs as the systemd service, it cannot see files under /home, /root or /run/user "
                "(ProtectHome=yes) and has its own private /tmp and /var/tmp (PrivateTmp=yes), even where you can "
                "see them: copy the policy into the service's state directory (StateDirectory=flgd), e.g. "
                "`sudo install -d -o flgd -g flgd -m 0750 /var/lib/flgd/policies && "
                "sudo install -o flgd -g flgd -m 0640 {path} /var/lib/flgd/policies/`, and load it from there")


class PolicyFileError(ValueError):
    """A policy file cannot be used; the message names the file and the problem."""

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"policy file {self.path}: {problem}")


class PolicyFileUnreadable(PolicyFileError):
    """The operating system refused to read the file (``os_error``; None for a file swapped while opened).

    Apart from its parent because it says nothing about the file's content: a permission, a disk or a
    rename in progress may be fixed a moment later, so a caller that keeps records (the gatekeeper) must
    not judge the file by it.
    """

    def __init__(self, path: str | os.PathLike[str], problem: str, os_error: OSError | None) -> None:
        super().__init__(path, problem)
        self.os_error = os_error


@dataclass(frozen=True)
class LoadedPolicy:
    network: QMapNetwork
    metadata: dict[str, Any]


def _weights_digest(tensors: dict[str, torch.Tensor]) -> str:
    """sha256 over (name, dtype, shape, raw bytes) of every tensor in name order."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        h.update(json.dumps([name, str(t.dtype), list(t.shape)]).encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def _metadata_digest(meta: dict[str, str]) -> str:
    body = {k: v for k, v in meta.items() if k != "metadata_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def _tensors_of(network: QMapNetwork) -> dict[str, torch.Tensor]:
    return {k: v.detach().cpu().clone().contiguous() for k, v in network.state_dict().items()}


def first_non_finite(tensors: dict[str, torch.Tensor], order: list[str]) -> str | None:
    """Describe the first floating-point tensor (in ``order``) holding NaN or Inf, or None if all are finite."""
    for name in order:
        t = tensors[name]
        if not t.is_floating_point():
            continue  # integer tensors (BN's num_batches_tracked) cannot be NaN
        finite = torch.isfinite(t)
        if not bool(finite.all()):
            bad = int((~finite).sum())
            kinds = "/".join(k for k, present in (("NaN", bool(torch.isnan(t).any())),
                                                   ("Inf", bool(torch.isinf(t).any()))) if present)
            return f"tensor {name!r}: {bad} of {t.numel()} values are not finite ({kinds})"
    return None


def save_policy(path: str | os.PathLike[str], network: QMapNetwork, metadata: dict[str, Any], *, mode: int = POLICY_MODE) -> None:
    """Write ``network`` and ``metadata`` (training_steps, cell, rolling_success, anything else) atomically.

    ``mode`` is the file's permission bits (default 0640, group-readable; see the module docstring).
    A network with a non-finite weight is refused (PolicyFileError), so a diverged network is never
    written as a policy or checkpoint.
    """
    path = Path(path)
    if network.variant not in VARIANTS:
        raise PolicyFileError(path, f"network variant {network.variant!r} is not one of {VARIANTS}")
    metadata = dict(metadata or {})
    steps = metadata.pop("training_steps", 0)
    cell = metadata.pop("cell", "")
    success = metadata.pop("rolling_success", None)
    if not (isinstance(steps, int) and steps >= 0):
        raise PolicyFileError(path, f"metadata training_steps: got {steps!r}, expected an integer >= 0")
    if success is not None and not (isinstance(success, (int, float)) and math.isfinite(success)):
        raise PolicyFileError(path, f"metadata rolling_success: got {success!r}, expected a number or None")
    try:
        extra = json.dumps(metadata, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise PolicyFileError(path, f"metadata is not JSON-serialisable: {exc}") from None
    tensors = _tensors_of(network)
    bad = first_non_finite(tensors, list(tensors))
    if bad is not None:
        raise PolicyFileError(path, f"not saved: the network has diverged: {bad}")
    meta = {
        "format": FORMAT,
        "format_version": str(FORMAT_VERSION),
        "variant": network.variant,
        "architecture": json.dumps(network.architecture(), sort_keys=True),
        "shapes": json.dumps({k: list(v.shape) for k, v in sorted(tensors.items())}),
        "training_steps": str(steps),
        "cell": str(cell),
        "rolling_success": json.dumps(None if success is None else float(success)),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "weights_sha256": _weights_digest(tensors),
        "extra": extra,
    }
    meta["metadata_sha256"] = _metadata_digest(meta)
    data = _st_save(tensors, metadata=meta)

    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, data, mode=mode)


def _read_file(path: Path) -> bytes:
    """The whole file, but only if it is a regular file of at most MAX_POLICY_BYTES (see the module docstring).

    ``os.stat`` comes first so that a device or FIFO is never even opened (opening some devices has side
    effects); the file is then opened non-blocking and checked again with ``fstat``, so a path swapped
    between the two calls cannot slip a FIFO or a huge file past the check, and at most the cap is read.
    """
    try:
        st = os.stat(path)
    except OSError as exc:
        raise PolicyFileUnreadable(path, _cannot_read(path, exc), exc) from None
    _check_regular(path, st)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
    except OSError as exc:
        raise PolicyFileUnreadable(path, _cannot_read(path, exc), exc) from None
    try:
        opened = os.fstat(fd)
        if (opened.st_dev, opened.st_ino) != (st.st_dev, st.st_ino):
            raise PolicyFileUnreadable(path, "the file was replaced while it was being opened; try again", None)
        _check_regular(path, opened)
        chunks, total = [], 0
        while total <= MAX_POLICY_BYTES:
            chunk = os.read(fd, min(1 << 24, MAX_POLICY_BYTES + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
    except OSError as exc:
        raise PolicyFileUnreadable(path, f"cannot read: {exc.strerror or exc}", exc) from None
    finally:
        os.close(fd)
    if total > MAX_POLICY_BYTES:
        raise PolicyFileError(path, f"grew beyond {_size_text(MAX_POLICY_BYTES)} while being read; refused")
    return b"".join(chunks)


def _check_regular(path: Path, st: os.stat_result) -> None:
    if not stat.S_ISREG(st.st_mode):
        kind = ("a directory" if stat.S_ISDIR(st.st_mode) else "a FIFO" if stat.S_ISFIFO(st.st_mode)
                else "a character device" if stat.S_ISCHR(st.st_mode) else "a block device"
                if stat.S_ISBLK(st.st_mode) else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
        raise PolicyFileError(path, f"is {kind}, expected a regular policy file ({POLICY_SUFFIX})")
    if st.st_size > MAX_POLICY_BYTES:
        raise PolicyFileError(path, f"is {_size_text(st.st_size)}, expected at most {_size_text(MAX_POLICY_BYTES)} "
                                    "(a policy is ~0.3 MB, a DenseNet-121 one ~30 MB; is this the right file?)")


def _size_text(n: int) -> str:
    return f"{n / (1024 * 1024):.1f} MB"


def _cannot_read(path: Path, exc: OSError) -> str:
    """The error text, with the systemd sandbox hint when the path is one the service cannot see.

    Under ProtectHome=yes /home appears empty or inaccessible (ENOENT or EACCES) and under PrivateTmp=yes
    /tmp is another directory (ENOENT), although the operator sees the file: without the hint the
    message contradicts what they see.
    """
    text = f"cannot read: {exc.strerror or exc}"
    where = os.path.abspath(path)
    if isinstance(exc, (FileNotFoundError, PermissionError)) and \
            any(where == d or where.startswith(d + "/") for d in _SANDBOX_HIDDEN):
        text += f" ({SANDBOX_HINT.format(path=where)})"
    return text


def _read_header(path: Path, blob: bytes) -> dict[str, Any]:
    if len(blob) < 8:
        raise PolicyFileError(path, f"truncated: {len(blob)} bytes, too short for a safetensors header")
    (n,) = struct.unpack("<Q", blob[:8])
    if n == 0 or n > MAX_HEADER_BYTES or 8 + n > len(blob):
        raise PolicyFileError(path, f"not a policy file or truncated: header length {n} does not fit the "
                                    f"{len(blob)}-byte file (a pickle or zip file renamed to a policy?)")
    try:
        header = json.loads(blob[8:8 + n].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise PolicyFileError(path, f"corrupt header (not valid JSON: {exc})") from None
    if not isinstance(header, dict):
        raise PolicyFileError(path, "corrupt header (not a JSON object)")
    return header


def _check_metadata(path: Path, header: dict[str, Any]) -> dict[str, str]:
    meta = header.get("__metadata__")
    if not isinstance(meta, dict) or not all(isinstance(v, str) for v in meta.values()):
        raise PolicyFileError(path, "no flgd metadata in the header (not a policy file, or corrupt)")
    if meta.get("format") != FORMAT:
        raise PolicyFileError(path, f"format: got {meta.get('format')!r}, expected {FORMAT!r}")
    if meta.get("format_version") != str(FORMAT_VERSION):
        raise PolicyFileError(path, f"format_version: got {meta.get('format_version')!r}, expected "
                                    f"{FORMAT_VERSION} (written by a different flgd version?)")
    for key in ("variant", "architecture", "shapes", "training_steps", "cell", "rolling_success", "created",
                "weights_sha256", "metadata_sha256", "extra"):
        if key not in meta:
            raise PolicyFileError(path, f"metadata key {key!r} is missing")
    if _metadata_digest(meta) != meta["metadata_sha256"]:
        raise PolicyFileError(path, "metadata checksum mismatch (the header was modified or corrupted)")
    return meta


def read_metadata(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The checked metadata of a policy file, decoded (without loading the weights into a network)."""
    path = Path(path)
    blob = _read_file(path)
    try:
        return _decode(_check_metadata(path, _read_header(path, blob)))
    except (ValueError, TypeError) as exc:
        if isinstance(exc, PolicyFileError):
            raise
        raise PolicyFileError(path, f"metadata value cannot be decoded: {exc}") from None


def _decode(meta: dict[str, str]) -> dict[str, Any]:
    extra = json.loads(meta["extra"])
    if not isinstance(extra, dict):
        raise ValueError(f"extra: got {type(extra).__name__}, expected a JSON object")
    return {
        **extra,
        "format": meta["format"],
        "format_version": int(meta["format_version"]),
        "variant": meta["variant"],
        "architecture": json.loads(meta["architecture"]),
        "shapes": json.loads(meta["shapes"]),
        "training_steps": int(meta["training_steps"]),
        "cell": meta["cell"],
        "rolling_success": json.loads(meta["rolling_success"]),
        "created": meta["created"],
        "weights_sha256": meta["weights_sha256"],
    }


# Where an expected architecture value comes from, for the message when a file's differs.
_EXPECTED_FROM = {"rotations": "learning.rotations in the config"}


def check_fits(path: str | os.PathLike[str], info: dict[str, Any], expected_variant: str | None = None,
               expected_architecture: dict[str, Any] | None = None) -> dict[str, Any]:
    """The file's architecture (without the variant) if it is the expected one; else PolicyFileError.

    ``info`` is ``read_metadata``'s result.  ``expected_architecture`` holds the keys that must be equal
    (e.g. ``{"rotations": 16}`` from the config, or a running network's whole ``architecture()``); a
    difference is named in one line, before any weights are loaded into a network that cannot take them.
    """
    variant = info["variant"]
    if variant not in VARIANTS:
        raise PolicyFileError(path, f"variant: got {variant!r}, expected one of {', '.join(VARIANTS)}")
    if expected_variant is not None and variant != expected_variant:
        raise PolicyFileError(path, f"variant: file holds a {variant!r} network, expected {expected_variant!r} "
                                    "(learning.network in the config)")
    arch = dict(info["architecture"]) if isinstance(info["architecture"], dict) else None
    if arch is None or arch.pop("variant", None) != variant:
        raise PolicyFileError(path, f"architecture {info['architecture']!r} does not match variant {variant!r}")
    for key, want in (expected_architecture or {}).items():
        if key == "variant":
            continue
        got = arch.get(key)
        if got != want:
            source = _EXPECTED_FROM.get(key, "the running network's")
            raise PolicyFileError(path, f"architecture: the file's {variant} network has {key} = {got!r}, "
                                        f"expected {want!r} ({source})")
    return arch


def load_policy(path: str | os.PathLike[str], expected_variant: str | None = None,
                expected_architecture: dict[str, Any] | None = None) -> LoadedPolicy:
    """Load and verify a policy file; raises PolicyFileError naming the file and the problem.

    ``expected_variant`` and ``expected_architecture``: see ``check_fits``.
    """
    path = Path(path)
    blob = _read_file(path)
    meta = _check_metadata(path, _read_header(path, blob))
    try:
        info = _decode(meta)
    except (ValueError, TypeError) as exc:
        raise PolicyFileError(path, f"metadata value cannot be decoded: {exc}") from None
    arch = check_fits(path, info, expected_variant, expected_architecture)
    variant = info["variant"]
    try:
        network = build_network(variant, **arch)
    except (TypeError, ValueError) as exc:
        raise PolicyFileError(path, f"architecture {info['architecture']!r} cannot be built: {exc}") from None
    try:
        tensors = _st_load(blob)
    except (SafetensorError, ValueError, RuntimeError) as exc:
        raise PolicyFileError(path, f"corrupt tensor data: {exc}") from None
    expected = network.state_dict()
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    if missing or unexpected:
        raise PolicyFileError(path, f"tensor names do not match a {variant!r} network: missing {missing[:5]}, "
                                    f"unexpected {unexpected[:5]}")
    for name, ref in expected.items():
        t = tensors[name]
        if t.shape != ref.shape or t.dtype != ref.dtype:
            raise PolicyFileError(path, f"tensor {name!r}: got {t.dtype} {list(t.shape)}, expected "
                                        f"{ref.dtype} {list(ref.shape)}")
    if info["shapes"] != {k: list(v.shape) for k, v in sorted(tensors.items())}:
        raise PolicyFileError(path, "recorded shapes do not match the stored tensors")
    if _weights_digest(tensors) != info["weights_sha256"]:
        raise PolicyFileError(path, "weights checksum mismatch (the tensor data is corrupt)")
    bad = first_non_finite(tensors, list(expected))
    if bad is not None:
        raise PolicyFileError(path, f"the network has diverged: {bad}; refused, it would act on garbage Q-maps")
    network.load_state_dict(tensors, strict=True)
    network.eval()
    return LoadedPolicy(network=network, metadata=info)
