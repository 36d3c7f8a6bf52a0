"""``flgd train`` end to end on the real simulated cell: outputs, resume, Ctrl-C, reproducibility."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from flgd.cell import Cell, CellFault
from flgd.config import load_config
from flgd.learning.policy_file import load_policy
from flgd.store import Store
from flgd.training.actions_csv import read_rows
from flgd.training.command import main as train_main

from tests.fakes.wrapped_cell import WrappedCell

REPO = Path(__file__).resolve().parents[1]
CONFIG = str(REPO / "cell_config" / "sim.yaml")
U = yaml.safe_load(Path(CONFIG).read_text())["learning"]["updates_per_action"]  # sim.yaml's, run synchronously
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

pytestmark = pytest.mark.slow  # most tests here start a training run


def _train(out: Path, *extra: str) -> int:
    return train_main(["--config", CONFIG, "--out", str(out), "--threads", "1", *extra])


def _checkpoints(out: Path) -> list[Path]:
    return sorted((out / "checkpoints").glob("checkpoint-*.safetensors"))


def _config_variant(tmp_path: Path, name: str, policy: str = "", **sections: dict) -> str:
    """sim.yaml with some keys changed, written beside the test's state dir; its paths made absolute."""
    cfg = yaml.safe_load(Path(CONFIG).read_text())
    for section, values in sections.items():
        cfg[section].update(values)
    cfg["policy"] = policy
    cfg["state_dir"] = str(tmp_path / "state")
    if cfg["learning"].get("init_trunk"):   # sim.yaml's trunk path is relative to it
        cfg["learning"]["init_trunk"] = load_config(CONFIG).learning.init_trunk
    config = tmp_path / f"{name}.yaml"
    config.write_text(yaml.safe_dump(cfg))
    return str(config)


def test_a_short_run_writes_log_checkpoint_and_curve_then_resumes(tmp_path, monkeypatch):
    out = tmp_path / "run"
    assert _train(out, "--steps", "3", "--seed", "5") == 0

    rows = read_rows(out / "actions.csv")
    assert [int(r["step"]) for r in rows] == [0, 1, 2]
    for r in rows:
        assert r["outcome"] in ("executed", "refused")
        assert r["primitive"] in ("grasp", "push", "shift")
        assert float(r["epsilon"]) > 0 and r["rule"]
        assert int(r["objects_left"]) >= 0 and r["scene_kind"] == "random 10"
        assert float(r["t_update"]) > 0 and float(r["duration"]) > 0
    assert U >= 1 and [int(r["updates"]) for r in rows] == [U, 2 * U, 3 * U]

    ckpts = _checkpoints(out)
    assert [c.name for c in ckpts] == [f"checkpoint-{3 * U:010d}.safetensors"]
    policy = load_policy(ckpts[0], expected_variant="fast")
    assert policy.metadata["training_steps"] == 3
    assert policy.metadata["train_variant"] == "flg" and policy.metadata["method"] == "FLG"
    assert policy.metadata["seed"] == 5 and policy.metadata["learner_updates"] == 3 * U
    assert (out / "curve.png").read_bytes()[:8] == PNG_MAGIC
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "finished" and info["step"] == 3 and info["settings"]["seed"] == 5

    # resume: same directory, higher target; the settings come from run.json
    assert train_main(["--out", str(out), "--steps", "5", "--threads", "1"]) == 0
    rows = read_rows(out / "actions.csv")
    assert [int(r["step"]) for r in rows] == [0, 1, 2, 3, 4]
    # the learner's count continues too: U more per action, none for an action the simulator discarded
    expected, count = [], 3 * U
    for r in rows[3:]:
        count += 0 if r["outcome"] == "discarded" else U
        expected.append(count)
    assert rows[3]["outcome"] != "discarded" and [int(r["updates"]) for r in rows[3:]] == expected
    info = json.loads((out / "run.json").read_text())
    assert [s["from_step"] for s in info["segments"]] == [0, 3]
    assert info["segments"][1]["from_updates"] == 3 * U
    assert f"checkpoint-{3 * U:010d}" in info["segments"][1]["source"]
    assert info["segments"][1]["code"] not in ("", None)
    assert info["segments"][1]["learning"]["updates_per_action"] == U
    assert info["segments"][0]["exploration"]["epsilon_start"] == 0.5
    assert info["segments"][0]["objects"]["object_set"] == "blocks"
    store = Store(out)
    try:
        kept = sum(r["outcome"] != "discarded" for r in rows)
        assert kept >= 4 and store.transition_count() == kept  # the first segment's replay, kept and extended
        assert store.next_step() == 5
    finally:
        store.close()
    assert _checkpoints(out)[-1].name == f"checkpoint-{expected[-1]:010d}.safetensors"

    # other settings for an existing run directory are refused, naming the flag
    assert train_main(["--out", str(out), "--variant", "dpen"]) == 2

    # shipping a checkpoint: a byte copy that loads, its metadata JSON and curve
    from flgd.training.export import export_policy

    dest = tmp_path / "policies" / "p.safetensors"
    info = export_policy(out, dest, "latest")
    assert dest.read_bytes() == _checkpoints(out)[-1].read_bytes()
    assert load_policy(dest).metadata["training_steps"] == 5
    saved = json.loads((tmp_path / "policies" / "p.json").read_text())
    assert saved == json.loads(json.dumps(info)) and saved["run_settings"]["seed"] == 5
    assert saved["resume_command"] == f"flgd train --out {out}"
    assert (tmp_path / "policies" / "p-curve.png").read_bytes()[:8] == PNG_MAGIC
    # the run named as the command line named it: an export committed beside its run names no machine's paths
    from flgd.training.export import main as export_main

    monkeypatch.chdir(tmp_path)
    assert export_main(["run", "policies/q.safetensors"]) == 0
    named = json.loads((tmp_path / "policies" / "q.json").read_text())
    assert named["exported_from"] == f"run/checkpoints/{_checkpoints(out)[-1].name}"
    assert named["resume_command"] == "flgd train --out run"


