"""Generate the preset highly cluttered scenes shipped in sim_cell/scenes/.

FLG's curriculum sometimes restarts from a preset highly cluttered scene
(paper IV-A).  The presets are piles of 20-24 blocks dropped into a small
square, saved in the scene format so every run sees the same piles:

    python -m sim_cell.presets [--out DIR] [--config cell_config/sim.yaml]
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from flgd.config import load_config
from sim_cell.cell import PRESET_DIR, SimCell

# (file name, object count, spread m, seed)
PRESETS = (("pile-20-a", 20, 0.07, 101), ("pile-20-b", 20, 0.08, 202), ("pile-22-c", 22, 0.09, 303),
           ("pile-24-d", 24, 0.10, 404))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sim_cell.presets", description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(PRESET_DIR))
    ap.add_argument("--config", default=str(Path(__file__).resolve().parents[1] / "cell_config" / "sim.yaml"))
    args = ap.parse_args(argv)
    base = load_config(args.config)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, count, spread, seed in PRESETS:
        cfg = dataclasses.replace(base, sim=dataclasses.replace(base.sim, objects=0, seed=seed, scene=""))
        with SimCell(cfg) as cell:
            got = cell.make_clutter(count, spread)
            cell.simulate(1.0)
            cell.save_scene(out / f"{name}.yaml")
            print(f"{name}: {got} objects")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
