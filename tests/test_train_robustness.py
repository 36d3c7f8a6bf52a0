"""``flgd train`` and ``flgd pretrain`` against damaged run directories and edge cases of the training loop:
a damaged run.json is refused (never taken for a new run), config.yaml is replaced atomically, the action log
tells the truth about scenes that end with objects left, and trainer-state priorities stay with their
transitions when a cycle fails after committing one."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

from flgd.cell import Cell
from flgd.config import load_config
from flgd.store import Store
from flgd.training.actions_csv import read_rows
from flgd.training.collector import LocalCollector
from flgd.training.pretrain import main as pretrain_main
from flgd.training.progress import LineProgress
from flgd.training.run import CONFIG_FILE, RunSettings, TrainingRun
from flgd.training.command import main as train_main

from tests.fakes.wrapped_cell import WrappedCell

REPO = Path(__file__).resolve().parents[1]
CONFIG = str(REPO / "cell_config" / "sim.yaml")


def _snapshot(directory: Path) -> dict[str, tuple[bytes, int]]:
    return {str(p.relative_to(directory)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(directory.rglob("*")) if p.is_file()}


def _damaged_run(tmp_path: Path, run_json: str) -> Path:
    """A run directory as a killed or hand-edited run could leave it: every file but run.json intact."""
    out = tmp_path / "run"
    (out / "checkpoints").mkdir(parents=True)
    (out / "run.json").write_text(run_json)
    (out / CONFIG_FILE).write_text(Path(CONFIG).read_text())
    (out / "flgd.sqlite").write_bytes(b"stands for a store of hours of training")
    (out / "checkpoints" / "checkpoint-0000000300.safetensors").write_bytes(b"weights")
    (out / "actions.csv").write_text("step,outcome\n0,executed\n")
    return out


@pytest.mark.parametrize("run_json, problem", [
    ('{"settings": {"variant": "flg", "objects": 10, "ste', "not valid JSON"),  # cut off mid-write
    ("", "not valid JSON"),
    ("[]", "expected a JSON object"),
    ("{}", "key 'settings'"),
    ('{"settings": [1, 2]}', "key 'settings'"),
    ('{"settings": {"variant": "flg", "seed": "zero"}}', "settings.seed: got 'zero'"),
    ('{"settings": {"variant": "vpg"}}', "settings.variant: got 'vpg'"),
    ('{"settings": {"variant": "flg"}, "segments": {}}', "key 'segments'"),
])
@pytest.mark.parametrize("with_config", [False, True])
def test_a_damaged_run_json_is_refused_with_the_file_named_and_the_run_untouched(tmp_path, capsys, run_json,
                                                                                 problem, with_config):
    out = _damaged_run(tmp_path, run_json)
    before = _snapshot(out)
    argv = ["--out", str(out), "--steps", "5", "--threads", "1"] + (["--config", CONFIG] if with_config else [])
    assert train_main(argv) == 2
    err = capsys.readouterr().err
    assert f"{out / 'run.json'}: " in err and problem in err
    assert "--config is required" not in err and "Traceback" not in err
    assert _snapshot(out) == before  # no new file (lock, store, log), nothing rewritten


def test_config_yaml_is_replaced_atomically_and_left_alone_when_unchanged(tmp_path, monkeypatch):
    out = tmp_path / "run"
    out.mkdir()
    run = TrainingRun(out, RunSettings(seed=1), load_config(CONFIG), LineProgress(io.StringIO(), False), threads=1)
    path = out / CONFIG_FILE
    path.write_text("learning: {truncated")  # what a kill during the old plain write_text could leave
    run._write_config()
    assert load_config(path).sim.seed == 1
    written = path.stat()
    run._write_config()  # a resume whose config did not change does not rewrite it
    assert path.stat().st_ino == written.st_ino and path.stat().st_mtime_ns == written.st_mtime_ns

    # a failure during the write leaves the old file whole and no temporary behind
    import flgd.atomic_file as atomic_file

    run2 = TrainingRun(out, RunSettings(seed=2), load_config(CONFIG), LineProgress(io.StringIO(), False), threads=1)
    old = path.read_bytes()

    def power_cut(*_a):
        raise OSError("power cut (injected)")

    monkeypatch.setattr(atomic_file.os, "replace", power_cut)
    with pytest.raises(OSError, match="power cut"):
        run2._write_config()
    assert path.read_bytes() == old
    assert sorted(p.name for p in out.iterdir()) == [CONFIG_FILE]


# --------------------------------------------------------------------------------------- the loop

class NothingGraspableCell(WrappedCell):
    """A real SimCell that reports "nothing graspable" after every action while objects remain (as a pile of
    objects too large for the gripper would), and whose scene reset fails the ``fail_reset``-th time."""

    def __init__(self, inner: Cell, fail_reset: int | None = None):
        super().__init__(inner)
        self.fail_reset, self.resets = fail_reset, 0
        self.left_when_judged: list[int] = []

    def workspace_empty_hint(self):
        self.left_when_judged.append(self.inner.object_count)
        return True

    def reset_scene(self):
        self.resets += 1
        if self.resets == self.fail_reset:
            raise RuntimeError("reset failed (injected)")
        self.inner.reset_scene()


def _train_in(out: Path, steps: int, fail_reset: int | None = None) -> tuple[TrainingRun, NothingGraspableCell]:
    collector = LocalCollector(lambda cell: NothingGraspableCell(cell, fail_reset))
    run = TrainingRun(out, RunSettings(steps=steps, seed=4), load_config(CONFIG), LineProgress(io.StringIO(), False),
                      threads=1, collector=collector)
    try:
        run.setup()
        assert run.train() == 0
        return run, collector.cell
    finally:
        run.close()


@pytest.mark.slow
def test_a_scene_that_ends_with_objects_left_logs_them_and_scene_ids_continue_on_resume(tmp_path):
    out = tmp_path / "run"
    _, cell = _train_in(out, steps=2)
    rows = read_rows(out / "actions.csv")
    assert [r["outcome"] for r in rows] == ["executed", "executed"]
    # every action ended its scene ("nothing graspable") with objects still there: the log says how many,
    # not 0, and each row carries the id of the scene it acted in
    assert cell.left_when_judged and min(cell.left_when_judged) > 0
    assert [int(r["objects_left"]) for r in rows] == cell.left_when_judged
    assert [r["scene"] for r in rows] == ["0", "1"] and {r["scene_kind"] for r in rows} == {"random 10"}

    _, cell = _train_in(out, steps=3)  # resume: a new scene, and a new id for it
    rows = read_rows(out / "actions.csv")
    assert [r["scene"] for r in rows] == ["0", "1", "2"]
    assert int(rows[2]["objects_left"]) == cell.left_when_judged[0] > 0


@pytest.mark.slow
def test_priorities_stay_with_their_transitions_when_a_cycle_fails_after_committing(tmp_path):
    """The first action's scene reset raises after its transition was stored and added to the replay: the
    trainer state must still pair every replay slot's priority with that slot's transition id."""
    from flgd.training.state import TRAINER_STATE, load_trainer_state

    out = tmp_path / "run"
    run, cell = _train_in(out, steps=3, fail_reset=1)
    assert cell.resets >= 2  # the injected failure happened and was recovered from
    store = Store(out)
    try:
        ids = [int(r[0]) for r in store.query("SELECT id FROM transitions ORDER BY id")]
        assert any(e["message"].startswith("RuntimeError: reset failed") for e in store.events("fault"))
    finally:
        store.close()
    assert len(ids) == len(run.replay) == 3
    state = load_trainer_state(out / TRAINER_STATE)
    assert state.priority_ids.tolist() == ids
    assert state.priorities.tolist() == pytest.approx([run.replay.priority(i) for i in range(3)])


# --------------------------------------------------------------------------------------- pretrain

def test_pretrain_refuses_a_batch_larger_than_the_training_frames_before_collecting(tmp_path, capsys):
    out = tmp_path / "pre"
    assert pretrain_main(["--config", CONFIG, "--out", str(out), "--frames", "10", "--held-out", "5",
                          "--batch", "8", "--steps", "1"]) == 2
    err = capsys.readouterr().err
    assert "--batch: got 8, expected at most the 5 training frames" in err
    assert not out.exists()  # refused before any directory, scene or frame


def _tiny_frames(n: int = 4) -> bytes:
    rng = np.random.default_rng(0)
    buf = io.BytesIO()
    np.savez_compressed(buf, color=rng.integers(0, 255, (n, 16, 16, 3), dtype=np.uint8),
                        height=rng.random((n, 16, 16)).astype(np.float16),
                        labels=rng.integers(0, 3, (n, 16, 16), dtype=np.uint8))
    return buf.getvalue()


@pytest.mark.parametrize("name, content, problem", [
    ("pretrain.json", b'{"settings": {"frames": 4, "held', "not valid JSON"),
    ("pretrain.json", b'["settings"]', "expected a JSON object with the settings object"),
    ("pretrain.json", b'{"status": "running"}', "key 'settings' is missing"),
    ("frames.npz", _tiny_frames()[:200], "cannot be read"),
    ("pretrain-state.pt", b"PK\x03\x04 not a torch file", "cannot be resumed from"),
])
def test_pretrain_names_a_damaged_file_and_keeps_it(tmp_path, capsys, name, content, problem):
    out = tmp_path / "pre"
    out.mkdir()
    if name == "pretrain-state.pt":
        (out / "frames.npz").write_bytes(_tiny_frames())
    (out / name).write_bytes(content)
    assert pretrain_main(["--config", CONFIG, "--out", str(out), "--frames", "4", "--held-out", "1",
                          "--batch", "2", "--steps", "1", "--threads", "1"]) == 2
    err = capsys.readouterr().err
    assert f"{out / name}: " in err and problem in err and "Traceback" not in err
    assert (out / name).read_bytes() == content
    assert not (out / "trunk.safetensors").exists()


def test_an_older_runs_top_level_worker_record_moves_into_its_segment_on_resume():
    from flgd.training.run import _move_old_worker_record

    stats = [{"worker": 0, "cycles": 40, "replacements": 0, "cpu_seconds": 12.5, "last_error": ""}]
    info = {"workers": stats, "segments": [{"from_step": 0, "workers": 1}, {"from_step": 40}]}
    _move_old_worker_record(info)
    assert "workers" not in info
    assert info["segments"][0]["worker_stats"] == stats and "worker_stats" not in info["segments"][1]
    _move_old_worker_record(info)   # nothing left to move: unchanged
    assert info["segments"][0]["worker_stats"] == stats
