"""Policy files: bit-identical round trip, atomic save, and refusal of malicious, truncated, corrupt
and mismatched files without executing anything from them."""

from __future__ import annotations

import io
import json
import os
import pathlib
import pickle
import zipfile

import numpy as np
import pytest
import torch

from flgd.learning import policy_file
from flgd.learning.networks import build_network, q_maps
from flgd.learning.policy_file import PolicyFileError, load_policy, read_metadata, save_policy
from flgd.perception import Heightmaps


@pytest.fixture(autouse=True)
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


META = {"training_steps": 1234, "cell": "sim-ur5e-rg2-d415", "rolling_success": 0.875, "note": "test"}


def trained_like(seed: int = 0, **arch):
    """A network whose BN running statistics are not the defaults (as after training)."""
    net = build_network("fast", 16, seed=seed, **arch)
    net.train()
    with torch.no_grad():
        net(torch.randn(2, 3, 32, 32), torch.randn(2, 1, 32, 32))
    return net.eval()


def scene() -> Heightmaps:
    rng = np.random.default_rng(0)
    return Heightmaps(rng.integers(0, 255, (40, 40, 3), dtype=np.uint8), (rng.random((40, 40)) * 0.05).astype(np.float32))


def test_save_then_load_gives_bit_identical_q_maps_and_the_metadata(tmp_path):
    net = trained_like()
    path = tmp_path / "policy.safetensors"
    save_policy(path, net, META)
    loaded = load_policy(path, expected_variant="fast")
    with torch.no_grad():
        assert torch.equal(q_maps(net, scene()), q_maps(loaded.network, scene()))
    m = loaded.metadata
    assert (m["variant"], m["training_steps"], m["cell"], m["rolling_success"], m["note"]) == \
        ("fast", 1234, "sim-ur5e-rg2-d415", 0.875, "test")
    assert m["format"] == "flgd-policy" and m["format_version"] == 1 and len(m["weights_sha256"]) == 64
    assert m["architecture"] == {"variant": "fast", "rotations": 16, "width": net.width}
    assert m["created"].endswith("+00:00")
    assert read_metadata(path)["training_steps"] == 1234
    assert [p.name for p in tmp_path.iterdir()] == ["policy.safetensors"]  # no temp file left


def test_a_pickle_payload_renamed_to_a_policy_is_refused_without_running(tmp_path):
    marker = tmp_path / "payload-ran"

    class Payload:
        def __reduce__(self):
            return (os.mkdir, (str(marker),))

    payload = pickle.dumps({"weights": Payload()})
    # The payload is live: unpickling it does create a directory (here a different one).
    probe = tmp_path / "probe---ran"  # same length: the pickle's string is length-prefixed
    pickle.loads(payload.replace(str(marker).encode(), str(probe).encode()))
    assert probe.exists()

    evil = tmp_path / "evil.safetensors"
    evil.write_bytes(payload)
    with pytest.raises(PolicyFileError, match="evil.safetensors.*not a policy file"):
        load_policy(evil)
    # torch.save's zip container with the same payload inside.
    buf = io.BytesIO()
    torch.save({"weights": Payload()}, buf)
    zipped = tmp_path / "zipped.safetensors"
    zipped.write_bytes(buf.getvalue())
    assert zipfile.is_zipfile(zipped)
    with pytest.raises(PolicyFileError, match="zipped.safetensors"):
        load_policy(zipped)
    assert not marker.exists()


