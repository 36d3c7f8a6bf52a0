"""The action logs of a `flgd bench emulated` root: pushes, the median cycle of a successful pick (cell clock), and
how many stored states have a point above 0.15 m / 0.2 m.  Usage: python action_logs.py ROOT > OUT.json"""

from __future__ import annotations

import json
import sqlite3
import sys

import numpy as np

from flgd.store.replay_rows import decode_heightmaps


def backend_logs(db: sqlite3.Connection) -> dict:
    rows = db.execute("select primitive, success, cell_time, outcome from actions order by step").fetchall()
    picks = [r[2] for r in rows if r[0] == "grasp" and r[1] == 1 and r[2] is not None]
    states = over_15 = over_20 = 0
    for n_rows, n_cols, color, height in db.execute("select rows, cols, color, height from states"):
        top = float(decode_heightmaps(n_rows, n_cols, color, height).height.max())
        states, over_15, over_20 = states + 1, over_15 + (top > 0.15), over_20 + (top > 0.2)
    return {"actions": len(rows), "pushes": sum(r[0] in ("push", "shift") for r in rows),
            "grasps": sum(r[0] == "grasp" for r in rows), "picks": len(picks),
            "median_cycle_of_a_pick_s": round(float(np.median(picks)), 3) if picks else None,
            "states": states, "states_over_0.15m": over_15, "states_over_0.2m": over_20,
            "outcomes": dict(db.execute("select outcome, count(*) from actions group by 1").fetchall())}


if __name__ == "__main__":
    root = sys.argv[1]
    print(json.dumps({b: backend_logs(sqlite3.connect(f"{root}/policy/{b}/state/flgd.sqlite"))
                      for b in ("sim", "emulated")}, indent=1))
