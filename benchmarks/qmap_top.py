"""``flgd bench qmap_top``: how flat the top of a policy's grasp Q-maps is, on fresh 20-block clutter.

Why: a greedy policy acts on the arg-max of 16 x 224 x 224 grasp values.  When
a large share of them sits within a few hundredths of the maximum, the arg-max
is decided by noise among grasps the network no longer tells apart, and frozen
grasp success falls although training success looked fine.  The pre-trained-trunk
runs showed exactly that (BENCHMARKS.md, "Flatness of the grasp Q-maps"): their maps flattened as training went on while the shipped policy's
stayed peaked.  This measures it for any policy files, on the same scenes.

For each scene (``--scenes`` random clutter of ``--count`` blocks, seeded) the
heightmaps are captured once; for each policy the grasp channel of every
rotation is read on the grasp mask (where objects are, as the agent masks it).
Reported per policy, as the median over scenes: the maximum grasp Q, the median
grasp Q on objects, and the share of masked pixel x rotation values within
0.02 / 0.05 / 0.10 of that scene's maximum.  No action is executed.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = REPO / "cell_config" / "sim.yaml"
MARGINS = (0.02, 0.05, 0.10)

__all__ = ["MARGINS", "top_shares", "main"]


def top_shares(grasp_q: np.ndarray, mask: np.ndarray, margins: tuple[float, ...] = MARGINS) -> tuple[float, list[float]]:
    """(max, shares): the maximum of ``grasp_q`` [R,H,W] on ``mask`` [H,W], and for each margin the fraction of
    masked values (all rotations) within that margin of the maximum."""
    q = np.asarray(grasp_q, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if q.ndim != 3 or q.shape[1:] != m.shape:
        raise ValueError(f"grasp_q {q.shape} and mask {m.shape}: expected [R,H,W] and [H,W]")
    if not m.any():
        raise ValueError("the mask is empty: no object pixel to measure")
    values = q[:, m]
    top = float(values.max())
    return top, [float((values >= top - d).mean()) for d in margins]


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="flgd bench qmap_top", description=__doc__.splitlines()[0])
    ap.add_argument("--policy", nargs="+", required=True, help="policy files (checkpoints too)")
    ap.add_argument("--config", default=str(DEFAULT_CONFIG))
    ap.add_argument("--scenes", type=int, default=24)
    ap.add_argument("--count", type=int, default=20, help="blocks per scene")
    ap.add_argument("--seed", type=int, default=11, help="scene seed (not one of the validation seeds 7-10)")
    args = ap.parse_args(argv)
    if args.scenes < 1 or args.count < 1:
        print("flgd bench qmap_top: --scenes and --count must be >= 1", file=sys.stderr)
        return 1

    import torch

    from flgd.clutter import grasp_mask
    from flgd.config import ConfigError, load_config
    from flgd.learning.networks import q_maps
    from flgd.learning.policy_file import PolicyFileError, load_policy
    from flgd.perception import frame_heightmaps
    from sim_cell.cell import SimCell

    try:
        config = load_config(args.config)
        networks = [(p, load_policy(p).network.eval()) for p in args.policy]
    except (ConfigError, PolicyFileError, OSError) as exc:
        print(f"flgd bench qmap_top: {exc}", file=sys.stderr)
        return 1
    config = dataclasses.replace(config, sim=dataclasses.replace(config.sim, seed=args.seed, object_set="blocks"))
    cell = SimCell(config)
    try:
        states = []
        for _ in range(args.scenes):
            cell.make_clutter(args.count)
            hm = frame_heightmaps(cell.capture(), config.workspace, config.camera.depth_range)
            mask = grasp_mask(np.asarray(hm.height), config.rewards, config.workspace.resolution)
            if mask.any():   # a scene whose blocks all fell off the table has nothing to measure
                states.append((hm, mask))
    finally:
        cell.close()

    print(f"# flgd bench qmap_top {' '.join(argv)}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cpus; {args.scenes} scenes of {args.count} blocks, "
          f"seed {args.seed}; medians over scenes")
    heads = " | ".join(f"within {d:.2f} of max" for d in MARGINS)
    print(f"\n| policy | max grasp Q | median grasp Q on objects | {heads} |\n|---|---|---|" + "---|" * len(MARGINS))
    for path, net in networks:
        tops, medians, shares = [], [], []
        for hm, mask in states:
            with torch.inference_mode():
                grasp = q_maps(net, hm, config.learning.rotations).numpy()[:, 0]
            top, share = top_shares(grasp, mask)
            tops.append(top)
            medians.append(float(np.median(grasp[:, mask])))
            shares.append(share)
        if not tops:
            print(f"| {path} | no scene with objects |" + " - |" * (1 + len(MARGINS)))
            continue
        mid = np.median(np.asarray(shares), axis=0)
        cells = " | ".join(f"{100 * s:.2f} %" for s in mid)
        print(f"| {path} | {np.median(tops):.2f} | {np.median(medians):.2f} | {cells} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