def test_cached_next_argmax_and_several_updates_per_action_in_a_real_run(tmp_path):
    """The agent's decisions feed the learner's a' cache through the cycle; the run reports its use."""
    config = _config_variant(tmp_path, "sim-cached",   # from scratch, from sim.yaml's pre-trained trunk
                             learning={"next_argmax_max_age": 100, "updates_per_action": 2, "batch_size": 2})
    out = tmp_path / "run"
    assert train_main(["--config", config, "--out", str(out), "--threads", "1", "--steps", "4",
                       "--seed", "3"]) == 0
    rows = read_rows(out / "actions.csv")
    assert [int(r["updates"]) for r in rows] == [2, 4, 6, 8]
    info = json.loads((out / "run.json").read_text())
    used = info["next_argmax"]
    assert used["reused"] > 0  # s' of the newest transition was decided on before it was sampled
    assert used["reused"] + used["computed"] <= 8 * 2  # at most one a' per sampled non-terminal transition


def _strings(data: object) -> list[str]:
    """Every string value in a parsed YAML document."""
    if isinstance(data, dict):
        return [s for v in data.values() for s in _strings(v)]
    if isinstance(data, list):
        return [s for v in data for s in _strings(v)]
    return [data] if isinstance(data, str) else []


def test_the_actor_argmax_recipe_runs_is_carried_compactly_and_resumes_elsewhere(tmp_path):
    """A few actions of the cheaper recipe (a' from the cell's decisions, never recomputed; 3 updates per
    action), then ``flgd.training.carry`` to a small directory that ``flgd train --out`` continues."""
    from flgd.training.carry import carry_run

    config = _config_variant(tmp_path, "sim-actor", learning={"actor_argmax": True, "updates_per_action": 3,
                                                              "checkpoint_every": 3})
    out = tmp_path / "run"
    assert train_main(["--config", config, "--out", str(out), "--threads", "1", "--steps", "4",
                       "--seed", "3"]) == 0
    info = json.loads((out / "run.json").read_text())
    assert info["segments"][0]["learning"]["actor_argmax"] is True
    assert info["next_argmax"]["reused"] > 0

    carried = carry_run(out, tmp_path / "carried", replay=2)
    assert (carried.updates, carried.transitions) == (12, 2)
    assert [p.name for p in (tmp_path / "carried" / "checkpoints").iterdir()] == [carried.checkpoint]
    assert sorted(p.name for p in (tmp_path / "carried").iterdir()) == sorted(
        ["actions.csv", "checkpoints", "config.yaml", "curve.png", "flgd.sqlite", "run.json",
         "trainer-state.safetensors"])
    with pytest.raises(FileExistsError):
        carry_run(out, tmp_path / "carried")

    dest = tmp_path / "carried"
    # its config names files relative to the copy, not the paths of the machine the run started on
    for run in (out, dest):
        run_config = yaml.safe_load((run / "config.yaml").read_text())
        assert [v for v in _strings(run_config) if str(tmp_path) in v or v.startswith("/")] == []
        assert run_config["state_dir"] == "."
    assert load_config(dest / "config.yaml").learning.init_trunk == load_config(CONFIG).learning.init_trunk
    assert dataclasses.replace(load_config(dest / "config.yaml"), source="") == dataclasses.replace(
        load_config(out / "config.yaml"), state_dir=str(dest), source="")   # the same settings, read there
    assert train_main(["--out", str(dest), "--steps", "6"]) == 0
    assert yaml.safe_load((dest / "config.yaml").read_text())["state_dir"] == "."   # still no machine's paths
    rows = read_rows(dest / "actions.csv")
    assert [int(r["step"]) for r in rows] == list(range(6))
    assert [int(r["updates"]) for r in rows[4:]] == [15, 18]  # the update count goes on from the checkpoint
    resumed = json.loads((dest / "run.json").read_text())
    assert len(resumed["segments"]) == 2 and resumed["segments"][1]["from_updates"] == 12
    store = Store(dest)
    try:
        assert store.transition_count() == 4  # the two carried and the two new
    finally:
        store.close()


