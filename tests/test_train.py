"""``flgd train`` end to end on the real simulated cell: outputs, resume, Ctrl-C, reproducibility."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from flgd.learning.policy_file import load_policy
from flgd.store import Store
from flgd.training.actionlog import read_rows
from flgd.training.run import main as train_main

REPO = Path(__file__).resolve().parents[1]
CONFIG = str(REPO / "cell_config" / "sim.yaml")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _train(out: Path, *extra: str) -> int:
    return train_main(["--config", CONFIG, "--out", str(out), "--threads", "1", *extra])


def _checkpoints(out: Path) -> list[Path]:
    return sorted((out / "checkpoints").glob("checkpoint-*.safetensors"))


def test_a_short_run_writes_log_checkpoint_and_curve_then_resumes(tmp_path):
    out = tmp_path / "run"
    assert _train(out, "--steps", "3", "--seed", "5") == 0

    rows = read_rows(out / "actions.csv")
    assert [int(r["step"]) for r in rows] == [0, 1, 2]
    for r in rows:
        assert r["outcome"] in ("executed", "refused")
        assert r["primitive"] in ("grasp", "push", "shift")
        assert float(r["epsilon"]) > 0 and r["rule"]
        assert int(r["objects_left"]) >= 0 and r["scene_kind"] == "random 10"
        assert float(r["t_update"]) > 0 and float(r["duration"]) > 0
    assert [int(r["updates"]) for r in rows] == [1, 2, 3]  # updates_per_action = 1, synchronous

    ckpts = _checkpoints(out)
    assert [c.name for c in ckpts] == ["checkpoint-0000000003.safetensors"]
    policy = load_policy(ckpts[0], expected_variant="fast")
    assert policy.metadata["training_steps"] == 3
    assert policy.metadata["train_variant"] == "flg" and policy.metadata["method"] == "FLG"
    assert policy.metadata["seed"] == 5 and policy.metadata["learner_updates"] == 3
    assert (out / "curve.png").read_bytes()[:8] == PNG_MAGIC
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "finished" and info["step"] == 3 and info["settings"]["seed"] == 5

    # resume: same directory, higher target; the settings come from run.json
    assert train_main(["--out", str(out), "--steps", "5", "--threads", "1"]) == 0
    rows = read_rows(out / "actions.csv")
    assert [int(r["step"]) for r in rows] == [0, 1, 2, 3, 4]
    assert [int(r["updates"]) for r in rows[3:]] == [4, 5]  # the learner's count continues too
    info = json.loads((out / "run.json").read_text())
    assert [s["from_step"] for s in info["segments"]] == [0, 3]
    assert info["segments"][1]["from_updates"] == 3
    assert "checkpoint-0000000003" in info["segments"][1]["source"]
    store = Store(out)
    try:
        assert store.transition_count() == 5  # the replay of the first segment was kept and extended
        assert store.next_step() == 5
    finally:
        store.close()
    assert _checkpoints(out)[-1].name == "checkpoint-0000000005.safetensors"

    # other settings for an existing run directory are refused, naming the flag
    assert train_main(["--out", str(out), "--variant", "dpen"]) == 2

    # shipping a checkpoint: a byte copy that loads, its metadata JSON and curve
    from flgd.training.export import export_policy

    dest = tmp_path / "policies" / "p.safetensors"
    info = export_policy(out, dest, "latest")
    assert dest.read_bytes() == _checkpoints(out)[-1].read_bytes()
    assert load_policy(dest).metadata["training_steps"] == 5
    saved = json.loads((tmp_path / "policies" / "p.json").read_text())
    assert saved == json.loads(json.dumps(info)) and saved["run_settings"]["seed"] == 5
    assert saved["resume_command"] == f"flgd train --out {out}"
    assert (tmp_path / "policies" / "p-curve.png").read_bytes()[:8] == PNG_MAGIC


def test_same_seed_same_actions(tmp_path):
    """Synchronous updates and fixed seeds: two runs of one command act identically."""
    logs = []
    for name in ("a", "b"):
        assert _train(tmp_path / name, "--steps", "3", "--seed", "2") == 0
        logs.append([(r["primitive"], r["row"], r["col"], r["rotation"], r["reward"], r["rule"])
                     for r in read_rows(tmp_path / name / "actions.csv")])
    assert logs[0] == logs[1]
    a, b = (load_policy(_checkpoints(tmp_path / n)[-1]).metadata["weights_sha256"] for n in ("a", "b"))
    assert a == b


def test_ctrl_c_leaves_a_resumable_consistent_run(tmp_path):
    out = tmp_path / "run"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.Popen([sys.executable, "-m", "flgd.cli", "train", "--config", CONFIG, "--out", str(out),
                             "--steps", "500", "--threads", "1", "--variant", "rho-fcn"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, cwd=REPO)
    try:
        deadline = time.monotonic() + 120
        while len(read_rows(out / "actions.csv")) < 2:
            assert proc.poll() is None, proc.stdout.read().decode()
            assert time.monotonic() < deadline, "no training step within 120 s"
            time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        output = proc.communicate(timeout=120)[0].decode()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, output
    assert "interrupted" in output

    store = Store(out)
    try:
        assert store.integrity_check() == "ok"
        steps = store.next_step()
        assert store.transition_count() == steps  # every logged step has its transition
    finally:
        store.close()
    rows = read_rows(out / "actions.csv")
    assert [int(r["step"]) for r in rows] == list(range(steps))
    ckpt = _checkpoints(out)[-1]
    policy = load_policy(ckpt, expected_variant="rho-fcn-fast")
    assert policy.metadata["training_steps"] == steps and policy.metadata["train_variant"] == "rho-fcn"
    assert json.loads((out / "run.json").read_text())["status"] == "interrupted"
    assert not list((out / "checkpoints").glob(".*.tmp"))

    assert train_main(["--out", str(out), "--steps", str(steps + 1), "--threads", "1"]) == 0
    assert [int(r["step"]) for r in read_rows(out / "actions.csv")] == list(range(steps + 1))


def test_bad_arguments_are_refused_with_the_flag_named(tmp_path, capsys):
    assert train_main(["--out", str(tmp_path / "x")]) == 2
    assert "--config is required" in capsys.readouterr().err
    assert _train(tmp_path / "y", "--objects", "0") == 2
    assert "--objects: got 0" in capsys.readouterr().err
    assert _train(tmp_path / "z", "--curriculum", "--objects", "12") == 2
    assert "the curriculum sets the object count" in capsys.readouterr().err
    bad = tmp_path / "real.yaml"
    bad.write_text((REPO / "cell_config" / "ur5e-d415.yaml").read_text())
    assert train_main(["--config", str(bad), "--out", str(tmp_path / "w")]) == 2
    assert "expected 'sim'" in capsys.readouterr().err
    assert not (tmp_path / "w").exists()
