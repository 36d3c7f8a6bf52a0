"""The benches' worker commands as Ray tasks (``flgd bench finetune --jobs N``): every command runs, its exit code
and its log come back."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("ray")

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow  # starts a Ray cluster


def test_commands_run_as_ray_tasks_with_their_exit_codes_and_logs(tmp_path):
    from benchmarks._daemon_runs import run_workers

    bad = tmp_path / "bad.yaml"
    bad.write_text("backend: sim\nlearning: {updates_per_action: -3}\n")
    jobs = [("good", ["check-config", str(REPO / "cell_config" / "sim.yaml")]),
            ("bad", ["check-config", str(bad)]),
            ("also-good", ["check-config", str(REPO / "cell_config" / "sim-shifted.yaml")])]
    codes = run_workers(jobs, tmp_path / "logs", 2, ray=True)
    assert codes["good"] == 0 and codes["also-good"] == 0 and codes["bad"] != 0
    assert "OK" in (tmp_path / "logs" / "good.log").read_text()
    assert "updates_per_action" in (tmp_path / "logs" / "bad.log").read_text()
