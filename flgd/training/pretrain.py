"""``flgd pretrain``: perception pre-training of the fast network's trunk in sim_cell (see flgd.learning.trunk).

Two resumable stages in one output directory:

* ``frames.npz``  -- labelled heightmaps: random clutter of ``--object-set``,
  photographed, then thinned one random object at a time (as if picked) and
  photographed again, so crowded and sparse scenes both occur.  Collected once;
  a rerun reuses it.
* ``trunk.safetensors`` -- the trunk, written at the end; ``pretrain-state.pt``
  holds network, optimiser and step every ``--save-every`` steps, and a rerun
  of the same command continues from it.  ``pretrain.json`` records the
  settings and the held-out losses; ``predictions.png`` shows, for held-out
  frames, the colour heightmap, the true and the predicted boundaries and
  interiors.

No robot action and no grasp label is involved: the trunk learns where objects
and their boundaries are, not where to grasp.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import signal
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from flgd.config import WorkspaceConfig
    from sim_cell.cell import SimCell

__all__ = ["collect_frames", "PretrainSettings", "PretrainFileError", "pretrain", "main"]

FRAMES_FILE = "frames.npz"
STATE_FILE = "pretrain-state.pt"
TRUNK_FILE = "trunk.safetensors"
INFO_FILE = "pretrain.json"
PICTURE_FILE = "predictions.png"
EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


class PretrainFileError(ValueError):
    """A damaged file in the output directory; the message names it and says what to do."""


def collect_frames(cell: SimCell, workspace: WorkspaceConfig, depth_range: tuple[float, float], frames: int,
                   objects: tuple[int, int], per_scene: int, rng: np.random.Generator,
                   progress=None, stop=lambda: False) -> dict[str, np.ndarray] | None:
    """``frames`` labelled heightmaps (colour, height, labels 0..k) from a cell that has ground truth;
    None when ``stop()`` turned true first."""
    from flgd.perception import make_heightmaps

    if not hasattr(cell, "capture_labelled"):
        raise ValueError(f"the {type(cell).__name__} cell has no ground-truth labels: pre-training needs sim_cell")
    colors, heights, labels = [], [], []
    while len(colors) < frames:
        if stop():
            return None
        cell.set_object_count(int(rng.integers(objects[0], objects[1] + 1)))
        cell.reset_scene()
        for _ in range(per_scene):
            if len(colors) >= frames or cell.object_count == 0:
                break
            frame, ids = cell.capture_labelled()
            # body ids -> 1..k, carried through the projection as the "colour" of each pixel's top point
            uniq = np.unique(ids[ids > 0])
            index = np.zeros(ids.shape, np.uint8)
            for k, body in enumerate(uniq, start=1):
                index[ids == body] = k
            hm = make_heightmaps(frame.color, frame.depth, frame.intrinsics, frame.depth_scale, frame.camera_pose,
                                 workspace, depth_range, cell.config.camera.depth_fill)
            # labels are never filled: an unseen cell has no body id
            lab = make_heightmaps(np.repeat(index[:, :, None], 3, axis=2), frame.depth, frame.intrinsics,
                                  frame.depth_scale, frame.camera_pose, workspace, depth_range, fill="none")
            colors.append(hm.color)
            heights.append(hm.height.astype(np.float16))
            labels.append(lab.color[:, :, 0].copy())
            states = cell.object_states()
            if states:
                cell.remove_object(states[int(rng.integers(len(states)))].body)
            if progress:
                progress(len(colors), frames)
    return {"color": np.stack(colors), "height": np.stack(heights), "labels": np.stack(labels)}


@dataclasses.dataclass(frozen=True)
class PretrainSettings:
    frames: int = 1200
    held_out: int = 100
    objects: tuple[int, int] = (4, 20)
    per_scene: int = 8
    steps: int = 3000
    batch: int = 8
    crop: int = 192
    learning_rate: float = 1e-3
    seed: int = 0
    save_every: int = 200


def _save_state(path: Path, net, optimizer, step: int, history: list[dict]) -> None:
    import torch

    from flgd.atomic_file import write_atomically

    buf = io.BytesIO()
    torch.save({"net": net.state_dict(), "optimizer": optimizer.state_dict(), "step": step,
                "history": json.dumps(history)}, buf)
    write_atomically(path, buf.getvalue())


def _held_out_loss(net, data: dict[str, np.ndarray], indices: np.ndarray, rotations: int, stride: int) -> dict:
    import torch

    from flgd.learning.trunk import labelled_batch, perception_loss

    rng = np.random.default_rng(0)
    totals: dict[str, float] = {}
    net.eval()
    with torch.inference_mode():
        for start in range(0, len(indices), 8):
            chunk = indices[start:start + 8]
            samples = [(data["color"][i], data["height"][i].astype(np.float32), data["labels"][i]) for i in chunk]
            rots = [int(i) % rotations for i in chunk]
            c, h, t, v = labelled_batch(samples, rots, rotations, stride, None, rng)
            for k, val in perception_loss(net(c, h), t, v).items():
                totals[k] = totals.get(k, 0.0) + float(val) * len(chunk)
    net.train()
    return {k: round(v / max(len(indices), 1), 5) for k, v in totals.items()}


def pretrain(out: Path, data: dict[str, np.ndarray], settings: PretrainSettings, stop=lambda: False,
             progress=None) -> dict:
    """Train (or continue training) the perception net on ``data``; writes the trunk file when done."""
    import torch

    from flgd.learning.networks import FastQNet
    from flgd.learning.trunk import PerceptionNet, labelled_batch, perception_loss, save_trunk

    rotations, stride = 16, FastQNet.stride
    n = len(data["labels"])
    if n <= settings.held_out:
        raise ValueError(f"{n} frames, but {settings.held_out} are held out: collect more (--frames)")
    if n - settings.held_out < settings.batch:  # sampled without replacement
        raise ValueError(f"batch {settings.batch}: only {n - settings.held_out} training frames ({n} minus "
                         f"{settings.held_out} held out); use a smaller --batch or more --frames")
    train_idx = np.arange(n - settings.held_out)
    held_idx = np.arange(n - settings.held_out, n)
    net = PerceptionNet(seed=settings.seed)
    optimizer = torch.optim.Adam(net.parameters(), lr=settings.learning_rate)
    step, history = 0, []
    state_path = out / STATE_FILE
    if state_path.exists():
        try:
            state = torch.load(state_path, weights_only=True)
            net.load_state_dict(state["net"])
            optimizer.load_state_dict(state["optimizer"])
            step, history = int(state["step"]), json.loads(state["history"])
            if not isinstance(history, list):
                raise ValueError(f"history: expected a list, got {type(history).__name__}")
        except Exception as exc:  # truncated, not a torch file, another network: all the same to the user
            raise PretrainFileError(
                f"{state_path}: cannot be resumed from ({type(exc).__name__}: {exc}); delete it to train "
                f"from step 0 again (the frames in {FRAMES_FILE} are kept)") from None
    if not history:
        history.append({"step": 0, **_held_out_loss(net, data, held_idx, rotations, stride)})
    rng = np.random.default_rng([settings.seed, step])
    net.train()
    t0 = time.monotonic()
    while step < settings.steps and not stop():
        pick = rng.choice(train_idx, size=settings.batch, replace=False)
        samples = [(data["color"][i], data["height"][i].astype(np.float32), data["labels"][i]) for i in pick]
        c, h, t, v = labelled_batch(samples, [int(r) for r in rng.integers(0, rotations, settings.batch)],
                                    rotations, stride, settings.crop, rng)
        loss = perception_loss(net(c, h), t, v)["total"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        step += 1
        if step % settings.save_every == 0 or step == settings.steps:
            history.append({"step": step, **_held_out_loss(net, data, held_idx, rotations, stride)})
            _save_state(state_path, net, optimizer, step, history)
        if progress:
            progress(step, settings.steps, loss.item(), time.monotonic() - t0)
    if step < settings.steps:
        _save_state(state_path, net, optimizer, step, history)
        return {"finished": False, "step": step, "history": history}
    info = {"finished": True, "step": step, "history": history, "held_out": history[-1],
            "settings": dataclasses.asdict(settings)}
    save_trunk(out / TRUNK_FILE, net, {k: v for k, v in info.items() if k != "history"})
    _write_picture(out / PICTURE_FILE, net, data, held_idx[::max(1, len(held_idx) // 4)][:4], rotations, stride)
    return info


def _write_picture(path: Path, net, data: dict[str, np.ndarray], indices: np.ndarray, rotations: int,
                   stride: int) -> None:
    """Rows of held-out frames: colour | true boundary | predicted | true interior | predicted."""
    import cv2
    import torch

    from flgd.learning.trunk import instance_targets, labelled_batch
    from flgd.learning.networks import unrotate_maps
    from flgd.visualize import write_png

    rows = []
    net.eval()
    with torch.inference_mode():
        for i in indices:
            samples = [(data["color"][i], data["height"][i].astype(np.float32), data["labels"][i])]
            c, h, _, _ = labelled_batch(samples, [0], rotations, stride, None, np.random.default_rng(0))
            out = unrotate_maps(net(c, h), [0], rotations, *data["labels"][i].shape)[0]
            truth = instance_targets(data["labels"][i])
            pred = [torch.sigmoid(out[1]).numpy(), torch.sigmoid(out[2]).numpy() * (torch.sigmoid(out[0]).numpy() > 0.5)]
            tiles = [data["color"][i]]
            for a, b in ((truth[1], pred[0]), (truth[2], pred[1])):
                for m in (a, b):
                    g = (np.clip(m, 0, 1) * 255).astype(np.uint8)
                    tiles.append(np.repeat(g[:, :, None], 3, axis=2))
            rows.append(np.concatenate(tiles, axis=1))
    net.train()
    img = np.concatenate(rows, axis=0)
    header = np.full((22, img.shape[1], 3), 255, np.uint8)
    for k, name in enumerate(("colour", "boundary: truth", "predicted", "interior: truth", "predicted")):
        cv2.putText(header, name, (k * data["labels"].shape[2] + 4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    (0, 0, 0), 1, cv2.LINE_AA)
    write_png(path, np.concatenate([header, img], axis=0))


def _recorded_settings(path: Path) -> dict | None:
    """The settings an output directory was started with (None: a new one); a damaged pretrain.json is refused,
    never taken for a new directory (which would rewrite it and mix settings)."""
    if not path.exists():
        return None
    fix = f"{path.parent} was not changed; restore {path.name} or use a new --out"
    from flgd.training.records import read_json_record

    try:
        info = read_json_record(path, fix)
    except ValueError as exc:
        raise PretrainFileError(str(exc)) from None
    settings = info.get("settings") if isinstance(info, dict) else None
    if not isinstance(settings, dict):
        what = (f"key 'settings' is {'missing' if settings is None else type(settings).__name__}"
                if isinstance(info, dict) else f"got {type(info).__name__}")
        raise PretrainFileError(f"{path}: expected a JSON object with the settings object; {what}; {fix}")
    return settings


def _load_frames(path: Path) -> dict[str, np.ndarray]:
    """The collected frames; a truncated or foreign frames.npz is a ``PretrainFileError`` naming it."""
    fix = "delete it and run the same command again to collect the frames anew"
    try:
        with np.load(path) as f:
            data = {k: f[k] for k in ("color", "height", "labels")}
    except KeyError as exc:
        raise PretrainFileError(f"{path}: array {exc} missing (expected color, height, labels); {fix}") from None
    except Exception as exc:  # a truncated zip surfaces as BadZipFile, EOFError, ValueError, OSError ...
        raise PretrainFileError(f"{path}: cannot be read ({type(exc).__name__}: {exc}); {fix}") from None
    if any(v.ndim == 0 for v in data.values()) or len({len(v) for v in data.values()}) != 1 \
            or data["labels"].ndim != 3:
        raise PretrainFileError(f"{path}: inconsistent arrays ({', '.join(f'{k} {v.shape}' for k, v in data.items())}"
                                f"; expected N frames of each, labels N x H x W); {fix}")
    return data


def _parser() -> argparse.ArgumentParser:
    d = PretrainSettings()
    ap = argparse.ArgumentParser(prog="flgd pretrain", description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", required=True, help="a sim cell config (camera, workspace, sim settings)")
    ap.add_argument("--out", required=True, help="output directory (resumable)")
    ap.add_argument("--object-set", default="random_urdfs/0[0-9][0-9]/*.urdf",
                    help="sim.object_set of the scenes (default: our 100 novel shapes, no blocks)")
    ap.add_argument("--frames", type=int, default=d.frames)
    ap.add_argument("--held-out", type=int, default=d.held_out, help="last N frames: held-out loss only")
    ap.add_argument("--min-objects", type=int, default=d.objects[0])
    ap.add_argument("--max-objects", type=int, default=d.objects[1])
    ap.add_argument("--steps", type=int, default=d.steps)
    ap.add_argument("--batch", type=int, default=d.batch)
    ap.add_argument("--crop", type=int, default=d.crop, help="side of the random crop of each rotated input (px)")
    ap.add_argument("--learning-rate", type=float, default=d.learning_rate)
    ap.add_argument("--seed", type=int, default=d.seed)
    ap.add_argument("--save-every", type=int, default=d.save_every)
    ap.add_argument("--threads", type=int, default=1)
    return ap


def main(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    from flgd.config import ConfigError, load_sim_config

    problems = [f"--{k.replace('_', '-')}: got {v!r}, expected >= {lo}" for k, v, lo in
                (("frames", args.frames, 2), ("held_out", args.held_out, 1), ("min_objects", args.min_objects, 1),
                 ("steps", args.steps, 0), ("batch", args.batch, 1), ("crop", args.crop, 32),
                 ("save_every", args.save_every, 1), ("threads", args.threads, 1)) if v < lo]
    if args.max_objects < args.min_objects or args.max_objects > 60:
        problems.append(f"--max-objects: got {args.max_objects}, expected {args.min_objects}..60")
    if args.frames <= args.held_out:
        problems.append(f"--frames: got {args.frames}, expected more than --held-out ({args.held_out})")
    elif args.batch > args.frames - args.held_out:  # a batch is drawn without replacement
        problems.append(f"--batch: got {args.batch}, expected at most the {args.frames - args.held_out} "
                        f"training frames (--frames {args.frames} minus --held-out {args.held_out})")
    if not args.learning_rate > 0:
        problems.append(f"--learning-rate: got {args.learning_rate}, expected > 0")
    if problems:
        print("flgd pretrain: " + "; ".join(problems), file=sys.stderr)
        return EXIT_USAGE
    try:
        config = load_sim_config(args.config, "ground truth exists only in sim_cell")
    except ConfigError as exc:
        print(f"flgd pretrain: {exc}", file=sys.stderr)
        return EXIT_USAGE
    settings = PretrainSettings(frames=args.frames, held_out=args.held_out,
                                objects=(args.min_objects, args.max_objects), steps=args.steps, batch=args.batch,
                                crop=args.crop, learning_rate=args.learning_rate, seed=args.seed,
                                save_every=args.save_every)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    info_path = out / INFO_FILE
    try:
        recorded = _recorded_settings(info_path)
    except PretrainFileError as exc:
        print(f"flgd pretrain: {exc}", file=sys.stderr)
        return EXIT_USAGE
    mine = {**dataclasses.asdict(settings), "object_set": args.object_set, "config": str(Path(args.config).resolve())}
    mine["objects"] = list(mine["objects"])
    changed = sorted(k for k in mine if recorded is not None and recorded.get(k) != mine[k] and k != "steps")
    if changed:
        print(f"flgd pretrain: {out} was started with other settings ({', '.join(changed)}); use a new --out",
              file=sys.stderr)
        return EXIT_USAGE
    from flgd.atomic_file import write_atomically

    write_atomically(info_path, json.dumps({"settings": mine, "status": "running"}, indent=2).encode(), mode=0o644)

    import torch

    torch.set_num_threads(args.threads)
    stopping: list[int] = []
    previous = {s: signal.signal(s, lambda signum, _f: stopping.append(signum)) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        frames_path = out / FRAMES_FILE
        if frames_path.exists():
            data = _load_frames(frames_path)
        else:
            from flgd.cell import make_cell

            sim = dataclasses.replace(config.sim, object_set=args.object_set, seed=args.seed, scene="")
            cell = make_cell(dataclasses.replace(config, sim=sim), "sim")
            try:
                data = collect_frames(cell, config.workspace, config.camera.depth_range, args.frames,
                                      settings.objects, settings.per_scene, np.random.default_rng(args.seed),
                                      progress=lambda k, n: print(f"\rframes {k}/{n}", end="", file=sys.stderr),
                                      stop=lambda: bool(stopping))
            finally:
                cell.close()
            print("", file=sys.stderr)
            if data is None:
                write_atomically(info_path, json.dumps({"settings": mine, "status": "interrupted", "step": 0},
                                                       indent=2).encode(), mode=0o644)
                print("flgd pretrain: interrupted while collecting frames; none kept, a rerun collects them again",
                      file=sys.stderr)
                return EXIT_INTERRUPTED
            buf = io.BytesIO()
            np.savez_compressed(buf, **data)
            write_atomically(frames_path, buf.getvalue(), mode=0o644)

        def progress(step: int, total: int, loss: float, elapsed: float) -> None:
            if step % 20 == 0 or step == total:
                print(f"\rstep {step}/{total} loss {loss:.3f} ({elapsed / 60:.1f} min)", end="", file=sys.stderr)

        info = pretrain(out, data, settings, stop=lambda: bool(stopping), progress=progress)
        print("", file=sys.stderr)
    except PretrainFileError as exc:
        print(f"\nflgd pretrain: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (ValueError, OSError) as exc:
        print(f"\nflgd pretrain: {exc}", file=sys.stderr)
        return EXIT_ERROR
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
    status = "finished" if info["finished"] else "interrupted"
    write_atomically(info_path, json.dumps({"settings": mine, "status": status, "step": info["step"],
                                            "history": info["history"]}, indent=2).encode(), mode=0o644)
    if not info["finished"]:
        print(f"flgd pretrain: stopped at step {info['step']}; run the same command to continue", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(f"flgd pretrain: {out / TRUNK_FILE} (held-out loss {info['held_out']})")
    return EXIT_OK
