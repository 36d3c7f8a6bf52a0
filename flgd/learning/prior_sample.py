"""A prior sample: transitions from the cell a policy was trained in, replayed beside a new cell's own.

Why: a fine-tune learns only from the new cell's few hundred transitions, and a network that sees nothing
else can forget what it knew (the fine-tuning dip).  Mixing a fixed share of each batch from a sample of the
training cell's transitions keeps the old task in every update (the rehearsal used against forgetting in
continual learning).  The sample is data, not weights: it holds heightmaps, actions and rewards, so it serves
whichever policy acts.

File format (NumPy ``.npz``, read with ``allow_pickle=False``; one array per key):

* ``format``         -- the string ``flgd-prior-sample/1``;
* ``states``         -- uint8, every distinct state packed as the replay packs it (uint8 colour + float16
  height, zlib) and concatenated; ``state_offsets`` (int64, one more than the states) cuts it;
* ``state``, ``next_state`` -- int64 per transition: indices into the states; ``next_state`` -1 = none (done);
* ``primitive``      -- int8 per transition, an index into ``flgd.actions.PRIMITIVES``;
* ``row``, ``col``, ``rotation`` -- int32 per transition; ``rotations`` -- the rotation count (scalar);
* ``reward``         -- float32; ``done`` -- bool per transition;
* ``source``         -- a JSON string: where the transitions came from.

``flgd prior-sample STATE_DIR OUT.npz`` writes one from the store of a stopped daemon or run.
"""

from __future__ import annotations

import argparse
import json
import sys
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from flgd.actions import PRIMITIVES, Action
from flgd.learning.replay import Transition, pack_heightmaps, state_key, unpack_heightmaps

if TYPE_CHECKING:
    from flgd.perception import Heightmaps

__all__ = ["FORMAT", "PriorSample", "PriorSampleError", "load_prior_sample", "write_prior_sample",
           "sample_from_store", "main"]

FORMAT = "flgd-prior-sample/1"
MAX_PRIOR_BYTES = 512 * 1024 * 1024  # a sample of a few hundred transitions is a few MB
_PER_TRANSITION = ("state", "next_state", "primitive", "row", "col", "rotation", "reward", "done")
_KEYS = ("format", "states", "state_offsets", "rotations", "source") + _PER_TRANSITION
_INTEGER = ("iu", "integers")
_DTYPES = (("format", "U", "text"), ("source", "U", "text"), ("states", "u", "bytes (uint8)"),
           ("state_offsets", *_INTEGER), ("rotations", *_INTEGER), ("state", *_INTEGER), ("next_state", *_INTEGER),
           ("primitive", *_INTEGER), ("row", *_INTEGER), ("col", *_INTEGER), ("rotation", *_INTEGER),
           ("reward", "fiu", "numbers"), ("done", "b", "booleans"))


class PriorSampleError(ValueError):
    """The prior sample file cannot be used; the message names the file, the key and what was expected."""


@dataclass(frozen=True)
class PriorSample:
    """The transitions of a prior sample, ready to be mixed into the learner's batches."""

    path: str
    transitions: tuple[Transition, ...]
    source: dict[str, Any]

    def __len__(self) -> int:
        return len(self.transitions)

    def draw(self, count: int, rng: np.random.Generator) -> list[Transition]:
        """``count`` transitions drawn uniformly (with replacement across calls, without within one)."""
        n = len(self.transitions)
        picks = rng.choice(n, size=count, replace=count > n)
        return [self.transitions[int(i)] for i in picks]


