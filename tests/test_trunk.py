"""Perception pre-training: ground-truth labels from sim_cell, the targets, training, trunk files and their use."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pybullet as p
import pytest
import torch

from flgd.config import load_config
from flgd.learning.networks import build_network
from flgd.learning.trunk import (HEAD_PARAMETERS, PerceptionNet, TrunkFileError, instance_targets, load_trunk,
                                 read_trunk, save_trunk)
from flgd.perception import base_to_pixel
from flgd.store import CheckpointDir
from flgd.training.pretrain import PretrainSettings, collect_frames, pretrain
from flgd.wiring import starting_network
from sim_cell.cell import SimCell
from sim_cell.objects import ObjectSpec
from tests.fakes.daemon import write_config

REPO = Path(__file__).resolve().parents[1]
BASE_CFG = load_config(REPO / "cell_config" / "sim.yaml")


def sim_config(**sim):
    return dataclasses.replace(BASE_CFG, sim=dataclasses.replace(BASE_CFG.sim, **sim))


# ------------------------------------------------------------------------------------------------ targets

def test_targets_of_two_touching_boxes():
    labels = np.zeros((40, 60), np.int32)
    labels[10:30, 10:30] = 3
    labels[10:30, 30:50] = 7          # touches the first along column 30
    obj, boundary, interior = instance_targets(labels)
    assert obj.sum() == 800 and obj[20, 20] == 1 and obj[5, 5] == 0
    # the shared edge and the outer edges are boundaries, the middles and the empty table are not
    assert boundary[20, 29] == 1 and boundary[20, 30] == 1 and boundary[20, 10] == 1 and boundary[9, 20] == 1
    assert boundary[20, 20] == 0 and boundary[20, 40] == 0 and boundary[2, 2] == 0
    # interior depth: 1 in each box's middle, small at its edges, 0 off objects, each box on its own scale
    assert interior[19:21, 19:21].max() == pytest.approx(1.0) and interior[19:21, 39:41].max() == pytest.approx(1.0)
    assert interior[20, 29] < 0.2 and interior[20, 30] < 0.2 and interior[5, 5] == 0
    with pytest.raises(ValueError, match="HxW"):
        instance_targets(np.zeros((2, 3, 4)))


def test_interior_depth_is_one_over_the_peak_at_the_edge_not_zero():
    """What the module doc promises (and the shipped trunk was trained on): edge pixels count distance 1."""
    labels = np.zeros((11, 11), np.int32)
    labels[2:9, 2:9] = 5
    interior = instance_targets(labels)[2]
    assert interior[5, 2:9].tolist() == pytest.approx([0.25, 0.5, 0.75, 1.0, 0.75, 0.5, 0.25])
    assert interior[2, 2] == pytest.approx(0.25) and interior[0, 0] == 0
    line = np.zeros((5, 9), np.int32)
    line[2, 1:8] = 1
    assert instance_targets(line)[2][2, 1:8].tolist() == pytest.approx([1.0] * 7)


# ------------------------------------------------------------------------------------------ sim ground truth

def test_labels_line_up_with_the_objects_and_follow_a_removal():
    from flgd.perception import make_heightmaps

    cell = SimCell(sim_config(objects=0, depth_noise=False, domain_randomization=False))
    try:
        ws, depth_range = cell.config.workspace, cell.config.camera.depth_range
        q = p.getQuaternionFromEuler([0, 0, 0])
        a, b = (cell.add_object(ObjectSpec(shape="bar", size=(0.04, 0.04, 0.04), color=c, position=(x, y, 0.021),
                                           orientation=q))
                for x, y, c in ((-0.55, -0.05, (0.9, 0.2, 0.1)), (-0.45, 0.08, (0.1, 0.2, 0.9))))
        frame, ids = cell.capture_labelled()
        assert set(np.unique(ids)) == {0, a, b}
        hm = make_heightmaps(frame.color, frame.depth, frame.intrinsics, frame.depth_scale, frame.camera_pose, ws,
                             depth_range)
        index = np.where(ids == a, 1, np.where(ids == b, 2, 0)).astype(np.uint8)
        lab = make_heightmaps(np.repeat(index[:, :, None], 3, 2), frame.depth, frame.intrinsics,
                              frame.depth_scale, frame.camera_pose, ws, depth_range, fill="none").color[:, :, 0]
        ra, ca = base_to_pixel(-0.55, -0.05, ws)
        rb, cb = base_to_pixel(-0.45, 0.08, ws)
        assert lab[ra, ca] == 1 and lab[rb, cb] == 2
        # labelled pixels are the cubes' tops (4 cm) and a few of their sides the camera sees; the table is not
        on = hm.height[lab > 0]
        assert np.all(on > 0.005) and np.mean(on > 0.035) > 0.9 and np.all(lab[hm.height < 0.005] == 0)
        assert 300 < (lab == 1).sum() < 500          # a 4 cm square is 20 x 20 px at 2 mm
        assert cell.remove_object(a) is True
        _, ids = cell.capture_labelled()
        assert set(np.unique(ids)) == {0, b}
        with pytest.raises(ValueError, match=str(a)):
            cell.remove_object(a)
        # collect_frames: fresh scenes of 2 objects, thinned after each picture
        data = collect_frames(cell, ws, depth_range, 3, (2, 2), 2, np.random.default_rng(0))
        assert data["color"].shape == (3, 224, 224, 3) and data["labels"].shape == (3, 224, 224)
        assert [int(m.max()) for m in data["labels"]] == [2, 1, 2]
        assert np.all(data["height"][data["labels"] > 0] > 0.005)
        assert collect_frames(cell, ws, depth_range, 3, (2, 2), 2, np.random.default_rng(0), stop=lambda: True) is None
    finally:
        cell.close()


# ------------------------------------------------------------------------------------------------- training

@pytest.fixture(scope="module")
def frames():
    cell = SimCell(sim_config(objects=6, object_set="random_urdfs/0[0-9][0-9]/*.urdf", seed=3))
    try:
        return collect_frames(cell, cell.config.workspace, cell.config.camera.depth_range, 12, (3, 6), 4,
                              np.random.default_rng(3))
    finally:
        cell.close()


def test_a_few_steps_lower_the_held_out_loss_and_a_rerun_continues(frames, tmp_path):
    settings = PretrainSettings(frames=12, held_out=3, steps=12, batch=2, crop=96, save_every=6, seed=0)
    info = pretrain(tmp_path, frames, dataclasses.replace(settings, steps=6))
    assert info["finished"] and info["step"] == 6
    first = info["history"]
    info = pretrain(tmp_path, frames, settings)          # continues from step 6
    assert info["finished"] and [h["step"] for h in info["history"]] == [0, 6, 12]
    assert info["history"][:2] == first[:2]
    assert info["held_out"]["total"] < info["history"][0]["total"]
    trunk = read_trunk(tmp_path / "trunk.safetensors")
    assert trunk.metadata["width"] == 12 and trunk.metadata["step"] == 12
    assert not any(k.startswith(HEAD_PARAMETERS) for k in trunk.tensors)
    picture = (tmp_path / "predictions.png").read_bytes()
    import cv2
    img = cv2.imdecode(np.frombuffer(picture, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape[1] == 5 * 224 and img.std() > 10


def test_a_stopped_run_keeps_its_state(frames, tmp_path):
    settings = PretrainSettings(frames=12, held_out=3, steps=50, batch=2, crop=64, save_every=100, seed=0)
    calls = []
    info = pretrain(tmp_path, frames, settings, stop=lambda: len(calls) >= 3,
                    progress=lambda *a: calls.append(a))
    assert not info["finished"] and info["step"] == 3
    assert torch.load(tmp_path / "pretrain-state.pt", weights_only=True)["step"] == 3
    assert not (tmp_path / "trunk.safetensors").exists()


# ------------------------------------------------------------------------------------------------ trunk files

def _trunk_file(tmp_path: Path, width: int = 12) -> tuple[Path, PerceptionNet]:
    net = PerceptionNet(width=width, seed=5)
    with torch.no_grad():
        for prm in net.parameters():
            prm.add_(0.01)                 # unlike any freshly built network
    path = tmp_path / f"trunk-{width}.safetensors"
    save_trunk(path, net, {"note": "test"})
    return path, net


def test_load_trunk_into_fast_and_rho_fcn_fast(tmp_path):
    path, source = _trunk_file(tmp_path)
    trunk = source.trunk_state()
    fast = build_network("fast", seed=1)
    head_before = {k: v.clone() for k, v in fast.state_dict().items() if k.startswith(HEAD_PARAMETERS)}
    names = load_trunk(fast, path)
    state = fast.state_dict()
    assert set(names) == set(trunk) and any(n.startswith("fuse.") for n in names)
    assert all(torch.equal(state[n], trunk[n]) for n in names)
    assert all(torch.equal(state[k], v) for k, v in head_before.items())   # Q-map output and value stay fresh
    rho = build_network("rho-fcn-fast", seed=1)
    names = load_trunk(rho, path)
    assert names and all(n.startswith(("enc1.", "enc2.", "enc3.", "context.")) for n in names)
    assert all(torch.equal(rho.state_dict()[n], trunk[n]) for n in names)


def test_a_trunk_that_does_not_fit_is_refused_and_leaves_the_network_alone(tmp_path):
    wide, _ = _trunk_file(tmp_path, width=16)
    fast = build_network("fast", seed=1)
    before = {k: v.clone() for k, v in fast.state_dict().items()}
    with pytest.raises(TrunkFileError, match=r"has shape .*trunk width 16, network width 12"):
        load_trunk(fast, wide)
    assert all(torch.equal(fast.state_dict()[k], v) for k, v in before.items())
    with pytest.raises(TrunkFileError, match="densenet121"):
        load_trunk(build_network("densenet121", seed=0), _trunk_file(tmp_path)[0])
    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(b"\x00" * 64)
    with pytest.raises(TrunkFileError, match=str(garbage)):
        load_trunk(fast, garbage)
    with pytest.raises(TrunkFileError, match="not found"):
        load_trunk(fast, tmp_path / "missing.safetensors")
    from safetensors.torch import save_file
    whole = _trunk_file(tmp_path)[1].trunk_state()
    partial = tmp_path / "partial.safetensors"
    save_file({k: v for k, v in whole.items() if not k.startswith("fuse.")}, str(partial),
              metadata={"format": "flgd-trunk-1", "width": "12", "info": "{}"})
    with pytest.raises(TrunkFileError, match="lacks .* e.g. fuse."):
        load_trunk(fast, partial)
    for width, info, problem in (("9999", "{}", "width 9999"), ("12", "[1, 2]", "info is a list")):
        odd = tmp_path / f"odd-{width}.safetensors"
        save_file(whole, str(odd), metadata={"format": "flgd-trunk-1", "width": width, "info": info})
        with pytest.raises(TrunkFileError, match=problem):
            load_trunk(fast, odd)
    diverged = {k: v.clone() for k, v in whole.items()}
    diverged["enc2.0.weight"].view(-1)[3] = float("nan")
    nan_file = tmp_path / "nan.safetensors"
    save_file(diverged, str(nan_file), metadata={"format": "flgd-trunk-1", "width": "12", "info": "{}"})
    with pytest.raises(TrunkFileError, match=r"'enc2.0.weight': 1 of .* not finite \(NaN\)"):
        load_trunk(fast, nan_file)
    assert all(torch.equal(fast.state_dict()[k], v) for k, v in before.items())
    other = tmp_path / "policy-like.safetensors"
    save_file({"enc1.0.weight": torch.zeros(12, 4, 3, 3)}, str(other), metadata={"format": "something-else"})
    with pytest.raises(TrunkFileError, match="format 'something-else'"):
        load_trunk(fast, other)


@pytest.mark.slow
def test_config_init_trunk_starts_a_fresh_network_from_it_and_a_bad_one_stops_train_and_run(tmp_path):
    path, source = _trunk_file(tmp_path)
    cfg_path = write_config(tmp_path, tmp_path / "state", learning={"init_trunk": path.name})
    cfg = load_config(cfg_path)
    assert cfg.learning.init_trunk == str(path.resolve())          # relative to the config file
    start = starting_network(cfg, CheckpointDir(tmp_path / "ck"), None)
    assert "trunk" in start.source and str(path.resolve()) in start.source
    assert torch.equal(start.network.state_dict()["enc1.0.weight"], source.trunk_state()["enc1.0.weight"])
    # a policy file wins over the trunk: the trunk is only a fresh network's start
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a trunk")
    bad_cfg = write_config(tmp_path, tmp_path / "state2", learning={"init_trunk": str(bad)})
    r = subprocess.run([sys.executable, "-m", "flgd.cli", "train", "--config", str(bad_cfg), "--steps", "1",
                        "--out", str(tmp_path / "run")], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 2 and "learning.init_trunk" in r.stderr and str(bad) in r.stderr, r.stderr
    assert not (tmp_path / "run" / "run.json").exists()
    r = subprocess.run([sys.executable, "-m", "flgd.cli", "run", "--config", str(bad_cfg),
                        "--socket", str(tmp_path / "s.sock")], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 1 and str(bad) in r.stderr, r.stderr
    assert not (tmp_path / "s.sock").exists()


@pytest.mark.slow
def test_pretrain_cli_refuses_bad_arguments_and_changed_settings(tmp_path):
    def run(*args):
        return subprocess.run([sys.executable, "-m", "flgd.cli", "pretrain", "--config",
                               str(REPO / "cell_config" / "sim.yaml"), *args], capture_output=True, text=True,
                              cwd=REPO, timeout=300)

    r = run("--out", str(tmp_path / "a"), "--frames", "5", "--held-out", "5")
    assert r.returncode == 2 and "--frames" in r.stderr
    r = run("--out", str(tmp_path / "a"), "--crop", "8")
    assert r.returncode == 2 and "--crop: got 8" in r.stderr
    r = run("--out", str(tmp_path / "b"), "--frames", "6", "--held-out", "2", "--steps", "2", "--batch", "2",
            "--crop", "64", "--min-objects", "2", "--max-objects", "3")
    assert r.returncode == 0, r.stderr
    info = json.loads((tmp_path / "b" / "pretrain.json").read_text())
    assert info["status"] == "finished" and info["step"] == 2
    r = run("--out", str(tmp_path / "b"), "--frames", "7", "--held-out", "2", "--steps", "4", "--batch", "2",
            "--crop", "64", "--min-objects", "2", "--max-objects", "3")
    assert r.returncode == 2 and "frames" in r.stderr and "new --out" in r.stderr


def test_the_shipped_trunk_is_sim_yamls_start_and_fits_both_fast_networks(tmp_path):
    assert BASE_CFG.learning.init_trunk == str((REPO / "policies" / "trunk-sim.safetensors").resolve())
    trunk = read_trunk(BASE_CFG.learning.init_trunk)
    assert trunk.metadata["width"] == 12 and trunk.metadata["finished"] is True
    assert trunk.metadata["held_out"]["total"] < 0.25          # it learned (a fresh net: about 1.7)
    start = starting_network(BASE_CFG, CheckpointDir(tmp_path / "ck"), None)
    assert "trunk" in start.source
    assert torch.equal(start.network.state_dict()["fuse.0.weight"], trunk.tensors["fuse.0.weight"])
    assert load_trunk(build_network("rho-fcn-fast", seed=0), BASE_CFG.learning.init_trunk)
