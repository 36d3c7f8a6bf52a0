"""The openings the pre-shape gave the grasps of a `flgd bench emulated` row, recomputed from its stored states, and
the gripper time of its picks.  Usage: python openings.py ROOT > OUT.json (ROOT: the bench's --root)."""

from __future__ import annotations

import json
import sqlite3
import sys

import numpy as np

from flgd.actions import rotation_angle
from flgd.config import load_config
from flgd.finger_preshape import preshape_width
from flgd.plans import centred_grasp_pixel
from flgd.store.replay_rows import decode_heightmaps

MARGIN = 0.01   # rule.md's margin (the rows' gripper.preshape_margin)


def backend(root: str, name: str) -> dict:
    cfg = load_config(f"{root}/policy/{name}/cell.yaml")
    db = sqlite3.connect(f"{root}/policy/{name}/state/flgd.sqlite")
    rows = db.execute("select t.row, t.col, t.rotation, t.rotations, s.rows, s.cols, s.color, s.height, "
                      "a.gripper_time, a.success from actions a join transitions t on a.transition_id = t.id "
                      "join states s on t.state_id = s.id where a.primitive = 'grasp'").fetchall()
    openings, pick_gripper = [], []
    for r, c, rotation, rotations, n_rows, n_cols, color, height, gripper_time, success in rows:
        h = decode_heightmaps(n_rows, n_cols, color, height).height
        angle = rotation_angle(rotation, rotations)
        row, col = (centred_grasp_pixel(h, r, c, angle, cfg) if cfg.robot.grasp_centring > 0.0
                    else (float(r), float(c)))
        fingertips = max(float(h[r, c]) - cfg.robot.grasp_depth, cfg.safety.min_table_clearance)
        openings.append(preshape_width(h, row, col, angle, fingertips, cfg.gripper.open_width, MARGIN,
                                       cfg.workspace.resolution, cfg.rewards.min_height))
        if success == 1 and gripper_time is not None:
            pick_gripper.append(gripper_time)
    w, g = np.array(openings), np.array(pick_gripper)
    return {"grasps": len(w), "median_opening_m": round(float(np.median(w)), 4),
            "fully_open_share": round(float((w >= cfg.gripper.open_width).mean()), 3),
            "mean_closing_saved_s_at_110_mm_s": round(float(((cfg.gripper.open_width - w) / 0.11).mean()), 3),
            "picks": len(g), "pick_gripper_time_median_s": round(float(np.median(g)), 3),
            "pick_gripper_time_mean_s": round(float(g.mean()), 3)}


if __name__ == "__main__":
    print(json.dumps({name: backend(sys.argv[1], name) for name in ("sim", "emulated")}, indent=1))
