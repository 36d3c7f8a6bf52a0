"""``flgd eval`` keeps finished work and refuses bad scenes up front (flgd.evaluation, flgd.visualize).

Faults are injected at the narrowest point -- ``SimCell.load_scene`` at the start of the second run, or
``flgd.visualize.write_png`` for a Q-map picture -- around the real simulated cell and a one-cube scene
with one action per run, so each evaluation takes a few seconds.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import stat
import time
from pathlib import Path

import numpy as np
import pybullet
import pytest

import flgd.visualize as visualize
import sim_cell.cell as sim_cell_module
from flgd.cli import main as flgd_main
from flgd.config import load_config
from flgd.evaluation.evaluator import EvalOptions, Evaluator
from flgd.evaluation.metrics import ActionEntry, RunLog
from flgd.evaluation.report import build_report, format_table
from flgd.evaluation.scene_sets import SceneSetError, check_scene, scene_from_argument
from flgd.learning.networks import build_network
from flgd.plans import move_kind

REPO = Path(__file__).resolve().parents[1]
SIM_CONFIG = REPO / "cell_config" / "sim.yaml"

CUBE = """  - shape: cube
    size: [0.04]
    color: [0.9, 0.2, 0.2]
    position: [{x}, {y}, 0.02]
    rpy: [0, 0, 0]
