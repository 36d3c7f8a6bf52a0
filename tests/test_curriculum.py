"""The paper IV-A curriculum schedule and the cell wrapper that applies it to new scenes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from flgd.cell import Cell, ExecutionResult
from flgd.config import load_config
from flgd.curriculum import Curriculum, CurriculumCell

REPO = Path(__file__).resolve().parents[1]


def test_object_count_schedule():
    c = Curriculum()
    assert [c.object_count(s) for s in (0, 1, 399)] == [10, 10, 10]
    assert [c.object_count(s) for s in (400, 499, 500, 599, 600)] == [11, 11, 12, 12, 13]
    assert c.object_count(1299) == 19 and c.object_count(1300) == 20
    assert c.object_count(10_000) == 20
    counts = [c.object_count(s) for s in range(3000)]
    assert all(b - a in (0, 1) for a, b in zip(counts, counts[1:]))  # gradual, never down


def test_presets_only_after_1500_steps_with_probability_02():
    c = Curriculum()
    presets = [Path("a.yaml"), Path("b.yaml"), Path("c.yaml")]
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    assert all(c.choose_preset(s, presets, rng) is None for s in (0, 500, 1499))
    assert rng.bit_generator.state == state  # the early phase draws nothing
    picks = [c.choose_preset(1500 + i, presets, rng) for i in range(20_000)]
    chosen = [p for p in picks if p is not None]
    assert 0.18 < len(chosen) / len(picks) < 0.22
    assert {p.name for p in chosen} == {"a.yaml", "b.yaml", "c.yaml"}
    assert c.choose_preset(2000, [], rng) is None
    never = Curriculum(preset_probability=0.0)
    assert all(never.choose_preset(5000, presets, rng) is None for _ in range(100))


def test_apply_to_config_sets_the_few_moves_phase_and_first_scene():
    cfg = load_config(REPO / "cell_config" / "sim.yaml")
    out = Curriculum(few_moves_steps=500).apply_to_config(cfg)
    assert out.exploration.curriculum_steps == 500 and out.sim.objects == 10
    assert out.exploration.curriculum_move_probability == cfg.exploration.curriculum_move_probability


@pytest.mark.parametrize("kwargs", [dict(start_objects=21), dict(max_objects=61), dict(ramp_every=0),
                                    dict(preset_probability=1.5), dict(preset_after=-1)])
def test_bad_schedules_are_refused(kwargs):
    with pytest.raises(ValueError, match="curriculum"):
        Curriculum(**kwargs)


class FakeSimCell(Cell):
    """A fake of SimCell's scene API only: records what the curriculum asks for (no physics)."""

    def __init__(self, config, objects: int):
        super().__init__(config)
        self.object_count = objects
        self.next_count = objects
        self.calls: list[tuple] = []

    def set_object_count(self, n: int) -> None:
        self.calls.append(("count", n))
        self.next_count = n

    def reset_scene(self) -> None:
        self.calls.append(("reset",))
        self.object_count = self.next_count

    def load_scene(self, scene) -> int:
        self.calls.append(("load", Path(scene).name))
        self.object_count = 22
        return 22

    def capture(self):
        raise AssertionError("not used")

    def execute(self, plan):
        return ExecutionResult(True)

    def gripper_width(self) -> float:
        return 0.0


def test_curriculum_cell_uses_the_step_for_count_and_presets_only_when_emptied():
    cfg = load_config(REPO / "cell_config" / "sim.yaml")
    inner = FakeSimCell(cfg, 10)
    step = {"now": 0}
    cell = CurriculumCell(inner, Curriculum(preset_probability=1.0), lambda: step["now"],
                          [Path("pile.yaml")], np.random.default_rng(0))
    inner.object_count = 0
    cell.reset_scene()                      # emptied, but before the preset phase
    assert inner.calls == [("count", 10), ("reset",)] and cell.scene_kind == "random 10"
    step["now"] = 900
    inner.calls.clear()
    cell.reset_scene()
    assert inner.calls == [("count", 16), ("reset",)]
    step["now"] = 1600
    inner.calls.clear()
    inner.object_count = 3                  # not emptied (e.g. a discarded action): random clutter
    cell.reset_scene()
    assert inner.calls == [("count", 20), ("reset",)]
    inner.calls.clear()
    inner.object_count = 0                  # emptied: the preset pile (probability 1 here)
    cell.reset_scene()
    assert inner.calls == [("load", "pile.yaml")]
    assert cell.scene_kind == "preset pile (22)" and cell.object_count == 22 and cell.scenes == 4


def test_curriculum_cell_reports_the_inner_cells_own_scene_kind():
    """A simulated cell with sim.packed_scenes may lay a packed scene where the curriculum asked for a reset."""
    cfg = load_config(REPO / "cell_config" / "sim.yaml")

    class PackingSimCell(FakeSimCell):
        def reset_scene(self) -> None:
            super().reset_scene()
            self.scene_kind = "packed 7"

    cell = CurriculumCell(PackingSimCell(cfg, 10), Curriculum(), lambda: 0, [], np.random.default_rng(0))
    cell.reset_scene()
    assert cell.scene_kind == "packed 7"


def test_curriculum_cell_needs_a_simulated_cell():
    cfg = load_config(REPO / "cell_config" / "sim.yaml")

    class NoScenes(Cell):
        def capture(self):
            raise AssertionError

        def execute(self, plan):
            raise AssertionError

        def gripper_width(self):
            return 0.0

    with pytest.raises(TypeError, match="set_object_count"):
        CurriculumCell(NoScenes(cfg), Curriculum(), lambda: 0, [], np.random.default_rng(0))
