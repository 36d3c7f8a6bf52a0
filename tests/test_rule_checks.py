"""A rule's decide.py, run on its recorded evaluations, reaches the decision recorded beside them: the shared pooling
(benchmarks/rule_checks.py) counts every part as each rule counted it when it decided."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"


@pytest.mark.parametrize("folder, record", [("steep-sides", "decision.json"),
                                            ("finger-clearance", "decision-2026-12-07.json"),
                                            ("steep-sides-confirm", "decision.json")])
def test_a_rules_decide_script_reproduces_its_recorded_decision(tmp_path, folder, record):
    out = tmp_path / "decision.json"
    done = subprocess.run([sys.executable, str(RESULTS / folder / "decide.py"), str(out)], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert json.loads(out.read_text()) == json.loads((RESULTS / folder / record).read_text())
    assert "chosen:" in done.stdout