def test_same_seed_same_actions(tmp_path):
    """Synchronous updates and fixed seeds: two runs of one command act identically."""
    logs = []
    for name in ("a", "b"):
        assert _train(tmp_path / name, "--steps", "3", "--seed", "2") == 0
        logs.append([(r["primitive"], r["row"], r["col"], r["rotation"], r["reward"], r["rule"])
                     for r in read_rows(tmp_path / name / "actions.csv")])
    assert logs[0] == logs[1]
    a, b = (load_policy(_checkpoints(tmp_path / n)[-1]).metadata["weights_sha256"] for n in ("a", "b"))
    assert a == b


def test_ctrl_c_leaves_a_resumable_consistent_run(tmp_path):
    out = tmp_path / "run"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.Popen([sys.executable, "-m", "flgd.cli", "train", "--config", CONFIG, "--out", str(out),
                             "--steps", "500", "--threads", "1", "--variant", "rho-fcn"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, cwd=REPO)
    try:
        deadline = time.monotonic() + 120
        while len(read_rows(out / "actions.csv")) < 2:
            assert proc.poll() is None, proc.stdout.read().decode()
            assert time.monotonic() < deadline, "no training step within 120 s"
            time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        output = proc.communicate(timeout=120)[0].decode()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, output
    assert "interrupted" in output

    store = Store(out)
    try:
        assert store.integrity_check() == "ok"
        steps = store.next_step()
        assert store.transition_count() == steps  # every logged step has its transition
    finally:
        store.close()
    rows = read_rows(out / "actions.csv")
    assert [int(r["step"]) for r in rows] == list(range(steps))
    ckpt = _checkpoints(out)[-1]
    policy = load_policy(ckpt, expected_variant="rho-fcn-fast")
    assert policy.metadata["training_steps"] == steps and policy.metadata["train_variant"] == "rho-fcn"
    assert json.loads((out / "run.json").read_text())["status"] == "interrupted"
    assert not list((out / "checkpoints").glob(".*.tmp"))

    assert train_main(["--out", str(out), "--steps", str(steps + 1), "--threads", "1"]) == 0
    assert [int(r["step"]) for r in read_rows(out / "actions.csv")] == list(range(steps + 1))


def test_bad_arguments_are_refused_with_the_flag_named(tmp_path, capsys):
    assert train_main(["--out", str(tmp_path / "x")]) == 2
    assert "--config is required" in capsys.readouterr().err
    assert _train(tmp_path / "y", "--objects", "0") == 2
    assert "--objects: got 0" in capsys.readouterr().err
    assert _train(tmp_path / "z", "--curriculum", "--objects", "12") == 2
    assert "the curriculum sets the object count" in capsys.readouterr().err
    bad = tmp_path / "real.yaml"
    bad.write_text((REPO / "cell_config" / "ur5e-d415.yaml").read_text())
    assert train_main(["--config", str(bad), "--out", str(tmp_path / "w")]) == 2
    assert "expected 'sim'" in capsys.readouterr().err
    assert not (tmp_path / "w").exists()


def test_set_changes_the_runs_config_and_every_resume_keeps_it(tmp_path, capsys, monkeypatch):
    """A recipe is a config plus named changes: run.json keeps them and every start applies them, so a resume from
    the run's config.yaml, or from the original --config, trains the same config; it may repeat them, not change
    them.  Keys the run sets itself are refused with the flag that sets them."""
    out = tmp_path / "run"
    trunk = load_config(CONFIG).learning.init_trunk
    monkeypatch.chdir(Path(trunk).parent)   # a relative file is read from where the command runs
    assert _train(out, "--steps", "1", "--set", "exploration.side_taper=0.003", "--set", "learning.batch_size=3",
                  "--set", f"learning.init_trunk={Path(trunk).name}") == 0
    kept = load_config(out / "config.yaml")
    assert kept.exploration.side_taper == 0.003 and kept.learning.batch_size == 3
    assert kept.learning.init_trunk == trunk   # config.yaml names it relative to the run: still the same file
    assert load_config(CONFIG).exploration.side_taper != 0.003   # the file named by --config is untouched
    run_json = (out / "run.json").read_text()
    assert train_main(["--out", str(out), "--steps", "2", "--set", "exploration.side_taper=0"]) == 2
    assert "--set: got ['exploration.side_taper=0']" in capsys.readouterr().err
    assert (out / "run.json").read_text() == run_json
    # the original command again (with --config, without --set): the changes still apply
    assert train_main(["--config", CONFIG, "--out", str(out), "--threads", "1", "--steps", "2"]) == 0
    kept = load_config(out / "config.yaml")
    assert kept.exploration.side_taper == 0.003 and kept.learning.batch_size == 3
    for item, message in (("exploration.no_such_key=1", "--set exploration.no_such_key: no such config key"),
                          ("exploration.side_taper=-1", "with --set exploration.side_taper=-1"),
                          ("side_taper=0", "--set 'side_taper=0': "),
                          ("sim.objects=5", "the run sets sim.objects itself; use --objects or --curriculum")):
        assert _train(tmp_path / "bad", "--set", item) == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / "bad").exists()