def write_prior_sample(path: str | Path, transitions: list[Transition], source: dict[str, Any]) -> int:
    """Write ``transitions`` to ``path`` (see the module doc); returns the number of distinct states stored.

    A state shared by several transitions (s' of one is s of the next) is stored once.
    """
    if not transitions:
        raise ValueError("a prior sample needs at least one transition")
    rotations = {t.action.rotations for t in transitions}
    if len(rotations) != 1:
        raise ValueError(f"transitions with different rotation counts: {sorted(rotations)}")
    index: dict[bytes, int] = {}
    blobs: list[bytes] = []

    def put(hm: Heightmaps) -> int:
        key = state_key(hm)
        if key not in index:
            index[key] = len(blobs)
            blobs.append(pack_heightmaps(hm))
        return index[key]

    state = [put(t.state) for t in transitions]
    next_state = [-1 if t.next_state is None else put(t.next_state) for t in transitions]
    offsets = np.cumsum([0] + [len(b) for b in blobs]).astype(np.int64)
    arrays: dict[str, Any] = {
        "format": np.array(FORMAT),
        "states": np.frombuffer(b"".join(blobs), dtype=np.uint8),
        "state_offsets": offsets,
        "rotations": np.array(rotations.pop(), dtype=np.int32),
        "source": np.array(json.dumps(source, sort_keys=True)),
        "state": np.array(state, dtype=np.int64),
        "next_state": np.array(next_state, dtype=np.int64),
        "primitive": np.array([PRIMITIVES.index(t.action.primitive) for t in transitions], dtype=np.int8),
        "row": np.array([t.action.row for t in transitions], dtype=np.int32),
        "col": np.array([t.action.col for t in transitions], dtype=np.int32),
        "rotation": np.array([t.action.rotation for t in transitions], dtype=np.int32),
        "reward": np.array([t.reward for t in transitions], dtype=np.float32),
        "done": np.array([t.done for t in transitions], dtype=bool),
    }
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:  # a file object: np.savez would otherwise append ".npz" to the name
        np.savez(f, **arrays)
    tmp.replace(path)
    return len(blobs)


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    where = f"prior sample {path}"
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise PriorSampleError(f"{where}: cannot be read ({exc.strerror or exc}); expected a file written by "
                               "`flgd prior-sample`") from None
    if not path.is_file():
        raise PriorSampleError(f"{where}: is not a file")
    if size > MAX_PRIOR_BYTES:
        raise PriorSampleError(f"{where}: {size} bytes, expected at most {MAX_PRIOR_BYTES}")
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in _KEYS if k not in data.files]
            if missing:
                raise PriorSampleError(f"{where}: missing key(s) {', '.join(missing)}; expected the keys of "
                                       f"{FORMAT} ({', '.join(_KEYS)})")
            return {k: data[k] for k in _KEYS}
    except PriorSampleError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise PriorSampleError(f"{where}: not a readable .npz file ({exc}); expected a file written by "
                               "`flgd prior-sample`") from None


def load_prior_sample(path: str | Path, rotations: int, shape: tuple[int, int]) -> PriorSample:
    """The sample at ``path``, checked against the network's ``rotations`` and the cell's heightmap ``shape``.

    Raises PriorSampleError naming the file, the key and the value for anything that does not fit: every
    transition is checked here, so that a bad one can never reach (and fail) an update.
    """
    path = Path(path)
    a = _read_arrays(path)
    where = f"prior sample {path}"
    fmt = str(a["format"]) if a["format"].ndim == 0 else repr(a["format"])
    if fmt != FORMAT:
        raise PriorSampleError(f"{where}: format is {fmt!r}, expected {FORMAT!r}")
    for key, kinds, what in _DTYPES:
        if a[key].dtype.kind not in kinds:
            raise PriorSampleError(f"{where}: key {key} holds {a[key].dtype}, expected {what}")
    n = int(a["state"].shape[0]) if a["state"].ndim == 1 else -1
    for key in _PER_TRANSITION:
        if a[key].ndim != 1 or a[key].shape[0] != n:
            raise PriorSampleError(f"{where}: key {key} has shape {a[key].shape}, expected ({n},) like 'state'")
    if n == 0:
        raise PriorSampleError(f"{where}: holds no transitions, expected at least one")
    if a["rotations"].ndim != 0 or int(a["rotations"]) != rotations:
        raise PriorSampleError(f"{where}: rotations is {a['rotations'].tolist()!r}, expected {rotations} "
                               "(the network's rotation count)")
    offsets = a["state_offsets"]
    blob = a["states"]
    if (offsets.ndim != 1 or offsets.shape[0] < 2 or offsets[0] != 0 or offsets[-1] != blob.shape[0]
            or np.any(np.diff(offsets) <= 0)):
        raise PriorSampleError(f"{where}: state_offsets do not cut 'states' ({blob.shape[0]} bytes) into "
                               "states, expected increasing offsets from 0 to its length")
    n_states = offsets.shape[0] - 1
    for key, low in (("state", 0), ("next_state", -1)):
        bad = np.flatnonzero((a[key] < low) | (a[key] >= n_states))
        if bad.size:
            raise PriorSampleError(f"{where}: {key}[{bad[0]}] is {int(a[key][bad[0]])}, expected {low}.."
                                   f"{n_states - 1} (the stored states)")
    bad = np.flatnonzero((a["next_state"] < 0) & ~a["done"].astype(bool))
    if bad.size:
        raise PriorSampleError(f"{where}: transition {bad[0]} has no next_state but done is false")
    bad = np.flatnonzero((a["primitive"] < 0) | (a["primitive"] >= len(PRIMITIVES)))
    if bad.size:
        raise PriorSampleError(f"{where}: primitive[{bad[0]}] is {int(a['primitive'][bad[0]])}, expected 0.."
                               f"{len(PRIMITIVES) - 1} ({', '.join(PRIMITIVES)})")
    for key, hi in (("row", shape[0]), ("col", shape[1]), ("rotation", rotations)):
        bad = np.flatnonzero((a[key] < 0) | (a[key] >= hi))
        if bad.size:
            raise PriorSampleError(f"{where}: {key}[{bad[0]}] is {int(a[key][bad[0]])}, expected 0..{hi - 1}")
    bad = np.flatnonzero(~np.isfinite(a["reward"]))
    if bad.size:
        raise PriorSampleError(f"{where}: reward[{bad[0]}] is {a['reward'][bad[0]]}, expected a finite number")
    try:
        source = json.loads(str(a["source"]))
    except (json.JSONDecodeError, TypeError):
        raise PriorSampleError(f"{where}: source is not JSON, expected a JSON object") from None

    states = []
    for k in range(n_states):
        piece = blob[offsets[k]:offsets[k + 1]].tobytes()
        try:
            hm = unpack_heightmaps(piece)
        except (zlib.error, ValueError) as exc:
            raise PriorSampleError(f"{where}: state {k} cannot be unpacked ({exc})") from None
        if tuple(hm.height.shape) != tuple(shape):
            raise PriorSampleError(f"{where}: state {k} is a {hm.height.shape[0]}x{hm.height.shape[1]} heightmap, "
                                   f"expected {shape[0]}x{shape[1]} (this cell's workspace at its resolution)")
        states.append(hm)
    keys = [state_key(hm) for hm in states]
    transitions = []
    for i in range(n):
        nxt = int(a["next_state"][i])
        action = Action(PRIMITIVES[int(a["primitive"][i])], int(a["row"][i]), int(a["col"][i]),
                        int(a["rotation"][i]), rotations)
        transitions.append(Transition(states[int(a["state"][i])], action, float(a["reward"][i]),
                                      None if nxt < 0 else states[nxt], bool(a["done"][i]),
                                      next_key=None if nxt < 0 else keys[nxt]))
    return PriorSample(str(path), tuple(transitions), source if isinstance(source, dict) else {"source": source})


