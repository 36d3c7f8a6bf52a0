"""The starting network (flgd.wiring): a checkpoint or policy of other rotations than the config's is not used."""

from __future__ import annotations

import logging

import pytest

from flgd.config import config_from_dict
from flgd.learning.networks import build_network
from flgd.learning.policy_file import PolicyFileError, save_policy
from flgd.store import CheckpointDir
from flgd.wiring import starting_network


def _save(path, rotations: int) -> None:
    save_policy(path, build_network("fast", rotations=rotations, seed=1), {"training_steps": 0})


def test_a_checkpoint_of_other_rotations_is_skipped_with_a_warning(tmp_path, caplog):
    checkpoints = CheckpointDir(tmp_path / "checkpoints")
    _save(checkpoints.path_for(4), rotations=8)
    cfg = config_from_dict({"state_dir": str(tmp_path), "learning": {"rotations": 16}})
    with caplog.at_level(logging.WARNING, logger="flgd"):
        start = starting_network(cfg, checkpoints, None)
    assert start.checkpoint is None and start.network.rotations == 16
    assert start.resumed_from_updates == 4  # numbering goes on above the skipped one
    assert any("rotations = 8, expected 16" in r.getMessage() for r in caplog.records)


def test_a_policy_of_other_rotations_is_refused(tmp_path):
    _save(tmp_path / "eight.safetensors", rotations=8)
    cfg = config_from_dict({"state_dir": str(tmp_path), "learning": {"rotations": 16}})
    with pytest.raises(PolicyFileError, match=r"rotations = 8, expected 16 \(learning.rotations in the config\)"):
        starting_network(cfg, CheckpointDir(tmp_path / "checkpoints"), str(tmp_path / "eight.safetensors"))
