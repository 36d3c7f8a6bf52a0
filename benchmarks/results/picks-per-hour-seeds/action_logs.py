"""The action logs of a `flgd bench emulated` root: pushes, the median cycle of a successful pick (cell clock), and
how many stored states have a point above 0.15 m / 0.2 m.  Usage: python action_logs.py ROOT > OUT.json"""
import json, sqlite3, sys
import numpy as np
from flgd.store.replay_rows import decode_heightmaps
root = sys.argv[1]
out = {}
for backend in ("sim", "emulated"):
    db = sqlite3.connect(f"{root}/policy/{backend}/state/flgd.sqlite")
    rows = db.execute("select primitive, success, cell_time, outcome, t_capture+t_perceive+t_decide+t_plan+t_judge+t_store, decide_hidden from actions order by step").fetchall()
    picks = [r[2] for r in rows if r[0] == "grasp" and r[1] == 1 and r[2] is not None]
    tall = [0, 0, 0]
    for rr, cc, color, height in db.execute("select rows, cols, color, height from states"):
        h = decode_heightmaps(rr, cc, color, height).height
        tall[0] += 1; tall[1] += int(h.max() > 0.15); tall[2] += int(h.max() > 0.2)
    out[backend] = {"actions": len(rows), "pushes": sum(r[0] in ("push", "shift") for r in rows),
                    "grasps": sum(r[0] == "grasp" for r in rows), "picks": len(picks),
                    "median_cycle_of_a_pick_s": round(float(np.median(picks)), 3) if picks else None,
                    "states": tall[0], "states_over_0.15m": tall[1], "states_over_0.2m": tall[2],
                    "outcomes": dict(db.execute("select outcome, count(*) from actions group by 1").fetchall())}
print(json.dumps(out, indent=1))