class FlakyCell(WrappedCell):
    """A real SimCell behind a wrapper that fails chosen executions like a simulator can (a fake of failures only):
    ``errors`` non-CellFault exceptions (pybullet giving up) and ``faults`` CellFaults."""

    def __init__(self, inner: Cell, errors: list[int], faults: list[int]):
        super().__init__(inner)
        self.errors, self.faults, self.calls = errors, faults, 0

    def execute(self, plan):
        self.calls += 1
        if self.calls in self.errors:
            raise RuntimeError("bodies 0 and 11 interpenetrate by 16 mm (injected)")
        if self.calls in self.faults:
            raise CellFault("protective stop (injected)")
        return self.inner.execute(plan)


def _run_with_flaky_cell(tmp_path, errors, faults, steps):
    import io

    from flgd.config import load_config
    from flgd.training.progress import LineProgress
    from flgd.training.run import RunSettings, TrainingRun

    from flgd.training.collector import LocalCollector

    out = tmp_path / "run"
    run = TrainingRun(out, RunSettings(steps=steps, seed=1), load_config(CONFIG), LineProgress(io.StringIO(), False),
                      threads=1, collector=LocalCollector(lambda cell: FlakyCell(cell, errors, faults)))
    try:
        run.setup()
        code = run.train()
        return code, run
    finally:
        run.close()


