"""Copy a training run's checkpoint out as a shipped policy, with a metadata JSON and the learning curve.

    python -m flgd.training.export RUN_DIR DEST.safetensors [--checkpoint latest|best|FILE]

The policy file is copied byte for byte (its checksums stay valid); next to it
go ``DEST.json`` (the policy's own metadata, the run's settings and segments,
the rolling success at the checkpoint, the command that resumes the run) and
``DEST-curve.png`` (the run's curve up to the checkpoint's step).  ``best``
picks the checkpoint with the highest rolling success over the last 200
grasps recorded in its metadata (training-time success, not a held-out test).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from flgd.learning.policy_file import PolicyFileError, load_policy, read_metadata
from flgd.training.actions_csv import read_rows
from flgd.training.curve import plot_curves
from flgd.training.run import RUN_FILE, read_run_info

__all__ = ["choose_checkpoint", "export_policy", "main"]


def choose_checkpoint(run_dir: Path, which: str) -> Path:
    ckpts = sorted((run_dir / "checkpoints").glob("checkpoint-*.safetensors"))
    if which not in ("latest", "best"):
        path = Path(which)
        if not path.exists():
            raise FileNotFoundError(f"--checkpoint: {path} does not exist")
        return path
    if not ckpts:
        raise FileNotFoundError(f"{run_dir}/checkpoints: no checkpoint yet")
    if which == "latest":
        return ckpts[-1]

    def score(p: Path) -> float:
        v = read_metadata(p).get("rolling_success_200")
        return -1.0 if v is None else float(v)

    return max(ckpts, key=lambda p: (score(p), p.name))


def export_policy(run_dir: Path, dest: Path, which: str = "latest") -> dict:
    """Copy the chosen checkpoint to ``dest`` and write ``dest``.json and ``dest``-curve.png; returns the JSON."""
    src = choose_checkpoint(run_dir, which)
    loaded = load_policy(src)  # refuse to ship a file that does not load
    meta = loaded.metadata
    run = read_run_info(run_dir)
    if run is None:
        raise FileNotFoundError(f"{run_dir / RUN_FILE}: does not exist; expected a flgd train run directory")
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".{dest.name}.tmp")
    shutil.copyfile(src, tmp)
    tmp.replace(dest)
    steps = int(meta["training_steps"])
    rows = [r for r in read_rows(run_dir / "actions.csv") if r.get("step") and int(r["step"]) < steps]
    curve = dest.with_name(dest.stem + "-curve.png")
    plot_curves(curve, {meta.get("train_variant", meta["variant"]): rows},
                title=f"{dest.name}: {steps} training steps in sim_cell")
    info = {
        "policy": dest.name,
        "size_bytes": dest.stat().st_size,
        "exported_from": str(src),
        "checkpoint_choice": which,
        "policy_metadata": {k: v for k, v in meta.items() if k != "shapes"},
        "run_settings": run.get("settings"),
        "run_segments": run.get("segments"),
        "run_status_at_export": {"status": run.get("status"), "step": run.get("step")},
        "learning_curve": curve.name,
        "resume_command": f"flgd train --out {run_dir}",
    }
    dest.with_suffix(".json").write_text(json.dumps(info, indent=2) + "\n")
    return info


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m flgd.training.export", description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("dest")
    ap.add_argument("--checkpoint", default="latest", help="latest, best, or a checkpoint file")
    args = ap.parse_args(argv)
    try:
        # the run as the command line named it: a relative name stays relative in the JSON
        info = export_policy(Path(args.run_dir), Path(args.dest), args.checkpoint)
    except (FileNotFoundError, PolicyFileError, OSError, ValueError) as exc:
        print(f"export: {exc}", file=sys.stderr)
        return 1
    m = info["policy_metadata"]
    print(f"{args.dest}: {m['variant']} after {m['training_steps']} steps, rolling success (200) "
          f"{m.get('rolling_success_200')}, {info['size_bytes']} bytes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
