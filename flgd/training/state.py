"""What a policy file does not hold but a resumed training run needs: target net, Adam, priorities.

Written next to each checkpoint as ``trainer-state.safetensors`` (atomic, like
policy files; safetensors so that loading never executes code).  It is used
on resume only when its ``updates`` equals the checkpoint's, otherwise the
learner starts with target = online weights, fresh Adam moments and the
replay's default priorities, and says so.

Tensors: ``target.<name>`` (target network), ``adam.<i>.<key>`` (per
parameter state of torch.optim.Adam), ``priority.ids`` (int64 store
transition ids), ``priority.values`` (float64 raw priorities), and the
remembered double-DQN a' of the replayed next states: ``argmax.keys`` (uint8,
one state key per row) and ``argmax.values`` (int64 rows of weights' update
count, rotation, channel, row, column; rotation -1 = nothing left to act on).
Without them a resumed learner with ``actor_argmax`` searches every replayed
next state again, a 16-rotation pass each; a state written before they
existed loads with none.
Metadata: ``updates`` and ``adam_groups`` (JSON of the hyper-parameters when saved; on restore the
configured ones are used, so an edited learning rate takes effect).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save

from flgd.atomic_file import remove_temporaries, write_atomically

__all__ = ["TRAINER_STATE", "TrainerState", "save_trainer_state", "load_trainer_state", "restore_learner",
           "remove_temporary"]

TRAINER_STATE = "trainer-state.safetensors"


@dataclass
class TrainerState:
    updates: int
    target: dict[str, torch.Tensor]
    adam_state: dict[int, dict[str, torch.Tensor]]
    adam_groups: list[dict]
    priority_ids: np.ndarray
    priorities: np.ndarray
    argmax: list[tuple[bytes, int, tuple[int, int, int, int] | None]] = field(default_factory=list)


def save_trainer_state(path: str | os.PathLike, learner, priority_ids: np.ndarray, priorities: np.ndarray) -> None:
    """Write the learner's target network, Adam state and the replay priorities (call with updates quiet)."""
    tensors: dict[str, torch.Tensor] = {}
    for k, v in learner.target.state_dict().items():
        tensors[f"target.{k}"] = v.detach().cpu().clone().contiguous()
    opt = learner.optimizer.state_dict()
    for i, st in opt["state"].items():
        for key, v in st.items():
            t = v if torch.is_tensor(v) else torch.tensor(float(v))
            tensors[f"adam.{int(i)}.{key}"] = t.detach().cpu().clone().contiguous()
    groups = [{k: v for k, v in g.items() if isinstance(v, (int, float, bool, list, tuple, type(None)))}
              for g in opt["param_groups"]]
    tensors["priority.ids"] = torch.from_numpy(np.asarray(priority_ids, dtype=np.int64).copy())
    tensors["priority.values"] = torch.from_numpy(np.asarray(priorities, dtype=np.float64).copy())
    remembered = learner.remembered_argmax()
    key_size = len(remembered[0][0]) if remembered else 16
    tensors["argmax.keys"] = torch.from_numpy(
        np.frombuffer(b"".join(key for key, _, _ in remembered), dtype=np.uint8).reshape(-1, key_size).copy())
    tensors["argmax.values"] = torch.tensor(
        [[version, *(index if index is not None else (-1, 0, 0, 0))] for _, version, index in remembered],
        dtype=torch.int64).reshape(-1, 5)
    meta = {"updates": str(int(learner.updates)), "adam_groups": json.dumps(groups)}
    data = save(tensors, metadata=meta)
    write_atomically(path, data)


def remove_temporary(directory: str | os.PathLike) -> int:
    """Delete ``.trainer-state.safetensors.*.tmp`` files of writes interrupted by a kill; how many.

    A trainer state is ~3x the policy's size, so each kill during a write would otherwise leave that much
    behind for good.  Call with the directory's writer not running (the daemon: at setup, under its lock).
    """
    return remove_temporaries(directory, TRAINER_STATE)


