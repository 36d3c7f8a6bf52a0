"""How a cell's learning parts are made: network, replay, agent, learner, gate, and a continued run's seeds.

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
from typing import Any, Callable

from flgd.config import CellConfig
from flgd.store import CheckpointDir, Store, StoreError

__all__ = ["StartingNetwork", "starting_network", "fresh_network", "rebuild_replay", "configured_prior",
           "build_agent_and_learner", "make_agent",
           "attach_gate", "resume_seed", "continuing_config"]

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
    network: Any
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


def fresh_network(config: CellConfig, seed: int | None) -> tuple[Any, str]:
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


def rebuild_replay(config: CellConfig, store: Store | None, seed: int | None = None) -> tuple[Any, str]:
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


def configured_prior(config: CellConfig, rotations: int, fine_tune: bool) -> Any:
    """The prior sample a fine-tune mixes into its batches (``finetune.prior_sample`` at ``prior_share``), or
    None.  Loaded once, at start: raises PriorSampleError naming the file when it cannot be used."""
    if not fine_tune or config.finetune.prior_share <= 0.0:
        return None
    from flgd.learning.prior_sample import load_prior_sample

    prior = load_prior_sample(config.finetune.prior_sample, rotations, config.workspace.shape)
    log.info("prior sample %s: %d transitions, %.0f %% of each batch", prior.path, len(prior),
             100 * config.finetune.prior_share)
    return prior


def build_agent_and_learner(config: CellConfig, network: Any, replay: Any, *,
                            checkpoint_callback: Callable[[Any, int], None] | None, updates: int = 0,
                            agent_seed: int | None = None, store: Store | None = None,
                            fine_tune: bool = False, prior: Any = None) -> tuple[Any, Any]:
    """The acting agent and its learner (which trains a copy of ``network`` and posts to the agent).

    With ``store`` the learner writes the replay priorities it sets back to it.  ``config`` is the one the
    learner runs with (``config.learner_settings`` applied); with ``fine_tune`` the agent explores at most
    ``finetune.max_epsilon``, and with no updates per action it does not explore at all.  ``prior``
    (``configured_prior``) is mixed into the learner's batches at ``finetune.prior_share``.
    """
    from flgd.learning.learner import Learner

    agent = make_agent(config, network, config.learning.seed if agent_seed is None else agent_seed, fine_tune)
    learner = Learner(config, network, replay, mailbox=agent.mailbox, checkpoint_callback=checkpoint_callback,
                      priority_sink=None if store is None else store.save_priorities, prior=prior,
                      prior_share=config.finetune.prior_share if prior is not None else 0.0)
    learner.updates = int(updates)
    replay.resume_annealing(int(updates))  # one batch per update: beta goes on where the run left it
    return agent, learner


def make_agent(config: CellConfig, network: Any, seed: int, fine_tune: bool = False) -> Any:
    """The acting agent with the daemon's exploration rules: a fine-tune explores at most
    ``finetune.max_epsilon``, a cell that does not learn not at all.  ``flgd train --workers`` builds its
    workers' agents here too."""
    from flgd.learning.agent import Agent

    agent = Agent(config, network, seed=seed)
    if fine_tune:
        agent.max_epsilon = config.finetune.max_epsilon
    if config.learning.updates_per_action == 0:
        agent.max_epsilon = 0.0  # learning is off: exploring would only cost picks
    return agent


def attach_gate(config: CellConfig, store: Store, agent: Any, learner: Any, state_dir: str | Path, step: int, *,
                fine_tune: bool, configured: Callable[[], tuple[Any, dict, str] | None],
                fresh: Callable[[], tuple[Any, dict, str]]) -> tuple[Any, str]:
    """(gatekeeper, note): the agent acts with the stored champion (on a first start the configured policy, or
    without one ``fresh``), exploration continues from the policy's recorded training steps when fine-tuning,
    and the learner hands its weights to the gate -- or, with ``gate.enabled`` false, straight to the agent.

    The daemon and ``flgd eval --learn`` both call this, so that what the evaluation measures is what the
    daemon does.  Raises GateError / PolicyFileError when there is no usable policy, StoreError on storage.
    """
    from flgd.gate.keeper import Gatekeeper

    gate = Gatekeeper(config, store, agent, state_dir)
    gate.on_champion = learner.set_anchor  # the learner's L2-SP anchor is what acts
    note = gate.restore(step, configured, fresh)
    offset = store.counter("exploration_offset", -1)
    if offset < 0:  # first start: exploration continues from the policy's recorded training steps
        offset = gate.champion.training_steps - step if fine_tune else 0
        store.set_counter("exploration_offset", offset)
    agent.exploration_offset = offset
    learner.mailbox = gate.handovers if gate.enabled else agent.mailbox
    return gate, note
