"""The rules between keys of a cell config, which single-field limits cannot express.

Among them: the workspace, home and place inside the safety envelope and the arm's reach (``flgd.config.reach``), motion within the safety caps, a backend
that exists and can drive the configured gripper (names from the leaf ``flgd.backends``, so validating a config
imports no cell, safety or plan module), and a CUDA device where one is asked for.
"""

from __future__ import annotations

import difflib
import math

from flgd.backends import BACKEND_GRIPPER_DRIVERS, backend_names
from flgd.config.messages import quote
from flgd.config.reach import check_reach
from flgd.config.schema import CellConfig
from flgd.disk_budget import MIN_STORE_BYTES
from flgd.geometry import WRIST_YAW_LIMIT

__all__ = ["check_relations", "parse_emulator_address", "parse_metrics_address", "RELEASE_GAP_MIN"]

RELEASE_GAP_MIN = 0.005   # m: a release gap below this is within the pads' give as a grip relaxes


def check_relations(cfg: CellConfig, problems: list[str]) -> None:
    """Constraints between keys, which single-field limits cannot express."""
    _check_backend(cfg, problems)
    if 0.0 < cfg.gate.max_share < cfg.gate.share:
        problems.append(f"gate.max_share: got {cfg.gate.max_share!r}, expected 0 (off) or >= gate.share "
                        f"({cfg.gate.share!r})")
    for key in ("min_attempts", "drop_min_attempts"):
        if getattr(cfg.gate, key) > cfg.gate.max_attempts:
            problems.append(f"gate.{key}: got {getattr(cfg.gate, key)}, expected <= gate.max_attempts "
                            f"({cfg.gate.max_attempts})")
    _check_device(cfg, problems)
    if 0 < cfg.storage.max_bytes < MIN_STORE_BYTES:
        problems.append(f"storage.max_bytes: got {cfg.storage.max_bytes}, expected 0 (no byte budget) or >= "
                        f"{MIN_STORE_BYTES} bytes (64 MiB: a useful replay beside a month's action log)")
    if cfg.finetune.prior_share > 0.0 and not cfg.finetune.prior_sample:
        problems.append(f"finetune.prior_share: got {cfg.finetune.prior_share!r} with no finetune.prior_sample, "
                        "expected a prior sample file (`flgd prior-sample`) or prior_share 0")
    ws, sf = cfg.workspace, cfg.safety
    for name in ("x", "y", "z"):
        lo, hi = getattr(ws, name)
        if not lo < hi:
            problems.append(f"workspace.{name}: got {[lo, hi]!r}, expected min < max")
        elo, ehi = getattr(sf, f"envelope_{name}")
        if not elo < ehi:
            problems.append(f"safety.envelope_{name}: got {[elo, ehi]!r}, expected min < max")
    if any(p.startswith(("workspace.", "safety.")) for p in problems):
        return  # the checks below compare these ranges
    for name in ("x", "y"):
        span = getattr(ws, name)[1] - getattr(ws, name)[0]
        cells = span / ws.resolution
        if abs(cells - round(cells)) > 1e-6 * max(1.0, cells):
            problems.append(f"workspace.resolution: got {ws.resolution!r}, expected a value that divides "
                            f"the workspace {name} span {span:.4f} m into whole pixels")
    rows, cols = ws.shape
    if min(rows, cols) < 32 or max(rows, cols) > 2048:
        problems.append(f"workspace: heightmap would be {rows}x{cols} px, expected 32..2048 px per side")
    for name in ("x", "y"):
        lo, hi = getattr(ws, name)
        elo, ehi = getattr(sf, f"envelope_{name}")
        if lo < elo or hi > ehi:
            problems.append(f"workspace.{name}: {[lo, hi]!r} is not inside safety.envelope_{name} "
                            f"{[elo, ehi]!r}; the whole workspace must be reachable safely")
    if ws.z[0] < sf.envelope_z[0] - 1e-9:
        problems.append(f"safety.envelope_z: lower bound {sf.envelope_z[0]!r} is below the table "
                        f"(workspace.z[0] = {ws.z[0]!r}); expected >= the table height")
    if ws.z[1] > sf.envelope_z[1] + 1e-9:
        problems.append(f"workspace.z: {list(ws.z)!r} is not inside safety.envelope_z {list(sf.envelope_z)!r}; "
                        f"expected the top of the region <= {sf.envelope_z[1]!r}, the whole workspace must be "
                        "reachable safely")
    # Home and place are checked as the safety envelope checks every pose of a plan (flgd/safety.py), so
    # a config that passes here cannot have its first homing refused.  Their tilt is 0 by construction:
    # a tool pose has only a yaw (a roll or pitch key is refused as unknown), so max_tilt always holds.
    floor = ws.table_z + sf.min_table_clearance
    for pose_key in ("home", "place"):
        pose = getattr(cfg.robot, pose_key)
        for axis, v in zip("xyz", pose.position):
            elo, ehi = getattr(sf, f"envelope_{axis}")
            if not elo <= v <= ehi:
                problems.append(f"robot.{pose_key}.position: {axis} = {v!r} is outside "
                                f"safety.envelope_{axis} {[elo, ehi]!r}")
        if pose.position[2] < floor - 1e-9:
            problems.append(f"robot.{pose_key}.position: z = {pose.position[2]!r} is below the table clearance "
                            f"floor {floor:.4f} m (workspace.z[0] {ws.table_z!r} + safety.min_table_clearance "
                            f"{sf.min_table_clearance!r}); expected z >= {floor:.4f}")
    # every plan turns the wrist within WRIST_YAW_LIMIT of the home yaw (flgd.plans.tool_yaw); a place outside it
    # would leave the next plan a turn of half a turn or more, which a controller may make the other way round
    turn = abs(math.remainder(cfg.robot.place.yaw - cfg.robot.home.yaw, 2 * math.pi))
    if turn > WRIST_YAW_LIMIT + 1e-9:
        problems.append(f"robot.place.yaw: {cfg.robot.place.yaw!r} rad is {math.degrees(turn):.1f} deg from "
                        f"robot.home.yaw {cfg.robot.home.yaw!r}; expected at most {math.degrees(WRIST_YAW_LIMIT):g} deg, the "
                        "wrist's range around its home angle")
    check_reach(cfg, problems)
    hx, hy = cfg.robot.home.position[0], cfg.robot.home.position[1]
    if ws.x[0] <= hx <= ws.x[1] and ws.y[0] <= hy <= ws.y[1]:
        problems.append(f"robot.home.position: (x, y) = ({hx!r}, {hy!r}) is over the workspace (x {list(ws.x)!r}, "
                        f"y {list(ws.y)!r}); every picture is taken with the arm at home, so the arm would be in "
                        "every heightmap. Expected a home beside the workspace, out of the camera's view")
    rb = cfg.robot
    for key in ("speed", "approach_speed", "raise_speed"):
        if getattr(rb, key) > sf.max_speed:
            problems.append(f"robot.{key}: got {getattr(rb, key)!r} m/s, expected <= safety.max_speed "
                            f"({sf.max_speed!r} m/s)")
    if rb.acceleration > sf.max_acceleration:
        problems.append(f"robot.acceleration: got {rb.acceleration!r} m/s^2, expected <= "
                        f"safety.max_acceleration ({sf.max_acceleration!r} m/s^2)")
    if rb.blend_radius > sf.max_blend_radius:
        problems.append(f"robot.blend_radius: got {rb.blend_radius!r} m, expected <= safety.max_blend_radius "
                        f"({sf.max_blend_radius!r} m)")
    if ws.z[0] + rb.lift_height > sf.envelope_z[1]:
        problems.append(f"robot.lift_height: table + {rb.lift_height!r} m is above safety.envelope_z "
                        f"upper bound {sf.envelope_z[1]!r}")
    gr = cfg.gripper
    if gr.closed_width >= gr.open_width:
        problems.append(f"gripper.closed_width: got {gr.closed_width!r}, expected < gripper.open_width "
                        f"({gr.open_width!r})")
    if not gr.closed_width < gr.success_threshold < gr.open_width:
        problems.append(f"gripper.success_threshold: got {gr.success_threshold!r}, expected between "
                        f"closed_width and open_width")
    if gr.release_gap and not RELEASE_GAP_MIN <= gr.release_gap <= gr.open_width - gr.closed_width:
        problems.append(f"gripper.release_gap: got {gr.release_gap!r} m, expected 0 (wait until open) or between "
                        f"{RELEASE_GAP_MIN} m (below it the pads may still hold the object as the grip relaxes) "
                        f"and the stroke open_width - closed_width ({gr.open_width - gr.closed_width!r} m)")
    if gr.preshape_margin and gr.driver == "tool_digital_output":
        problems.append(f"gripper.preshape_margin: got {gr.preshape_margin!r} m with gripper.driver "
                        "tool_digital_output, expected 0: a gripper switched by a tool output only opens and closes "
                        "fully, it cannot be set to an opening")
    ex = cfg.exploration
    if ex.epsilon_end > ex.epsilon_start:
        problems.append(f"exploration.epsilon_end: got {ex.epsilon_end!r}, expected <= epsilon_start "
                        f"({ex.epsilon_start!r})")
    if ex.finger_clearance > rb.grasp_depth:
        problems.append(f"exploration.finger_clearance: got {ex.finger_clearance!r} m, expected 0 (off) or at most "
                        f"robot.grasp_depth ({rb.grasp_depth!r} m): the fingertips go no deeper below the surface")
    if cfg.rewards.shift_height < cfg.rewards.min_height:
        problems.append(f"rewards.shift_height: got {cfg.rewards.shift_height!r}, expected >= "
                        f"rewards.min_height ({cfg.rewards.min_height!r})")
    intr = cfg.camera.intrinsics
    if not (0 <= intr.cx < intr.width and 0 <= intr.cy < intr.height):
        problems.append(f"camera.intrinsics: principal point ({intr.cx}, {intr.cy}) lies outside the "
                        f"{intr.width}x{intr.height} image")
    for key in ("table_shade", "light_ambient", "light_diffuse", "object_friction"):
        lo, hi = getattr(cfg.sim, key)
        if lo > hi:
            problems.append(f"sim.{key}: got {[lo, hi]!r}, expected min <= max")
    if not 0 < cfg.camera.depth_range[0] < cfg.camera.depth_range[1]:
        problems.append(f"camera.depth_range: got {list(cfg.camera.depth_range)!r}, expected 0 < min < max")
    if cfg.camera.emulator:
        try:
            parse_emulator_address(cfg.camera.emulator)
        except ValueError as exc:
            problems.append(f"camera.emulator: {exc}")
    if not cfg.state_dir:
        problems.append("state_dir: got '', expected a directory path")
    if cfg.metrics:
        try:
            parse_metrics_address(cfg.metrics)
        except ValueError as exc:
            problems.append(f"metrics: {exc}")


