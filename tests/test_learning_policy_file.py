"""Policy files: bit-identical round trip, atomic save, and refusal of malicious, truncated, corrupt
and mismatched files without executing anything from them."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import pathlib
import pickle
import shutil
import socket
import stat
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from flgd.config import CellConfig
from flgd.learning import policy_file
from flgd.learning.networks import build_network, q_maps
from flgd.learning.policy_file import MAX_POLICY_BYTES, PolicyFileError, load_policy, read_metadata, save_policy
from flgd.perception import Heightmaps
from flgd.store import CheckpointDir

REPO = Path(__file__).resolve().parents[1]


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


def small_net(seed: int = 0):
    return build_network("fast", 16, seed=seed).eval()


def save_unchecked(path: Path, net, monkeypatch) -> None:
    """Save ``net`` as an older flgd (without the finiteness check) would have: valid checksums, bad weights."""
    with monkeypatch.context() as m:
        m.setattr(policy_file, "first_non_finite", lambda *a: None)
        save_policy(path, net, {"training_steps": 1})


def poisoned(value: float, seed: int = 0) -> tuple[object, str]:
    """A network with one ``value`` (nan/inf) in its second floating-point tensor, and that tensor's name."""
    net = small_net(seed)
    names = [k for k, v in net.state_dict().items() if v.is_floating_point()]
    name = names[1]
    with torch.no_grad():
        net.state_dict()[name].view(-1)[0] = value
    return net, name


# --------------------------------------------------------------------------- non-finite policies

@pytest.mark.parametrize("value, kind", [(float("nan"), "NaN"), (float("inf"), "Inf"), (float("-inf"), "Inf")])
def test_a_policy_file_with_a_non_finite_weight_is_refused_naming_file_and_tensor(tmp_path, monkeypatch, value,
                                                                                    kind):
    net, name = poisoned(value)
    path = tmp_path / "diverged.safetensors"
    save_unchecked(path, net, monkeypatch)
    with pytest.raises(PolicyFileError) as err:
        load_policy(path, expected_variant="fast")
    msg = str(err.value)
    assert str(path) in msg and repr(name) in msg and kind in msg and "diverged" in msg, msg


def test_saving_a_diverged_network_is_refused_and_writes_nothing(tmp_path):
    net, name = poisoned(float("nan"))
    path = tmp_path / "p.safetensors"
    with pytest.raises(PolicyFileError, match="diverged") as err:
        save_policy(path, net, {})
    assert repr(name) in str(err.value)
    assert list(tmp_path.iterdir()) == []  # no file, no temp file


def test_a_diverged_checkpoint_is_skipped_and_the_daemon_resumes_from_the_older_good_one(tmp_path, monkeypatch):
    from flgd.wiring import starting_network

    ckpts = CheckpointDir(tmp_path / "checkpoints", keep=3)
    ckpts.write(lambda p: save_policy(p, small_net(1), {}), 100)
    bad, _ = poisoned(float("nan"), seed=2)
    ckpts.write(lambda p: save_unchecked(p, bad, monkeypatch), 200)
    cfg = dataclasses.replace(CellConfig(), learning=dataclasses.replace(CellConfig().learning, init_trunk=""))
    start = starting_network(cfg, ckpts, None)
    assert start.checkpoint == ckpts.path_for(100) and start.resumed_from_updates == 100
    assert all(torch.isfinite(v).all() for v in start.network.state_dict().values() if v.is_floating_point())


def _controller(tmp_path: Path):
    from flgd.daemon.controller import Controller

    cfg = dataclasses.replace(CellConfig(), state_dir=str(tmp_path / "state"))
    return Controller(cfg)


def test_flgctl_policy_load_of_a_diverged_file_is_an_error_reply_and_the_running_policy_stays(tmp_path,
                                                                                              monkeypatch):
    from flgd.daemon.commands import policy_load
    from flgd.daemon.protocol import ProtocolError

    net, name = poisoned(float("nan"))
    path = tmp_path / "diverged.safetensors"
    save_unchecked(path, net, monkeypatch)
    ctl = _controller(tmp_path)  # not set up: no learner, and none is needed (the file is refused before it)
    assert ctl.learner is None
    with pytest.raises(ProtocolError) as err:
        policy_load(ctl, str(path))
    assert err.value.code == "failed" and "running policy stays" in err.value.message
    assert str(path) in err.value.message and repr(name) in err.value.message


# --------------------------------------------------------------------------- what a policy path may be

def test_dev_zero_is_refused_at_once_without_reading_it():
    start = time.monotonic()
    for fn in (lambda: load_policy("/dev/zero"), lambda: read_metadata("/dev/zero")):
        with pytest.raises(PolicyFileError, match="character device") as err:
            fn()
        assert "/dev/zero" in str(err.value) and "regular" in str(err.value)
    assert time.monotonic() - start < 5


def test_a_fifo_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "policy.safetensors"
    os.mkfifo(fifo)
    result: list = []

    def load():
        try:
            load_policy(fifo)
        except PolicyFileError as exc:
            result.append(str(exc))

    t = threading.Thread(target=load, daemon=True)
    t.start()
    t.join(10)
    if t.is_alive():  # unblock the thread before failing (open a writer)
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail("load_policy blocked on a FIFO")
    assert result and "FIFO" in result[0] and str(fifo) in result[0]


