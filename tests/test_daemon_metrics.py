"""``flgd run --metrics``: a running sim daemon scraped on loopback; the numbers are flgctl's."""

from __future__ import annotations

import re
import socket
import subprocess
import sys
import urllib.request

import pytest
from prometheus_client.parser import text_string_to_metric_families

from flgd.daemon.metrics import PhaseHistograms
from tests.fakes.daemon import REPO, write_config


def _scrape(port: int) -> dict[str, list]:
    """metric family name -> its samples, parsed from the text format by the client library's own parser."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=30) as r:
        assert r.status == 200
        text = r.read().decode()
    return {fam.name: fam.samples for fam in text_string_to_metric_families(text)}


def _value(families: dict, name: str, **labels: str) -> float:
    """The value of the sample ``name`` with ``labels`` (a counter's family is named without ``_total``)."""
    for samples in families.values():
        for sample in samples:
            if sample.name == name and all(sample.labels.get(k) == v for k, v in labels.items()):
                return sample.value
    raise KeyError(f"{name} {labels}")


@pytest.mark.slow
def test_a_scrape_of_a_running_daemon_agrees_with_flgctl(daemon_factory):
    d = daemon_factory(args=["--autostart", "--metrics", "127.0.0.1:0"]).start().wait_ready()
    port = int(re.search(r"metrics: serving http://127\.0\.0\.1:(\d+)/metrics", d.log()).group(1))
    d.wait_for(lambda s: s["cycles"] >= 4, "4 cycles")
    d.ok("pause")
    status = d.wait_for(lambda s: s["state"] == "PAUSED" and not s["cycle_in_flight"], "the cycle to finish")
    stats = d.ok("stats")
    m = _scrape(port)

    assert _value(m, "flgd_state", state="PAUSED") == 1
    assert sum(_value(m, "flgd_state", state=s) for s in ("STARTING", "IDLE", "RUNNING", "FAULT", "STOPPING")) == 0
    assert _value(m, "flgd_cycles_total") == stats["cycles"] == status["cycles"]
    assert _value(m, "flgd_grasp_attempts_total") == stats["grasp_attempts"]
    assert _value(m, "flgd_grasp_successes_total") == stats["grasp_successes"]
    assert _value(m, "flgd_grasp_success_ratio", window="50") == stats["grasp_success_last_50"]
    assert _value(m, "flgd_picks_per_hour") == stats["picks_per_hour"]
    for part in ("motion", "gripper", "waiting"):
        assert _value(m, "flgd_cycle_split_seconds", part=part) == stats["timing_median"][part]
    assert _value(m, "flgd_decide_hidden_ratio") == stats["decide_hidden_share"]
    for kind in ("push", "shift"):
        assert _value(m, "flgd_moves_total", kind=kind) == stats["moves"][kind]
    assert _value(m, "flgd_plans_refused_total") == stats["plans_refused"]
    assert _value(m, "flgd_frames_refused_total") == stats["frames_refused"]
    assert sum(s.value for s in m["flgd_faults"] if s.name == "flgd_faults_total") == stats["faults"]
    assert _value(m, "flgd_learner_updates_total") >= status["learner_updates"]  # the learner goes on
    assert "flgd_learner_backlog" in m and "flgd_learner_dropped_updates" in m and "flgd_learner_skipped_updates" in m
    assert _value(m, "flgd_policy_info", source=status["policy"]) == 1
    assert _value(m, "flgd_cell_info", backend="sim") == 1
    gate = status["gate"]
    assert _value(m, "flgd_gate_enabled") == 1
    assert _value(m, "flgd_gate_policy_id", role="champion") == gate["champion"]["id"]
    assert _value(m, "flgd_gate_actions_total", role="champion") == gate["champion"]["live"]["actions"]
    # every phase's histogram counts each logged cycle but the newest (whose store time comes later)
    for phase in PhaseHistograms.PHASES:
        count = _value(m, "flgd_cycle_phase_seconds_count", phase=phase)
        assert count == stats["cycles"] - 1, phase
        assert _value(m, "flgd_cycle_phase_seconds_bucket", phase=phase, le="+Inf") == count
    cycle_sum = _value(m, "flgd_cycle_phase_seconds_sum", phase="cycle")
    assert 0 < cycle_sum <= stats["cycle_time_total"]
    assert _value(m, "process_resident_memory_bytes") > 0

    d.ok("stop")
    assert d.wait_exit() == 0


@pytest.mark.slow
def test_metrics_are_off_unless_asked_for(daemon_factory):
    d = daemon_factory().start().wait_ready()
    assert "metrics: serving" not in d.log()
    d.ok("stop")
    assert d.wait_exit() == 0


def test_a_metrics_port_in_use_is_refused_before_the_cell_or_the_state_directory(tmp_path):
    taken = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    taken.bind(("127.0.0.1", 0))
    taken.listen(1)
    try:
        port = taken.getsockname()[1]
        cfg = write_config(tmp_path, tmp_path / "state")
        p = subprocess.run([sys.executable, "-m", "flgd.cli", "run", "--config", str(cfg), "--no-status-line",
                            "--metrics", f"127.0.0.1:{port}", "--socket", str(tmp_path / "s.sock")],
                           capture_output=True, text=True, cwd=REPO, timeout=120)
    finally:
        taken.close()
    assert p.returncode == 1
    assert f"metrics: cannot listen on 127.0.0.1:{port}" in p.stderr, p.stderr
    assert not (tmp_path / "state").exists() and not (tmp_path / "s.sock").exists()

