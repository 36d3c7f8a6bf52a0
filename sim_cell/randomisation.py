"""Domain randomisation of the simulated cell: what is drawn at random for a scene and each object.

Per scene (with ``sim.domain_randomization``): the table's shade and friction and the light.  Per random
object: its kind from ``sim.object_set``, its size, a palette colour (jittered, plus the cell's
``sim.object_color_shift``) and, with domain randomisation, its friction and density.  Everything is
drawn from the cell's scene generator in a fixed order, so that a seed gives the same scenes.
"""

from __future__ import annotations

import numpy as np
import pybullet as p

from flgd.config import CellConfig
from sim_cell import objects, shapes

Light = tuple[tuple[float, float, float], float, float]   # (direction, ambient, diffuse)

# VPG-like block colours (tableau), jittered per object
_PALETTE = np.array([[78, 121, 167], [89, 161, 79], [156, 117, 95], [242, 142, 43], [237, 201, 72],
                     [186, 176, 172], [255, 87, 89], [176, 122, 161], [118, 183, 178], [255, 157, 167]]) / 255.0


class Randomiser:
    """Draws the random parts of a cell's scenes from ``rng`` (the cell's scene generator); ``light`` is
    the scene's light, as last drawn."""

    def __init__(self, config: CellConfig, rng: np.random.Generator, client: int):
        self.rng = rng
        self.light: Light = ((0.3, -0.2, 1.0), 0.6, 0.4)   # what the camera renders with
        self._config = config
        self._client = client
        self._object_groups = objects.resolve_object_groups(config.sim.object_set)
        self._natural_extents: dict[str, tuple[float, float, float]] = {}

    def randomise_domain(self, table: int) -> None:
        """A new table shade and friction, and a new ``light`` (nothing changes when not randomised)."""
        rng, sim = self.rng, self._config.sim
        if sim.domain_randomization:
            shade = rng.uniform(*sim.table_shade)
            tint = rng.uniform(-0.05, 0.05, 3)
            p.changeVisualShape(table, -1, rgbaColor=[*np.clip(shade + tint, 0, 1), 1.0],
                                physicsClientId=self._client)
            p.changeDynamics(table, -1, lateralFriction=float(rng.uniform(0.4, 0.8)),
                             physicsClientId=self._client)
            direction = (float(rng.uniform(-0.5, 0.5)), float(rng.uniform(-0.5, 0.5)), 1.0)
            self.light = (direction, float(rng.uniform(*sim.light_ambient)), float(rng.uniform(*sim.light_diffuse)))

    def random_spec(self) -> objects.ObjectSpec:
        """One random object of ``sim.object_set`` (pose still to be chosen)."""
        rng, config = self.rng, self._config
        kind = objects.draw_object_kind(self._object_groups, rng)
        colour = self._object_colour()
        dr = config.sim.domain_randomization
        friction = float(rng.uniform(*config.sim.object_friction)) if dr else 0.6
        if kind.startswith("block:"):
            shape = kind.split(":", 1)[1]
            return self.block_spec(shape, shapes.random_block_dims(shape, rng), colour, friction)
        if kind.startswith(objects.MESH_PREFIX):
            path = kind[len(objects.MESH_PREFIX):]
            density = float(rng.uniform(400, 900)) if dr else 600.0
            mass = max(objects.mesh_volume(path) * density, 0.02)
            return objects.ObjectSpec(mesh=path, color=colour, mass=mass, friction=friction)
        if kind not in self._natural_extents:
            self._natural_extents[kind] = objects.natural_extents(kind, self._client)
        scale = objects.graspable_scale(self._natural_extents[kind], float(rng.uniform(0.05, 0.09)),
                                        config.gripper.open_width, config.learning.rotations)
        mass = float(rng.uniform(0.03, 0.15)) if dr else None
        return objects.ObjectSpec(urdf=kind, scale=scale, color=colour, mass=mass, friction=friction)

    def _object_colour(self) -> tuple[float, float, float]:
        """A palette colour, jittered, plus the cell's ``sim.object_color_shift``."""
        rng = self.rng
        base = _PALETTE[int(rng.integers(len(_PALETTE)))] + rng.uniform(-0.06, 0.06, 3)
        return tuple(np.clip(base + np.asarray(self._config.sim.object_color_shift), 0, 1).tolist())

    def block_spec(self, shape: str, dims: tuple[float, ...], colour: tuple[float, float, float] | None = None,
                   friction: float | None = None) -> objects.ObjectSpec:
        """A procedural block with this cell's colours, densities and frictions (random where the
        domain is randomised); ``colour``/``friction`` given when the caller drew them already."""
        rng = self.rng
        dr = self._config.sim.domain_randomization
        if colour is None:
            colour = self._object_colour()
        if friction is None:
            friction = float(rng.uniform(*self._config.sim.object_friction)) if dr else 0.6
        density = float(rng.uniform(400, 900)) if dr else 600.0
        volume = float(np.prod(shapes.make_block(shape, dims).extents)) * 0.7
        return objects.ObjectSpec(shape=shape, size=dims, color=colour, mass=max(volume * density, 0.02),
                                  friction=friction)
