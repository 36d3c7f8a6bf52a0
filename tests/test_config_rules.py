"""The config's cross-key rules (flgd/config/rules.py): envelope, home and place poses, backends and their
gripper drivers, the learner's device; each problem named in one message."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest
import torch
import yaml

from flgd.config import ConfigError, config_from_dict, load_config
from flgd.learning.learner import resolve_device

REPO = Path(__file__).resolve().parents[1]
SIM = REPO / "cell_config" / "sim.yaml"

pytestmark = pytest.mark.usefixtures("one_torch_thread")


# --------------------------------------------------------------------------- cross-key config checks

def sim_data() -> dict:
    return yaml.safe_load(SIM.read_text())


def problems_of(data: dict) -> list[str]:
    with pytest.raises(ConfigError) as err:
        config_from_dict(data, "cell.yaml")
    return err.value.problems


def test_workspace_top_must_lie_inside_the_envelope():
    data = sim_data()
    data["workspace"]["z"] = [0.0, 0.9]
    (p,) = problems_of(data)
    assert p.startswith("workspace.z:") and "0.9" in p and "safety.envelope_z" in p and "0.45" in p


@pytest.mark.parametrize("pose", ["home", "place"])
def test_home_and_place_must_clear_the_table_floor(pose):
    data = sim_data()
    data["robot"][pose]["position"][2] = 0.002  # inside envelope_z [0, 0.45], below 0 + 0.004
    (p,) = problems_of(data)
    assert p.startswith(f"robot.{pose}.position:") and "0.002" in p and "clearance floor" in p \
        and "safety.min_table_clearance" in p


def test_home_and_place_have_no_tilt_to_configure():
    data = sim_data()
    data["robot"]["home"]["rpy"] = [0.3, 0.0, 0.0]
    (p,) = problems_of(data)
    assert p.startswith("robot.home.rpy: unknown key")


def test_unknown_backend_is_a_config_error_with_a_suggestion():
    data = sim_data()
    data["backend"] = "ur5"
    problems = problems_of(data)
    assert any(p.startswith("backend: got 'ur5'") and "'sim'" in p and "did you mean 'ur5e'" in p
               for p in problems), problems


def test_a_gripper_driver_the_backend_cannot_drive_is_a_config_error():
    data = yaml.safe_load((REPO / "cell_config" / "ur5e-d415.yaml").read_text())
    data["gripper"]["driver"] = "sim"
    (p,) = problems_of(data)
    assert p.startswith("gripper.driver: got 'sim'") and "'rg2_xmlrpc'" in p and "backend 'ur5e'" in p


@pytest.mark.parametrize("gap", [0.002, 0.1])
def test_a_release_gap_within_the_pads_give_or_past_the_stroke_is_a_config_error(gap):
    data = yaml.safe_load((REPO / "cell_config" / "ur5e-d415.yaml").read_text())
    data["gripper"]["release_gap"] = gap
    (p,) = problems_of(data)
    assert p.startswith(f"gripper.release_gap: got {gap!r}") and "0.005" in p
    data["gripper"]["release_gap"] = 0.0   # wait until open
    config_from_dict(data, "cell.yaml")


def test_a_preshape_on_a_gripper_that_only_opens_and_closes_is_a_config_error():
    data = yaml.safe_load((REPO / "cell_config" / "ur5e-d415.yaml").read_text())
    data["gripper"]["preshape_margin"] = 0.01
    config_from_dict(data, "cell.yaml")   # the RG2's XML-RPC driver sets any opening
    data["gripper"]["driver"] = "tool_digital_output"
    (p,) = problems_of(data)
    assert p.startswith("gripper.preshape_margin: got 0.01 m with gripper.driver tool_digital_output")


def test_the_simulator_accepts_a_real_driver_so_a_real_config_can_swap_to_sim():
    data = sim_data()
    data["gripper"]["driver"] = "rg2_xmlrpc"
    config_from_dict(data, "cell.yaml")


def test_check_config_reports_the_new_problems(tmp_path, capsys):
    from flgd.check_config import main

    data = sim_data()
    data["workspace"]["z"] = [0.0, 0.9]
    data["backend"] = "nope"
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    assert main([str(path)]) == 1
    err = capsys.readouterr().err
    assert str(path) in err and "workspace.z" in err and "backend: got 'nope'" in err


def test_cuda_on_a_machine_without_cuda_is_a_config_error(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    data = sim_data()
    data["learning"]["device"] = "cuda"
    (p,) = problems_of(data)
    assert p.startswith("learning.device: got 'cuda'") and "no CUDA device" in p and "'cpu' or 'auto'" in p
    with pytest.raises(ConfigError, match="learning.device"):
        resolve_device("cuda", "cell.yaml")


@pytest.fixture
def keep_logging():
    """``flgd run`` in-process replaces the root log handlers with one on this test's (soon closed) stderr."""
    import logging

    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