"""
HEADER = "format: flgd-scene\nversion: 1\nobjects:\n"


def _scene(tmp_path: Path, name: str, *entries: str) -> Path:
    path = tmp_path / name
    path.write_text(HEADER + "".join(entries))
    return path


def _cube(x: float = 0.15, y: float = 0.15) -> str:
    return CUBE.format(x=x, y=y)


def _urdf(name: str, x: float = 0.0, y: float = 0.0) -> str:
    return f"  - urdf: {name}\n    position: [{x}, {y}, 0.03]\n"


@pytest.fixture(scope="module")
def config():
    return load_config(SIM_CONFIG)


@pytest.fixture
def one_cube(tmp_path: Path) -> Path:
    return _scene(tmp_path, "one-cube.yaml", _cube())


def _eval(capsys, *args: str) -> tuple[int, str, str]:
    code = flgd_main(["eval", "--config", str(SIM_CONFIG), "--fresh", *args])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return code, out, err


def _second_run_start(monkeypatch, fault, json_out: Path | None = None) -> list[dict]:
    """Fault injection: the second ``SimCell.load_scene`` (the start of run 2) calls ``fault`` first.

    Returns a list that receives the ``json_out`` report as it was on disk at that moment (if any).
    """
    original = sim_cell_module.SimCell.load_scene
    calls = []
    on_disk: list[dict] = []

    def load_scene(self, scene, *args, **kwargs):
        calls.append(scene)
        if len(calls) == 2:
            if json_out is not None and json_out.exists():
                on_disk.append(json.loads(json_out.read_text()))
            fault()
        return original(self, scene, *args, **kwargs)

    monkeypatch.setattr(sim_cell_module.SimCell, "load_scene", load_scene)
    return on_disk


def _assert_first_run_saved(report: dict, status: str) -> None:
    assert report["status"] == status and report["complete"] is False
    assert (report["runs_finished"], report["runs_planned"]) == (1, 2)
    [scene] = report["scenes"]
    assert scene["scene"] == "one-cube" and scene["runs"] == 1
    [row] = scene["run_logs"]
    assert row["run"] == 1 and row["actions"] == 1 and row["end"] in ("cleared", "action-limit")


# ----------------------------------------------------------------------------- finished runs survive

def test_an_error_in_the_second_run_stops_with_the_first_run_saved(capsys, tmp_path, monkeypatch, one_cube):
    def simulator_breaks():
        raise pybullet.error("fault injection: physics server died")

    out = tmp_path / "r.json"
    on_disk = _second_run_start(monkeypatch, simulator_breaks, out)
    code, stdout, err = _eval(capsys, "--scenes", str(one_cube), "--runs", "2", "--max-actions", "1",
                              "--json", str(out), "--quiet")
    assert code == 1
    # the message names the scene, the run and what failed
    assert "one-cube" in err and "run 2 of 2" in err and "pybullet.error" in err and "fault injection" in err
    # the report was already on disk after run 1 (so even a kill -9 would have kept it) ...
    [checkpoint] = on_disk
    assert checkpoint["status"] == "in-progress" and checkpoint["runs_finished"] == 1
    # ... and the final one says it is partial, and why
    report = json.loads(out.read_text())
    _assert_first_run_saved(report, "failed")
    assert "run 2 of 2" in report["stopped"] and "pybullet.error" in report["stopped"]
    assert stdout.startswith("PARTIAL REPORT (failed): 1 of 2 runs finished") and "one-cube" in stdout
    assert out.with_suffix(".png").is_file()


def test_ctrl_c_saves_and_prints_the_finished_runs_and_exits_130(capsys, tmp_path, monkeypatch, one_cube):
    def ctrl_c():
        raise KeyboardInterrupt

    _second_run_start(monkeypatch, ctrl_c)
    out = tmp_path / "r.json"
    code, stdout, err = _eval(capsys, "--scenes", str(one_cube), "--runs", "2", "--max-actions", "1",
                              "--json", str(out), "--quiet")
    assert code == 130 and "Ctrl-C" in err
    _assert_first_run_saved(json.loads(out.read_text()), "interrupted")
    assert "PARTIAL REPORT (interrupted): 1 of 2 runs finished" in stdout


def test_sigterm_saves_the_finished_runs_and_exits_143(capsys, tmp_path, monkeypatch, one_cube):
    unhandled = []
    sentinel = lambda signum, frame: unhandled.append(signum)   # noqa: E731 -- if flgd eval installs no handler
    previous = signal.signal(signal.SIGTERM, sentinel)
    try:
        def sigterm():
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(50):   # the handler runs in the main thread at the next bytecode boundary
                time.sleep(0.01)

        _second_run_start(monkeypatch, sigterm)
        out = tmp_path / "r.json"
        code, stdout, err = _eval(capsys, "--scenes", str(one_cube), "--runs", "2", "--max-actions", "1",
                                  "--json", str(out), "--quiet")
        assert signal.getsignal(signal.SIGTERM) is sentinel, "flgd eval must restore the previous handler"
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert not unhandled
    assert code == 143 and "SIGTERM" in err
    _assert_first_run_saved(json.loads(out.read_text()), "interrupted")
    assert "PARTIAL REPORT" in stdout


def test_a_qmap_write_error_stops_with_a_clear_error_and_keeps_the_first_run(capsys, tmp_path, monkeypatch,
                                                                            one_cube):
    original = visualize.write_png
    calls = []

    def write_png(path, image):   # fault injection: the disk fills up at the second Q-map picture
        calls.append(Path(path))
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return original(path, image)

    monkeypatch.setattr(visualize, "write_png", write_png)
    out = tmp_path / "r.json"
    code, stdout, err = _eval(capsys, "--scenes", str(one_cube), "--runs", "2", "--max-actions", "1",
                              "--json", str(out), "--save-qmaps", str(tmp_path / "q"), "--quiet")
    assert code == 1
    assert "one-cube" in err and "run 2 of 2" in err and "OSError" in err and "No space left" in err
    _assert_first_run_saved(json.loads(out.read_text()), "failed")


def test_run_numbers_agree_in_progress_json_qmap_folders_and_captions(capsys, tmp_path, monkeypatch, one_cube):
    original = visualize.qmap_picture
    captions = []

    def qmap_picture(*args, **kwargs):
        captions.append(kwargs["caption"])
        return original(*args, **kwargs)

    monkeypatch.setattr(visualize, "qmap_picture", qmap_picture)
    out, qdir = tmp_path / "r.json", tmp_path / "q"
    code, stdout, err = _eval(capsys, "--scenes", str(one_cube), "--runs", "2", "--max-actions", "1",
                              "--json", str(out), "--save-qmaps", str(qdir))
    assert code == 0, err
    report = json.loads(out.read_text())
    assert report["status"] == "complete" and report["complete"] is True
    assert (report["runs_finished"], report["runs_planned"]) == (2, 2)
    assert "PARTIAL" not in stdout
    assert [row["run"] for row in report["scenes"][0]["run_logs"]] == [1, 2]
    assert sorted(p.name for p in (qdir / "scenes" / "one-cube").iterdir()) == ["run01", "run02"]
    assert [c.split(" action")[0] for c in captions] == ["one-cube run 1", "one-cube run 2"]
    assert "one-cube run 1 of 2:" in err and "one-cube run 2 of 2:" in err


def test_run_numbers_start_at_one(config, one_cube):
    with Evaluator(config, build_network("fast", rotations=16, seed=0), EvalOptions(runs=1)) as ev:
        with pytest.raises(ValueError, match="run number: got 0, expected an integer >= 1"):
            ev.run(scene_from_argument(str(one_cube)), 0)


def test_a_partial_report_says_so_and_a_complete_one_must_have_every_run():
    spec = scene_from_argument("pile-20-a")
    log = RunLog(scene="pile-20-a", run=1, objects=3, actions=(ActionEntry("grasp", True),), objects_left=2,
                 objects_grasped=1, end="action-limit")
    kwargs = dict(policy={"path": "p"}, config="c", options={"runs": 3}, seconds=1.0)
    partial = build_report([(spec, [log])], status="interrupted", runs_planned=3, stopped="terminated by SIGTERM",
                           **kwargs)
    assert partial["complete"] is False and partial["runs_finished"] == 1
    lines = format_table(partial).splitlines()
    assert lines[0] == lines[-1] == "PARTIAL REPORT (interrupted): 1 of 3 runs finished: terminated by SIGTERM"
    with pytest.raises(ValueError, match="status complete: 1 runs finished, expected runs_planned \\(3\\)"):
        build_report([(spec, [log])], status="complete", runs_planned=3, **kwargs)
    with pytest.raises(ValueError, match="status: got 'done'"):
        build_report([(spec, [log])], status="done", **kwargs)
    complete = build_report([(spec, [log]), (scene_from_argument("pile-20-a"), [])], **kwargs)
    assert complete["complete"] is True and "PARTIAL" not in format_table(complete)
    assert len(complete["scenes"]) == 1   # a scene without a finished run is left out


# ----------------------------------------------------------------------------- scenes refused up front

def test_missing_urdf_and_object_outside_the_workspace_are_refused_by_name(config, tmp_path):
    ws = config.workspace
    half = (ws.x[1] - ws.x[0]) / 2
    fine = _scene(tmp_path, "fine.yaml", _cube(), _urdf("duck"), _urdf("cube_small.urdf", 0.1, -0.1),
                  _cube(half - 0.001, -half + 0.001))
    assert check_scene(scene_from_argument(str(fine)), ws) == 4

    missing = _scene(tmp_path, "missing-urdf.yaml", _cube(), _urdf("no_such_model.urdf"))
    with pytest.raises(SceneSetError) as info:
        check_scene(scene_from_argument(str(missing)), ws)
    msg = str(info.value)
    assert "missing-urdf.yaml" in msg and "objects[1]" in msg and "no_such_model.urdf" in msg and "not found" in msg

    outside = _scene(tmp_path, "outside.yaml", _cube(half + 0.05, 0.0))
    with pytest.raises(SceneSetError) as info:
        check_scene(scene_from_argument(str(outside)), ws, "sim.yaml")
    msg = str(info.value)
    assert "outside.yaml" in msg and "objects[0]" in msg and "[0.274, 0, 0.02]" in msg
    assert "outside the workspace of sim.yaml" in msg and "x in [-0.224, 0.224]" in msg

    below = _scene(tmp_path, "below.yaml", CUBE.format(x=0.0, y=0.0).replace("0.02]", "-0.2]"))
    with pytest.raises(SceneSetError, match=r"objects\[0\].*z > -0.05"):
        check_scene(scene_from_argument(str(below)), ws)
    empty = _scene(tmp_path, "empty.yaml")
    empty.write_text(HEADER.replace("objects:\n", "objects: []\n"))
    with pytest.raises(SceneSetError, match="empty.yaml: no objects \\(the objects list is empty\\)"):
        check_scene(scene_from_argument(str(empty)), ws)


def test_the_urdf_check_agrees_with_the_simulator(config, tmp_path):
    from sim_cell.cell import SimCell
    from sim_cell.scenes import SceneError

    fine = _scene(tmp_path, "fine.yaml", _urdf("duck"), _urdf("cube_small.urdf", 0.1, -0.1))
    missing = _scene(tmp_path, "missing-urdf.yaml", _urdf("no_such_model.urdf"))
    cell = SimCell(config)
    try:
        assert cell.load_scene(fine) == 2
        with pytest.raises(SceneError, match="no_such_model.urdf"):
            cell.load_scene(missing)
    finally:
        cell.close()


def test_a_bad_scene_among_good_ones_is_refused_before_anything_is_simulated(capsys, tmp_path, monkeypatch,
                                                                            one_cube):
    created = []
    monkeypatch.setattr(sim_cell_module.SimCell, "__init__", lambda self, *a, **k: created.append(a))
    outside = _scene(tmp_path, "outside.yaml", _cube(), _cube(0.0, -0.3))
    missing = _scene(tmp_path, "missing-urdf.yaml", _urdf("no_such_model.urdf"))
    out = tmp_path / "r.json"
    code, _, err = _eval(capsys, "--scenes", str(one_cube), str(outside), "--json", str(out))
    assert code == 1 and "outside.yaml: objects[1]" in err and "outside the workspace" in err
    code, _, err = _eval(capsys, "--scenes", str(one_cube), str(missing), "--json", str(out))
    assert code == 1 and "missing-urdf.yaml: objects[0]" in err and "no_such_model.urdf" in err
    assert created == [] and not out.exists()


# ----------------------------------------------------------------------------- pictures

def test_write_png_replaces_atomically_and_keeps_the_file_mode(tmp_path):
    path = tmp_path / "p.png"
    good = np.full((8, 8, 3), 200, np.uint8)
    visualize.write_png(path, good)
    assert stat.S_IMODE(path.stat().st_mode) == 0o644   # not the temp file's 0600
    before = path.read_bytes()
    os.chmod(path, 0o640)
    with pytest.raises(Exception):
        visualize.write_png(path, np.zeros((0, 0, 3), np.uint8))   # cannot be encoded
    assert path.read_bytes() == before   # the old picture is whole, not truncated
    visualize.write_png(path, np.zeros((8, 8, 3), np.uint8))
    assert path.read_bytes() != before and stat.S_IMODE(path.stat().st_mode) == 0o640
    assert [p.name for p in tmp_path.iterdir()] == ["p.png"]   # no temp file left behind


def test_greedy_action_names_moves_as_plans_move_kind_does(config):
    # visualize.greedy_action gets only rewards.shift_height from the daemon, so it keeps its own copy of
    # the push/shift rule; this pins it to flgd.plans.move_kind.
    limit = config.rewards.shift_height
    for h in (0.0, limit - 1e-4, limit, limit + 1e-4, 0.05):
        height = np.full((8, 8), h, np.float32)
        q = np.zeros((4, 2, 8, 8), np.float32)
        q[1, 1, 3, 4] = 1.0
        no = np.zeros((8, 8), np.uint8)
        action = visualize.greedy_action(q, no, np.ones((8, 8), np.uint8), height, limit)
        assert action.primitive == move_kind(h, config), h


def test_the_table_counts_aborted_runs_beside_the_rates_that_leave_them_out():
    spec = scene_from_argument("pile-20-a")
    ok = RunLog(scene="pile-20-a", run=1, objects=3, actions=(ActionEntry("grasp", True),) * 3, objects_left=0,
                objects_grasped=3, end="cleared")
    gave_up = RunLog(scene="pile-20-a", run=2, objects=3, actions=(ActionEntry("grasp", False),), objects_left=3,
                     objects_grasped=0, end="unstable")
    report = build_report([(spec, [ok, gave_up])], policy={"path": "p"}, config="c", options={"runs": 2},
                          seconds=1.0)
    lines = format_table(report).splitlines()
    header = lines[1].split()
    assert header[:4] == ["scene", "runs", "aborted", "complete"]
    overall = next(ln for ln in lines if ln.startswith("OVERALL")).split()
    assert overall[1:4] == ["2", "1", "100.0%"]   # 2 runs, 1 aborted, the rate over the other one
