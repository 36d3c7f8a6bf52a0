"""What ``flgd run`` refuses, or says, before it touches the cell: a socket another daemon owns, a policy that
is missing or does not fit, a state directory that is a file -- one clear line each."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest


from flgd.learning.networks import build_network
from flgd.learning.policy_file import save_policy
from flgd.training.state import TRAINER_STATE
from tests.fakes.daemon import REPO, DaemonProcess, write_config

pytestmark = pytest.mark.slow  # every test here starts a daemon

SHIPPED = REPO / "policies" / "flg-sim.safetensors"


def _run(config: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "flgd.cli", "run", "--config", str(config), "--no-status-line",
                           *args], capture_output=True, text=True, cwd=REPO, timeout=timeout)


def _policy(path: Path, **arch) -> Path:
    save_policy(path, build_network("fast", seed=3, **arch), {"training_steps": 1, "cell": "test"})
    return path


def test_a_second_daemon_on_the_same_socket_exits_and_leaves_the_first_reachable(daemon_factory, tmp_path):
    first = daemon_factory().start().wait_ready()
    (tmp_path / "second").mkdir()
    second = DaemonProcess(tmp_path / "second", state_dir=tmp_path / "second" / "state")
    second.socket = first.socket
    try:
        assert second.start().wait_exit(timeout=120) == 1
        # it stopped before the state directory, the store or the cell were touched
        assert not (tmp_path / "second" / "state").exists(), second.log()
        assert f"another flgd is running or starting on {first.socket}" in second.log(), second.log()
    finally:
        second.cleanup()
    assert first.socket.exists()
    assert first.ok("status")["state"] == "IDLE"
    assert first.ctl("status").returncode == 0


def test_a_missing_policy_is_an_error_even_when_a_checkpoint_would_be_used(tmp_path):
    state = tmp_path / "state"
    _policy(state / "checkpoints" / "checkpoint-0000000002.safetensors")
    cfg = write_config(tmp_path, state)
    missing = tmp_path / "no-such-policy.safetensors"
    p = _run(cfg, "--policy", str(missing), "--socket", str(tmp_path / "s.sock"), timeout=90)
    assert p.returncode == 1
    (line,) = p.stderr.strip().splitlines()
    assert line.startswith("flgd run: --policy: policy file ") and str(missing) in line and "No such file" in line
    assert not (tmp_path / "s.sock").exists()


def test_a_policy_with_other_rotations_than_the_config_is_refused(tmp_path):
    cfg = write_config(tmp_path, tmp_path / "state")
    eight = _policy(tmp_path / "eight.safetensors", rotations=8)
    p = _run(cfg, "--policy", str(eight), "--socket", str(tmp_path / "s.sock"))
    assert p.returncode == 1
    (line,) = p.stderr.strip().splitlines()
    assert "rotations = 8, expected 16 (learning.rotations in the config)" in line and str(eight) in line


def test_a_state_dir_that_is_a_file_is_refused_naming_the_key(tmp_path):
    afile = tmp_path / "state-file"
    afile.write_text("not a directory")
    for state_dir, culprit in ((afile, afile), (afile / "below", afile)):
        cfg = write_config(tmp_path, state_dir)
        p = _run(cfg, "--socket", str(tmp_path / "s.sock"))
        assert p.returncode == 1
        (line,) = p.stderr.strip().splitlines()
        assert f"config {cfg}: state_dir: {culprit} is a file" in line and "expected a directory" in line, line


def test_an_overridden_policy_is_named_leftovers_are_cleaned_and_a_misfit_load_is_one_line(daemon_factory, tmp_path):
    state = tmp_path / "state"
    _policy(state / "checkpoints" / "checkpoint-0000000002.safetensors")
    leftover = state / f".{TRAINER_STATE}.k3x9q1.tmp"  # what a kill during a trainer-state write leaves
    leftover.write_bytes(b"half a file")
    d = daemon_factory(args=["--policy", str(SHIPPED)]).start().wait_ready()
    log = d.log()
    assert f"policy {SHIPPED} acts as the champion; learning resumes from the checkpoint" in log, log
    assert not leftover.exists()
    narrow = _policy(tmp_path / "narrow.safetensors", width=8)
    p = d.ctl("policy", "load", str(narrow))
    assert p.returncode == 1
    assert len(p.stderr.strip().splitlines()) == 1, p.stderr  # before: ~40 lines of torch size mismatches
    line = p.stderr.strip()
    assert "width = 8, expected 12 (the running network's)" in line and "the running policy stays" in line
    assert d.ok("status")["state"] == "IDLE"
