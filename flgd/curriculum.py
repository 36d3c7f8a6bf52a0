"""The training curriculum of paper IV-A, and the cell wrapper that applies it to new scenes.

The paper's schedule (steps = actions taken so far):

* the first ``few_moves_steps`` (500) steps take few moves: the agent keeps a
  chosen move only with probability ``exploration.curriculum_move_probability``
  (that knob lives in the agent; ``apply_to_config`` sets its step count);
* scenes start with ``start_objects`` (10) objects; from ``ramp_start`` (400)
  one more object is added every ``ramp_every`` (100) steps until
  ``max_objects`` (20) -- "we then increase gradually the number of blocks
  until 20 are reached" (the rate is ours: 20 objects at step 1,300, before
  the preset phase starts);
* after ``preset_after`` (1,500) steps, whenever the robot has emptied the
  workspace, the next scene is one of the preset highly cluttered piles
  (sim_cell/scenes) with probability ``preset_probability`` (0.2), chosen
  uniformly.

The object count takes effect at the next new scene (a scene in progress is
never changed).  Only the scene source is decided here; the cycle, agent and
learner are the daemon's.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from flgd.cell import Cell, WrappedCell
from flgd.config import CellConfig

__all__ = ["Curriculum", "CurriculumCell"]


@dataclass(frozen=True)
class Curriculum:
    start_objects: int = 10
    max_objects: int = 20
    ramp_start: int = 400
    ramp_every: int = 100
    few_moves_steps: int = 500
    preset_after: int = 1500
    preset_probability: float = 0.2

    def __post_init__(self) -> None:
        if not 0 <= self.start_objects <= self.max_objects <= 60:
            raise ValueError(f"curriculum objects: got start {self.start_objects}, max {self.max_objects}; "
                             "expected 0 <= start <= max <= 60")
        if self.ramp_start < 0 or self.ramp_every < 1 or self.few_moves_steps < 0 or self.preset_after < 0:
            raise ValueError("curriculum steps: expected ramp_start, few_moves_steps, preset_after >= 0 and "
                             f"ramp_every >= 1, got {self}")
        if not 0.0 <= self.preset_probability <= 1.0:
            raise ValueError(f"curriculum preset_probability: got {self.preset_probability!r}, expected 0..1")

    def object_count(self, step: int) -> int:
        """Objects in a random scene started at ``step``."""
        if step < self.ramp_start:
            return self.start_objects
        added = 1 + (step - self.ramp_start) // self.ramp_every
        return min(self.max_objects, self.start_objects + added)

    def preset_allowed(self, step: int) -> bool:
        return step >= self.preset_after and self.preset_probability > 0.0

    def choose_preset(self, step: int, presets: list[Path], rng: np.random.Generator) -> Path | None:
        """After the workspace was emptied at ``step``: a preset scene to load, or None for random clutter.

        Draws from ``rng`` only once the preset phase has started, so the
        earlier part of a run does not depend on the preset settings.
        """
        if not self.preset_allowed(step) or not presets:
            return None
        if rng.random() >= self.preset_probability:
            return None
        return presets[int(rng.integers(len(presets)))]

    def apply_to_config(self, config: CellConfig) -> CellConfig:
        """``config`` with the few-moves phase and the starting object count of this curriculum."""
        return dataclasses.replace(
            config,
            exploration=dataclasses.replace(config.exploration, curriculum_steps=self.few_moves_steps),
            sim=dataclasses.replace(config.sim, objects=self.object_count(0)))


class CurriculumCell(WrappedCell):
    """A simulated cell whose new scenes follow a curriculum; everything else is the inner cell's.

    ``step_of`` returns the current training step (the cycle runner's
    counter).  The inner cell must offer ``set_object_count``, ``load_scene``
    and ``object_count`` (sim_cell.SimCell does).
    """

    def __init__(self, inner: Cell, curriculum: Curriculum, step_of: Callable[[], int], presets: list[Path],
                 rng: np.random.Generator):
        for attr in ("set_object_count", "load_scene", "object_count"):
            if not hasattr(inner, attr):
                raise TypeError(f"the curriculum needs a simulated cell with {attr}; got {type(inner).__name__}")
        super().__init__(inner)
        self.curriculum = curriculum
        self.step_of = step_of
        self.presets = list(presets)
        self.rng = rng
        self.scenes = 0
        self.scene_kind = f"random {inner.object_count}"

    def reset_scene(self) -> None:
        step = int(self.step_of())
        emptied = self.inner.object_count == 0
        preset = self.curriculum.choose_preset(step, self.presets, self.rng) if emptied else None
        if preset is not None:
            placed = self.inner.load_scene(preset)
            self.scene_kind = f"preset {preset.stem} ({placed})"
        else:
            n = self.curriculum.object_count(step)
            self.inner.set_object_count(n)
            self.inner.reset_scene()
            self.scene_kind = getattr(self.inner, "scene_kind", f"random {n}")   # a packed scene says so
        self.scenes += 1

    @property
    def object_count(self) -> int:
        return self.inner.object_count