def test_truncated_files_are_refused_at_every_length(tmp_path):
    path = tmp_path / "p.safetensors"
    save_policy(path, trained_like(width=4), META)
    blob = path.read_bytes()
    cut = tmp_path / "cut.safetensors"
    for n in [0, 4, 8, 20, 100, len(blob) // 3, len(blob) // 2, len(blob) - 100, len(blob) - 1]:
        cut.write_bytes(blob[:n])
        with pytest.raises(PolicyFileError, match="cut.safetensors"):
            load_policy(cut)


def test_single_bit_flips_anywhere_are_refused(tmp_path):
    path = tmp_path / "p.safetensors"
    save_policy(path, trained_like(width=4), META)
    blob = bytearray(path.read_bytes())
    (header_len,) = np.frombuffer(bytes(blob[:8]), dtype="<u8")
    rng = np.random.default_rng(0)
    positions = list(range(0, 8)) + list(rng.integers(8, 8 + header_len, 60)) + \
        list(rng.integers(8 + header_len, len(blob), 60)) + [len(blob) - 1]
    flipped = tmp_path / "flipped.safetensors"
    for pos in positions:
        bad = bytearray(blob)
        bad[pos] ^= 1 << int(rng.integers(8))
        flipped.write_bytes(bytes(bad))
        with pytest.raises(PolicyFileError, match="flipped.safetensors"):
            load_policy(flipped)


def _rewrite_metadata(src: pathlib.Path, dst: pathlib.Path, **changes) -> None:
    """Re-sign a file with changed metadata (a well-formed but mismatched policy)."""
    from safetensors.torch import load, save

    blob = src.read_bytes()
    (n,) = np.frombuffer(blob[:8], dtype="<u8")
    meta = json.loads(blob[8:8 + int(n)])["__metadata__"]
    meta.update(changes)
    meta["metadata_sha256"] = policy_file._metadata_digest(meta)
    dst.write_bytes(save(load(blob), metadata=meta))


def test_mismatched_variant_shapes_and_versions_are_refused(tmp_path):
    path = tmp_path / "p.safetensors"
    save_policy(path, trained_like(width=4), META)
    with pytest.raises(PolicyFileError, match="expected 'densenet121'"):
        load_policy(path, expected_variant="densenet121")
    wrong = tmp_path / "wrong.safetensors"
    _rewrite_metadata(path, wrong, architecture=json.dumps({"variant": "fast", "rotations": 16, "width": 6}))
    with pytest.raises(PolicyFileError, match=r"wrong.safetensors: tensor .*expected"):
        load_policy(wrong)
    _rewrite_metadata(path, wrong, variant="rho-fcn",
                      architecture=json.dumps({"variant": "rho-fcn", "rotations": 16}))
    with pytest.raises(PolicyFileError, match="tensor names do not match"):
        load_policy(wrong)
    _rewrite_metadata(path, wrong, format_version="99")
    with pytest.raises(PolicyFileError, match="format_version"):
        load_policy(wrong)
    _rewrite_metadata(path, wrong, variant="alexnet")
    with pytest.raises(PolicyFileError, match="variant"):
        load_policy(wrong)
    with pytest.raises(PolicyFileError, match="cannot read"):
        load_policy(tmp_path / "missing.safetensors")


def test_save_is_atomic_a_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "p.safetensors"
    old = trained_like(seed=1, width=4)
    save_policy(path, old, META)
    before = path.read_bytes()

    def broken_replace(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(policy_file.os, "replace", broken_replace)
    with pytest.raises(OSError, match="No space"):
        save_policy(path, trained_like(seed=2, width=4), {"training_steps": 9})
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["p.safetensors"]
    monkeypatch.undo()
    save_policy(path, trained_like(seed=2, width=4), {"training_steps": 9})
    assert load_policy(path).metadata["training_steps"] == 9
    with pytest.raises(PolicyFileError, match="training_steps"):
        save_policy(path, old, {"training_steps": -1})
    assert os.path.getsize(path) > 0


@pytest.mark.parametrize("variant", ["densenet121", "rho-fcn"])
def test_the_densenet_variants_round_trip_too(tmp_path, variant):
    net = build_network(variant, 16, seed=1).eval()
    path = tmp_path / f"{variant}.safetensors"
    save_policy(path, net, {"training_steps": 5})
    loaded = load_policy(path, expected_variant=variant)
    assert loaded.network.variant == variant
    state = loaded.network.state_dict()
    assert all(torch.equal(state[k], v) for k, v in net.state_dict().items())
