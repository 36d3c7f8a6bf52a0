"""``flgd eval --workers N``: the runs of a frozen evaluation spread over N Ray workers.

Each run is one unit of work: (scene, run number) evaluated by the ordinary ``Evaluator`` in a worker, on a
fresh simulated cell seeded from (``--seed``, the scene's position, the run number).  So a run's result does
not depend on N or on which worker ran it: ``--workers 2`` and ``--workers 8`` give the same report.  It is
not the single-process evaluation's (there one cell's random stream runs through every run of an object set),
so compare evaluations made the same way.

The report is the single-process one (``build_report`` over the runs in scene and run order); with ``--json``
it is rewritten after every finished run, in whatever order runs finish.  A worker that dies has its run
given to a fresh worker (``MAX_RETRIES`` times); an error inside a run stops the evaluation as it does in one
process.  Online learning (``--learn``) is sequential by nature and stays single-process.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from flgd.config import CellConfig
from flgd.evaluation.evaluator import EvalOptions, EvaluationError
from flgd.evaluation.metrics import RunLog
from flgd.evaluation.scene_sets import SceneSpec

if TYPE_CHECKING:
    from flgd.learning.networks import QMapNetwork

__all__ = ["ParallelEvaluator", "EvalWorker", "run_seed", "MAX_RETRIES"]

MAX_RETRIES = 2  # a run whose worker died is given to a fresh worker at most this many times


def run_seed(seed: int, scene_index: int, run: int) -> int:
    """The seed of one run of a parallel evaluation: its scenes, sensor noise and policy draws."""
    return int(np.random.SeedSequence([int(seed), int(scene_index), int(run)]).generate_state(1)[0] >> 1)


class EvalWorker:
    """A Ray worker of ``flgd eval --workers``: the policy loaded once, one fresh ``Evaluator`` per run."""

    def __init__(self, config: CellConfig, network: QMapNetwork, options: EvalOptions, training_steps: int,
                 threads: int = 1) -> None:
        import torch

        torch.set_num_threads(max(1, int(threads)))
        self.config = config
        self.options = options
        self.training_steps = training_steps
        self.network = network  # a torch module, sent once through Ray's object store
        self.network.eval()

    def run(self, spec: SceneSpec, scene_index: int, number: int) -> RunLog:
        from flgd.evaluation.evaluator import Evaluator

        options = dataclasses.replace(self.options, seed=run_seed(self.options.seed, scene_index, number))
        evaluator = Evaluator(self.config, self.network, options, training_steps=self.training_steps)
        try:
            return evaluator.run(spec, number)
        finally:
            evaluator.close()


class ParallelEvaluator:
    """The ``Evaluator`` interface (``results``, ``progress``, ``evaluate``, ``close``) over Ray workers."""

    def __init__(self, config: CellConfig, network: QMapNetwork, options: EvalOptions, *, training_steps: int = 0,
                 workers: int, address: str | None = None,
                 progress: Callable[[SceneSpec, RunLog], None] | None = None) -> None:
        if options.learn:
            raise ValueError("--workers: a learning evaluation (--learn) runs in one process; drop one of the two")
        if workers < 1:
            raise ValueError(f"--workers: got {workers}, expected >= 1")
        if config.backend != "sim":
            raise EvaluationError(f"{config.source}: backend {config.backend!r}: flgd eval runs in the simulated "
                                  "cell; use a config with backend: sim (e.g. cell_config/sim.yaml)")
        self.config = config
        self.options = options
        self.training_steps = training_steps
        self.workers = workers
        self.address = address
        self.progress = progress
        self.results: list[tuple[SceneSpec, list[RunLog]]] = []
        self.network = network
        self.engine: Any = None

    def _spawn(self, actor_class: Any, network_ref: Any) -> Any:
        return actor_class.remote(self.config, network_ref, self.options, self.training_steps)

    def evaluate(self, scenes: list[SceneSpec]) -> list[tuple[SceneSpec, list[RunLog]]]:
        """Every run of every scene (module doc); ``results`` grows as runs finish, kept in scene/run order."""
        from flgd.training.ray_engine import remote_class, start_engine, worker_lost_errors

        self.results = [(spec, []) for spec in scenes]
        units = [(i, number) for i in range(len(scenes)) for number in range(1, self.options.runs + 1)]
        if not units:
            return self.results
        self.engine = start_engine(self.address, self.workers)
        ray = self.engine.ray
        lost = worker_lost_errors(ray)
        actor_class = remote_class(ray, EvalWorker, cpus=1.0)
        weights_ref = ray.put(self.network)
        idle = [self._spawn(actor_class, weights_ref) for _ in range(min(self.workers, len(units)))]
        todo = list(reversed(units))
        retries: dict[tuple[int, int], int] = {}
        in_flight: dict[Any, tuple[Any, tuple[int, int]]] = {}
        while todo or in_flight:
            while todo and idle:
                actor, unit = idle.pop(), todo.pop()
                in_flight[actor.run.remote(scenes[unit[0]], unit[0], unit[1])] = (actor, unit)
            ready, _ = ray.wait(list(in_flight), num_returns=1, timeout=1.0)  # Ctrl-C and SIGTERM get a turn
            if not ready:
                continue
            actor, (index, number) = in_flight.pop(ready[0])
            spec = scenes[index]
            try:
                log = ray.get(ready[0])
            except ray.exceptions.RayTaskError as exc:  # the run itself raised: stop, as in one process
                inner = exc.cause if isinstance(getattr(exc, "cause", None), BaseException) else exc
                what = str(inner) if isinstance(inner, EvaluationError) else f"{type(inner).__name__}: {inner}"
                raise EvaluationError(f"scene {spec.name} ({spec.describe()}), run {number} of "
                                      f"{self.options.runs}: {what}; the evaluation stopped there") from None
            except lost as exc:  # its worker died: a fresh one runs it again
                retries[(index, number)] = retries.get((index, number), 0) + 1
                if retries[(index, number)] > MAX_RETRIES:
                    raise EvaluationError(f"scene {spec.name}, run {number}: its worker died "
                                          f"{retries[(index, number)]} times ({str(exc).splitlines()[0]})") from None
                try:
                    ray.kill(actor)
                except Exception:  # already gone
                    pass
                todo.append((index, number))
                idle.append(self._spawn(actor_class, weights_ref))
                continue
            except ray.exceptions.RayError as exc:  # Ray itself failed (object store, scheduling ...)
                raise EvaluationError(f"scene {spec.name}, run {number}: Ray: {type(exc).__name__}: "
                                      f"{str(exc).splitlines()[0] if str(exc) else ''}") from None
            logs = self.results[index][1]
            logs.append(log)
            logs.sort(key=lambda r: r.run)
            idle.append(actor)
            if self.progress is not None:
                self.progress(spec, log)
        return self.results

    def close(self) -> None:
        if self.engine is not None:
            self.engine.stop()
            self.engine = None
