"""``flgd bench depth_model``: the simulated camera's depth against a D415's published numbers.

Why: a policy trained on a kinder camera than the cell's acts on what the real
one adds (specks, holes, shadows).  This renders random scenes of a cell config
twice from the same seed -- once with the config's depth noise, once without --
and reads off, pixel for pixel:

* on the flat table away from objects (Intel's flat-target conditions; the
  camera looking straight down): the share of pixels with a reading (fill
  rate; the datasheet promises >= 99 %), the RMS depth error without gross
  errors (both renders rounded to the depth unit, 1 mm: about 0.4 mm of it in
  quadrature) and the share of gross errors (|error| > 10 mm: outliers, flying
  pixels);
* over the whole frame and beside objects (within 6 px of one): the share of
  pixels without a reading the noise-free render had (edge holes, the stereo
  shadow, dropouts).

Beside them, the RMS error Intel's stereo formula gives at the table's distance,
z^2 * subpixel / (fx * baseline) with the D415's 55 mm baseline and a typical
subpixel of 0.08 (Intel, "Tuning depth cameras for best performance"), at this
config's fx and at the D415's best depth resolution (1280x720, 65 deg HFOV).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = REPO / "cell_config" / "sim.yaml"
D415_BASELINE = 0.055          # m, between the two imagers
D415_SUBPIXEL = 0.08           # px, Intel's typical subpixel for a well-textured target
D415_HD_FX = 640.0 / math.tan(math.radians(65.0 / 2))   # px at 1280x720, 65 deg horizontal field of view
D415_FILL_RATE = 0.99          # the datasheet's fill rate on a flat target
GROSS_ERROR = 0.010            # m: a reading off by more than this is an outlier, not noise
NEAR_OBJECT_PX = 6             # px: "beside an object"

__all__ = ["stereo_rms", "depth_stats", "main"]


def stereo_rms(z: float, fx: float, subpixel: float = D415_SUBPIXEL, baseline: float = D415_BASELINE) -> float:
    """Intel's RMS depth error (m) of a stereo camera at distance ``z`` (m) and focal length ``fx`` (px)."""
    return z * z * subpixel / (fx * baseline)