def _cuda_config(tmp_path: Path) -> Path:
    data = sim_data()
    data["learning"]["device"] = "cuda"
    data["learning"]["init_trunk"] = ""
    data["policy"] = ""
    data["state_dir"] = str(tmp_path / "state")
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_flgd_run_with_cuda_but_no_cuda_exits_1_with_a_clear_message(tmp_path, monkeypatch, capsys, keep_logging):
    from flgd.daemon import run

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    path = _cuda_config(tmp_path)
    assert run.main(["--config", str(path), "--socket", str(tmp_path / "s.sock"), "--no-status-line"]) == 1
    err = capsys.readouterr().err
    assert str(path) in err and "learning.device" in err and "Traceback" not in err


def test_a_device_error_found_only_at_learner_construction_is_still_a_clear_exit_1(tmp_path, monkeypatch,
                                                                                  capsys, keep_logging):
    """Defence in depth: should the config check be bypassed, the learner's error is a ConfigError that
    ``flgd run`` reports (not a traceback) before anything moves."""
    import flgd.config.rules as config_rules
    from flgd.daemon import run

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(config_rules, "_check_device", lambda cfg, problems: None)
    path = _cuda_config(tmp_path)
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    assert run.main(["--config", str(path), "--socket", str(tmp_path / "s.sock"), "--no-status-line"]) == 1
    err = capsys.readouterr().err
    assert "learning.device" in err and "no CUDA device" in err and "Traceback" not in err
    assert not (tmp_path / "s.sock").exists()
    assert {sig: signal.getsignal(sig) for sig in before} == before


def test_shipped_configs_still_pass():
    for path in sorted((REPO / "cell_config").glob("*.yaml")):
        load_config(path)


# --------------------------------------------------------------------------- the arm's reach (flgd/config/reach.py)

def _moved_out(data: dict, dx: float) -> dict:
    """The sim cell with workspace, envelope, home and place all moved ``dx`` further from the base in x
    (every box check still holds: the mistake only the reach can catch)."""
    data["workspace"]["x"] = [round(v - dx, 3) for v in data["workspace"]["x"]]
    data["safety"]["envelope_x"] = [round(v - dx, 3) for v in data["safety"]["envelope_x"]]
    for pose in ("home", "place"):
        data["robot"][pose]["position"][0] = round(data["robot"][pose]["position"][0] - dx, 3)
    return data


@pytest.mark.parametrize("backend", ["sim", "ur5e"])
def test_a_workspace_2_4_to_3_1_m_from_the_base_is_out_of_the_ur5es_reach(backend):
    data = _moved_out(sim_data(), 2.3)  # workspace x [-3.024, -2.576]: 2.6-3.0 m from the base
    if backend == "ur5e":
        data["backend"] = "ur5e"
        data.setdefault("gripper", {})["driver"] = "rg2_xmlrpc"
    problems = problems_of(data)
    assert len(problems) == 4, problems
    ws, env, home, place = problems
    assert ws.startswith("workspace:") and "-3.024" in ws and "reach of 0.85 m" in ws and "UR5e" in ws
    assert env.startswith("safety.envelope:") and "-3.08" in env and "no point of the envelope" in env
    assert home.startswith("robot.home.position:") and "-2.75" in home and "reach of 0.85 m" in home
    assert place.startswith("robot.place.position:") and "-2.8" in place


def test_one_far_workspace_corner_is_named_and_the_shipped_configs_are_within_reach():
    data = sim_data()
    data["workspace"]["y"] = [-0.524, 0.224]  # the far corner (x -0.724, y -0.524) is 0.89 m out
    data["safety"]["envelope_y"] = [-0.60, 0.40]
    (p,) = problems_of(data)
    assert p.startswith("workspace:") and "y -0.524" in p and "0.89 m away" in p
    for path in sorted((REPO / "cell_config").glob("*.yaml")):
        load_config(path)  # raises ConfigError if any part were out of reach
