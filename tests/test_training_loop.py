"""The one training loop over a collector: what any collector's cycles become in the run's store, replay,
learner and actions.csv -- shown with a scripted collector of two cells, and the write-ahead intent of the
collector that runs one simulated cell in the run's process."""

from __future__ import annotations

import dataclasses
import io
from pathlib import Path
from typing import Any

import pytest

from flgd.actions import Action
from flgd.config import load_config
from flgd.cycle_record import CycleOutcome
from flgd.learning.replay import Transition
from flgd.learning_stack import Handover
from flgd.store import Store
from flgd.training.actions_csv import read_rows
from flgd.training.collected import CellReport, CollectedCycle
from flgd.training.collector import CollectorStart, LocalCollector
from flgd.training.progress import LineProgress
from flgd.training.run import RunSettings, TrainingCellError, TrainingRun

from tests.fakes.store_rows import action_row, random_heightmaps
from tests.fakes.wrapped_cell import WrappedCell

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "cell_config" / "sim.yaml"


def _cycle(scene: int, state, next_state, outcome: CycleOutcome = CycleOutcome.EXECUTED,
           success: bool = True) -> CollectedCycle:
    transition = None if outcome == CycleOutcome.FAULT else \
        Transition(state, Action("grasp", 1, 2, 3), float(success), next_state, False)
    row = action_row(999, outcome=str(outcome), success=int(success))   # the cell's own step: replaced
    return CollectedCycle(row, transition, outcome, "grasp", success, objects_left=3, scene=scene,
                          scene_kind="random 4")


class ScriptedCollector:
    """Two cells whose reports are given in advance, in the order they arrive (a stand-in for Ray workers)."""

    handover = Handover.NOBODY
    cells = 2

    def __init__(self, reports: list[CellReport]) -> None:
        self.reports = list(reports)
        self.go_ons: list[tuple[int, int]] = []
        self.started_at: int | None = None
        self.closed = False

    def prepare(self) -> None:
        pass

    def start(self, start: CollectorStart) -> None:
        self.started_at = start.step

    def next_report(self, timeout: float) -> CellReport | None:
        return self.reports.pop(0) if self.reports else None

    def go_on(self, cell: int, step: int) -> None:
        self.go_ons.append((cell, step))

    @property
    def in_flight(self) -> int:
        return 0

    def where(self, cell: int) -> str:
        return f"worker {cell}: "

    def status(self) -> dict[str, str]:
        return {"objects": "3/3"}

    def segment_info(self) -> dict[str, Any]:
        return {"workers": 2}

    def stats(self) -> dict[str, Any]:
        return {}

    def close(self) -> None:
        self.closed = True


def _run(tmp_path: Path, collector, steps: int) -> TrainingRun:
    config = load_config(CONFIG)
    # no update in these few steps: the loop's bookkeeping is what is shown, not learning
    config = dataclasses.replace(config, learning=dataclasses.replace(config.learning, min_replay=1000))
    return TrainingRun(tmp_path / "run", RunSettings(steps=steps, seed=1), config,
                       LineProgress(io.StringIO(), False), threads=1, collector=collector)


