"""Cell config loading and `flgd check-config`."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from flgd.config import CellConfig, ConfigError, config_from_dict, config_to_dict, load_config

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = sorted((ROOT / "cell_config").glob("*.yaml"))
FLGD = Path(sys.executable).parent / "flgd"


def run_check(path: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(FLGD), "check-config", str(path)], capture_output=True, text=True, timeout=60)


def test_there_are_shipped_configs() -> None:
    names = {p.name for p in SHIPPED}
    assert {"sim.yaml", "ur5e-d415.yaml"} <= names


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_check_config_passes_on_shipped_configs(path: Path) -> None:
    result = run_check(path)
    assert result.returncode == 0, result.stderr
    assert "OK" in result.stdout
    # What is printed is the effective config, and it loads back to the same thing.
    printed = yaml.safe_load(result.stdout)
    cfg = load_config(path)
    assert printed == config_to_dict(cfg)
    assert config_from_dict(printed, "printed") == config_from_dict(config_to_dict(cfg), "printed")


def test_defaults_match_the_paper_resolution() -> None:
    cfg = load_config(ROOT / "cell_config" / "sim.yaml")
    assert cfg.workspace.shape == (224, 224) and cfg.workspace.resolution == 0.002
    assert isinstance(cfg, CellConfig) and cfg.exploration.top_m == 10 and cfg.learning.gamma == 0.5


def base() -> dict:
    return yaml.safe_load((ROOT / "cell_config" / "sim.yaml").read_text())


def with_change(path: str, value) -> dict:
    data = base()
    node = data
    keys = path.split(".")
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    node[keys[-1]] = value
    return data


BROKEN = {
    "unknown key with suggestion": (with_change("workspace.resolutoin", 0.002),
                                    ["workspace.resolutoin", "unknown key", "did you mean 'resolution'"]),
    "unknown section": (with_change("rewrads", {"delta": 0.01}), ["rewrads", "did you mean 'rewards'"]),
    "wrong type": (with_change("robot.speed", "fast"), ["robot.speed", "'fast'", "number"]),
    "negative resolution": (with_change("workspace.resolution", -0.002),
                            ["workspace.resolution", "-0.002", "> 0.0", "m/px"]),
    "workspace min > max": (with_change("workspace.x", [-0.2, -0.7]), ["workspace.x", "min < max"]),
    "list of wrong length": (with_change("camera.pose.position", [0.1, 0.2]),
                             ["camera.pose.position", "a list of 3"]),
    "bool for number": (with_change("rewards.tau1", True), ["rewards.tau1", "True", "integer"]),
    "bad enum": (with_change("gripper.driver", "robotiq"), ["gripper.driver", "'robotiq'", "'rg2_xmlrpc'"]),
    "speed above the safety cap": (with_change("robot.speed", 2.0), ["robot.speed", "safety.max_speed"]),
    "raise speed above the safety cap": (with_change("robot.raise_speed", 2.0), ["robot.raise_speed",
                                                                                 "safety.max_speed"]),
    "workspace outside the envelope": (with_change("safety.envelope_x", [-0.6, -0.2]),
                                       ["workspace.x", "safety.envelope_x"]),
    "home outside the envelope": (with_change("robot.home", {"position": [0.5, 0.0, 0.3], "yaw": 0.0}),
                                  ["robot.home.position", "x = 0.5"]),
    "home over the workspace": (with_change("robot.home", {"position": [-0.5, 0.1, 0.3], "yaw": 0.0}),
                                ["robot.home.position", "over the workspace", "in every heightmap"]),
    "resolution not dividing": (with_change("workspace.resolution", 0.0031), ["workspace.resolution", "whole pixels"]),
    "nan value": (with_change("rewards.delta", float("nan")), ["rewards.delta", "finite"]),
    "epsilon out of range": (with_change("exploration.epsilon_start", 1.5), ["exploration.epsilon_start", "<= 1.0"]),
    "section not a mapping": (with_change("camera", [1, 2, 3]), ["camera", "a mapping"]),
}


@pytest.mark.parametrize("name", sorted(BROKEN))
def test_broken_configs_are_refused_with_a_clear_message(name: str, tmp_path: Path) -> None:
    data, needles = BROKEN[name]
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    result = run_check(path)
    assert result.returncode != 0
    assert str(path) in result.stderr
    for needle in needles:
        assert needle in result.stderr, f"{needle!r} missing from:\n{result.stderr}"
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize("text,needle", [
    ("workspace: [1, 2\n", "invalid YAML at line"),
    ("- just\n- a list\n", "expected a mapping"),
    ("robot: {speed: }\n", "robot.speed"),
    ("backend: sim\nsafety:\n  max_speed: 0.1\n  max_speed: 3.0\n", "duplicate key 'max_speed'"),
])
def test_malformed_files(text: str, needle: str, tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    result = run_check(path)
    assert result.returncode != 0 and needle in result.stderr and "Traceback" not in result.stderr


def test_missing_file_and_directory(tmp_path: Path) -> None:
    missing = run_check(tmp_path / "nope.yaml")
    assert missing.returncode != 0 and "nope.yaml" in missing.stderr and "file not found" in missing.stderr
    a_dir = run_check(tmp_path)
    assert a_dir.returncode != 0 and "directory" in a_dir.stderr


def test_all_problems_are_reported_at_once() -> None:
    data = with_change("robot.speed", "fast")
    data["workspace"]["resolution"] = -1
    with pytest.raises(ConfigError) as info:
        config_from_dict(data, "x.yaml")
    assert len(info.value.problems) == 2


def test_relative_state_dir_is_relative_to_the_config_file(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "cell.yaml"
    path.parent.mkdir()
    path.write_text(yaml.safe_dump(with_change("state_dir", "state")))
    assert load_config(path).state_dir == str((tmp_path / "sub" / "state").resolve())


def test_exponent_floats_without_a_dot_are_numbers(tmp_path: Path) -> None:
    """PyYAML (YAML 1.1) reads 5e-4 as a string; the config loader reads it as YAML 1.2 does."""
    path = tmp_path / "cell.yaml"
    path.write_text("learning:\n  learning_rate: 5e-4\n  weight_decay: 1E-5\nrobot:\n  descent_contact_force: +2e1\n")
    cfg = load_config(path)
    assert cfg.learning.learning_rate == 5e-4 and cfg.learning.weight_decay == 1e-5
    assert cfg.robot.descent_contact_force == 20.0
    # an integer key given as an exponent float is refused with the key named, not silently truncated
    path.write_text("learning:\n  batch_size: 4e0\n")
    with pytest.raises(ConfigError, match="learning.batch_size"):
        load_config(path)
    # the resolver is the loader's own: plain PyYAML still reads a string
    assert yaml.safe_load("x: 5e-4")["x"] == "5e-4"


def test_a_given_policy_fine_tunes_with_the_finetune_settings_and_no_policy_trains_with_learning() -> None:
    from flgd.config import fine_tunes, learner_settings

    cfg = load_config(ROOT / "cell_config" / "sim.yaml")
    tuned, why = fine_tunes(cfg)
    assert tuned and "finetune" in why
    ft = learner_settings(cfg, True).learning
    assert (ft.learning_rate, ft.updates_per_action, ft.batchnorm, ft.min_replay) == (
        cfg.finetune.learning_rate, cfg.finetune.updates_per_action, cfg.finetune.batchnorm, cfg.finetune.min_replay)
    anchored = dataclasses.replace(cfg, finetune=dataclasses.replace(cfg.finetune, anchor_weight=0.3))
    assert learner_settings(anchored, True).learning.anchor_weight == 0.3
    assert learner_settings(anchored, False).learning.anchor_weight == cfg.learning.anchor_weight
    assert ft.learning_rate != cfg.learning.learning_rate and ft.updates_per_action != cfg.learning.updates_per_action
    # training's cheaper target (a' from the acting decision, one twin) is not a fine-tune's unless it says so
    assert (cfg.learning.actor_argmax, cfg.learning.grasp_twins) == (True, "one")
    assert (ft.actor_argmax, ft.grasp_twins) == (False, "both")
    scratch = config_from_dict({"policy": ""})
    assert not fine_tunes(scratch)[0] and learner_settings(scratch, False) is scratch


def test_check_config_says_which_learner_settings_apply() -> None:
    out = run_check(ROOT / "cell_config" / "sim.yaml")
    assert out.returncode == 0, out.stderr
    assert "learner settings that apply in flgd run and flgd eval --learn: finetune" in out.stdout
    assert "# gate on" in out.stdout


@pytest.mark.parametrize("data, needle", [
    ({"gate": {"share": 1.5}}, "gate.share"),
    ({"gate": {"min_attempts": 900, "max_attempts": 800}}, "gate.min_attempts: got 900, expected <= gate.max_attempts"),
    ({"finetune": {"batchnorm": "moving"}}, "finetune.batchnorm"),
    ({"finetune": {"max_epsilon": -0.1}}, "finetune.max_epsilon"),
    ({"finetune": {"anchor_weight": -1}}, "finetune.anchor_weight"),
    ({"gate": {"handover_evry": 3}}, "handover_evry"),
])
def test_gate_and_finetune_keys_are_checked(data: dict, needle: str) -> None:
    with pytest.raises(ConfigError, match=needle.replace(".", r"\.")):
        config_from_dict(data)


def test_a_config_without_a_gate_section_gets_the_shipped_gate(tmp_path):
    shipped = load_config(Path(__file__).resolve().parents[1] / "cell_config" / "sim.yaml").gate
    bare = tmp_path / "bare.yaml"
    bare.write_text("backend: sim\n")
    assert load_config(bare).gate == shipped


def test_validating_a_backend_imports_no_cell_safety_or_plans_module() -> None:
    """The config is the bottom layer: checking ``backend:`` and ``gripper.driver`` reads the backend names from
    the leaf ``flgd.backends``, never from the cell registry (which imports safety, plans and the config)."""
    script = ("import sys, flgd.config as c\n"
              "c.config_from_dict({'backend': 'ur5e', 'gripper': {'driver': 'rg2_xmlrpc'}})\n"
              "try:\n"
              "    c.config_from_dict({'backend': 'ur5', 'gripper': {'driver': 'sim'}})\n"
              "except c.ConfigError as exc:\n"
              "    print(exc.problems[0])\n"
              "print(sorted(m for m in ('flgd.cell', 'flgd.safety', 'flgd.plans') if m in sys.modules))\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == [
        "backend: got 'ur5', expected one of 'sim', 'ur5e'; did you mean 'ur5e'?", "[]"]
