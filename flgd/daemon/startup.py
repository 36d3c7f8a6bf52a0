"""What the daemon does once, before its first cycle, and what stops it from starting.

Each step is a function of what it needs, returning what it made; ``Controller.setup`` calls them in order.  A
problem an operator must fix is a ``StartupError`` whose message names it (the state directory that is locked or
unreadable, the policy or prior-sample file, the cell that does not connect); a store that cannot be opened is not
one of them: the daemon starts in FAULT and says why, so that `flgctl status` can tell the operator.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from flgd.cell import Cell, CellFault, make_cell
from flgd.config import CellConfig
from flgd.store import CheckpointDir, Store, StoreError

if TYPE_CHECKING:
    from flgd.learning.networks import QMapNetwork
    from flgd.learning_stack import LearningStack, TrainerStateRestore

__all__ = ["StartupError", "lock_state_dir", "open_store", "remove_unfinished_files", "start_step",
           "start_network", "load_prior", "connect_cell", "gate_errors", "gate_problem", "log_trainer_state"]

log = logging.getLogger("flgd")


class StartupError(RuntimeError):
    """The daemon cannot start (bad policy, cell does not connect, state dir locked ...)."""


def lock_state_dir(state_dir: Path) -> int:
    """The state directory's lock (one process per state directory): its file descriptor, held while running."""
    from flgd.state_dir_lock import StateDirBusy
    from flgd.state_dir_lock import lock_state_dir as take_lock

    try:
        return take_lock(state_dir, create=True)
    except StateDirBusy as exc:
        raise StartupError(str(exc)) from None
    except OSError as exc:  # a daemon without the lock could share the store with the next one
        raise StartupError(f"cannot lock the state directory {state_dir}: {exc.strerror or exc}; "
                           "make it (or its parent) exist and readable by this user, then start again") from None


def open_store(config: CellConfig, state_dir: Path) -> tuple[Store | None, str]:
    """(store, '') or (None, why it cannot be opened): the daemon then starts, and stays, in FAULT until a reset
    finds it usable."""
    sc = config.storage
    try:
        return Store(state_dir, keep_transitions=config.learning.replay_capacity, max_bytes=sc.max_bytes or None,
                     action_log_days=sc.action_log_days, min_free_bytes=sc.min_free_bytes), ""
    except StoreError as exc:
        log.error("%s", exc)
        return None, str(exc)


def remove_unfinished_files(checkpoints: CheckpointDir, state_dir: Path) -> None:
    """Checkpoint and trainer-state files an interrupted run left half written (never read: they are renamed into
    place only when complete)."""
    from flgd.training.state import remove_temporary

    for what, remove, where in (("checkpoint", checkpoints.remove_temporary, checkpoints.directory),
                                ("trainer-state", lambda: remove_temporary(state_dir), state_dir)):
        try:
            removed = remove()
            if removed:
                log.info("removed %d unfinished %s file(s) of an interrupted run", removed, what)
        except OSError as exc:
            log.warning("cannot clean %s: %s", where, exc)


def start_step(store: Store | None, state_dir: Path) -> int:
    """The action this start continues at (0 on a first start, or when the store could not be opened)."""
    try:
        step = store.next_step() if store is not None else 0
    except StoreError as exc:
        raise StartupError(f"the action log in {state_dir} cannot be read: {exc}") from exc
    if step > 0:
        log.info("continuing at action %d: the cell's and the learning's random seeds are drawn from "
                 "(seed, %d)", step, step)
    return step


def start_network(learning: LearningStack, policy: str | None) -> QMapNetwork:
    """Resume from the newest readable checkpoint; else the given policy; else a fresh network."""
    from flgd.learning.policy_file import PolicyFileError
    from flgd.learning.trunk import TrunkFileError

    try:
        return learning.start_from(policy)
    except (PolicyFileError, TrunkFileError) as exc:
        raise StartupError(str(exc)) from exc


def load_prior(learning: LearningStack, rotations: int) -> None:
    """The fine-tune's prior sample (``finetune.prior_sample``), loaded once for every learner built."""
    from flgd.learning.prior_sample import PriorSampleError

    try:
        learning.load_prior(rotations)
    except PriorSampleError as exc:
        raise StartupError(f"finetune.prior_sample: {exc}") from exc


def connect_cell(config: CellConfig) -> Cell:
    """The configured cell, connected (``flgd.cell.make_cell``)."""
    try:
        return make_cell(config)
    except CellFault as exc:
        raise StartupError(f"cell {config.backend!r} failed to connect: {exc}") from exc
    except (ValueError, ImportError, OSError, RuntimeError) as exc:
        raise StartupError(f"cell {config.backend!r} cannot be created: {exc}") from exc


def gate_errors() -> tuple[type[Exception], ...]:
    """What building the gate raises when it cannot restore a policy to act with, or its records cannot be used."""
    from flgd.gate.keeper import GateError
    from flgd.learning.policy_file import PolicyFileError

    return (GateError, PolicyFileError, StoreError, OSError)


def gate_problem(exc: BaseException, state_dir: Path) -> str:
    """One of ``gate_errors`` in an operator's words."""
    from flgd.gate.keeper import GateError
    from flgd.learning.policy_file import PolicyFileError

    if isinstance(exc, (GateError, PolicyFileError)):
        return f"no policy to act with: {exc}"
    return f"the gate's records in {state_dir} cannot be used: {exc}"


def log_trainer_state(outcome: TrainerStateRestore, state_dir: Path, resumed_from_checkpoint: bool) -> None:
    """What a resumed learner's target network and Adam moments started from, in the log (status shows it too)."""
    from flgd.training.state import TRAINER_STATE

    said = outcome.describe()
    if outcome.restored:
        log.info("trainer state %s from %s", said, state_dir / TRAINER_STATE)
    elif outcome.problem:
        log.warning("trainer state not used: %s", said)
    elif outcome.other_update is not None:
        log.warning("trainer state: %s", said)
    elif resumed_from_checkpoint:
        log.info("trainer state: %s", said)