def test_two_cells_cycles_are_kept_under_consecutive_steps_with_their_scenes_states_and_faults(tmp_path):
    a0, a1, a2 = (random_heightmaps(i) for i in range(3))
    b0, b1 = (random_heightmaps(10 + i) for i in range(2))
    copy_of_a1 = dataclasses.replace(a1, height=a1.height.copy(), color=a1.color.copy())  # as sent back by Ray
    reports = [
        CellReport(cell=0, cycles=[_cycle(0, a0, a1)], decisions=[(b"k0", 0, (0, 1, 2, 3))]),
        CellReport(cell=1, cycles=[_cycle(0, b0, b1)],
                   notes=[("give-up", "3 actions without a grasp", "3 actions without a grasp: new scene")]),
        CellReport(cell=0, cycles=[_cycle(0, copy_of_a1, a2, success=False)]),
        CellReport(cell=0, cycles=[_cycle(0, a2, a2, outcome=CycleOutcome.FAULT)]),
        CellReport(cell=0, cycles=[_cycle(0, random_heightmaps(20), random_heightmaps(21))]),
    ]
    collector = ScriptedCollector(reports)
    run = _run(tmp_path, collector, steps=5)
    try:
        run.setup()
        assert collector.started_at == 0
        assert run.train() == 0
        assert ("worker 1: 3 actions without a grasp", ) == tuple(
            e["message"] for e in run.store.events("give-up"))
        assert run.learner._next_argmax[b"k0"] == (0, (0, 1, 2, 3))   # a cell's a' reaches the learner
        assert len(run.replay) == 4   # the fault's cycle has nothing to learn
    finally:
        run.close()
    assert collector.closed
    # each report's cell goes on at the run's next step, until the last step is kept
    assert collector.go_ons == [(0, 1), (1, 2), (0, 3), (0, 4)]
    store = Store(tmp_path / "run")
    try:
        assert [r["step"] for r in store.action_log()] == [0, 1, 2, 3, 4]
        assert store.transition_count() == 4
        # a1 came back as a copy of cell 0's last next state: kept once (a0, a1, a2, b0, b1 and the last two)
        assert store.state_count() == 7
    finally:
        store.close()
    rows = read_rows(tmp_path / "run" / "actions.csv")
    assert [int(r["step"]) for r in rows] == [0, 1, 2, 4]   # a fault's row stays in the store's action log
    # run-wide scene ids: one per cell's scene, a new one after a fault
    assert [int(r["scene"]) for r in rows] == [0, 1, 0, 2]


def test_a_replaced_worker_starts_a_new_scene_in_the_run_though_it_numbers_its_own_from_zero_again(tmp_path):
    s = [random_heightmaps(i) for i in range(6)]
    reports = [CellReport(cell=1, incarnation=0, cycles=[_cycle(0, s[0], s[1])]),
               CellReport(cell=1, incarnation=1, cycles=[_cycle(0, s[1], s[2])]),   # the replacement's scene 0
               CellReport(cell=1, incarnation=1, cycles=[_cycle(0, s[2], s[3])])]
    run = _run(tmp_path, ScriptedCollector(reports), steps=3)
    try:
        run.setup()
        assert run.train() == 0
    finally:
        run.close()
    rows = read_rows(tmp_path / "run" / "actions.csv")
    assert [int(r["scene"]) for r in rows] == [0, 1, 1]


def test_a_cells_error_stops_the_run_after_its_rows_are_kept_and_names_the_cell(tmp_path):
    s0, s1 = random_heightmaps(0), random_heightmaps(1)
    failing = CellReport(cell=1, cycles=[_cycle(0, s0, s1)],
                         error="RuntimeError: 5 cell faults in a row; last: bodies 0 and 11 overlap")
    collector = ScriptedCollector([failing])
    run = _run(tmp_path, collector, steps=5)
    try:
        run.setup()
        with pytest.raises(TrainingCellError, match="^worker 1: RuntimeError: 5 cell faults in a row"):
            run.train()
        assert run.step == 1 and run.store.transition_count() == 1
    finally:
        run.close()


@pytest.mark.slow
def test_a_cell_in_the_runs_process_writes_its_intent_to_the_runs_store_before_it_moves(tmp_path):
    """Write-ahead in ``flgd train``: the decided action is in the run's store before the simulated arm moves,
    as in the daemon, although the cycle is kept by the loop."""
    seen: list[tuple[int, str]] = []
    holder: dict[str, TrainingRun] = {}

    class Watching(WrappedCell):
        """The real simulated cell, noting the run's newest action-log row whenever it is told to move."""

        def execute(self, plan):
            log = holder["run"].store.action_log()
            seen.append((int(log[-1]["step"]), str(log[-1]["outcome"])) if log else (-1, ""))
            return self.inner.execute(plan)

    run = _run(tmp_path, LocalCollector(Watching), steps=2)
    holder["run"] = run
    try:
        run.setup()
        assert run.train() == 0
    finally:
        run.close()
    moves = [m for m in seen if m[0] >= 0]   # before them: the move home as the cell starts, before any decision
    assert {step for step, _ in moves} == {0, 1} and all(outcome == "pending" for _, outcome in moves)
