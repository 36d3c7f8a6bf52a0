"""The shipped sim config with test changes, a block placed by hand, and an object's state by body."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pybullet as p

from flgd.config import load_config
from sim_cell.cell import SimCell
from sim_cell.objects import ObjectSpec

REPO = Path(__file__).resolve().parents[2]
BASE_CFG = load_config(REPO / "cell_config" / "sim.yaml")


def make_config(**sim):
    return dataclasses.replace(BASE_CFG, sim=dataclasses.replace(BASE_CFG.sim, **sim))


def cube_at(cell: SimCell, x: float, y: float, size=(0.06, 0.03, 0.03), yaw: float = 0.0) -> int:
    q = p.getQuaternionFromEuler([0.0, 0.0, yaw])
    return cell.add_object(ObjectSpec(shape="bar", size=size, color=(0.9, 0.2, 0.1),
                                      position=(x, y, size[2] / 2 + 0.001), orientation=q))


def state(cell: SimCell, body: int):
    return next((s for s in cell.object_states() if s.body == body), None)