def load_trainer_state(path: str | os.PathLike) -> TrainerState:
    """Read a trainer state; anything unreadable or incomplete is a ValueError naming the file (OSError if absent)."""
    from safetensors import SafetensorError, safe_open

    path = Path(path)
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
        tensors = load_file(str(path))
    except SafetensorError as exc:  # not an Exception subclass its callers could otherwise expect
        raise ValueError(f"{path}: not a readable trainer state: {exc}") from None
    try:
        updates = int(meta["updates"])
        groups = json.loads(meta["adam_groups"])
        target = {k[len("target."):]: v for k, v in tensors.items() if k.startswith("target.")}
        adam: dict[int, dict[str, torch.Tensor]] = {}
        for k, v in tensors.items():
            if k.startswith("adam."):
                _, i, key = k.split(".", 2)
                adam.setdefault(int(i), {})[key] = v
        priority_ids, priorities = tensors["priority.ids"].numpy(), tensors["priority.values"].numpy()
        argmax = _remembered_argmax(tensors)
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"{path}: trainer state is incomplete: {exc!r}") from None
    return TrainerState(updates, target, adam, groups, priority_ids, priorities, argmax)


def _remembered_argmax(tensors: dict[str, torch.Tensor]) -> list[tuple[bytes, int, tuple[int, int, int, int] | None]]:
    """The saved a' entries; none in a state written before they were saved."""
    if "argmax.keys" not in tensors and "argmax.values" not in tensors:
        return []
    keys, values = tensors["argmax.keys"].numpy(), tensors["argmax.values"].numpy()
    if keys.ndim != 2 or values.ndim != 2 or values.shape[1] != 5 or len(keys) != len(values):
        raise ValueError(f"argmax.keys {keys.shape} and argmax.values {values.shape} do not pair up "
                         "(expected [n, key size] and [n, 5])")
    return [(row.tobytes(), int(v[0]), None if v[1] < 0 else (int(v[1]), int(v[2]), int(v[3]), int(v[4])))
            for row, v in zip(keys, values)]


def restore_learner(learner, state: TrainerState) -> None:
    """Load target weights and Adam state into ``learner``.

    Everything is checked against the learner's network before anything is loaded (a ValueError names the
    first misfit), so a state of another network leaves the learner untouched instead of half restored.
    """
    expected = learner.target.state_dict()
    if set(state.target) != set(expected):
        missing, extra = sorted(set(expected) - set(state.target)), sorted(set(state.target) - set(expected))
        raise ValueError(f"trainer state's target network does not fit: missing {missing[:3]}, "
                         f"unexpected {extra[:3]}")
    for name, tensor in expected.items():
        if tuple(state.target[name].shape) != tuple(tensor.shape):
            raise ValueError(f"trainer state's target.{name} has shape {tuple(state.target[name].shape)}, "
                             f"the network {tuple(tensor.shape)}")
    params = [p for g in learner.optimizer.param_groups for p in g["params"]]
    for i, st in state.adam_state.items():
        if not 0 <= i < len(params):
            raise ValueError(f"trainer state has Adam state for parameter {i}; the network has {len(params)}")
        for key in ("exp_avg", "exp_avg_sq"):
            if key in st and tuple(st[key].shape) != tuple(params[i].shape):
                raise ValueError(f"trainer state's adam.{i}.{key} has shape {tuple(st[key].shape)}, "
                                 f"parameter {i} {tuple(params[i].shape)}")
    if len(state.adam_groups) != len(learner.optimizer.param_groups):
        raise ValueError(f"trainer state has {len(state.adam_groups)} Adam parameter groups, the learner "
                         f"{len(learner.optimizer.param_groups)}")
    learner.target.load_state_dict(state.target)
    # The moments are state and come back; learning rate and the other settings stay the configured
    # ones, so that an edited config (say a lower learning rate to fine-tune) takes effect on resume.
    groups = learner.optimizer.state_dict()["param_groups"]
    learner.optimizer.load_state_dict({"state": {i: dict(s) for i, s in state.adam_state.items()},
                                       "param_groups": groups})
    learner.remember_argmax(state.argmax)
