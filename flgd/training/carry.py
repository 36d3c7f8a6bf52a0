"""A compact copy of a training run that another machine can continue.

    python -m flgd.training.carry RUN_DIR DEST [--replay N]

A run directory holds the whole replay (13 KiB and more per state, a few hundred MB after a few thousand steps)
and three checkpoints; it does not outlive a machine that is handed back.  DEST gets what a resume needs and small
enough to commit: ``run.json``, ``config.yaml``, ``actions.csv`` and the curve, the latest checkpoint and the
trainer state written with it (target network, Adam moments), and a store with the full action log and events but
only the newest N transitions (default 300) with their priorities.  ``flgd train --out DEST`` then continues at the
run's step, update count, weights and optimizer state; what it loses is the older replay, so the continuation is
not the run it would have been on the first machine (run.json's next segment says where it came from).
DEST's ``config.yaml`` names its files relative to DEST, so a copy committed beside them names no machine's paths.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sqlite3
import sys
from dataclasses import dataclass
from pathlib import Path

from flgd.config import dump_config, load_config
from flgd.state_dir_lock import StateDirBusy, lock_state_dir
from flgd.store import DB_NAME, Store
from flgd.training.run import CONFIG_FILE, CURVE_FILE, LOG_FILE, RUN_FILE
from flgd.training.settings import portable_config
from flgd.training.state import TRAINER_STATE, load_trainer_state

__all__ = ["CarriedRun", "carry_run", "main"]

DEFAULT_REPLAY = 300


@dataclass(frozen=True)
class CarriedRun:
    dest: Path
    checkpoint: str
    updates: int
    transitions: int
    total_bytes: int


def _latest_checkpoint(run_dir: Path) -> Path:
    ckpts = sorted((run_dir / "checkpoints").glob("checkpoint-*.safetensors"))
    if not ckpts:
        raise FileNotFoundError(f"{run_dir / 'checkpoints'}: no checkpoint; expected a flgd train run directory "
                                "that has taken at least one checkpoint")
    return ckpts[-1]


def carry_run(run_dir: Path, dest: Path, replay: int = DEFAULT_REPLAY) -> CarriedRun:
    """Write the compact copy of ``run_dir`` to ``dest`` (which must not exist or be empty)."""
    if replay < 1:
        raise ValueError(f"--replay: got {replay!r}, expected >= 1 transitions")
    for name in (RUN_FILE, CONFIG_FILE, DB_NAME):
        if not (run_dir / name).is_file():
            raise FileNotFoundError(f"{run_dir / name}: does not exist; expected a flgd train run directory")
    if dest.exists() and any(dest.iterdir()):
        raise FileExistsError(f"{dest}: exists and is not empty; expected a new directory")
    config = load_config(run_dir / CONFIG_FILE)  # refuse a copy whose config the resume could not read
    checkpoint = _latest_checkpoint(run_dir)
    updates = int(checkpoint.stem.split("-")[-1])
    state = load_trainer_state(run_dir / TRAINER_STATE)  # refuse a copy that would resume without its optimizer
    if state.updates != updates:
        raise ValueError(f"{run_dir / TRAINER_STATE}: of update {state.updates}, the latest checkpoint "
                         f"{checkpoint.name} of {updates}; run `flgd train --out {run_dir}` and stop it with "
                         "Ctrl-C first, so that both are written together")
    try:
        fd = lock_state_dir(run_dir, create=False)  # a run still training there would change what is copied
    except StateDirBusy as exc:
        raise RuntimeError(f"{exc}; stop that run first") from None
    try:
        dest.mkdir(parents=True, exist_ok=True)
        (dest / "checkpoints").mkdir()
        for name in (RUN_FILE, LOG_FILE, CURVE_FILE, TRAINER_STATE):
            if (run_dir / name).is_file():
                shutil.copyfile(run_dir / name, dest / name)
        (dest / CONFIG_FILE).write_text(dump_config(portable_config(config, dest.resolve())))
        shutil.copyfile(checkpoint, dest / "checkpoints" / checkpoint.name)
        source = sqlite3.connect(run_dir / DB_NAME)
        try:
            target = sqlite3.connect(dest / DB_NAME)
            try:
                source.backup(target)  # a consistent copy, write-ahead log included
            finally:
                target.close()
        finally:
            source.close()
    finally:
        os.close(fd)
    store = Store(dest)
    try:
        store.prune(replay)
        transitions = store.transition_count()
    finally:
        store.close()
    db = sqlite3.connect(dest / DB_NAME, isolation_level=None)
    try:
        db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        db.execute("PRAGMA journal_mode=DELETE")  # one file, nothing beside it to forget in a commit
        db.execute("VACUUM")
    finally:
        db.close()
    total = sum(p.stat().st_size for p in dest.rglob("*") if p.is_file())
    return CarriedRun(dest, checkpoint.name, updates, transitions, total)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m flgd.training.carry", description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("dest")
    ap.add_argument("--replay", type=int, default=DEFAULT_REPLAY, help="newest transitions kept (default 300)")
    args = ap.parse_args(argv)
    try:
        carried = carry_run(Path(args.run_dir).resolve(), Path(args.dest), args.replay)
    except (FileNotFoundError, FileExistsError, RuntimeError, ValueError, OSError, sqlite3.Error) as exc:  # ConfigError is a ValueError
        print(f"carry: {exc}", file=sys.stderr)
        return 1
    print(f"{carried.dest}: {carried.checkpoint} ({carried.updates} updates), {carried.transitions} transitions, "
          f"{carried.total_bytes / 1e6:.1f} MB; continue with: flgd train --out {carried.dest}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
