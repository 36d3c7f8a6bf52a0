"""``flgd bench drops``: the watch that follows a lifted object through its plans, on a real simulated cell."""

from __future__ import annotations

import math

import numpy as np
import pybullet as p
import pytest

from benchmarks.drops import DropWatch, held_geometry, summary
from flgd.plans import GripperCommand, Plan, plan_grasp, plan_home
from flgd.safety import check_plan
from sim_cell.arm_driver import ArmDriver
from sim_cell.cell import SimCell
from sim_cell.world import World
from tests.fakes.sim import cube_at, make_config, state


@pytest.fixture
def watched_cell():
    watch = DropWatch()
    originals = watch.wrap(SimCell, ArmDriver, World)
    cell = SimCell(make_config(objects=0, depth_noise=False, domain_randomization=False))
    yield cell, watch
    cell.close()
    DropWatch.restore(SimCell, ArmDriver, World, originals)


def _grasp(cell: SimCell, body: int, yaw: float) -> Plan:
    s = state(cell, body)
    return plan_grasp(s.position[0], s.position[1], s.top - cell.config.workspace.table_z, yaw, cell.config)


def test_a_block_carried_out_is_followed_to_the_opening_and_is_no_drop(watched_cell):
    cell, watch = watched_cell
    body = cube_at(cell, -0.55, 0.05, size=(0.05, 0.03, 0.03), yaw=-0.4)
    cell.execute(check_plan(_grasp(cell, body, -0.4 + math.pi / 2), cell.config))
    cell.execute(check_plan(plan_home(cell.config), cell.config))
    assert cell.stats["grasped_out"] == 1
    [record] = watch.records
    assert record["shape"] == "bar" and record["left_at"].endswith(":open") and not record["dropped"]
    assert abs(record["centre_mm"][0]) < 3 and record["tilt_deg"] < 5   # centred between the pads, level
    assert record["extent_closing_mm"] == pytest.approx(30, abs=3)       # the 3 cm side between the pads
    assert summary(watch.records)["carried_out"]["n"] == 1 and summary(watch.records)["dropped"]["n"] == 0


def test_a_block_let_go_outside_the_workspace_is_a_drop_where_it_left(watched_cell):
    cell, watch = watched_cell
    body = cube_at(cell, -0.55, 0.05, size=(0.05, 0.03, 0.03))
    grasp = _grasp(cell, body, math.pi / 2)
    let_go = GripperCommand(cell.config.gripper.open_width, cell.config.gripper.force, "let go")
    # opened at home (beside the table) before the width is measured: a grip that gave way on the way there
    steps = tuple(st for step in grasp.steps for st in ((let_go, step) if step.label == "held" else (step,)))
    cell.execute(check_plan(Plan("grasp", steps), cell.config))
    assert cell.stats["dropped"] == 1
    [record] = watch.records
    assert record["dropped"] and record["lost"] and record["left_at"] == "grasp:let go"
    assert summary(watch.records)["dropped"]["left_at"] == {"grasp:let go": 1}


def test_held_geometry_is_in_the_tool_frame():
    """Tool turned 90 degrees about the vertical: an object 1 cm along base y sits 1 cm along the tool's x."""
    tcp = np.eye(4)
    tcp[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    tcp[:3, 3] = [0.5, 0.0, 0.2]
    box = np.array([[x, y, z] for x in (0.49, 0.51) for y in (0.0, 0.02) for z in (0.19, 0.21)])
    geo = held_geometry(tcp, (0.5, 0.01, 0.2), p.getQuaternionFromEuler([0, 0, 0]), box)
    assert geo["centre_mm"] == pytest.approx([10.0, 0.0, 0.0], abs=1e-6)
    assert geo["extent_closing_mm"] == pytest.approx(20.0) and geo["extent_pads_mm"] == pytest.approx(20.0)
    assert geo["tilt_deg"] == pytest.approx(0.0, abs=1e-6)


def test_a_grasps_tapers_are_read_on_its_heightmap_where_and_how_it_closes():
    from flgd.config import CellConfig
    from flgd.perception import Heightmaps, pixel_to_base

    cfg = CellConfig()
    h = np.zeros((224, 224), np.float32)
    for c in range(90, 111):   # a prism's ridge along y (rows) at column 100: its sides slope along x
        h[85:115, c] = 0.035 * (1 - abs(c - 100) / 10.0)
    watch = DropWatch()
    watch._heightmaps = Heightmaps(color=np.zeros((224, 224, 3), np.uint8), height=h)
    x, y, _ = pixel_to_base(100, 100, 0.035, cfg.workspace)
    across = watch._grasp_tapers(cfg, plan_grasp(x, y, 0.035, 0.0, cfg))
    along = watch._grasp_tapers(cfg, plan_grasp(x, y, 0.035, math.pi / 2, cfg))
    assert min(across) >= 4.0 and along == [0.0, 0.0]
    assert watch._grasp_tapers(cfg, plan_home(cfg)) is None
