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
  other metadata, so a flipped bit anywhere in the file is caught.

Metadata fields: format, format_version, variant, architecture (JSON),
shapes (JSON name -> shape), training_steps, cell, rolling_success, created
(UTC ISO 8601), weights_sha256, metadata_sha256, and ``extra`` (JSON of any
other caller-supplied keys).

Saving is atomic: the bytes go to a temporary file in the target directory,
which is fsynced, renamed over the target and the directory fsynced, so a
crash leaves either the old or the new file, never a torn one.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load as _st_load
from safetensors.torch import save as _st_save

from flgd.atomic_file import write_atomically
from flgd.learning.networks import VARIANTS, QMapNetwork, build_network

__all__ = ["FORMAT", "FORMAT_VERSION", "POLICY_SUFFIX", "PolicyFileError", "LoadedPolicy", "save_policy",
           "load_policy", "read_metadata"]

FORMAT = "flgd-policy"
FORMAT_VERSION = 1
POLICY_SUFFIX = ".safetensors"
MAX_HEADER_BYTES = 16 * 1024 * 1024
_KNOWN_FIELDS = ("training_steps", "cell", "rolling_success")


class PolicyFileError(ValueError):
    """A policy file cannot be used; the message names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"policy file {self.path}: {problem}")


@dataclass(frozen=True)
class LoadedPolicy:
    network: QMapNetwork
    metadata: dict


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


def save_policy(path: str | os.PathLike, network: QMapNetwork, metadata: dict) -> None:
    """Write ``network`` and ``metadata`` (training_steps, cell, rolling_success, anything else) atomically."""
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
    write_atomically(path, data)


def _read_header(path: Path, blob: bytes) -> dict:
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


def _check_metadata(path: Path, header: dict) -> dict[str, str]:
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


def read_metadata(path: str | os.PathLike) -> dict:
    """The checked metadata of a policy file, decoded (without loading the weights into a network)."""
    path = Path(path)
    try:
        blob = path.read_bytes()
    except OSError as exc:
        raise PolicyFileError(path, f"cannot read: {exc.strerror or exc}") from None
    try:
        return _decode(_check_metadata(path, _read_header(path, blob)))
    except (ValueError, TypeError) as exc:
        if isinstance(exc, PolicyFileError):
            raise
        raise PolicyFileError(path, f"metadata value cannot be decoded: {exc}") from None


def _decode(meta: dict[str, str]) -> dict:
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


def load_policy(path: str | os.PathLike, expected_variant: str | None = None) -> LoadedPolicy:
    """Load and verify a policy file; raises PolicyFileError naming the file and the problem."""
    path = Path(path)
    try:
        blob = path.read_bytes()
    except OSError as exc:
        raise PolicyFileError(path, f"cannot read: {exc.strerror or exc}") from None
    meta = _check_metadata(path, _read_header(path, blob))
    try:
        info = _decode(meta)
    except (ValueError, TypeError) as exc:
        raise PolicyFileError(path, f"metadata value cannot be decoded: {exc}") from None
    variant = info["variant"]
    if variant not in VARIANTS:
        raise PolicyFileError(path, f"variant: got {variant!r}, expected one of {', '.join(VARIANTS)}")
    if expected_variant is not None and variant != expected_variant:
        raise PolicyFileError(path, f"variant: file holds a {variant!r} network, expected {expected_variant!r} "
                                    "(learning.network in the config)")
    arch = dict(info["architecture"]) if isinstance(info["architecture"], dict) else None
    if arch is None or arch.pop("variant", None) != variant:
        raise PolicyFileError(path, f"architecture {info['architecture']!r} does not match variant {variant!r}")
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
    network.load_state_dict(tensors, strict=True)
    network.eval()
    return LoadedPolicy(network=network, metadata=info)
