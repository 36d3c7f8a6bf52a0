"""A gate on a real store with real policy files, as the daemon builds it, without a cell."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import torch

from flgd.config import CellConfig
from flgd.cycle import CycleRecord
from flgd.cycle_record import CycleOutcome
from flgd.gate.keeper import Gatekeeper
from flgd.learning.agent import Agent
from flgd.learning.networks import build_network
from flgd.store import Store

def gate_config(**gate) -> CellConfig:
    cfg = CellConfig()
    base = dict(share=0.5, min_attempts=10, drop_min_attempts=10, max_attempts=200, rollback_min_attempts=10,
                promote_confidence=0.95, drop_confidence=0.95, rollback_confidence=0.95)
    base.update(gate)
    # every grasp rotation allowed: the gate's test maps are narrower than the open gripper (grasps in view)
    return dataclasses.replace(cfg, gate=dataclasses.replace(cfg.gate, **base),
                               learning=dataclasses.replace(cfg.learning, device="cpu"),
                               exploration=dataclasses.replace(cfg.exploration, grasp_in_view=False))


def make_network(seed: int):
    return build_network("fast", rotations=16, seed=seed)


def same_weights(a, b) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return all(torch.equal(sa[k], sb[k]) for k in sa)


class GateCell:
    """A gate on a store in ``tmp``, as the daemon builds it (``gate_options``: the Gatekeeper's keyword
    arguments); ``reopen`` is a restart."""

    def __init__(self, tmp: Path, config: CellConfig, configured=None, **gate_options):
        self.tmp, self.config, self.gate_options = tmp, config, gate_options
        self.configured = configured if configured is not None else make_network(1)
        self.step = 0
        self.open()

    def open(self) -> None:
        self.store = Store(self.tmp)
        self.agent = Agent(self.config, make_network(99), seed=0)
        self.gate = Gatekeeper(self.config, self.store, self.agent, self.tmp, **self.gate_options)
        self.note = self.gate.restore(self.step, self._configured, self._fresh)

    def _configured(self):
        return None if self.configured is False else (self.configured, {"training_steps": 4000}, "policy P")

    def _fresh(self):
        return make_network(7), {"training_steps": 0}, "fresh network"

    def reopen(self) -> None:
        self.store.close()
        self.open()

    def hand_over(self, network) -> None:
        self.gate.handovers.post(network.state_dict(), version=100 + self.step)
        assert self.gate.take_handover(self.step)

    def act(self, policy: int | None, success: bool, primitive: str = "grasp",
            outcome: CycleOutcome = CycleOutcome.EXECUTED):
        """One cycle credited to ``policy``: committed to the store, then shown to the gate (as the daemon does)."""
        rec = CycleRecord(outcome=outcome, step=self.step, time=time.time(), backend="sim", kind=primitive,
                          success=success if primitive == "grasp" else None, reward=float(success),
                          policy=policy, rule="greedy")
        rec.action = type("A", (), {"primitive": primitive, "row": 1, "col": 1, "rotation": 0})()
        self.store.commit_cycle(rec.row(), None)
        self.step += 1
        return self.gate.after_cycle(rec)
