"""The emulated cell's bin: what the gripper lets go of over the place pose leaves the table, as into a bin on a
cell; the sim backend takes a placed object out at the same moment.  Without it, placed objects piled up beside the
workspace, spread over its border and were grasped at, half seen."""

from __future__ import annotations

import dataclasses

from flgd.config import load_config
from sim_cell.emulator.world import BIN_CHECK_STEPS, EmulatorWorld
from sim_cell.objects import ObjectSpec
from tests.fakes.realsense import SIM_CONFIG


def test_an_object_dropped_over_the_place_pose_leaves_the_table_and_one_in_the_workspace_stays():
    cfg = load_config(SIM_CONFIG)
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, objects=0))
    ws, place = cfg.workspace, cfg.robot.place.position
    assert not (ws.y[0] <= place[1] <= ws.y[1] and ws.x[0] <= place[0] <= ws.x[1]), "the place is beside the workspace"
    with EmulatorWorld(cfg) as world:
        sim = world.cell
        dropped = sim.add_object(ObjectSpec(shape="cube", size=(0.04,), position=(place[0], place[1], 0.10)))
        kept = sim.add_object(ObjectSpec(shape="cube", size=(0.04,),
                                         position=((ws.x[0] + ws.x[1]) / 2, (ws.y[0] + ws.y[1]) / 2, 0.03)))
        world.step(4 * BIN_CHECK_STEPS)
        assert dropped not in sim._world.objects and kept in sim._world.objects
        assert sim._world.stats["grasped_out"] == 1
