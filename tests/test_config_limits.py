"""The config loader against hostile or broken YAML: size and alias caps, long values, huge integers, merge
keys, empty files -- each one clear line, quickly, never a traceback or a hang."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from flgd.config import MAX_CONFIG_BYTES, ConfigError, load_config, parse_metrics_address

REPO = Path(__file__).resolve().parents[1]


def _problems(path: Path) -> list[str]:
    with pytest.raises(ConfigError) as err:
        load_config(path)
    return err.value.problems


def _bomb(levels: int = 9) -> str:
    """The billion-laughs document: 9 ** levels values from a dozen lines, quoted in a known key."""
    lines = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, levels + 1):
        lines.append(f"a{i}: &a{i} [" + ",".join([f"*a{i - 1}"] * 9) + "]")
    lines.append(f"name: *a{levels}")
    return "\n".join(lines) + "\n"


def _check_config_with_1_gb(path: Path) -> subprocess.CompletedProcess:
    """``flgd check-config`` in a subprocess whose address space is capped, so a loader that balloons fails
    alone instead of taking the test run with it."""
    code = ("import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30)); "
            "from flgd.check_config import main; sys.exit(main([sys.argv[1]]))")
    return subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=120,
                          cwd=REPO)


def test_an_alias_bomb_is_refused_before_it_is_expanded(tmp_path):
    cfg = tmp_path / "bomb.yaml"
    cfg.write_text(_bomb())
    p = _check_config_with_1_gb(cfg)  # before the fix: past 3 GB building the error message
    assert p.returncode == 1, p.stderr[-2000:]
    assert "Traceback" not in p.stderr
    assert "aliases" in p.stderr and "more than" in p.stderr and str(cfg) in p.stderr


def test_an_alias_that_contains_itself_is_refused(tmp_path):
    cfg = tmp_path / "loop.yaml"
    cfg.write_text("name: &a [*a]\n")
    (problem,) = _problems(cfg)
    assert "refers to the node that contains it" in problem and "line 1" in problem


def test_a_file_over_the_size_cap_is_refused_before_it_is_parsed(tmp_path):
    cfg = tmp_path / "huge.yaml"
    cfg.write_text("backend: sim\n" + "# padding\n" * (MAX_CONFIG_BYTES // 10 + 1))
    (problem,) = _problems(cfg)
    assert "KiB" in problem and f"at most {MAX_CONFIG_BYTES // 1024} KiB" in problem


def test_a_device_is_read_no_further_than_the_cap():
    p = _check_config_with_1_gb(Path("/dev/zero"))  # before the fix: read until memory ran out
    assert p.returncode == 1 and "Traceback" not in p.stderr, p.stderr[-2000:]
    assert f"more than {MAX_CONFIG_BYTES // 1024} KiB" in p.stderr


@pytest.mark.parametrize("value, shown", [
    ("x" * 100_000, "xxx"),
    ("[" + ",".join(["1"] * 3000) + "]", "[1, 1, 1"),
    ("{" + ",".join(f"k{i}: {i}" for i in range(2000)) + "}", "{'k0': 0"),
])
def test_a_long_value_is_quoted_short_in_the_error(tmp_path, value, shown):
    cfg = tmp_path / "long.yaml"
    cfg.write_text(f"backend: sim\nrobot:\n  host: {value}\n  speed: {value}\n")
    problems = _problems(cfg)
    assert any(p.startswith("robot.speed: got ") for p in problems), problems
    for p in problems:
        assert len(p) < 300, p[:400]
    assert any(shown in p for p in problems)


def test_a_long_unknown_key_is_quoted_short(tmp_path):
    cfg = tmp_path / "key.yaml"
    cfg.write_text("backend: sim\n? " + "k" * 50_000 + "\n: 1\n")  # "? key": YAML's long-key syntax
    (problem,) = _problems(cfg)
    assert "unknown key" in problem and len(problem) < 400


def test_an_integer_too_long_for_python_is_a_clear_error_not_a_traceback(tmp_path):
    cfg = tmp_path / "int.yaml"
    cfg.write_text("backend: sim\nlearning:\n  seed: " + "9" * 5000 + "\n")
    (problem,) = _problems(cfg)
    assert "line 3" in problem and "5000 characters" in problem and "too long" in problem


@pytest.mark.parametrize("key", ["seed", "batch_size"])
def test_an_integer_beyond_64_bits_is_refused_with_its_size_not_its_digits(tmp_path, key):
    cfg = tmp_path / "int.yaml"
    cfg.write_text(f"backend: sim\nlearning:\n  {key}: " + "9" * 400 + "\n")
    (problem,) = _problems(cfg)
    assert problem.startswith(f"learning.{key}: got an integer of 400 digits")
    assert "64-bit" in problem


def test_merge_keys_work_and_explicit_keys_override_them(tmp_path):
    cfg = tmp_path / "merge.yaml"
    cfg.write_text("backend: sim\nrobot:\n  home: &h {position: [-0.45, 0.30, 0.30], yaw: 0.0}\n"
                   "  place:\n    <<: *h\n    yaw: 0.5\n")
    c = load_config(cfg)
    assert c.robot.place.position == (-0.45, 0.30, 0.30) and c.robot.place.yaw == 0.5


def test_a_duplicate_explicit_key_beside_a_merge_is_still_refused(tmp_path):
    cfg = tmp_path / "merge.yaml"
    cfg.write_text("backend: sim\nrobot:\n  home: &h {position: [-0.45, 0.30, 0.30], yaw: 0.0}\n"
                   "  place:\n    <<: *h\n    yaw: 0.5\n    yaw: 0.6\n")
    (problem,) = _problems(cfg)
    assert "duplicate key 'yaw'" in problem and "line 7" in problem


@pytest.mark.parametrize("text", ["", "# only a comment\n", "---\n"])
def test_an_empty_config_file_is_refused(tmp_path, text):
    cfg = tmp_path / "empty.yaml"
    cfg.write_text(text)
    (problem,) = _problems(cfg)
    assert "empty" in problem and "state_dir" in problem
    p = subprocess.run([sys.executable, "-m", "flgd.cli", "check-config", str(cfg)], capture_output=True,
                       text=True, timeout=60, cwd=REPO)
    assert p.returncode == 1 and str(cfg) in p.stderr and "empty" in p.stderr


@pytest.mark.parametrize("value, ok", [
    ("127.0.0.1:9808", True), ("[::1]:0", True), ("localhost:1", True), ("", True), ("9808", True),
    ("98080", False), ("127.0.0.1:", False), (":9808", False), ("127.0.0.1:70000", False),
    ("::1:9808", False), ("host name:1", False), ("127.0.0.1:-1", False),
])
def test_the_metrics_address_is_validated(tmp_path, value, ok):
    cfg = tmp_path / "m.yaml"
    cfg.write_text(f"backend: sim\nmetrics: '{value}'\n")
    if ok:
        assert load_config(cfg).metrics == value
    else:
        (problem,) = _problems(cfg)
        assert problem.startswith("metrics: got ") and "expected HOST:PORT" in problem


def test_a_bare_metrics_port_binds_the_loopback_only():
    assert parse_metrics_address("9808") == ("127.0.0.1", 9808)
    assert parse_metrics_address("0") == ("127.0.0.1", 0)


def test_a_nul_character_in_a_path_is_a_config_problem_not_an_internal_error(tmp_path):
    cfg = tmp_path / "nul.yaml"
    cfg.write_text('backend: sim\npolicy: "/var/lib/flgd/a\\0b.flgp"\n')
    (problem,) = _problems(cfg)
    assert problem.startswith("policy: got ") and "NUL character" in problem


def test_check_config_into_a_pipe_closed_early_prints_no_traceback():
    # the reader takes one line and goes away; the rest of the config printout meets a closed pipe
    p = subprocess.run(f"{sys.executable} -m flgd.cli check-config cell_config/sim.yaml | head -c 10 >/dev/null",
                       shell=True, capture_output=True, text=True, timeout=60, cwd=REPO)
    assert "Traceback" not in p.stderr and "BrokenPipeError" not in p.stderr, p.stderr


# --------------------------------------------------------------------------- config loading: bad input is a clear error

def _load(tmp_path: Path, text: str):
    path = tmp_path / "cell.yaml"
    path.write_text(text)
    return load_config(path), path


@pytest.mark.parametrize("text, expect", [
    ("? [a, b]\n: 1\n", "cannot be a key"),                               # was TypeError: unhashable
    ("camera:\n  depth_scale: " + "1" * 400 + "\n", "camera.depth_scale"),  # was OverflowError
    ("[" * 5000 + "]" * 5000 + "\n", "nested too deeply"),               # was RecursionError
    ("camera:\n  serial: 819612070593\n", "quote the value"),
])
def test_malformed_config_is_a_config_error_naming_the_file(tmp_path, text, expect):
    with pytest.raises(ConfigError) as info:
        _load(tmp_path, text)
    assert str(tmp_path / "cell.yaml") in str(info.value) and expect in str(info.value)
