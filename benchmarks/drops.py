"""``flgd bench drops``: where lifted objects leave the gripper, and how they were held when they did.

Why: a drop (an object lifted by a grasp and then lost out of the cell) is a failed grasp and a lost
object; the count alone does not say whether the grip was off-centre, the object too long for the pads,
or the carry too hard.  This runs ``flgd eval``'s evaluator (frozen, greedy) and follows every object
that a grasp's lift step lifted through the rest of its plan and the place plan that carries it: the
step during which it left the gripper, and how it sat in the fingers when the lift ended (its centre in
the tool frame: x along the closing axis, y along the pads, z along the fingers; its tilt; its size).

The simulator is observed, not changed: ``SimCell``'s plan steps are wrapped to look after each one.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from flgd.config import CellConfig
    from flgd.perception import Heightmaps
    from flgd.plans import Plan

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = REPO / "cell_config" / "sim.yaml"
STEP_METHODS = ("run_line", "run_gripper", "fingers_at_rest")   # of sim_cell.arm_driver.ArmDriver


def held_geometry(tcp: np.ndarray, position: Any, orientation: Any, points: np.ndarray) -> dict[str, Any]:
    """How an object sits in the fingers: its centre in the tool frame (mm), the angle between its long
    horizontal side and the pads (deg), and its extent along the closing axis and along the pads (mm)."""
    import pybullet as p

    inv = np.linalg.inv(tcp)
    centre = inv[:3, :3] @ np.asarray(position) + inv[:3, 3]
    local = (inv[:3, :3] @ np.asarray(points).T).T + inv[:3, 3]
    rot = np.asarray(p.getMatrixFromQuaternion(orientation)).reshape(3, 3)
    in_tool = inv[:3, :3] @ rot
    tilt = float(np.degrees(np.arccos(np.clip(max(abs(in_tool[2, :])), -1.0, 1.0))))
    return {"centre_mm": [round(float(v) * 1000, 1) for v in centre],
            "tilt_deg": round(tilt, 1),
            "extent_closing_mm": round(float(np.ptp(local[:, 0])) * 1000, 1),
            "extent_pads_mm": round(float(np.ptp(local[:, 1])) * 1000, 1),
            "extent_fingers_mm": round(float(np.ptp(local[:, 2])) * 1000, 1)}


class DropWatch:
    """Lifted objects followed step by step; ``records`` holds one entry per object a lift step lifted."""

    def __init__(self) -> None:
        self.records: list[dict[str, Any]] = []
        self._following: dict[int, dict[str, Any]] = {}
        self._labels: list[str] = []
        self._step = 0
        self._depth = 0
        self._plan = ""
        self._heightmaps: Heightmaps | None = None
        self._tapers: list[float] | None = None
        self.grasp_tapers: list[list[float]] = []   # every grasp's, in order; a record's "grasp" indexes it

    def wrap(self, cell_class: type, arm_class: type, world_class: type) -> dict[str, Any]:
        """Install the observers; returns the originals (``restore`` puts them back)."""
        from flgd.plans import LIFT_LABEL

        originals = {"execute": cell_class.execute, **{name: getattr(arm_class, name) for name in STEP_METHODS}}
        originals["remove_lost"] = world_class.remove_lost
        import flgd.cycle

        originals["frame_heightmaps"] = flgd.cycle.frame_heightmaps
        watch = self

        def frame_heightmaps(*args: Any, **kw: Any) -> Heightmaps:
            watch._heightmaps = originals["frame_heightmaps"](*args, **kw)   # what the next decision sees
            return watch._heightmaps

        def execute(cell: Any, checked: Any) -> Any:
            watch._labels = [s.label or type(s).__name__ for s in checked.verify(cell.config).steps]
            watch._step, watch._depth, watch._plan = 0, 0, checked.plan.primitive
            watch._tapers = watch._grasp_tapers(cell.config, checked.plan)
            if checked.plan.primitive == "grasp":
                watch.grasp_tapers.append(watch._tapers or [])
            try:
                return originals["execute"](cell, checked)
            finally:   # what left the gripper in this plan (lost or not, counted by now) is followed no further
                watch._following = {b: r for b, r in watch._following.items() if r["left_at"] is None}

        def stepped(name: str) -> Any:
            def method(arm: Any, *args: Any, **kw: Any) -> Any:
                watch._depth += 1
                try:
                    return originals[name](arm, *args, **kw)
                finally:
                    watch._depth -= 1
                    if watch._depth == 0:
                        label = watch._labels[watch._step] if watch._step < len(watch._labels) else "retreat"
                        watch._step += 1
                        watch._after_step(arm, label, label == LIFT_LABEL)
            return method

        def remove_lost(world: Any, body: int) -> None:
            record = watch._following.pop(body, None)
            if record is not None:
                record["lost"] = True
                record["dropped"] = body in world.lifted or body in world.held
            originals["remove_lost"](world, body)

        cell_class.execute = execute
        flgd.cycle.frame_heightmaps = frame_heightmaps
        for name in STEP_METHODS:
            setattr(arm_class, name, stepped(name))
        world_class.remove_lost = remove_lost
        return originals

    @staticmethod
    def restore(cell_class: type, arm_class: type, world_class: type, originals: dict[str, Any]) -> None:
        import flgd.cycle

        flgd.cycle.frame_heightmaps = originals.pop("frame_heightmaps")
        world_class.remove_lost = originals.pop("remove_lost")
        cell_class.execute = originals.pop("execute")
        for name, method in originals.items():
            setattr(arm_class, name, method)

    def _grasp_tapers(self, config: CellConfig, plan: Plan) -> list[float] | None:
        """The sides' tapers (mm, ``flgd.side_slope``) where a grasp plan's pads meet the object, on the heightmap
        it was decided on; None for other plans."""
        from flgd.perception import base_to_pixel
        from flgd.side_slope import SIDE_RISE, side_tapers

        if plan.primitive != "grasp" or self._heightmaps is None or plan.target is None:
            return None
        row, col = base_to_pixel(plan.target[0], plan.target[1], config.workspace)
        height = self._heightmaps.height
        if not (0 <= row < height.shape[0] and 0 <= col < height.shape[1]):
            return None
        tapers = side_tapers(height, row, col, plan.angle, config.workspace.resolution, config.gripper.open_width,
                             config.robot.grasp_depth, SIDE_RISE, config.safety.min_table_clearance)
        return [round(1000 * t, 1) for t in tapers]

    def _after_step(self, arm: Any, label: str, lift: bool) -> None:
        import pybullet as p

        world = arm._world
        if lift:
            for record in self._following.values():   # a body lifted again: its earlier record ends here
                record.setdefault("left_at", "lifted again")
            self._following = {}
            tcp = arm.tcp()
            lifted = arm.in_gripper() | arm.contacts.held()   # what execute marks as lifted next
            for body in sorted(lifted):
                position, orientation = p.getBasePositionAndOrientation(body, physicsClientId=arm._client)
                obj = world.objects[body]
                record = {"shape": obj.spec.shape or obj.spec.label, "size_mm": [round(v * 1000, 1)
                                                                                 for v in obj.spec.size],
                          "lifted_with": len(lifted), "width_mm": round(arm._robot.width() * 1000, 1),
                          "taper_mm": self._tapers, "grasp": len(self.grasp_tapers) - 1,
                          **held_geometry(tcp, position, orientation, obj.world_points(arm._client)),
                          "left_at": None, "lost": False, "dropped": False}
                self._following[body] = record
                self.records.append(record)
            return
        inside = arm.in_gripper()
        for body, record in list(self._following.items()):
            if body in inside:
                record["left_at"] = None   # touching one pad for a moment is not leaving: it came back
            elif record["left_at"] is None:
                record["left_at"] = f"{self._plan}:{label}"
                tcp = arm.tcp()[:3, 3]
                record["tcp_when_left_mm"] = [round(float(v) * 1000) for v in tcp]


def summary(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Dropped against carried out, side by side: counts, where they left, and how they were held."""
    def describe(rows: list[dict[str, Any]]) -> dict[str, Any]:
        if not rows:
            return {"n": 0}
        centre = np.array([r["centre_mm"] for r in rows])
        return {"n": len(rows),
                "left_at": dict(Counter(str(r["left_at"]) for r in rows)),
                "shapes": dict(Counter(r["shape"] for r in rows)),
                "lifted_with_another": sum(r["lifted_with"] > 1 for r in rows),
                "median_abs_centre_mm": [round(float(v), 1) for v in np.median(np.abs(centre), axis=0)],
                "median_tilt_deg": round(float(np.median([r["tilt_deg"] for r in rows])), 1),
                "median_extent_closing_mm": round(float(np.median([r["extent_closing_mm"] for r in rows])), 1),
                "median_extent_pads_mm": round(float(np.median([r["extent_pads_mm"] for r in rows])), 1)}
    dropped = [r for r in records if r["dropped"]]
    held = [r for r in records if r["left_at"] and r["left_at"].endswith(":open") and not r["lost"]]
    other = [r for r in records if r not in dropped and r not in held]
    return {"dropped": describe(dropped), "carried_out": describe(held), "other": describe(other)}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="flgd bench drops", description=__doc__.splitlines()[0])
    ap.add_argument("--policy", default=str(REPO / "policies" / "flg-sim.safetensors"))
    ap.add_argument("--config", default=str(DEFAULT_CONFIG))
    ap.add_argument("--objects", default="blocks", help="object set (sim.object_set syntax)")
    ap.add_argument("--count", type=int, default=20, help="objects per scene")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--seeds", type=int, nargs="+", default=[7, 8, 9, 10],
                    help="evaluation seeds (default: the validation seeds)")
    ap.add_argument("--out", help="write the records and the summary as JSON here")
    args = ap.parse_args(argv)
    if args.runs < 1 or args.count < 1:
        print("flgd bench drops: --runs and --count must be >= 1", file=sys.stderr)
        return 1

    from flgd.config import ConfigError, load_config
    from flgd.evaluation.evaluator import EvalOptions, EvaluationError, Evaluator
    from flgd.evaluation.scene_sets import clutter_scene
    from flgd.learning.policy_file import PolicyFileError, load_policy
    from sim_cell.arm_driver import ArmDriver
    from sim_cell.cell import SimCell
    from sim_cell.world import World

    try:
        config = load_config(args.config)
        network = load_policy(args.policy).network
        scene = clutter_scene(args.objects, args.count)
    except (ConfigError, PolicyFileError, ValueError) as exc:
        print(f"flgd bench drops: {exc}", file=sys.stderr)
        return 1
    watch = DropWatch()
    originals = watch.wrap(SimCell, ArmDriver, World)
    runs = []
    try:
        for seed in args.seeds:
            with Evaluator(config, network, EvalOptions(runs=args.runs, seed=seed)) as ev:
                for log in (log for _, logs in ev.evaluate([scene]) for log in logs):
                    runs.append({"seed": seed, "run": log.run, "dropped": log.objects_dropped,
                                 "grasps": sum(a.kind == "grasp" for a in log.actions),
                                 "picks": sum(a.kind == "grasp" and a.success for a in log.actions),
                                 "actions": len(log.actions), "end": log.end})
                    print(f"seed {seed} run {log.run}: {log.objects_dropped} dropped", flush=True)
    except EvaluationError as exc:
        print(f"flgd bench drops: {exc}", file=sys.stderr)
        return 1
    finally:
        DropWatch.restore(SimCell, ArmDriver, World, originals)
    result = {"command": "flgd bench drops " + " ".join(argv), "machine": f"{platform.node()} "
              f"({platform.machine()}, {os.cpu_count()} cpus)", "runs": runs,
              "summary": summary(watch.records), "records": watch.records, "grasp_tapers_mm": watch.grasp_tapers}
    print(json.dumps(result["summary"], indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