def parse_metrics_address(text: str) -> tuple[str, int]:
    """(host, port) of ``HOST:PORT`` (``[::1]:PORT`` for IPv6), or of a bare ``PORT`` on the loopback
    (the page needs no login: reaching it from elsewhere is something to ask for); ValueError saying what
    was expected.

    Port 0 asks the system for a free port (the daemon logs the one it got).
    """
    expected = "expected HOST:PORT such as 127.0.0.1:9808, a PORT alone for the loopback, or '' for no metrics"
    if text.isdigit():
        if int(text) > 65535:
            raise ValueError(f"got {quote(text)}: port is not a number 0..65535; {expected}")
        return "127.0.0.1", int(text)
    return _split_host_port(text, 0, expected)


def parse_emulator_address(text: str) -> tuple[str, int]:
    """(host, port) of ``camera.emulator``'s ``HOST:PORT`` (``[::1]:PORT`` for IPv6): where ``flgd emulate``
    serves the camera's frames; ValueError saying what was expected."""
    return _split_host_port(text, 1, "expected HOST:PORT of `flgd emulate`'s camera feed such as 127.0.0.1:50415, "
                                     "or '' for a real camera")


def _split_host_port(text: str, lowest_port: int, expected: str) -> tuple[str, int]:
    host, sep, port_text = text.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host or any(c.isspace() for c in host) or (":" in host and not text.startswith("[")):
        raise ValueError(f"got {quote(text)}, {expected}")
    if not port_text.isdigit() or not lowest_port <= int(port_text) <= 65535:
        raise ValueError(f"got {quote(text)}: port {quote(port_text)} is not a number {lowest_port}..65535; "
                         f"{expected}")
    return host, int(port_text)