def test_a_directory_is_refused(tmp_path):
    with pytest.raises(PolicyFileError, match="is a directory"):
        load_policy(tmp_path)


def test_a_file_over_the_size_cap_is_refused_before_it_is_read(tmp_path):
    big = tmp_path / "huge.safetensors"
    with open(big, "wb") as f:  # sparse: takes no disk space
        f.truncate(MAX_POLICY_BYTES + 1)
    start = time.monotonic()
    with pytest.raises(PolicyFileError) as err:
        load_policy(big)
    assert time.monotonic() - start < 5
    msg = str(err.value)
    assert str(big) in msg and "512.0 MB" in msg and "expected at most" in msg


def test_the_shipped_policy_still_loads():
    shipped = sorted((REPO / "policies").glob("*.safetensors"))
    policies = [p for p in shipped if not p.name.startswith("trunk")]
    assert policies
    for p in policies:
        assert load_policy(p).network is not None


# --------------------------------------------------------------------------- permissions and the sandbox hint

def test_saved_policies_and_checkpoints_are_group_readable_whatever_the_umask(tmp_path):
    old = os.umask(0o077)
    try:
        save_policy(tmp_path / "p.safetensors", small_net(), {})
        ckpt = CheckpointDir(tmp_path / "ckpt").write(lambda p: save_policy(p, small_net(), {}), 5)
    finally:
        os.umask(old)
    for p in (tmp_path / "p.safetensors", ckpt):
        assert stat.S_IMODE(p.stat().st_mode) == 0o640, oct(p.stat().st_mode)


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("setpriv") is None, reason="needs root and setpriv")
def test_flgctl_policy_save_copy_works_for_a_group_member_who_is_not_the_daemons_user():
    """The daemon (here root) saves into a 0750 state directory; flgctl runs as another uid in its group."""
    base = Path(tempfile.mkdtemp(prefix="flgd-perm-", dir="/tmp"))
    try:
        os.chmod(base, 0o755)
        state = base / "state"
        state.mkdir(mode=0o750)
        os.chmod(state, 0o750)
        saved = state / "policies" / "policy-x.safetensors"
        old = os.umask(0o027)  # the unit's UMask
        try:
            save_policy(saved, small_net(), {})
        finally:
            os.umask(old)
        out = base / "out"
        out.mkdir()
        os.chown(out, 65534, 0)
        sock_path = base / "flgd.sock"
        srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        srv.bind(str(sock_path))
        os.chmod(sock_path, 0o666)
        srv.listen(1)

        def serve():
            conn, _ = srv.accept()
            with conn:
                conn.recv(65536)
                conn.sendall((json.dumps({"ok": True, "state": "IDLE", "result": {"saved": str(saved),
                                                                                   "learner_updates": 3}})
                              + "\n").encode())

        threading.Thread(target=serve, daemon=True).start()
        dest = out / "mine.safetensors"
        p = subprocess.run(["setpriv", "--reuid=65534", "--regid=0", "--clear-groups", sys.executable, "-m",
                            "flgd.ctl", "--socket", str(sock_path), "policy", "save", str(dest)],
                           capture_output=True, text=True, timeout=120, cwd=REPO)
        srv.close()
        assert p.returncode == 0, p.stderr
        assert dest.read_bytes() == saved.read_bytes()
        assert "policy saved" in p.stdout
    finally:
        shutil.rmtree(base, ignore_errors=True)


@pytest.mark.parametrize("where", ["/tmp/flgd-no-such-policy.safetensors", "/home/op/flgd-no-such.safetensors",
                                   "/var/tmp/flgd-no-such.safetensors"])
def test_not_found_under_a_sandboxed_path_explains_protecthome_and_privatetmp(where):
    with pytest.raises(PolicyFileError) as err:
        load_policy(where)
    msg = str(err.value)
    assert where in msg and "No such file or directory" in msg
    assert "PrivateTmp" in msg and "ProtectHome" in msg and "/var/lib/flgd/policies" in msg


def test_not_found_elsewhere_has_no_sandbox_hint():
    # A fixed path outside every sandboxed prefix: the repository itself may be checked out under /tmp or /home.
    missing = Path("/var/lib/flgd-test-no-such-dir/no-such-policy.safetensors")
    assert not missing.exists()
    with pytest.raises(PolicyFileError) as err:
        load_policy(missing)
    assert "No such file or directory" in str(err.value) and "PrivateTmp" not in str(err.value)


def test_the_unit_state_directory_is_where_the_hint_points():
    unit = (REPO / "systemd" / "flgd.service").read_text()
    assert "StateDirectory=flgd\n" in unit and "ProtectHome=yes" in unit and "PrivateTmp=yes" in unit
    assert "UMask=0027" in unit  # saved policies (0640) and their directory (0750) stay group-readable


def test_write_atomically_sets_the_mode_before_the_file_appears(tmp_path):
    from flgd.atomic_file import write_atomically

    target = tmp_path / "f"
    write_atomically(target, b"x", mode=0o640)
    assert stat.S_IMODE(target.stat().st_mode) == 0o640
    write_atomically(target, b"y")
    assert stat.S_IMODE(target.stat().st_mode) == 0o600 and target.read_bytes() == b"y"