def sample_from_store(state_dir: str | Path, count: int, seed: int = 0) -> tuple[list[Transition], dict[str, Any]]:
    """``count`` transitions drawn at random from the store in ``state_dir`` (all when it holds fewer)."""
    from flgd.store import Store

    store = Store(state_dir)
    try:
        total = store.transition_count()
        rng = np.random.default_rng(seed)
        picks = set(rng.choice(total, size=min(count, total), replace=False).tolist()) if total else set()
        # streamed: a full store holds 20,000 states, far more than need to be in memory at once
        chosen = [st for k, st in enumerate(store.iter_transitions()) if k in picks]
    finally:
        store.close()
    transitions = [Transition(st.state, st.action, st.reward, st.next_state, st.done) for st in chosen]
    source = {"state_dir": Path(state_dir).name, "stored_transitions": total, "count": len(chosen),
              "seed": seed, "steps": [st.step for st in chosen]}
    return transitions, source


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="flgd prior-sample",
        description="Write a prior sample (finetune.prior_sample) from the transitions a stopped daemon or run "
                    "stored in STATE_DIR: --count of them drawn at random.")
    parser.add_argument("state_dir")
    parser.add_argument("out", help="the .npz file to write")
    parser.add_argument("--count", type=int, default=300, help="transitions to draw (default 300)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the draw")
    args = parser.parse_args(argv)
    if args.count < 1:
        print(f"flgd prior-sample: --count is {args.count}, expected at least 1", file=sys.stderr)
        return 2
    if not (Path(args.state_dir) / "flgd.sqlite").is_file():
        print(f"flgd prior-sample: {args.state_dir} holds no store (flgd.sqlite), expected the state directory "
              "of a daemon or run", file=sys.stderr)
        return 2
    transitions, source = sample_from_store(args.state_dir, args.count, args.seed)
    if not transitions:
        print(f"flgd prior-sample: the store in {args.state_dir} holds no transitions", file=sys.stderr)
        return 1
    states = write_prior_sample(args.out, transitions, source)
    print(f"wrote {args.out}: {len(transitions)} transitions, {states} states, "
          f"{Path(args.out).stat().st_size / 1e6:.1f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