def _check_backend(cfg: CellConfig, problems: list[str]) -> None:
    """The backend must be registered and the gripper driver one it can drive (no hardware library imported:
    the registry maps names to "module:attribute" strings)."""
    names = backend_names()
    if cfg.backend not in names:
        close = difflib.get_close_matches(cfg.backend, names, n=1)
        hint = f"; did you mean '{close[0]}'?" if close else ""
        problems.append(f"backend: got {cfg.backend!r}, expected one of {', '.join(repr(n) for n in names)}{hint}")
        return
    drivers = BACKEND_GRIPPER_DRIVERS.get(cfg.backend)
    if drivers is not None and cfg.gripper.driver not in drivers:
        problems.append(f"gripper.driver: got {cfg.gripper.driver!r}, expected one of "
                        f"{', '.join(repr(d) for d in drivers)} for backend {cfg.backend!r}")


def _check_device(cfg: CellConfig, problems: list[str]) -> None:
    """``learning.device: cuda`` needs a CUDA device on this machine; found here, it is a config error
    before anything starts, not a traceback from the learner.  torch is imported only in that case."""
    if cfg.learning.device != "cuda":
        return
    try:
        import torch
        available = bool(torch.cuda.is_available())
    except Exception as exc:  # a broken torch install: say so here rather than later
        problems.append(f"learning.device: got 'cuda', but torch cannot be asked for CUDA devices ({exc}); "
                        "expected 'cpu' or 'auto'")
        return
    if not available:
        problems.append("learning.device: got 'cuda', but torch finds no CUDA device on this machine (CPU-only "
                        "torch build, or no usable NVIDIA driver); expected 'cpu' or 'auto' (see docs/real-cell.md: "
                        "A GPU on the cell PC)")
