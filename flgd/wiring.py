"""How a cell's learning parts start: the start network, the replay from the store, the agent, the prior sample,
and the seeds of a continued run.

``flgd.learning_stack.LearningStack`` puts them together, the one way for the
daemon (``flgd run``), ``flgd eval --learn``, ``flgd train`` and the benches, so
that resuming from a state directory means the same thing for all of them:
the newest readable checkpoint wins over a given policy, which wins over a
fresh network; the replay is rebuilt from the store's newest transitions with
their stored priorities, and the priorities the learner sets are written back.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from flgd.config import CellConfig
from flgd.store import CheckpointDir, Store, StoreError

if TYPE_CHECKING:
    from flgd.learning.agent import Agent
    from flgd.learning.networks import QMapNetwork
    from flgd.learning.prior_sample import PriorSample
    from flgd.learning.replay import PrioritizedReplay

__all__ = ["StartingNetwork", "starting_network", "fresh_network", "rebuild_replay", "configured_prior",
           "make_agent", "resume_seed", "continuing_config"]

log = logging.getLogger("flgd")


def resume_seed(seed: int, at: int, stream: int | None = None) -> int:
    """The seed of a random stream in a run that continues at ``at``: the one resume-seed rule.

    ``at`` is where the run continues: a restarted daemon's next action (one draw per configured seed), a
    resumed ``flgd train``'s segment (one draw per ``stream``: learning, sim, replay, agent, curriculum).  At
    the start (``at`` 0) the configured seed itself, so a first start is reproducible from its config alone;
    after it a draw from (seed, at[, stream]), so that a continued run meets new simulated scenes and makes
    new exploration draws instead of replaying those it began with.  (The daemon's draws are 31-bit and the
    segments' 32-bit, so that a state directory written by either continues with the seeds it would have drawn.)"""
    import numpy as np

    if at <= 0:
        return int(seed)
    if stream is None:
        return int(np.random.SeedSequence([int(seed), int(at)]).generate_state(1)[0] >> 1)
    return int(np.random.SeedSequence([int(seed), int(at), int(stream)]).generate_state(1)[0])


def continuing_config(config: CellConfig, step: int) -> CellConfig:
    """``config`` with the simulator's and the learning's (agent, replay, learner) seeds of a run continuing at
    ``step`` (``resume_seed``); the same config at step 0."""
    import dataclasses

    if step <= 0:
        return config
    return dataclasses.replace(
        config, sim=dataclasses.replace(config.sim, seed=resume_seed(config.sim.seed, step)),
        learning=dataclasses.replace(config.learning, seed=resume_seed(config.learning.seed, step)))


@dataclass(frozen=True)
class StartingNetwork:
    network: QMapNetwork
    source: str                  # what it is, for status lines and policy metadata
    resumed_from_updates: int    # learner update count to continue from (0 = not resumed)
    checkpoint: Path | None      # the checkpoint loaded, if any


def starting_network(config: CellConfig, checkpoints: CheckpointDir, policy_path: str | None) -> StartingNetwork:
    """The newest readable checkpoint; else ``policy_path``; else a fresh seeded network (``fresh_network``).

    A bad ``policy_path`` raises ``PolicyFileError``; unusable checkpoints are
    skipped with a warning, but the update numbering continues above them so
    checkpoint pruning never removes the new ones.
    """
    from flgd.learning.policy_file import PolicyFileError, load_policy

    variant = config.learning.network
    fits = {"rotations": config.learning.rotations}
    existing = checkpoints.checkpoints()
    resumed = CheckpointDir.updates_of(existing[0]) if existing else 0
    for path in existing:
        try:
            loaded = load_policy(path, expected_variant=variant, expected_architecture=fits)
        except PolicyFileError as exc:
            log.warning("skipping unusable checkpoint: %s", exc)
            continue
        updates = CheckpointDir.updates_of(path)
        log.info("resuming from %s (%d learner updates)", path, updates)
        return StartingNetwork(loaded.network, f"checkpoint {path}", updates, path)
    if policy_path:
        loaded = load_policy(policy_path, expected_variant=variant, expected_architecture=fits)
        return StartingNetwork(loaded.network, f"policy {policy_path}", resumed, None)
    network, source = fresh_network(config, config.learning.seed)
    return StartingNetwork(network, source, resumed, None)


def fresh_network(config: CellConfig, seed: int | None) -> tuple[QMapNetwork, str]:
    """(network, description): a new network of the config's variant, its perception layers taken from
    ``learning.init_trunk`` when one is set (``TrunkFileError`` naming the file when it does not fit)."""
    from flgd.learning.networks import build_network

    lc = config.learning
    network = build_network(lc.network, rotations=lc.rotations, seed=seed)
    source = f"fresh {lc.network} network (seed {seed})"
    if lc.init_trunk:
        from flgd.learning.trunk import load_trunk

        load_trunk(network, lc.init_trunk)
        source += f", trunk {lc.init_trunk}"
    return network, source


def rebuild_replay(config: CellConfig, store: Store | None,
                   seed: int | None = None) -> tuple[PrioritizedReplay, str]:
    """(replay, problem): a replay holding the store's newest ``replay_capacity`` transitions.

    ``problem`` is '' or the store error that stopped the rebuild part-way.
    """
    from flgd.learning.replay import PrioritizedReplay, Transition

    lc = config.learning
    replay = PrioritizedReplay.from_config(lc, seed=seed)
    problem = ""
    if store is not None:
        try:
            for st in store.iter_transitions(limit=lc.replay_capacity):
                replay.add(Transition(st.state, st.action, st.reward, st.next_state, st.done), st.priority,
                           tag=st.id)
        except StoreError as exc:
            problem = str(exc)
    log.info("replay rebuilt with %d transitions", len(replay))
    return replay, problem


def configured_prior(config: CellConfig, rotations: int, fine_tune: bool) -> PriorSample | None:
    """The prior sample a fine-tune mixes into its batches (``finetune.prior_sample`` at ``prior_share``), or
    None.  Loaded once, at start: raises PriorSampleError naming the file when it cannot be used."""
    if not fine_tune or config.finetune.prior_share <= 0.0:
        return None
    from flgd.learning.prior_sample import load_prior_sample

    prior = load_prior_sample(config.finetune.prior_sample, rotations, config.workspace.shape)
    log.info("prior sample %s: %d transitions, %.0f %% of each batch", prior.path, len(prior),
             100 * config.finetune.prior_share)
    return prior


def make_agent(config: CellConfig, network: QMapNetwork, seed: int, fine_tune: bool = False) -> Agent:
    """The acting agent with the daemon's exploration rules: a fine-tune explores at most
    ``finetune.max_epsilon``, a cell that does not learn not at all.  ``flgd train --workers`` builds its
    workers' agents here too."""
    from flgd.learning.agent import Agent

    if config.learning.updates_per_action == 0:
        max_epsilon = 0.0  # learning is off: exploring would only cost picks
    else:
        max_epsilon = config.finetune.max_epsilon if fine_tune else 1.0
    return Agent(config, network, seed=seed, max_epsilon=max_epsilon)