def test_simulator_errors_and_faults_are_survived_and_logged(tmp_path):
    code, run = _run_with_flaky_cell(tmp_path, errors=[1], faults=[3], steps=3)
    assert code == 0 and run.step == 3
    store = Store(tmp_path / "run")
    try:
        faults = [e["message"] for e in store.events("fault")]
    finally:
        store.close()
    assert any("RuntimeError: bodies 0 and 11" in m for m in faults)
    assert any("protective stop (injected)" in m for m in faults)


def test_a_simulator_error_after_the_write_ahead_intent_leaves_that_step_interrupted_and_the_run_goes_on(tmp_path):
    """The first action's own motion fails (execution 1 is the move home before the first capture): its intent
    was written, no row completes it; the step is used up and marked interrupted, the next action takes the next."""
    code, run = _run_with_flaky_cell(tmp_path, errors=[2], faults=[], steps=3)
    assert code == 0 and run.step == 3
    store = Store(tmp_path / "run")
    try:
        log = [(int(r["step"]), r["outcome"]) for r in store.action_log()]
    finally:
        store.close()
    assert log[0] == (0, "interrupted") and [step for step, _ in log] == [0, 1, 2]
    assert all(outcome != "pending" for _, outcome in log[1:])


def test_a_cell_that_keeps_failing_stops_the_run(tmp_path):
    from flgd.training import cell_loop

    with pytest.raises(RuntimeError, match="cell faults in a row"):
        _run_with_flaky_cell(tmp_path, errors=list(range(1, 50)), faults=[], steps=20)
    assert cell_loop.MAX_CONSECUTIVE_FAULTS == 5


def test_a_run_can_start_from_a_policy_file_and_refuses_a_bad_one(tmp_path, capsys):
    """--init-policy: the weights come from the file (then train on), the replay starts empty."""
    from flgd.learning.networks import build_network

    shipped = REPO / "policies" / "flg-sim.safetensors"
    out = tmp_path / "finetune"
    assert _train(out, "--steps", "1", "--seed", "2", "--init-policy", str(shipped)) == 0
    info = json.loads((out / "run.json").read_text())
    assert info["settings"]["init_policy"] == str(shipped.resolve())
    assert info["segments"][0]["source"] == f"policy {shipped.resolve()}"
    trained = load_policy(_checkpoints(out)[-1], expected_variant="fast").network.state_dict()
    start = load_policy(shipped, expected_variant="fast").network.state_dict()
    fresh = build_network("fast", 16, seed=2).state_dict()
    weights = [k for k, v in start.items() if v.is_floating_point() and v.ndim > 1]
    # U Adam steps move a weight by about U * lr at most; a fresh network is nowhere near the policy
    assert max(float((trained[k] - start[k]).abs().max()) for k in weights) < 0.02
    assert max(float((fresh[k] - start[k]).abs().max()) for k in weights) > 0.1
    store = Store(out)
    try:
        assert store.transition_count() == 1
    finally:
        store.close()

    # resuming with another start is refused; a file that is not a policy never starts a run
    assert train_main(["--out", str(out), "--steps", "2", "--init-policy", str(tmp_path / "other.safetensors")]) == 2
    assert "was started with" in capsys.readouterr().err
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a policy")
    assert _train(tmp_path / "never", "--steps", "1", "--init-policy", str(bad)) == 2
    err = capsys.readouterr().err
    assert "--init-policy" in err and "bad.safetensors" in err
    assert not (tmp_path / "never" / "run.json").exists()


def test_the_action_log_names_packed_scenes_as_packed(tmp_path):
    """sim.packed_scenes mixes packed arrangements into training; the log must not call them random drops."""
    config = _config_variant(tmp_path, "packed", policy=str(load_config(CONFIG).policy), sim={"packed_scenes": 1.0},
                             learning={"init_trunk": "", "updates_per_action": 1})
    out = tmp_path / "run"
    assert train_main(["--config", config, "--out", str(out), "--threads", "1", "--steps", "2",
                       "--seed", "2"]) == 0
    rows = read_rows(out / "actions.csv")
    first = int(rows[0]["objects_left"]) + (rows[0]["success"] == "1")   # objects before the first action
    assert len(rows) == 2 and {r["scene_kind"] for r in rows} == {f"packed {first}"}


