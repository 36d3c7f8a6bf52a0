"""The rule's checks over the three rows: `python check.py [NEW_ROOT REF_ROOT]` (the `--root` folders of a clearance
row and its `picks-per-hour-home-read/` row, with `{seed}` in them, for the guarded moves stopped on contact, which
only the action logs hold).  Prints one JSON object."""

from __future__ import annotations

import json
import sqlite3
import statistics
import sys
from pathlib import Path

HERE = Path(__file__).parent
REF = HERE.parent / "picks-per-hour-home-read"
SEEDS = (0, 1, 2)


def contact_stops(root: str) -> dict[str, int]:
    out = {}
    for backend in ("sim", "emulated"):
        db = sqlite3.connect(f"{root}/policy/{backend}/state/flgd.sqlite")
        out[backend] = db.execute("select count(*) from actions where contact_stop_mm is not null "
                                  "and primitive = 'grasp'").fetchone()[0]
    return out


def main(argv: list[str]) -> dict:
    rows = []
    for s in SEEDS:
        new, ref = (json.loads((d / f"{n}-s{s}.json").read_text())["policy"]
                    for d, n in ((HERE, "clearance"), (REF, "home-read")))
        logs, ref_logs = (json.loads((d / f"{n}-s{s}-logs.json").read_text())
                          for d, n in ((HERE, "clearance"), (REF, "home-read")))
        e, sim = new["emulated"], new["sim"]
        row = {"seed": s, "picks_per_hour": round(e["picks_per_hour_cell_clock"], 1),
               "reference_picks_per_hour": round(ref["emulated"]["picks_per_hour_cell_clock"], 1),
               "emulated": [e["picks"], e["grasps"]], "sim": [sim["picks"], sim["grasps"]],
               "emulated_minus_sim_points": round(100 * (e["grasp_success"] - sim["grasp_success"]), 1),
               "protective_stops": logs["emulated"]["outcomes"].get("fault", 0),
               "states_over_0.2m": logs["emulated"]["states_over_0.2m"] + logs["sim"]["states_over_0.2m"],
               "pick_cycle_s": logs["emulated"]["median_cycle_of_a_pick_s"],
               "reference_pick_cycle_s": ref_logs["emulated"]["median_cycle_of_a_pick_s"]}
        if len(argv) == 2:
            row["contact_stops"] = contact_stops(argv[0].format(seed=s))
            row["reference_contact_stops"] = contact_stops(argv[1].format(seed=s))
        rows.append(row)
    pooled = {k: [sum(r[k][i] for r in rows) for i in (0, 1)] for k in ("emulated", "sim")}
    ref_pooled = {}
    for backend in ("emulated", "sim"):
        refs = [json.loads((REF / f"home-read-s{s}.json").read_text())["policy"][backend] for s in SEEDS]
        ref_pooled[backend] = [sum(r["picks"] for r in refs), sum(r["grasps"] for r in refs)]
    median = statistics.median(r["picks_per_hour"] for r in rows)
    check1 = (median >= 600 and all(abs(r["emulated_minus_sim_points"]) <= 3 for r in rows)
              and all(r["protective_stops"] <= 2 for r in rows) and all(r["states_over_0.2m"] == 0 for r in rows))
    rate = {k: 100 * v[0] / v[1] for k, v in pooled.items()}
    ref_rate = {k: 100 * v[0] / v[1] for k, v in ref_pooled.items()}
    check2 = (all(rate[k] >= ref_rate[k] - 2 for k in rate)
              and all(r["pick_cycle_s"] < r["reference_pick_cycle_s"] for r in rows)
              and sum(r["protective_stops"] for r in rows) <= 2
              and ("contact_stops" not in rows[0]
                   or sum(r["contact_stops"]["emulated"] for r in rows)
                   <= sum(r["reference_contact_stops"]["emulated"] for r in rows) + 10))
    return {"rows": rows, "pooled": pooled, "reference_pooled": ref_pooled,
            "pooled_percent": {k: round(v, 2) for k, v in rate.items()},
            "reference_pooled_percent": {k: round(v, 2) for k, v in ref_rate.items()},
            "median_picks_per_hour": median, "check1_met": check1, "check2_adopted": check2}


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1:]), indent=1))
