"""Step 1 of rule.md: which side-taper limits separate the lifted objects that fell from those carried out.

Reads `flgd bench drops` JSONs (each record's `taper_mm`: the two sides' tapers of the grasp that lifted it) and
prints, for each limit L, the share of falls and of carries whose grasp the limit would have refused (larger taper
> L), and the share of all grasps it refuses.  Usage: python candidates.py DROPS.json [DROPS.json ...]
"""

from __future__ import annotations

import json
import sys

LIMITS_MM = (2.0, 4.0, 6.0, 8.0)


def fate(record: dict) -> str | None:
    """carried (released at the place), fell (dropped out of the cell or left the gripper before the place
    opened it), or None (lifted again, or still followed when the run ended)."""
    left = record.get("left_at")
    if record.get("dropped"):
        return "fell"
    if left and left.endswith(":open") and not record.get("lost"):
        return "carried"
    if left and (left.startswith("grasp:") or left.startswith("place:")):
        return "fell"
    return None


def main(paths: list[str]) -> dict:
    records, grasps = [], []
    for path in paths:
        data = json.load(open(path))
        records += [r for r in data["records"] if r.get("taper_mm")]
        grasps += [g for g in data.get("grasp_tapers_mm", []) if g]
    by = {k: [max(r["taper_mm"]) for r in records if fate(r) == k] for k in ("fell", "carried")}
    out = {"fell": len(by["fell"]), "carried": len(by["carried"]), "grasps": len(grasps), "limits": {}}
    for limit in LIMITS_MM:
        f = sum(t > limit for t in by["fell"]) / max(len(by["fell"]), 1)
        c = sum(t > limit for t in by["carried"]) / max(len(by["carried"]), 1)
        g = sum(max(t) > limit for t in grasps) / max(len(grasps), 1)
        out["limits"][f"{limit:g} mm"] = {"fell_refused": round(f, 3), "carried_refused": round(c, 3),
                                          "grasps_refused": round(g, 3), "score": round(f - c, 3)}
    return out


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1:]), indent=1))
