"""``flgd bench calibration_watch``: does the calibration watch stay quiet on a calibrated cell and speak up on a
moved camera?

Frames only: the watch needs nothing but the frame each cycle captures, so a sim cell captures (and lays out a new
scene every few frames) without moving the arm: a frame costs a render, not a cycle.

1. **Unmoved**: ``--frames`` (default 1,000) frames of the cell as configured (its depth noise, domain
   randomisation, packed scenes if ``--packed-scenes``): drift events (target: 0), frames without enough table,
   the largest single-frame and smoothed tilt and offset against the limits, and the fit's cost per frame.
2. **Moved**: for each camera error below (the config's ``camera_pose_error`` replaced), the frame at which the
   drift event came (target: within 20) and the estimate against the error's true effect on the table.  The last
   two are errors the table cannot show (a slide parallel to it, a turn about the vertical): reported, not judged.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import statistics
import time
from pathlib import Path

from flgd.calibration_watch import CalibrationWatch, fit_table_plane, table_points
from flgd.config import CameraPoseErrorConfig, load_config

REPO = Path(__file__).resolve().parents[1]
DEG = math.radians(1.0)
# (name, error, visible to the table?)
MOVES = [
    ("up 1 cm", CameraPoseErrorConfig(position=(0.0, 0.0, 0.01)), True),
    ("down 1 cm", CameraPoseErrorConfig(position=(0.0, 0.0, -0.01)), True),
    ("roll 1 deg", CameraPoseErrorConfig(rpy=(DEG, 0.0, 0.0)), True),
    ("pitch 1 deg", CameraPoseErrorConfig(rpy=(0.0, DEG, 0.0)), True),
    ("1 cm and 1 deg (0.58 cm each axis, 0.58 deg each axis)",
     CameraPoseErrorConfig(position=(0.00577, -0.00577, 0.00577), rpy=(0.577 * DEG, -0.577 * DEG, 0.577 * DEG)),
     True),
    ("sim-shifted.yaml (1.3 cm, 1.7 deg)", load_config(REPO / "cell_config" / "sim-shifted.yaml").sim.camera_pose_error,
     True),
    ("sideways 1 cm", CameraPoseErrorConfig(position=(0.007, 0.007, 0.0)), False),
    ("yaw 1 deg", CameraPoseErrorConfig(rpy=(0.0, 0.0, DEG)), False),
]


def _run(cfg, frames: int, new_scene_every: int, until_event: bool = False) -> dict:
    """Feed ``frames`` captures to a watch; what it saw."""
    from sim_cell.cell import SimCell

    watch = CalibrationWatch(cfg.calibration_watch, cfg.workspace, cfg.rewards, cfg.camera.depth_range)
    events, fit_ms = [], []
    worst = {"frame_tilt": 0.0, "frame_offset": 0.0, "smoothed_tilt": 0.0, "smoothed_offset": 0.0}
    with SimCell(cfg) as cell:
        for i in range(frames):
            if i and i % new_scene_every == 0:
                cell.reset_scene()
            frame = cell.capture()
            t0 = time.perf_counter()
            plane = fit_table_plane(table_points(frame.depth, frame.depth_scale, frame.intrinsics,
                                                 frame.camera_pose, cfg.workspace, cfg.camera.depth_range),
                                    cfg.workspace, cfg.rewards)
            fit_ms.append(1000 * (time.perf_counter() - t0))
            event = watch.observe(plane)
            if plane is not None:
                tilt, offset = watch.estimate()
                worst["frame_tilt"] = max(worst["frame_tilt"], plane.tilt_degrees)
                worst["frame_offset"] = max(worst["frame_offset"], abs(plane.offset))
                worst["smoothed_tilt"] = max(worst["smoothed_tilt"], tilt)
                worst["smoothed_offset"] = max(worst["smoothed_offset"], abs(offset))
            if event is not None:
                events.append({"frame": i + 1, "kind": event.kind, "message": event.message})
                if until_event:
                    break
    est = watch.estimate()
    return {"frames": watch.frames + watch.unjudged, "judged": watch.frames, "unjudged": watch.unjudged,
            "events": events, "estimate_tilt_degrees": None if est is None else round(est[0], 4),
            "estimate_offset_mm": None if est is None else round(1000 * est[1], 3),
            "max_frame_tilt_degrees": round(worst["frame_tilt"], 4),
            "max_frame_offset_mm": round(1000 * worst["frame_offset"], 3),
            "max_smoothed_tilt_degrees": round(worst["smoothed_tilt"], 4),
            "max_smoothed_offset_mm": round(1000 * worst["smoothed_offset"], 3),
            "fit_median_ms": round(statistics.median(fit_ms), 2) if fit_ms else None}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="flgd bench calibration_watch", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default=str(REPO / "cell_config" / "sim.yaml"), help="the sim cell (calibrated)")
    parser.add_argument("--frames", type=int, default=1000, help="frames of the unmoved cell (default 1000)")
    parser.add_argument("--moved-frames", type=int, default=20, help="frames given to each moved camera (20)")
    parser.add_argument("--new-scene-every", type=int, default=3, help="frames per scene (default 3)")
    parser.add_argument("--packed-scenes", type=float, default=None, help="override sim.packed_scenes")
    parser.add_argument("--seed", type=int, default=None, help="override sim.seed")
    parser.add_argument("--skip-moved", action="store_true", help="only the unmoved cell")
    parser.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    args = parser.parse_args(argv)
    cfg = load_config(Path(args.config))
    sim = cfg.sim
    if args.packed_scenes is not None:
        sim = dataclasses.replace(sim, packed_scenes=args.packed_scenes)
    if args.seed is not None:
        sim = dataclasses.replace(sim, seed=args.seed)
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(sim, camera_pose_error=CameraPoseErrorConfig()))
    cw = cfg.calibration_watch
    t0 = time.perf_counter()
    quiet = _run(cfg, args.frames, args.new_scene_every)
    config_name = os.path.relpath(Path(args.config).resolve(), REPO)
    result = {"benchmark": "calibration_watch", "config": config_name, "limits": dataclasses.asdict(cw),
              "packed_scenes": cfg.sim.packed_scenes, "seed": cfg.sim.seed,
              "machine": f"{platform.machine()} {os.cpu_count()} cpus, {platform.python_version()}",
              "unmoved": quiet, "unmoved_seconds": round(time.perf_counter() - t0, 1), "moved": []}
    print(f"unmoved: {quiet['frames']} frames ({quiet['unjudged']} with too little table), "
          f"{len(quiet['events'])} drift events (target 0); largest tilt {quiet['max_frame_tilt_degrees']:.3f} deg "
          f"in a frame, {quiet['max_smoothed_tilt_degrees']:.3f} smoothed (limit {cw.max_tilt_degrees:g}); largest "
          f"offset {quiet['max_frame_offset_mm']:.2f} mm in a frame, {quiet['max_smoothed_offset_mm']:.2f} smoothed "
          f"(limit {cw.max_offset_mm:g}); fit {quiet['fit_median_ms']} ms per frame")
    if not args.skip_moved:
        for name, error, visible in MOVES:
            moved = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, camera_pose_error=error))
            r = _run(moved, args.moved_frames, args.new_scene_every, until_event=True)
            first = next((e["frame"] for e in r["events"] if e["kind"] == "calibration_drift"), None)
            r.update({"name": name, "error": dataclasses.asdict(error), "visible": visible,
                      "drift_at_frame": first})
            result["moved"].append(r)
            verdict = f"drift at frame {first}" if first else f"no drift in {args.moved_frames} frames"
            print(f"moved {name}: {verdict}; estimate tilt {r['estimate_tilt_degrees']} deg, offset "
                  f"{r['estimate_offset_mm']} mm{'' if visible else ' (invisible to the table)'}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
    return 0
