"""``flgd bench emulated``: the production backend (ur_rtde, RG2 XML-RPC, pyrealsense2) on ``flgd emulate``,
beside the sim backend on the same scenes and seed; then every fault kind injected during motion.

    flgd bench emulated --root runs/emulated --cycles 200 --faults 10 [--parts policy faults calibrate] [--serial]
        [--free-speed M_S] [--acceleration M_S2] [--raise-speed M_S] [--contact-clearance M] [--blend-radius M]
        [--release-gap M] [--preshape-margin M] [--home-at-place] [--carry-at-grasp-yaw] [--out FILE]

*policy*: ``flgd run`` with the shipped policy, frozen (``finetune.updates_per_action: 0``), on
cell_config/ur5e-emulated.yaml (backend ur5e against the emulator) and on the same file with ``backend: sim``,
until ``--cycles`` actions each; grasp success per grasp, picks per action, the cycle's time split (capture,
perceive, decide, plan, execute, judge, store), the controller's own time (all but execute), and picks per hour
both on the wall clock and on the cell's own clock (the emulator's or the simulator's time for the motions, the
controller's own work on the wall clock), the motion's, the gripper's and the waiting (the arm still while the
controller works) parts of a cycle on the cell's clock, the share of decision time hidden behind the place, and
the real-time factor the emulator's clock achieved.
*faults*: the daemon on the emulator; each kind raised ``--faults`` times at a random instant of a motion, then
what a person does (release the e-stop and power the arm on at the pendant, reset the gripper, plug the camera
in) and ``flgctl reset`` + ``start``: latched, no motion started after the fault before the reset, recovered,
and the action log without a gap.  Both parts resume from their state directories.
*calibrate*: the emulated camera put ``CAMERA_ERROR`` away from ``camera.pose``, a marker on the gripper, an empty
table, and ``flgd calibrate`` through ur_rtde and pyrealsense2: the written pose against the truth.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import signal
import sqlite3
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[1]
EMULATED = REPO / "cell_config" / "ur5e-emulated.yaml"
FAULT_KINDS = ("protective-stop", "emergency-stop", "stop-script", "gripper-trip", "camera-stop", "drop-rtde")
PERSON = {"emergency-stop": ("release-emergency-stop", "power-on"), "gripper-trip": ("gripper-reset",),
          "camera-stop": ("camera-resume",)}   # what a person does before the reset
CAMERA_ERROR = {"position": [0.012, -0.008, 0.006], "rpy": [0.01, -0.008, 0.015]}  # m; rad, the camera's axes
MARKER_OFFSET = ("-0.08", "0", "-0.02")   # m in the tool frame: beside the wrist, seen from above
PHASES = ("t_capture", "t_perceive", "t_decide", "t_plan", "t_execute", "t_judge", "t_store")


def _write_config(root: Path, backend: str, host: str, robot: dict[str, Any] | None = None,
                  gripper: dict[str, Any] | None = None, seed: int | None = None) -> Path:
    from flgd.config import load_config

    data = yaml.safe_load(EMULATED.read_text())
    shipped = load_config(EMULATED)
    data.update(backend=backend, state_dir=str(root / "state"), policy=str(shipped.policy))
    data["robot"]["host"] = host
    data["robot"].update(robot or {})
    data["gripper"].update(gripper or {})
    if seed is not None:   # both cells lay out the same scenes from it
        data["sim"]["seed"] = int(seed)
    for key, cap in (("speed", "max_speed"), ("raise_speed", "max_speed"), ("acceleration", "max_acceleration"),
                     ("blend_radius", "max_blend_radius")):
        if key in (robot or {}):
            data["safety"][cap] = max(float(data["safety"].get(cap, 0.0)), float(robot[key]))
    data["camera"]["emulator"] = f"{host}:{data['camera']['emulator'].rsplit(':', 1)[1]}"
    data["learning"]["init_trunk"] = str(shipped.learning.init_trunk)
    data["finetune"].update(prior_sample=str(shipped.finetune.prior_sample), updates_per_action=0)
    root.mkdir(parents=True, exist_ok=True)
    path = root / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


class _Process:
    """A ``flgd`` subcommand in the background, its output in ``log``."""

    def __init__(self, argv: list[str], log: Path) -> None:
        self.log = open(log, "ab")
        self.proc = subprocess.Popen([sys.executable, "-m", "flgd.cli", *argv], stdout=self.log,
                                     stderr=subprocess.STDOUT, cwd=REPO, env=dict(os.environ, OMP_NUM_THREADS="1"))

    def stop(self, timeout: float = 120.0) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


class _Daemon(_Process):
    def __init__(self, config: Path, root: Path) -> None:
        self.socket = root / "flgd.sock"
        super().__init__(["run", "--config", str(config), "--socket", str(self.socket), "--autostart",
                          "--no-status-line"], root / "daemon.log")

    def call(self, cmd: str, **args: Any) -> dict:
        from flgd.ctl import Client

        with Client(self.socket, timeout=150.0) as c:
            return c.call(cmd, **args)

    def wait_for(self, predicate, what: str, timeout: float = 600.0) -> dict:
        from flgd.ctl import DaemonUnreachable

        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"flgd run exited with {self.proc.returncode} waiting for {what}")
            try:
                reply = self.call("status")  # not ok while the daemon is still starting
                if reply.get("ok") and predicate(reply["result"]):
                    return reply["result"]
            except DaemonUnreachable:
                pass
            time.sleep(0.3)
        raise TimeoutError(f"{what}: not within {timeout:.0f} s")


def _emulator(config: Path, root: Path, time_scale: float) -> _Process:
    faults = root / "faults.sock"
    emu = _Process(["emulate", "--config", str(config), "--faults", str(faults), "--time-scale", str(time_scale)],
                   root / "emulator.log")
    deadline = time.monotonic() + 120
    while not faults.exists():
        if emu.proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"flgd emulate did not start: see {root / 'emulator.log'}")
        time.sleep(0.2)
    emu.faults = faults
    return emu


def _rows(state_dir: Path) -> list[dict]:
    db = sqlite3.connect(state_dir / "flgd.sqlite")
    db.row_factory = sqlite3.Row
    try:
        return [dict(r) for r in db.execute("SELECT * FROM actions ORDER BY step")]
    finally:
        db.close()


def _policy_summary(rows: list[dict], cycles: int) -> dict[str, Any]:
    rows = rows[:cycles]
    decided = [r for r in rows if r["outcome"] in ("executed", "refused")]
    grasps = [r for r in decided if r["primitive"] == "grasp"]
    picks = sum(1 for r in grasps if r["success"] == 1)
    executed = [r for r in rows if r["outcome"] == "executed" and r["duration"]]
    phases = {p: statistics.median(r[p] for r in executed if r[p] is not None) for p in PHASES} if executed else {}
    own = [r["duration"] - (r["t_execute"] or 0.0) for r in executed]
    wall_total = sum(r["duration"] or 0.0 for r in rows)
    cell_total = sum(_cycle_on_cell_clock(r) for r in rows)
    timed = [r for r in executed if r.get("cell_time") is not None]   # the cell's side: motion and gripper
    return {"cycles": len(rows), "grasps": len(grasps), "picks": picks,
            "grasp_success": picks / len(grasps) if grasps else None,
            "picks_per_action": picks / len(decided) if decided else None,
            "outcomes": {o: sum(1 for r in rows if r["outcome"] == o) for o in {r["outcome"] for r in rows}},
            "median_cycle_s": statistics.median(r["duration"] for r in executed) if executed else None,
            "median_controller_s": statistics.median(own) if own else None,
            "median_cycle_cell_clock_s": (statistics.median(_cycle_on_cell_clock(r) for r in executed)
                                          if executed else None),
            "median_motion_s": (statistics.median(r["cell_time"] - (r.get("gripper_time") or 0.0) for r in timed)
                                if timed else None),
            "median_gripper_s": statistics.median(r.get("gripper_time") or 0.0 for r in timed) if timed else None,
            "median_waiting_s": (statistics.median(_cycle_on_cell_clock(r) - r["cell_time"] for r in timed)
                                 if timed else None),
            "decide_hidden_share": _hidden_share(executed),
            "picks_per_hour_wall": picks * 3600.0 / wall_total if wall_total > 0 else None,
            "picks_per_hour_cell_clock": picks * 3600.0 / cell_total if cell_total > 0 else None,
            "median_phase_s": phases}


def _hidden_share(rows: list[dict]) -> float | None:
    """Of the decision time, the part made while the arm placed the previous pick (``robot.decide_while_placing``)."""
    deciding = sum(r["t_decide"] or 0.0 for r in rows)
    return sum(r.get("decide_hidden") or 0.0 for r in rows) / deciding if deciding > 0 else None


def _cycle_on_cell_clock(row: dict) -> float:
    """A cycle as the arm lives it: the controller's own work (wall clock) plus its plans on the cell's clock
    (the emulator's or the simulator's; a row without one counts its wall time)."""
    duration = row["duration"] or 0.0
    if row.get("cell_time") is None or duration == 0.0:   # as flgd.store.schema.CYCLE_ON_CELL_CLOCK_SQL
        return duration
    return duration - (row["t_execute"] or 0.0) + row["cell_time"]


def _operator_reset(daemon: _Daemon) -> bool:
    """What the plant's operator does on a FAULT: flgctl reset (again if the arm's 5 s unlock rule refuses it),
    then start; True when the daemon accepted both."""
    for _ in range(3):
        if daemon.call("reset")["ok"]:
            return bool(daemon.call("start")["ok"])
        time.sleep(2.0)
    return False


def _restarted(daemon: _Daemon, config: Path, root: Path) -> _Daemon:
    """What the operator does when resets keep failing: restart the service (systemctl restart flgd)."""
    daemon.stop()
    fresh = _Daemon(config, root)
    fresh.wait_for(lambda st: True, "the daemon started again", timeout=120)
    return fresh


def run_policy(root: Path, cycles: int, time_scale: float, host: str,
               robot: dict[str, Any] | None = None, gripper: dict[str, Any] | None = None,
               seed: int | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for backend in ("sim", "ur5e"):
        row = root / ("sim" if backend == "sim" else "emulated")
        config = _write_config(row, backend, host, robot, gripper, seed)
        done = len(_rows(row / "state")) if (row / "state" / "flgd.sqlite").exists() else 0
        if done < cycles:
            emu = _emulator(config, row, time_scale) if backend == "ur5e" else None
            daemon = _Daemon(config, row)
            try:
                faults = json.loads((row / "faults.json").read_text()) if (row / "faults.json").exists() else []
                while True:  # an emptied real table pauses the daemon (a person refills it); a fault is reset
                    st = daemon.wait_for(lambda st: st["cycles"] >= cycles or st["state"] in ("PAUSED", "FAULT"),
                                         f"{cycles} cycles on {backend}", timeout=cycles * 120.0)
                    if st["cycles"] >= cycles:
                        break
                    if st["state"] == "FAULT":  # what an operator does: reset, or restart the service
                        faults.append({"cycle": st["cycles"], "cause": st["cause"],
                                       "reset": _operator_reset(daemon)})
                        if not faults[-1]["reset"]:
                            daemon = _restarted(daemon, config, row)
                            faults[-1]["restarted"] = True
                        (row / "faults.json").write_text(json.dumps(faults, indent=1))
                        continue
                    from sim_cell.emulator.faults import inject

                    inject(emu.faults, "refill")
                    daemon.call("start")
                if emu is not None:   # how fast the emulator's clock ran while the daemon cycled on it
                    from sim_cell.emulator.faults import inject

                    (row / "clock.json").write_text(json.dumps(inject(emu.faults, "status").get("clock")))
            finally:
                daemon.stop()
                if emu is not None:
                    emu.stop()
        out["emulated" if backend == "ur5e" else "sim"] = _policy_summary(_rows(row / "state"), cycles)
        if (row / "clock.json").exists():
            out["emulated"]["emulator_clock"] = json.loads((row / "clock.json").read_text())
        if (row / "faults.json").exists():  # faults the cell raised on its own (not injected)
            out["emulated" if backend == "ur5e" else "sim"]["faults"] = json.loads((row / "faults.json").read_text())
        print(f"{backend}: {json.dumps(out['emulated' if backend == 'ur5e' else 'sim'])}", flush=True)
    return out


def run_faults(root: Path, repeats: int, time_scale: float, resume: dict[str, Any], host: str,
               robot: dict[str, Any] | None = None, gripper: dict[str, Any] | None = None) -> dict[str, Any]:
    from flgd.ctl import DaemonUnreachable
    from sim_cell.emulator.faults import inject

    config = _write_config(root, "ur5e", host, robot, gripper)
    results: dict[str, list[dict]] = {k: list(resume.get(k, [])) for k in FAULT_KINDS}
    unplanned: list[dict] = (json.loads((root / "unplanned.json").read_text())
                             if (root / "unplanned.json").exists() else [])
    emu = _emulator(config, root, time_scale)
    daemon = _Daemon(config, root)
    try:
        for kind in FAULT_KINDS:
            while len(results[kind]) < repeats:
                st = daemon.wait_for(lambda st: st["state"] in ("RUNNING", "PAUSED", "FAULT"), "running")
                if st["state"] == "PAUSED":  # the table emptied: a person refills it
                    inject(emu.faults, "refill")
                    daemon.call("start")
                    continue
                if st["state"] == "FAULT":  # a fault the cell raised on its own: recorded apart, reset
                    unplanned.append({"cycle": st["cycles"], "cause": st["cause"], "reset": _operator_reset(daemon)})
                    if not unplanned[-1]["reset"]:
                        daemon = _restarted(daemon, config, root)
                        unplanned[-1]["restarted"] = True
                    (root / "unplanned.json").write_text(json.dumps(unplanned, indent=1))
                    continue
                base = st["cycles"]
                st = daemon.wait_for(lambda st: st["cycles"] > base or st["state"] in ("PAUSED", "FAULT"),
                                     "a cycle before the fault")
                if st["state"] != "RUNNING":
                    continue
                inject(emu.faults, f"{kind} --during-motion")
                record: dict[str, Any] = {"latched": False, "recovered": False, "daemon_exited": None}
                try:
                    st = daemon.wait_for(lambda st: st["state"] == "FAULT", f"{kind} latched", timeout=90)
                    record.update(latched=True, cause=st["cause"])
                except TimeoutError:
                    record["cause"] = "not latched within 90 s"
                except RuntimeError:  # the daemon died: recorded, and started again as systemd would
                    record["daemon_exited"] = daemon.proc.returncode
                    daemon.stop()
                    daemon = _Daemon(config, root)
                    daemon.wait_for(lambda st: True, "the daemon started again", timeout=120)
                raised = inject(emu.faults, "status")["raised"][-1]
                record["during_motion"] = raised["during_motion"]
                time.sleep(1.0)  # the daemon has latched: any motion it still started would show now
                record["motions_after_fault"] = inject(emu.faults, "status").get("motions_since_last_fault")
                for person in PERSON.get(kind, ()):
                    inject(emu.faults, person)
                try:
                    for _ in range(3):  # a reset may race the arm's own 5 s protective-stop rule
                        if daemon.call("reset")["ok"]:
                            break
                        time.sleep(2.0)
                    reply = daemon.call("start")
                except DaemonUnreachable:  # it died in the recovery: recorded, started again
                    daemon.proc.wait(30)
                    record["daemon_exited"] = daemon.proc.returncode
                    daemon.stop()
                    daemon = _Daemon(config, root)
                    daemon.wait_for(lambda st: True, "the daemon started again", timeout=120)
                    reply = daemon.call("start")
                if reply["ok"]:
                    try:
                        daemon.wait_for(lambda st: st["cycles"] > base + 1 or st["state"] == "PAUSED",
                                        "a cycle after the recovery", timeout=120)
                        record["recovered"] = True  # a cycle ran after it (or the table emptied on it)
                    except TimeoutError:
                        pass
                results[kind].append(record)
                print(f"{kind} #{len(results[kind])}: {json.dumps(record)}", flush=True)
                (root / "faults.json").write_text(json.dumps(results, indent=1))
    finally:
        daemon.stop()
        emu.stop()
    rows = _rows(root / "state")
    steps = [r["step"] for r in rows]
    return {"kinds": {k: {"injected": len(v), "latched": sum(r["latched"] for r in v),
                          "during_motion": sum(bool(r.get("during_motion")) for r in v),
                          "moved_after_fault": sum(bool(r.get("motions_after_fault")) for r in v),
                          "recovered": sum(r["recovered"] for r in v),
                          "daemon_exited": sum(r.get("daemon_exited") is not None for r in v)}
                      for k, v in results.items()},
            "action_rows": len(rows), "gaps_in_log": sum(1 for a, b in zip(steps, steps[1:]) if b != a + 1),
            "pending_rows": sum(1 for r in rows if r["outcome"] == "pending"), "unplanned_faults": unplanned,
            "records": results}


def run_calibrate(root: Path, time_scale: float, host: str) -> dict[str, Any]:
    import math

    import numpy as np

    from flgd.config import load_config
    from flgd.geometry import rpy_to_matrix
    from sim_cell.camera import CameraModel

    config = _write_config(root, "ur5e", host)
    data = yaml.safe_load(config.read_text())
    data["sim"].update(objects=0, camera_pose_error=CAMERA_ERROR)
    config.write_text(yaml.safe_dump(data))
    before = load_config(config)
    truth = CameraModel.from_config(before.camera, before.sim.camera_pose_error).pose
    faults = root / "faults.sock"
    emu = _Process(["emulate", "--config", str(config), "--faults", str(faults), "--time-scale", str(time_scale),
                    "--marker", "aruco", "--marker-offset", *MARKER_OFFSET], root / "emulator.log")
    try:
        deadline = time.monotonic() + 120
        while not faults.exists():
            if emu.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"flgd emulate did not start: see {root / 'emulator.log'}")
            time.sleep(0.2)
        started = time.monotonic()
        run = subprocess.run([sys.executable, "-m", "flgd.cli", "calibrate", "--config", str(config), "--marker",
                              "aruco", "--marker-offset", *MARKER_OFFSET, "--margin", "0.1"],
                             capture_output=True, text=True, cwd=REPO)
        seconds = time.monotonic() - started
    finally:
        emu.stop()
    (root / "calibrate.log").write_text(run.stdout + run.stderr)
    out: dict[str, Any] = {"exit_code": run.returncode, "seconds": round(seconds, 1), "camera_error": CAMERA_ERROR,
                           "marker_offset": [float(v) for v in MARKER_OFFSET],
                           "detections": sum("marker at pixel" in line for line in run.stdout.splitlines())}
    if run.returncode == 0:
        after = load_config(config)
        turn = rpy_to_matrix(*after.camera.pose.rpy).T @ truth[:3, :3]
        out.update(position_error_mm=round(1000 * float(np.linalg.norm(np.asarray(after.camera.pose.position)
                                                                         - truth[:3, 3])), 3),
                   rotation_error_deg=round(math.degrees(math.acos(min(1.0, (np.trace(turn) - 1) / 2))), 4),
                   configured_error_mm=round(1000 * float(np.linalg.norm(np.asarray(before.camera.pose.position)
                                                                          - truth[:3, 3])), 1))
    print(f"calibrate: {json.dumps(out)}", flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="flgd bench emulated", description=__doc__.split("\n\n")[0])
    p.add_argument("--root", type=Path, default=Path("runs/emulated"))
    p.add_argument("--cycles", type=int, default=200)
    p.add_argument("--faults", type=int, default=10, help="injections of each fault kind")
    p.add_argument("--parts", nargs="+", choices=("policy", "faults", "calibrate"),
                   default=["policy", "faults", "calibrate"])
    p.add_argument("--time-scale", type=float, default=1.0, help="the emulator's physics against real time")
    p.add_argument("--out", type=Path, default=None, help="summary JSON (default ROOT/summary.json)")
    p.add_argument("--host", default="127.0.0.1", help="the loopback address the emulator serves on")
    p.add_argument("--free-speed", type=float, default=None, help="robot.speed (m/s) of both cells' free moves; "
                                                                  "safety.max_speed raised to it where lower")
    p.add_argument("--acceleration", type=float, default=None, help="robot.acceleration (m/s^2); "
                                                                    "safety.max_acceleration raised to it where lower")
    p.add_argument("--raise-speed", type=float, default=None, help="robot.raise_speed (m/s): a grasp's lift above "
                                                                   "the approach height; safety.max_speed raised to it")
    p.add_argument("--contact-clearance", type=float, default=None,
                   help="robot.contact_clearance (m): a grasp slow only this far above the highest point around it")
    p.add_argument("--blend-radius", type=float, default=None,
                   help="robot.blend_radius (m): free moves of a plan blended into one path")
    p.add_argument("--release-gap", type=float, default=None,
                   help="gripper.release_gap (m): a release goes on once the fingers opened this far")
    p.add_argument("--preshape-margin", type=float, default=None,
                   help="gripper.preshape_margin (m): a grasp opens only as wide as its fingers need, set on the way")
    p.add_argument("--home-at-place", action="store_true",
                   help="robot.home = robot.place: the arm waits and the camera takes its pictures with the arm over "
                        "the bin, so a pick goes from its raise straight to where it is placed")
    p.add_argument("--carry-at-grasp-yaw", action="store_true",
                   help="robot.carry_at_grasp_yaw: the wrist keeps the grasp's angle to home and the place")
    p.add_argument("--capture-on-the-way", action="store_true",
                   help="robot.capture_on_the_way: the picture taken on the grasp's move home, the decision during it")
    p.add_argument("--seed", type=int, default=None, help="sim.seed of both cells' scenes (default: the emulated "
                                                          "config's, 0)")
    p.add_argument("--serial", action="store_true", help="robot.decide_while_placing off: the arm goes home after "
                                                         "each place and waits there for the next decision")
    args = p.parse_args(argv)
    root = args.root.resolve()
    out = args.out or root / "summary.json"
    summary: dict[str, Any] = json.loads(out.read_text()) if out.exists() else {}
    if "policy" in args.parts:
        robot: dict[str, Any] = {"decide_while_placing": False} if args.serial else {}
        if args.free_speed is not None:
            robot["speed"] = args.free_speed
        if args.acceleration is not None:
            robot["acceleration"] = args.acceleration
        if args.raise_speed is not None:
            robot["raise_speed"] = args.raise_speed
        if args.contact_clearance is not None:
            robot["contact_clearance"] = args.contact_clearance
        if args.blend_radius is not None:
            robot["blend_radius"] = args.blend_radius
        if args.home_at_place:
            robot["home"] = yaml.safe_load(EMULATED.read_text())["robot"]["place"]
        if args.carry_at_grasp_yaw:
            robot["carry_at_grasp_yaw"] = True
        if args.capture_on_the_way:
            robot["capture_on_the_way"] = True
        gripper = {} if args.release_gap is None else {"release_gap": args.release_gap}
        if args.preshape_margin is not None:
            gripper["preshape_margin"] = args.preshape_margin
        summary["policy"] = run_policy(root / "policy", args.cycles, args.time_scale, args.host, robot, gripper,
                                       args.seed)
    if "faults" in args.parts:
        previous = root / "faults" / "faults.json"
        resume = json.loads(previous.read_text()) if previous.exists() else {}
        summary["faults"] = run_faults(root / "faults", args.faults, args.time_scale, resume, args.host,
                                       {"capture_on_the_way": True} if args.capture_on_the_way else None,
                                       None if args.preshape_margin is None
                                       else {"preshape_margin": args.preshape_margin})
    if "calibrate" in args.parts:
        summary["calibrate"] = run_calibrate(root / "calibrate", args.time_scale, args.host)
    summary.update(command="flgd bench emulated " + " ".join(argv if argv is not None else sys.argv[1:]),
                   machine=f"{platform.machine()}, {os.cpu_count()} cores", date=str(datetime.date.today()),
                   commit=subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                         cwd=REPO).stdout.strip())
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(summary, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
