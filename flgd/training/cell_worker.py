"""A training worker: one simulated cell with its own seed, acting network and agent, in a Ray actor.

``flgd train --workers N`` runs N of these (``flgd.training.ray_collector``).  Each builds everything inside its
own process -- torch limited to its threads, the PyBullet simulation, the network, the daemon's agent
(``flgd.wiring.make_agent``) -- from plain data (the config, the run settings, a weights dictionary), so nothing
that holds a simulator or a thread is ever pickled.  ``collect`` runs one cycle of the run's training cell
(``flgd.training.cell_loop.TrainingCell``) with the newest weights the learner sent and returns its
``CellReport``.  The worker stores nothing itself; a worker that dies loses at most the cycle it was running.
"""

from __future__ import annotations

import dataclasses
import os
from typing import TYPE_CHECKING, Any

import numpy as np

from flgd.config import CellConfig

if TYPE_CHECKING:
    from flgd.training.collected import CellReport
    from flgd.training.settings import RunSettings

__all__ = ["CellWorker", "worker_seed"]


def worker_seed(seed: int, segment: int, worker: int, incarnation: int, stream: int) -> int:
    """A worker's seed for one random stream (sim, agent, curriculum): distinct per run seed, segment, worker,
    restart of that worker and stream, so that no two workers -- or a worker and its replacement -- lay out
    the same scenes or make the same exploration draws."""
    return int(np.random.SeedSequence([int(seed), int(segment), int(worker), int(incarnation),
                                       int(stream)]).generate_state(1)[0])


class CellWorker:
    """One simulated cell of a multi-worker run (module doc); made a Ray actor by the driver."""

    def __init__(self, config: CellConfig, settings: RunSettings, index: int, incarnation: int, segment: int,
                 weights: dict[str, Any], version: int, step: int = 0, threads: int = 1) -> None:
        import torch

        from flgd.learning.networks import build_network
        from flgd.training.cell_loop import TrainingCell
        from flgd.wiring import make_agent

        torch.set_num_threads(max(1, int(threads)))
        self.index, self.incarnation = index, incarnation
        seed = settings.seed
        config = dataclasses.replace(
            config, sim=dataclasses.replace(config.sim, seed=worker_seed(seed, segment, index, incarnation, 2)))
        lc = config.learning
        network = build_network(lc.network, rotations=lc.rotations, seed=0)
        self.agent = make_agent(config, network, worker_seed(seed, segment, index, incarnation, 4))
        self.agent.act_with(weights, None, version)
        # the run's step: the curriculum's first scene and the exploration schedule follow it
        self.loop = TrainingCell(config, settings, self.agent, step=step,
                                 curriculum_seed=worker_seed(seed, segment, index, incarnation, 5))

    def pid(self) -> int:
        return os.getpid()

    def collect(self, step: int, weights: dict[str, Any] | None = None, version: int = -1) -> CellReport:
        """One cycle at the run's ``step`` with ``weights`` (the learner's newest, when it sent them) acting."""
        if weights is not None:
            self.agent.mailbox.post(weights, version=version)
        report = self.loop.collect(step)
        report.cell, report.incarnation = self.index, self.incarnation
        report.weights_version = self.agent.weights_version
        return report

    def close(self) -> None:
        self.loop.close()