def test_give_up_after_starts_a_new_scene_after_that_many_actions_without_a_grasp(tmp_path, capsys):
    out = tmp_path / "run"
    # a fresh network on 10 objects: long stretches without a successful grasp
    config = _config_variant(tmp_path, "fresh", learning={"init_trunk": "", "updates_per_action": 1})
    assert train_main(["--config", config, "--out", str(out), "--threads", "1", "--steps", "8", "--seed", "1",
                       "--give-up-after", "3"]) == 0
    rows = read_rows(out / "actions.csv")
    streak, expected_scene, give_ups = 0, int(rows[0]["scene"]), 0
    for before, after in zip(rows, rows[1:]):
        grasped = before["primitive"] == "grasp" and before["success"] == "1"
        streak = 0 if grasped else streak + 1
        cleared = before["objects_left"] == "1" and grasped
        if streak >= 3 or cleared:
            expected_scene += 1
            give_ups += streak >= 3
            streak = 0
            assert int(after["objects_left"]) >= 8   # a fresh scene of 10 (one may settle outside the workspace)
        assert int(after["scene"]) == expected_scene
    assert give_ups >= 1
    events = Store(out).events("give-up")
    assert len(events) == give_ups and "3 actions without a successful grasp" in events[0]["message"]
    assert json.loads((out / "run.json").read_text())["settings"]["give_up_after"] == 3
    # resuming keeps the setting; another value is refused with the flag named
    assert train_main(["--out", str(out), "--steps", "9", "--threads", "1"]) == 0
    assert train_main(["--out", str(out), "--steps", "10", "--threads", "1", "--give-up-after", "5"]) == 2
    assert "--give-up-after: got 5" in capsys.readouterr().err
    assert train_main(["--config", str(config), "--out", str(tmp_path / "neg"), "--give-up-after", "-1"]) == 2


class ResetFailsOnce(FlakyCell):
    """The flaky wrapper whose first scene reset fails as a simulator can (a fake of that failure only)."""

    def __init__(self, inner: Cell):
        super().__init__(inner, errors=[], faults=[])
        self.resets = 0

    def reset_scene(self):
        self.resets += 1
        if self.resets == 1:
            raise RuntimeError("object 4 settles at 3.1 m/s (injected)")
        self.inner.reset_scene()


def test_a_give_up_whose_new_scene_fails_is_recovered_like_a_fault(tmp_path):
    import dataclasses
    import io

    from flgd.training.progress import LineProgress
    from flgd.training.run import RunSettings, TrainingRun

    config = dataclasses.replace(load_config(CONFIG), policy="")   # a fresh network: grasps fail
    from flgd.training.collector import LocalCollector

    collector = LocalCollector(ResetFailsOnce)
    run = TrainingRun(tmp_path / "run", RunSettings(steps=4, seed=1, give_up_after=1), config,
                      LineProgress(io.StringIO(), False), threads=1, collector=collector)
    try:
        run.setup()
        assert run.train() == 0 and run.step == 4
        assert collector.cell.resets >= 2   # the failed reset, then the recovery's
    finally:
        run.close()
    store = Store(tmp_path / "run")
    try:
        assert store.events("give-up")
        assert any("object 4 settles" in e["message"] for e in store.events("fault"))
    finally:
        store.close()


def test_train_is_refused_on_a_state_directory_a_daemon_holds(tmp_path):
    from flgd.state_dir_lock import lock_state_dir

    out = tmp_path / "cell-state"
    held = lock_state_dir(out, create=True)  # what a running flgd run (or flgd calibrate) holds
    try:
        p = subprocess.run([sys.executable, "-m", "flgd.cli", "train", "--config", CONFIG, "--out", str(out),
                            "--steps", "5", "--threads", "1"], capture_output=True, text=True, timeout=120, cwd=REPO)
    finally:
        os.close(held)
    assert p.returncode != 0
    assert "is using the state directory" in p.stderr + p.stdout and "Traceback" not in p.stderr, p.stderr
    assert not (out / "flgd.sqlite").exists(), "nothing of the daemon's was touched"
