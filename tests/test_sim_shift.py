"""The knobs that make a second, different simulated cell: each changes what it claims, is refused out of range,
and at its default leaves the training cell as it was."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pybullet as p
import pytest

from flgd.config import ConfigError, CameraPoseErrorConfig, config_from_dict, load_config
from flgd.perception import frame_heightmaps
from sim_cell.cell import SimCell
from sim_cell.objects import ObjectSpec

REPO = Path(__file__).resolve().parents[1]
BASE_CFG = load_config(REPO / "cell_config" / "sim.yaml")


def make_config(**sim):
    return dataclasses.replace(BASE_CFG, sim=dataclasses.replace(BASE_CFG.sim, **sim))


def plate_at(cell: SimCell, x: float, y: float) -> int:
    size = (0.05, 0.05, 0.04)
    return cell.add_object(ObjectSpec(shape="bar", size=size, color=(0.9, 0.2, 0.1),
                                      position=(x, y, size[2] / 2 + 0.001)))


def object_centre_px(cfg, **sim) -> tuple[float, float]:
    """(row, col) centroid of what stands on the table in the heightmap of a cell with one plate."""
    with SimCell(make_config(objects=0, depth_noise=False, domain_randomization=False, **sim)) as cell:
        plate_at(cell, -0.52, 0.06)
        hm = frame_heightmaps(cell.capture(), cfg.workspace, cfg.camera.depth_range)
    rows, cols = np.nonzero(hm.height > 0.015)
    assert rows.size > 300
    return float(rows.mean()), float(cols.mean())


def seen_at(cfg, error: CameraPoseErrorConfig, point: np.ndarray) -> np.ndarray:
    """Where perception, told the configured pose, puts a point that the true camera sees: T_conf T_true^-1 p."""
    from sim_cell.camera import CameraModel

    conf = CameraModel.from_config(cfg.camera).pose
    true = CameraModel.from_config(cfg.camera, error).pose
    return (conf @ np.linalg.inv(true) @ np.append(point, 1.0))[:3]


@pytest.mark.parametrize("error", [
    CameraPoseErrorConfig(position=(0.02, 0.0, 0.0)),
    CameraPoseErrorConfig(position=(0.0, -0.015, 0.01)),
    CameraPoseErrorConfig(rpy=(0.03, 0.0, 0.0)),
    CameraPoseErrorConfig(rpy=(0.0, -0.02, 0.05)),
])
def test_camera_pose_error_moves_objects_in_the_heightmap_by_the_expected_pixels(error):
    cfg = BASE_CFG
    r0, c0 = object_centre_px(cfg)
    r1, c1 = object_centre_px(cfg, camera_pose_error=error)
    top = np.array([-0.52, 0.06, cfg.workspace.table_z + 0.04])
    expected = seen_at(cfg, error, top) - top
    res = cfg.workspace.resolution
    # rows follow y, columns follow x (perception.base_to_pixel)
    assert abs((c1 - c0) - expected[0] / res) < 1.5, (c1 - c0, expected[0] / res)
    assert abs((r1 - r0) - expected[1] / res) < 1.5, (r1 - r0, expected[1] / res)
    assert np.hypot(r1 - r0, c1 - c0) > 4    # every case here moves the plate by 5 px or more


def test_frames_carry_the_configured_pose_not_the_true_one():
    err = CameraPoseErrorConfig(position=(0.01, 0.0, 0.0), rpy=(0.0, 0.02, 0.0))
    with SimCell(make_config(objects=0, camera_pose_error=err)) as cell:
        frame = cell.capture()
    with SimCell(make_config(objects=0)) as cell:
        assert np.allclose(frame.camera_pose, cell.capture().camera_pose)


def _depth_error(**sim) -> tuple[float, float]:
    """(std of depth noise in mm, share of pixels without a reading) over a table with objects."""
    cfg_clean = make_config(objects=3, depth_noise=False, seed=4)
    with SimCell(cfg_clean) as clean, SimCell(make_config(objects=3, depth_noise=True, seed=4, **sim)) as noisy:
        a, b = clean.capture().depth.astype(float), noisy.capture().depth.astype(float)
    both = (a > 0) & (b > 0)
    return float(np.std((a - b)[both])), float(np.mean(b == 0))


def test_depth_noise_keys_change_the_depth_statistics():
    std0, holes0 = _depth_error()
    std4, _ = _depth_error(depth_noise_std=0.004)
    assert 3.0 < std4 / std0 < 5.0            # the noise std scales with the key (quantisation blurs the base)
    _, holes_drop = _depth_error(depth_dropout=0.1)
    assert 0.09 < holes_drop - holes0 < 0.11
    _, holes_none = _depth_error(depth_dropout=0.0, depth_edge_holes=0.0)
    assert holes_none < holes0


def _colours(**sim) -> tuple[float, float]:
    """(mean colour of object pixels, mean colour of table pixels) in the colour heightmap."""
    cfg = make_config(objects=6, depth_noise=False, seed=3, **sim)
    with SimCell(cfg) as cell:
        hm = frame_heightmaps(cell.capture(), cfg.workspace, cfg.camera.depth_range)
    obj = hm.height > 0.008
    table = hm.height < 0.002
    return float(hm.color[obj].mean()), float(hm.color[table].mean())


def test_colour_and_light_keys_change_the_colour_heightmap():
    obj0, table0 = _colours()
    obj1, table1 = _colours(object_color_shift=(-0.3, -0.3, -0.3))
    assert obj0 - obj1 > 30 and abs(table1 - table0) < 1.0
    _, table_white = _colours(table_shade=(0.9, 0.9))
    assert table_white - table0 > 60
    obj_dim, table_dim = _colours(light_ambient=(0.2, 0.2), light_diffuse=(0.2, 0.2))
    assert obj0 - obj_dim > 20 and table0 - table_dim > 20


def test_friction_and_mass_keys_change_the_objects():
    with SimCell(make_config(objects=4, seed=11)) as a, \
            SimCell(make_config(objects=4, seed=11, object_friction=(1.2, 1.2), object_mass_scale=2.0)) as b:
        for sa, sb in zip(a.object_states(), b.object_states()):
            da = p.getDynamicsInfo(sa.body, -1, physicsClientId=a._client)
            db = p.getDynamicsInfo(sb.body, -1, physicsClientId=b._client)
            assert db[0] == pytest.approx(2.0 * da[0], rel=1e-6)
            assert db[1] == pytest.approx(1.2)


def test_defaults_draw_the_training_cell_as_before():
    """Scenes of seed 11 as drawn before these keys existed (commit aa59605): same table shade and friction, light,
    objects, poses, colours, masses and frictions, and the renderer looks from the configured pose."""
    before = [("triangular_prism", (-0.6107, -0.0825), (0.7184, 0.5278, 0.6787), 0.02618, 0.5696),
              ("cylinder", (-0.6775, 0.0629), (0.8894, 0.6147, 0.221), 0.03833, 0.5432),
              ("l_block", (-0.5159, 0.1096), (0.3854, 0.6204, 0.3321), 0.07023, 0.5678),
              ("hexagonal_prism", (-0.5854, 0.0133), (0.6344, 0.5095, 0.6105), 0.05305, 0.6681)]
    with SimCell(make_config(objects=4, seed=11)) as cell:
        states = cell.object_states()
        assert np.allclose(cell._true_camera.pose, cell._camera.pose)
        table = p.getVisualShapeData(cell._world.table, physicsClientId=cell._client)[0][7]
        assert np.allclose(table[:3], (0.5956, 0.5783, 0.5346), atol=2e-4)
        assert p.getDynamicsInfo(cell._world.table, -1, physicsClientId=cell._client)[1] == pytest.approx(0.6803, abs=2e-4)
        direction, ambient, diffuse = cell._randomiser.light
        assert np.allclose(direction, (-0.1976, -0.4486, 1.0), atol=2e-4)
        assert (ambient, diffuse) == (pytest.approx(0.7335, abs=2e-4), pytest.approx(0.336, abs=2e-4))
        assert len(states) == len(before)
        for s, (label, xy, rgb, mass, friction) in zip(states, before):
            vis = p.getVisualShapeData(s.body, physicsClientId=cell._client)[0][7]
            dyn = p.getDynamicsInfo(s.body, -1, physicsClientId=cell._client)
            assert s.label == label
            assert np.allclose(s.position[:2], xy, atol=2e-4)
            assert np.allclose(vis[:3], rgb, atol=2e-4)
            assert dyn[0] == pytest.approx(mass, abs=2e-5) and dyn[1] == pytest.approx(friction, abs=2e-4)


@pytest.mark.parametrize("sim, needle", [
    ({"camera_pose_error": {"position": [0.08, 0, 0]}}, "sim.camera_pose_error.position[0]: got 0.08"),
    ({"camera_pose_error": {"rpy": [0, 0, -0.2]}}, "sim.camera_pose_error.rpy[2]: got -0.2"),
    ({"depth_noise_std": 0.05}, "sim.depth_noise_std: got 0.05"),
    ({"depth_dropout": -0.1}, "sim.depth_dropout: got -0.1"),
    ({"table_shade": [0.7, 0.3]}, "sim.table_shade: got [0.7, 0.3], expected min <= max"),
    ({"object_color_shift": [0, 1.5, 0]}, "sim.object_color_shift[1]: got 1.5"),
    ({"light_ambient": [0.5]}, "sim.light_ambient: got [0.5]"),
    ({"object_friction": [0.9, 0.4]}, "sim.object_friction: got [0.9, 0.4], expected min <= max"),
    ({"object_mass_scale": 10}, "sim.object_mass_scale: got 10"),
])
def test_out_of_range_knobs_are_refused_naming_key_and_value(sim, needle):
    with pytest.raises(ConfigError) as err:
        config_from_dict({"backend": "sim", "state_dir": "/tmp/x", "sim": sim}, source="shifted.yaml")
    assert needle in str(err.value), str(err.value)
    assert "shifted.yaml" in str(err.value)


SECOND_CELLS = [REPO / "cell_config" / "sim-shifted.yaml", *sorted((REPO / "benchmarks" / "cells").glob("*.yaml"))]


@pytest.mark.parametrize("path", SECOND_CELLS, ids=lambda p: p.name)
def test_the_second_cells_differ_from_the_training_cell_only_in_the_simulated_world(path):
    """What `flgd bench finetune` compares across cells is the cell; the learner, gate and everything else must be
    the shipped ones, or a change to sim.yaml leaves the second cells measuring something else."""
    from flgd.config import config_to_dict

    train = config_to_dict(load_config(REPO / "cell_config" / "sim.yaml"))
    other = config_to_dict(load_config(path))
    differs = sorted(k for k in train if k not in ("sim", "state_dir", "name") and train[k] != other[k])
    assert differs == [], f"{path.name} differs from sim.yaml in {differs}"
    assert train["sim"] != other["sim"]
