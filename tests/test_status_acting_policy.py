"""``flgctl status`` in FAULT with no store: the policy named is the one that acts after ``flgctl reset``."""

from __future__ import annotations

import dataclasses

from flgd.config import CellConfig
from flgd.daemon import commands
from flgd.daemon.controller import Controller
from tests.fakes.gate import GateCell, gate_config, make_network



def test_status_with_no_store_names_the_stored_champion_that_acts_after_reset_not_the_learners_source(tmp_path):
    """A start on a read-only or full state directory leaves the daemon in FAULT with no store and no gate:
    neither the checkpoint the learner resumed from nor the configured file is acting; after the reset the
    gate's stored champion is."""
    cell = GateCell(tmp_path, gate_config())
    cell.hand_over(make_network(12))
    cell.gate.promote(cell.step, "operator", "test")  # champion #2, from the learner
    cell.store.close()
    ctl = Controller(dataclasses.replace(CellConfig(), state_dir=str(tmp_path)), policy_path="/cell/configured.safetensors")
    ctl.policy_source = "checkpoint checkpoints/ckpt-000100.safetensors"  # what the learner resumed from
    policy = commands.status(ctl)["policy"]
    assert "champion #2" in policy and "learner update" in policy and "after flgctl reset" in policy, policy
    assert "configured.safetensors" not in policy and "ckpt-000100" not in policy

    first = Controller(dataclasses.replace(CellConfig(), state_dir=str(tmp_path / "new")),
                       policy_path="/cell/configured.safetensors")
    first.policy_source = "checkpoint somewhere"
    policy = commands.status(first)["policy"]  # a first start: the configured policy becomes champion #1
    assert "/cell/configured.safetensors" in policy and "after flgctl reset" in policy, policy