def depth_stats(noisy: np.ndarray, clean: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    """Per-frame numbers from metric depth with and without noise (0 = no reading) and the object labels
    (0 = no object) of the same render."""
    objects = labels != 0
    near = cv2.dilate(objects.astype(np.uint8), np.ones((2 * NEAR_OBJECT_PX + 1,) * 2, np.uint8)) > 0
    seen = clean > 0
    table_z = float(np.median(clean[seen & ~objects])) if (seen & ~objects).any() else 0.0
    flat = seen & ~near & (np.abs(clean - table_z) < 0.005)
    read = noisy > 0
    err = (noisy - clean)[flat & read]
    gross = np.abs(err) > GROSS_ERROR
    beside = seen & near & ~objects
    return {
        "table_z_m": table_z,
        "flat_pixels": int(flat.sum()),
        "flat_fill_rate": float(read[flat].mean()) if flat.any() else 0.0,
        "flat_rms_m": float(np.sqrt(np.mean(err[~gross] ** 2))) if (~gross).any() else 0.0,
        "flat_gross_share": float(gross.mean()) if err.size else 0.0,
        "frame_missing_share": float((seen & ~read).sum() / max(1, seen.sum())),
        "beside_objects_missing_share": float((beside & ~read).sum() / max(1, beside.sum())),
        "object_missing_share": float((objects & seen & ~read).sum() / max(1, (objects & seen).sum())),
    }


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="flgd bench depth_model", description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(DEFAULT_CONFIG), help="the cell whose camera is measured")
    ap.add_argument("--scenes", type=int, default=10, help="random scenes, each rendered with and without noise")
    ap.add_argument("--objects", type=int, default=10, help="objects per scene")
    ap.add_argument("--seed", type=int, default=0, help="seed of the first scene (each next one +1)")
    ap.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    args = ap.parse_args(argv)
    if args.scenes < 1 or args.objects < 0:
        print("flgd bench depth_model: --scenes must be >= 1 and --objects >= 0", file=sys.stderr)
        return 1

    from flgd.config import ConfigError, load_config
    from sim_cell.cell import SimCell

    try:
        config = load_config(args.config)
    except (ConfigError, OSError) as exc:
        print(f"flgd bench depth_model: {exc}", file=sys.stderr)
        return 1
    if not config.sim.depth_noise:
        print(f"flgd bench depth_model: {args.config}: sim.depth_noise is off, nothing to measure", file=sys.stderr)
        return 1
    scale = config.camera.depth_scale
    frames = []
    for i in range(args.scenes):
        sim = dataclasses.replace(config.sim, seed=args.seed + i, objects=args.objects)
        views = []
        for noise in (True, False):   # the scene draws do not depend on the noise: the same scene twice
            cell = SimCell(dataclasses.replace(config, sim=dataclasses.replace(sim, depth_noise=noise)))
            try:
                frame, labels = cell.capture_labelled()
            finally:
                cell.close()
            views.append((frame.depth.astype(np.float64) * scale, labels))
        (noisy, noisy_labels), (clean, labels) = views
        if not np.array_equal(noisy_labels, labels):
            print(f"flgd bench depth_model: scene seed {args.seed + i} drew a different scene with the noise off",
                  file=sys.stderr)
            return 1
        stats = depth_stats(noisy, clean, labels)
        if not stats["flat_pixels"]:
            print(f"flgd bench depth_model: scene seed {args.seed + i}: no flat table pixel away from objects (is "
                  f"the camera looking straight down at the table?)", file=sys.stderr)
            return 1
        frames.append(stats)

    def med(key: str) -> float:
        return float(np.median([f[key] for f in frames]))

    fx = float(config.camera.intrinsics.fx)
    z = med("table_z_m")
    result = {
        "benchmark": "depth_model", "config": str(args.config), "scenes": args.scenes, "objects": args.objects,
        "seed": args.seed, "machine": f"{platform.machine()} {os.cpu_count()} cpus, {platform.python_version()}",
        "model": {k: getattr(config.sim, k) for k in ("depth_noise_std", "depth_dropout", "depth_edge_holes",
                                                       "depth_outliers", "stereo_shadow")},
        "table_z_m": round(z, 4),
        "d415": {"rms_m_at_config_fx": round(stereo_rms(z, fx), 6), "rms_m_at_1280x720": round(stereo_rms(z, D415_HD_FX), 6),
                 "fill_rate_min": D415_FILL_RATE, "subpixel": D415_SUBPIXEL, "baseline_m": D415_BASELINE},
        "medians": {k: round(med(k), 6) for k in frames[0] if k not in ("table_z_m",)},
        "frames": frames,
    }
    m = result["medians"]
    print(f"# flgd bench depth_model {' '.join(argv)}")
    print(f"{args.scenes} scenes of {args.objects} objects from seed {args.seed}; medians over scenes; "
          f"table at {1000 * z:.0f} mm")
    print("| | D415 (Intel) | this cell |\n|---|---|---|")
    print(f"| RMS depth error, flat table | {1000 * stereo_rms(z, fx):.2f} mm at fx {fx:.0f}; "
          f"{1000 * stereo_rms(z, D415_HD_FX):.2f} mm at 1280x720 | {1000 * m['flat_rms_m']:.2f} mm |")
    print(f"| fill rate, flat table | >= {100 * D415_FILL_RATE:.0f} % | {100 * m['flat_fill_rate']:.2f} % |")
    print(f"| gross errors (> {1000 * GROSS_ERROR:.0f} mm), flat table | not published | "
          f"{100 * m['flat_gross_share']:.2f} % |")
    print(f"| no reading: whole frame / within {NEAR_OBJECT_PX} px beside objects / on objects | - | "
          f"{100 * m['frame_missing_share']:.2f} % / {100 * m['beside_objects_missing_share']:.1f} % / "
          f"{100 * m['object_missing_share']:.2f} % |")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
