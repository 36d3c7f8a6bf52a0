"""What ``flgd run`` checks before it claims the socket or touches the cell: things an operator must fix.

Why a separate step: each of these used to surface late and sideways (a state
directory that is a file as a FAULT saying "unexpected storage error
(FileExistsError ...)", a ``--policy`` that does not exist not at all when a
checkpoint was there).  Here each is one line naming the file, the key and
what was expected, and the daemon exits before anything moves.
"""

from __future__ import annotations

import logging
from pathlib import Path

from flgd.config import CellConfig

__all__ = ["PreflightError", "check_state_dir", "check_policy", "warn_if_policy_unused"]

log = logging.getLogger("flgd")


class PreflightError(RuntimeError):
    """The daemon must not start; the message says what to fix."""


def check_state_dir(config: CellConfig) -> None:
    """``state_dir`` must be a directory, or a path where one can be made (every existing part a directory)."""
    path = Path(config.state_dir)
    probe = path
    while True:
        if probe.exists() or probe.is_symlink():
            if not probe.is_dir():
                what = "is a file" if probe.is_file() else "exists and is not a directory"
                where = "" if probe == path else f" (it is part of {path})"
                raise PreflightError(f"config {config.source}: state_dir: {probe} {what}{where}, expected a "
                                     "directory where flgd keeps its store and checkpoints")
            return
        if probe.parent == probe:
            return
        probe = probe.parent


def check_policy(config: CellConfig, policy_arg: str | None) -> str | None:
    """The policy file ``flgd run`` was asked to start from, checked; None if none was named.

    A named file must exist and be a policy this cell can run (variant and rotations of the config),
    even when a checkpoint will take precedence over it: a mistyped name must not go unnoticed.
    """
    from flgd.learning.policy_file import PolicyFileError, check_fits, read_metadata

    path = policy_arg or config.policy or None
    if not path:
        return None
    where = "--policy" if policy_arg else f"config {config.source}: policy"
    try:
        check_fits(path, read_metadata(path), config.learning.network, {"rotations": config.learning.rotations})
    except PolicyFileError as exc:
        raise PreflightError(f"{where}: {exc}") from None
    return str(path)


def warn_if_policy_unused(policy: str | None, acting: str, learner_source: str, state_dir: str) -> None:
    """One log line when the named policy is not what the daemon acts with (the gate's champion is) or not what
    the learner resumes from (a checkpoint is)."""
    if not policy:
        return
    if policy not in acting:
        log.warning("policy %s is not acting: the gate's %s acts (state directory %s); to make %s act, "
                    "flgctl policy load it", policy, acting, state_dir, policy)
    elif policy not in learner_source:
        log.warning("policy %s acts as the champion; learning resumes from the %s in %s (to learn from %s "
                    "instead, flgctl policy load it)", policy, learner_source, state_dir, policy)
