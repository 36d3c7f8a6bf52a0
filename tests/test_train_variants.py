"""The three trained variants: one trunk, and only the head and the masks differ."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from flgd.config import config_from_dict, config_to_dict, load_config
from flgd.learning.networks import RhoFcnFastQNet, build_network, q_maps
from flgd.learning.policy_file import load_policy, save_policy
from flgd.perception import Heightmaps
from flgd.training.run import TRAIN_VARIANTS, RunSettings, effective_config, variant_network

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("variant,network,masks", [("flg", "fast", True), ("dpen", "fast", False),
                                                   ("rho-fcn", "rho-fcn-fast", True)])
def test_effective_config_of_each_variant(tmp_path, variant, network, masks):
    base = load_config(REPO / "cell_config" / "sim.yaml")
    cfg = effective_config(base, RunSettings(variant=variant, objects=7, seed=4), tmp_path)
    assert (cfg.learning.network, cfg.exploration.masks) == (network, masks)
    assert cfg.sim.objects == 7 and cfg.sim.seed == 4 and cfg.learning.seed == 4
    assert cfg.state_dir == str(tmp_path) and cfg.policy == ""
    assert TRAIN_VARIANTS[variant][:2] == (network, masks)
    # a resumed segment gets other, reproducible streams
    again = effective_config(base, RunSettings(variant=variant, seed=4), tmp_path, segment=1)
    assert again.sim.seed != 4 and again.sim.seed == effective_config(base, RunSettings(variant=variant, seed=4),
                                                                      tmp_path, segment=1).sim.seed
    # the config round-trips through YAML-able data (rho-fcn-fast is a valid learning.network)
    assert config_from_dict(config_to_dict(cfg)).learning.network == network


def test_curriculum_settings_set_the_few_moves_phase(tmp_path):
    base = load_config(REPO / "cell_config" / "sim.yaml")
    cfg = effective_config(base, RunSettings(curriculum=True, grasp_only=True), tmp_path)
    assert cfg.exploration.curriculum_steps == 500 and cfg.sim.objects == 10 and cfg.exploration.grasp_only


def test_rho_fcn_fast_is_the_fast_trunk_one_stage_deeper_with_a_x16_head():
    fast, rho = build_network("fast", seed=0), build_network("rho-fcn-fast", seed=0)
    assert isinstance(rho, RhoFcnFastQNet) and rho.stride == 16 and fast.stride == 8
    # same trunk weights for the same seed (the comparison isolates the head)
    for name in ("enc1", "enc2", "enc3", "context"):
        a, b = getattr(fast, name).state_dict(), getattr(rho, name).state_dict()
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    x = torch.randn(2, 4, 64, 64)
    rho.eval()
    with torch.no_grad():
        advantage, value = rho.advantage_and_value(x)
        coarse = rho.advantage(rho.enc4(rho.context(rho.enc3(rho.enc2(rho.enc1(x))))))
    assert coarse.shape[2:] == (4, 4) and advantage.shape == (2, 2, 64, 64) and value.shape == (2, 1)
    # no skip: the output is exactly the coarse map upsampled x16
    up = torch.nn.functional.interpolate(coarse, scale_factor=16, mode="bilinear", align_corners=False)
    assert torch.allclose(advantage, up)


def test_rho_fcn_fast_q_maps_and_policy_round_trip(tmp_path):
    net = build_network("rho-fcn-fast", rotations=4, seed=1).eval()
    rng = np.random.default_rng(0)
    hm = Heightmaps(color=rng.integers(0, 255, (40, 56, 3), dtype=np.uint8),
                    height=rng.uniform(0, 0.05, (40, 56)).astype(np.float32))
    with torch.no_grad():
        q = q_maps(net, hm, 4)
    assert q.shape == (4, 2, 40, 56)
    save_policy(tmp_path / "p.safetensors", net, {"training_steps": 3})
    loaded = load_policy(tmp_path / "p.safetensors", expected_variant="rho-fcn-fast")
    with torch.no_grad():
        assert torch.equal(q_maps(loaded.network, hm, 4), q)


def test_a_relative_policy_path_is_relative_to_the_config_file(tmp_path):
    text = (REPO / "cell_config" / "sim.yaml").read_text()
    lines = [ln for ln in text.splitlines() if not ln.startswith("policy:")]
    sub = tmp_path / "cfg"
    sub.mkdir()
    (sub / "cell.yaml").write_text("\n".join(lines + ['policy: "../policies/p.safetensors"']) + "\n")
    cfg = load_config(sub / "cell.yaml")
    assert cfg.policy == str(tmp_path / "policies" / "p.safetensors")


def test_the_shipped_sim_policy_is_the_configs_default_and_loads():
    cfg = load_config(REPO / "cell_config" / "sim.yaml")
    path = Path(cfg.policy)
    assert path.parent == REPO / "policies" and path.stat().st_size < 50 * 1024 * 1024
    policy = load_policy(path, expected_variant=cfg.learning.network)
    meta = policy.metadata
    assert meta["curriculum"] is True and meta["train_variant"] == "flg" and meta["training_steps"] > 0
    import json

    sidecar = json.loads(path.with_suffix(".json").read_text())
    assert sidecar["policy_metadata"]["weights_sha256"] == meta["weights_sha256"]
    assert (path.parent / sidecar["learning_curve"]).exists()


@pytest.mark.parametrize("trunk,variant,network,masks", [
    ("densenet121", "flg", "densenet121", True), ("densenet121", "dpen", "densenet121", False),
    ("densenet121", "rho-fcn", "rho-fcn", True), ("rho-fcn", "flg", "densenet121", True),
    ("rho-fcn-fast", "dpen", "fast", False), ("fast", "rho-fcn", "rho-fcn-fast", True)])
def test_the_variant_picks_head_and_masks_and_learning_network_the_trunk(tmp_path, trunk, variant, network, masks):
    base = load_config(REPO / "cell_config" / "sim.yaml")
    base = dataclasses.replace(base, learning=dataclasses.replace(base.learning, network=trunk))
    cfg = effective_config(base, RunSettings(variant=variant), tmp_path)
    assert (cfg.learning.network, cfg.exploration.masks) == (network, masks)
    assert variant_network(variant, network) == network   # a run's own config resumes with the same network


@pytest.mark.slow
def test_a_densenet121_config_trains_a_few_steps_and_writes_a_loadable_policy(tmp_path):
    """The paper's network is trainable, not only built: a tiny run on CPU (56 x 56 heightmaps, 2 rotations)."""
    from flgd.training.command import main as train_main

    cfg = yaml.safe_load((REPO / "cell_config" / "sim.yaml").read_text())
    cfg["policy"] = ""
    cfg["state_dir"] = str(tmp_path / "state")
    cfg["workspace"]["resolution"] = 0.008
    cfg["learning"].update(network="densenet121", init_trunk="", rotations=2, updates_per_action=1, device="cpu")
    config = tmp_path / "densenet.yaml"
    config.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "run"
    assert train_main(["--config", str(config), "--out", str(out), "--threads", "1", "--steps", "2",
                       "--objects", "3"]) == 0
    (last,) = sorted((out / "checkpoints").glob("checkpoint-*.safetensors"))[-1:]
    loaded = load_policy(last, expected_variant="densenet121")
    assert loaded.metadata["train_variant"] == "flg" and loaded.metadata["variant"] == "densenet121"
    assert loaded.metadata["training_steps"] == 2
    fresh = build_network("densenet121", rotations=2, seed=0).state_dict()
    trained = loaded.network.state_dict()
    assert any(not torch.equal(fresh[k], trained[k]) for k in fresh if fresh[k].is_floating_point())
