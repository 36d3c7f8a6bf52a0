"""Packed arrangements (sim_cell.packed): blocks laid flush in rows, settled in the simulated cell."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from flgd.config import ConfigError, load_config
from flgd.perception import frame_heightmaps
from sim_cell.cell import SimCell
from sim_cell.packed import PACKED_SHAPES, packed_scene
from sim_cell.objects import ObjectSpec
from sim_cell.shapes import make_block

REPO = Path(__file__).resolve().parents[1]
CFG = load_config(REPO / "cell_config" / "sim.yaml")


def _cfg(**sim):
    sim = {"objects": 0, "depth_noise": False, **sim}
    return dataclasses.replace(CFG, sim=dataclasses.replace(CFG.sim, **sim))


def _spec(shape, dims):
    return ObjectSpec(shape=shape, size=dims)


def _blobs(cell: SimCell) -> int:
    """Connected object regions in the heightmap, gaps up to 2 px (4 mm) bridged."""
    hm = frame_heightmaps(cell.capture(), cell.config.workspace, cell.config.camera.depth_range)
    mask = (np.nan_to_num(hm.height) > cell.config.rewards.min_height).astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    return cv2.connectedComponents(mask)[0] - 1


@pytest.fixture(scope="module")
def cell():
    c = SimCell(_cfg())
    yield c
    c.close()


def test_a_packed_scene_is_a_few_rows_of_touching_blocks_inside_the_workspace():
    ws = CFG.workspace
    hx, hy = (ws.x[1] - ws.x[0]) / 2, (ws.y[1] - ws.y[0]) / 2
    for seed in range(20):
        scene = packed_scene(np.random.default_rng(seed), hx, hy, 0.03, _spec)
        assert 2 <= len(scene.objects) <= 30
        assert {o.shape for o in scene.objects} <= set(PACKED_SHAPES)
        for o in scene.objects:
            x, y, z = o.position
            assert abs(x) < hx and abs(y) < hy and 0.0 < z < 0.06
            assert abs(o.orientation[0]) < 1e-12 and abs(o.orientation[1]) < 1e-12   # standing on a face
        # every block has a neighbour whose centre is within the two blocks' half-diagonals plus 3 mm
        pos = np.array([o.position[:2] for o in scene.objects])
        reach = np.array([np.hypot(*make_block(o.shape, o.size).extents[:2]) / 2 for o in scene.objects])
        d = np.linalg.norm(pos[:, None] - pos[None], axis=2) + np.eye(len(pos)) * 9
        assert np.all((d <= reach[:, None] + reach[None] + 0.003).any(axis=1))
    with pytest.raises(ValueError, match="groups: got 4, expected 1..3"):
        packed_scene(np.random.default_rng(0), hx, hy, 0.03, _spec, groups=4)


def test_packed_scenes_settle_in_place_as_few_blobs_and_repeat_with_the_seed(cell):
    blobs, objects = [], []
    for groups in (1, 2, 3):
        n = cell.make_packed(groups)
        before = np.array([s.position for s in cell.object_states()])
        cell.simulate(1.0)
        after = np.array([s.position for s in cell.object_states()])
        assert cell.object_count == n >= 2 * groups     # nothing fell off, toppled out or was discarded
        assert np.max(np.linalg.norm(after - before, axis=1)) < 0.005
        blobs.append(_blobs(cell))
        objects.append(n)
    # the blocks of a group touch: one region per group, however many blocks it has
    assert blobs == [1, 2, 3] and all(n > b for n, b in zip(objects, blobs))
    same = [SimCell(_cfg(seed=11)) for _ in range(2)]
    try:
        poses = [(c.make_packed(), np.round([s.position for s in c.object_states()], 4)) for c in same]
    finally:
        for c in same:
            c.close()
    assert poses[0][0] == poses[1][0] and np.array_equal(poses[0][1], poses[1][1])


def test_sim_packed_scenes_sets_the_share_of_new_scenes_that_are_packed(tmp_path):
    c = SimCell(_cfg(packed_scenes=1.0, objects=20))
    try:
        counts = []
        for _ in range(3):
            c.reset_scene()
            counts.append((c.object_count, _blobs(c), c.scene_kind))
    finally:
        c.close()
    assert all(n >= 2 and 1 <= blobs <= 3 for n, blobs, _ in counts)   # packed: one to three groups
    assert [kind for _, _, kind in counts] == [f"packed {n}" for n, _, _ in counts]   # what a training log records
    c = SimCell(_cfg(packed_scenes=0.0, objects=20))
    try:
        c.reset_scene()
        assert c.object_count == 20 and c.scene_kind == "random 20"   # a dropped scene of sim.objects
    finally:
        c.close()
    bad = tmp_path / "bad.yaml"
    bad.write_text((REPO / "cell_config" / "sim.yaml").read_text().replace(
        "  domain_randomization: true\n", "  domain_randomization: true\n  packed_scenes: 1.5\n"))
    with pytest.raises(ConfigError, match=r"sim\.packed_scenes.*1\.5"):
        load_config(bad)


@pytest.mark.slow
def test_eval_and_bench_eval_run_packed_scenes(tmp_path, capsys):
    from benchmarks import eval as bench_eval

    out = tmp_path / "packed.json"
    assert bench_eval.main(["--fresh", "--parts", "packed", "--validation-runs", "1", "--max-actions", "2",
                            "--json", str(out)]) == 0
    reports = json.loads(out.read_text())
    assert list(reports) == [f"packed arrangements, seed {s}" for s in bench_eval.VALIDATION_SEEDS]
    scenes = [r["scenes"][0] for r in reports.values()]
    assert all(s["scene"] == "packed blocks" and s["runs"] == 1 and s["objects"] >= 2 for s in scenes)
    # each seed lays its own arrangement (the runs' object counts are not all the same)
    assert len({tuple(log["objects"] for log in s["run_logs"]) for s in scenes}) > 1
    successes, attempts, _, counted = bench_eval.validation_pooled(reports, bench_eval._packed_name)
    assert counted == 4 and attempts == sum(r["overall"]["grasp_attempts"] for r in reports.values())
    assert "packed arrangements (seeds 7, 8, 9, 10 pooled): grasp success" in capsys.readouterr().out
