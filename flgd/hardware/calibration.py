"""``flgd calibrate --config FILE``: measure the camera pose on the real cell, VPG-style.

A flat marker (an ArUco tag, or a checkerboard) is fixed to the gripper facing
up, at ``--marker-offset`` in the tool frame.  The arm moves the tool through
a grid of poses over the workspace; every pose passes the safety envelope
first.  At each pose the marker centre is found with OpenCV in the colour
image, its 3D point read from the aligned depth, and paired with the marker
position the arm reports.  ``fit_camera_pose_and_offset`` then solves
camera -> base, a depth-scale correction and the marker offset's x and y.

The grid cycles the tool yaw through 0, +80 and -80 degrees (all top-down).
With one yaw for every pose, a wrong ``--marker-offset`` would shift every
marker point by the same vector; the fit would move the camera by it and the
residual would stay low.  With the yaw varied, the offset's horizontal part is
observable and is estimated with the camera pose.  Its vertical part (tool z)
is not: top-down, the tool z axis is always vertical, so o_z still has to be
measured.

A given offset that differs from the estimate by more than
``OFFSET_TOLERANCE_MM`` is refused rather than silently replaced.  The
estimate would give a consistent camera pose, but a large discrepancy means
the offset was mis-measured or given in the wrong frame or sign. The z
component, which nothing can check, was very likely measured the same way.
Writing a camera pose a robot will move by, on an offset we know to be wrong,
is the wrong default: the user is shown both offsets and asked to measure and
re-run.  Within the tolerance, the joint fit (with the estimated x, y) is
written.

The result (``camera.pose`` position + rpy and ``camera.depth_scale_correction``)
is written back into the config file in place -- only those lines change, the
rest of the file (comments included) stays as it was -- with the RMS residual
in a comment.  It is refused (exit code 1, file untouched) when the residual
is above ``--max-residual-mm`` (default 5 mm: about twice the D415's depth
noise at 0.7 m, and well under the 2 mm/px heightmap's tolerance for grasps),
when the depth correction is implausible (outside 0.9..1.1), when fewer
than 6 poses gave a detection, or when the marker offset disagrees with the
estimate (above).
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import cv2
import numpy as np
import yaml

from flgd.atomic_file import write_atomically
from flgd.cell import Cell, CellFault, Frame
from flgd.config import CellConfig, ConfigError, config_from_dict, load_config
from flgd.geometry import ToolPose, matrix_to_rpy, rotvec_to_matrix, rpy_to_matrix
from flgd.hardware.calibration_math import CalibrationError, CalibrationFit, fit_camera_pose_and_offset
from flgd.plans import MoveL, Plan
from flgd.safety import PlanRefused, check_plan
from flgd.state_dir_lock import StateDirBusy, lock_state_dir

__all__ = ["main", "find_marker", "grid_poses", "marker_camera_point", "write_calibration",
           "CalibrationOptions", "collect_points", "DEFAULT_MAX_RESIDUAL_MM", "CALIBRATION_YAWS",
           "OFFSET_TOLERANCE_MM"]

DEFAULT_MAX_RESIDUAL_MM = 5.0
MIN_DETECTIONS = 6
CORRECTION_RANGE = (0.9, 1.1)
OFFSET_TOLERANCE_MM = 5.0  # given vs estimated marker offset (x, y) beyond this: refused
# Tool yaws cycled over the grid.  All within (-90, +90) deg, so the shortest turn between any two (the way a
# MoveL goes) passes through 0: the wrist swings back and forth and never winds up, and no step is exactly
# 180 deg (whose direction would be ambiguous).  +-80 keeps the offset well conditioned (the information on
# o_x, o_y is 0.80 of that of an even 0/120/240 spread, which would wind the wrist by 120 deg per pose).  A
# cycle of 3 does not line up with the rows of the grid, so yaw is not correlated with position.
CALIBRATION_YAWS = (0.0, math.radians(80.0), math.radians(-80.0))
_DEPTH_WINDOW = 2  # px: the marker depth is the median of a (2w+1)^2 window around its centre


@dataclass(frozen=True)
class CalibrationOptions:
    marker: str = "aruco"                 # "aruco" or "checkerboard"
    aruco_dict: str = "DICT_4X4_50"
    aruco_id: int = 0
    checkerboard: tuple[int, int] = (4, 3)  # inner corners (columns, rows)
    marker_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  # marker centre in the tool frame, m
    grid: tuple[int, int] = (4, 4)
    heights: tuple[float, ...] = (0.10, 0.20)  # TCP heights above the table, m
    margin: float = 0.05                  # m inside the workspace edges
    settle: float = 1.0                   # s to wait after a move before capturing
    max_residual_mm: float = DEFAULT_MAX_RESIDUAL_MM


# --------------------------------------------------------------------------- detection

def find_marker(color: np.ndarray, options: CalibrationOptions) -> tuple[float, float] | None:
    """Sub-pixel (u, v) of the marker centre in an RGB image, or None if it is not seen."""
    gray = cv2.cvtColor(np.ascontiguousarray(color), cv2.COLOR_RGB2GRAY)
    if options.marker == "aruco":
        if not hasattr(cv2.aruco, options.aruco_dict):
            raise ValueError(f"--aruco-dict: unknown dictionary {options.aruco_dict!r}")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, options.aruco_dict))
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        corners, ids, _ = cv2.aruco.ArucoDetector(dictionary, params).detectMarkers(gray)
        if ids is None:
            return None
        for c, i in zip(corners, ids.ravel()):
            if int(i) == options.aruco_id:
                centre = c.reshape(4, 2).mean(axis=0)
                return float(centre[0]), float(centre[1])
        return None
    if options.marker == "checkerboard":
        found, corners = cv2.findChessboardCorners(gray, options.checkerboard,
                                                   flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found:
            return None
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1),
                                   (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3))
        centre = corners.reshape(-1, 2).mean(axis=0)
        return float(centre[0]), float(centre[1])
    raise ValueError(f"--marker: got {options.marker!r}, expected 'aruco' or 'checkerboard'")


def marker_camera_point(frame: Frame, uv: tuple[float, float], depth_scale: float) -> np.ndarray | None:
    """Deproject the marker centre with the median depth around it (camera frame, metres)."""
    u, v = uv
    r, c = int(round(v)), int(round(u))
    w = _DEPTH_WINDOW
    h_img, w_img = frame.depth.shape
    if not (w <= r < h_img - w and w <= c < w_img - w):
        return None
    patch = frame.depth[r - w:r + w + 1, c - w:c + w + 1].astype(np.float64)
    valid = patch[patch > 0]
    if valid.size < patch.size // 2:
        return None
    z = float(np.median(valid)) * depth_scale
    k = frame.intrinsics
    return np.array([(u - k[0, 2]) / k[0, 0] * z, (v - k[1, 2]) / k[1, 1] * z, z])


# --------------------------------------------------------------------------- motion

def grid_poses(config: CellConfig, options: CalibrationOptions) -> list[ToolPose]:
    """Top-down tool poses over the workspace: grid x grid at each height, the yaw cycling through
    ``CALIBRATION_YAWS`` pose by pose (so that the marker offset can be estimated)."""
    ws = config.workspace
    nx, ny = options.grid
    xs = np.linspace(ws.x[0] + options.margin, ws.x[1] - options.margin, nx)
    ys = np.linspace(ws.y[0] + options.margin, ws.y[1] - options.margin, ny)
    points = [(float(x), float(y), ws.table_z + h) for h in options.heights for x in xs for y in ys]
    return [ToolPose.top_down(x, y, z, CALIBRATION_YAWS[i % len(CALIBRATION_YAWS)])
            for i, (x, y, z) in enumerate(points)]


def collect_points(cell: Cell, options: CalibrationOptions, *, tool_pose: Callable[[], Sequence[float]],
                   log: Callable[[str], None] = print, sleep: Callable[[float], None] = time.sleep,
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Move through the grid, detect the marker; return matched camera points (N, 3), and the TCP positions
    (N, 3) and tool rotations (N, 3, 3) the arm reported at them."""
    cfg = cell.config
    rb = cfg.robot
    device_scale_of = lambda frame: frame.depth_scale / cfg.camera.depth_scale_correction  # noqa: E731
    cam_pts, tcp_pts, tool_rots = [], [], []
    poses = grid_poses(cfg, options)
    for i, pose in enumerate(poses, 1):
        where = f"pose {i}/{len(poses)} at ({pose.position[0]:.3f}, {pose.position[1]:.3f}, {pose.position[2]:.3f})"
        try:
            checked = check_plan(Plan("calibrate", (MoveL(pose, rb.speed, rb.acceleration, "calibrate"),)), cfg)
        except PlanRefused as exc:
            log(f"{where}: skipped, outside the safety envelope ({exc})")
            continue
        result = cell.execute(checked)
        if not result.completed:
            log(f"{where}: skipped, {result.failure}")
            continue
        sleep(options.settle)
        frame = cell.capture()
        uv = find_marker(frame.color, options)
        point = None if uv is None else marker_camera_point(frame, uv, device_scale_of(frame))
        if point is None:
            log(f"{where}: marker not {'seen' if uv is None else 'measured (no depth at its centre)'}")
            continue
        actual = np.asarray(tool_pose(), dtype=float)
        cam_pts.append(point)
        tcp_pts.append(actual[:3])
        tool_rots.append(rotvec_to_matrix(actual[3:6]))
        log(f"{where}: marker at pixel ({uv[0]:.1f}, {uv[1]:.1f}), depth {point[2]:.4f} m")
    return (np.array(cam_pts).reshape(-1, 3), np.array(tcp_pts).reshape(-1, 3),
            np.array(tool_rots).reshape(-1, 3, 3))


# --------------------------------------------------------------------------- writing the config

_TOP_KEY = re.compile(r"^(?P<key>[A-Za-z_][\w-]*)\s*:")


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip(" "))


def _is_content(line: str) -> bool:
    s = line.strip()
    return bool(s) and not s.startswith("#")


def _section(lines: list[str], name: str) -> tuple[int, int]:
    """(index of the top-level ``name:`` line, index one past its block)."""
    start = next((i for i, ln in enumerate(lines) if _indent(ln) == 0 and (m := _TOP_KEY.match(ln))
                  and m.group("key") == name), None)
    if start is None:
        return -1, -1
    end = start + 1
    while end < len(lines) and (not _is_content(lines[end]) or _indent(lines[end]) > 0):
        end += 1
    while end > start + 1 and not _is_content(lines[end - 1]):  # trailing blanks/comments belong outside
        end -= 1
    return start, end


def _child(lines: list[str], start: int, end: int, key: str) -> tuple[int, int, int]:
    """(first, one-past-last, indent) of child ``key`` within a section block; (-1, -1, indent) if absent."""
    child_indent = next((_indent(lines[i]) for i in range(start + 1, end) if _is_content(lines[i])), 2)
    pattern = re.compile(rf"^ {{{child_indent}}}{re.escape(key)}\s*:")
    for i in range(start + 1, end):
        if pattern.match(lines[i]):
            j = i + 1
            while j < end and (not _is_content(lines[j]) or _indent(lines[j]) > child_indent):
                j += 1
            while j > i + 1 and not _is_content(lines[j - 1]):
                j -= 1
            return i, j, child_indent
    return -1, -1, child_indent


def _num(v: float, digits: int) -> str:
    return f"{v:.{digits}f}".rstrip("0").rstrip(".") if v != 0 else "0.0"


def write_calibration(path: str | os.PathLike, fit: CalibrationFit) -> CellConfig:
    """Write camera.pose and camera.depth_scale_correction into the YAML file, keeping everything else.

    The new text is validated as a config before it atomically replaces the file.
    """
    p = Path(path)
    text = p.read_text(encoding="utf-8")
    lines = text.splitlines()
    position = fit.camera_pose[:3, 3]
    rpy = matrix_to_rpy(fit.camera_pose[:3, :3])
    stamp = datetime.datetime.now().strftime("%Y-%m-%d %H:%M")
    start, end = _section(lines, "camera")
    if start < 0:
        lines += ["camera:"]
        start, end = len(lines) - 1, len(lines)
    ps, pe, ind = _child(lines, start, end, "pose")
    pad = " " * ind
    pose_block = [f"{pad}pose:                    # written by flgd calibrate {stamp}: RMS residual "
                  f"{fit.rms_mm:.2f} mm over {fit.used} points",
                  f"{pad}  position: [{', '.join(_num(v, 6) for v in position)}]",
                  f"{pad}  rpy: [{', '.join(_num(v, 8) for v in rpy)}]"]
    if ps < 0:
        lines[end:end] = pose_block
        end += len(pose_block)
    else:
        lines[ps:pe] = pose_block
        end += len(pose_block) - (pe - ps)
    cs, ce, _ = _child(lines, start, end, "depth_scale_correction")
    corr = [f"{pad}depth_scale_correction: {fit.depth_scale_correction:.5f}   # written by flgd calibrate"]
    if cs < 0:
        lines[end:end] = corr
    else:
        lines[cs:ce] = corr
    new_text = "\n".join(lines) + ("\n" if text.endswith("\n") or not text else "")
    cfg = config_from_dict(yaml.safe_load(new_text), str(p))  # never write a file that no longer loads
    got = np.array(cfg.camera.pose.position)
    got_r = rpy_to_matrix(*cfg.camera.pose.rpy)
    if not np.allclose(got, position, atol=1e-5) or not np.allclose(got_r, fit.camera_pose[:3, :3], atol=1e-6) \
            or abs(cfg.camera.depth_scale_correction - fit.depth_scale_correction) > 1e-4:
        raise ConfigError(str(p), ["camera.pose: the rewritten file does not read back as written"])
    write_atomically(p, new_text.encode("utf-8"), mode=p.stat().st_mode & 0o777)
    return load_config(p)


def check_fit(fit: CalibrationFit, options: CalibrationOptions) -> str | None:
    """Why a fit must not be written, or None."""
    if fit.used < MIN_DETECTIONS:
        return f"only {fit.used} usable marker detections (at least {MIN_DETECTIONS} needed)"
    if not fit.rms_mm <= options.max_residual_mm:  # a NaN residual is refused too
        return (f"RMS residual {fit.rms_mm:.2f} mm is above --max-residual-mm {options.max_residual_mm} "
                f"(marker loose on its mount, bad depth, or the tool not where its pose says?)")
    lo, hi = CORRECTION_RANGE
    if not lo <= fit.depth_scale_correction <= hi:
        return f"depth-scale correction {fit.depth_scale_correction:.4f} is outside {lo}..{hi}: implausible"
    if fit.marker_offset is not None:
        given = np.asarray(options.marker_offset, dtype=float)
        est = np.asarray(fit.marker_offset, dtype=float)
        off_mm = float(np.linalg.norm(est[:2] - given[:2]) * 1e3)
        if not off_mm <= OFFSET_TOLERANCE_MM:
            return (f"the marker is not where --marker-offset says: given {_fmt_offset(given)} m, estimated "
                    f"{_fmt_offset(est)} m from the tool yaws ({off_mm:.1f} mm apart in tool x/y, tolerance "
                    f"{OFFSET_TOLERANCE_MM} mm; z cannot be estimated and is the given one). Measure the marker "
                    f"centre in the tool frame and re-run with --marker-offset X Y Z (the estimate suggests "
                    f"--marker-offset {np.round(est[0], 4) + 0.0:.4f} {np.round(est[1], 4) + 0.0:.4f} Z, with Z "
                    f"measured)")
    return None


def _fmt_offset(o: np.ndarray) -> str:
    return "(" + ", ".join(f"{v + 0.0:.4f}" for v in np.round(o, 4)) + ")"   # + 0.0: no "-0.0000"


# --------------------------------------------------------------------------- command line

def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="flgd calibrate", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", required=True, help="the real cell's config file; camera.pose is written into it")
    ap.add_argument("--marker", choices=("aruco", "checkerboard"), default="aruco")
    ap.add_argument("--aruco-dict", default="DICT_4X4_50", help="OpenCV ArUco dictionary name")
    ap.add_argument("--aruco-id", type=int, default=0)
    ap.add_argument("--checkerboard", default="4x3", help="inner corners COLSxROWS")
    ap.add_argument("--marker-offset", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"),
                    help="marker centre in the tool frame, m (tool z points down along the fingers); measure it. "
                         "X and Y are estimated from the varied tool yaws and the run is refused if they differ "
                         f"by more than {OFFSET_TOLERANCE_MM:g} mm; Z cannot be estimated (the tool is always "
                         "top-down) and an error in it moves the fitted camera by the same amount")
    ap.add_argument("--grid", type=int, nargs=2, default=(4, 4), metavar=("NX", "NY"))
    ap.add_argument("--heights", type=float, nargs="+", default=(0.10, 0.20),
                    help="TCP heights above the table, m")
    ap.add_argument("--margin", type=float, default=0.05, help="inset from the workspace edges, m")
    ap.add_argument("--settle", type=float, default=1.0, help="wait after each move before capturing, s")
    ap.add_argument("--max-residual-mm", type=float, default=DEFAULT_MAX_RESIDUAL_MM)
    ap.add_argument("--dry-run", action="store_true", help="measure and report, but do not write the config")
    return ap


def _options(args: argparse.Namespace) -> CalibrationOptions:
    m = re.fullmatch(r"(\d+)x(\d+)", args.checkerboard)
    if not m or min(int(m.group(1)), int(m.group(2))) < 2:
        raise ValueError(f"--checkerboard: got {args.checkerboard!r}, expected COLSxROWS like 4x3")
    if min(args.grid) < 2:
        raise ValueError(f"--grid: got {args.grid}, expected at least 2 x 2")
    # NaN passes every "< 0" test and would switch the residual gate off, so finiteness is checked first.
    for flag, value, ok, expected in (
            ("--max-residual-mm", args.max_residual_mm, lambda v: v > 0, "a finite number > 0"),
            ("--settle", args.settle, lambda v: v >= 0, "a finite number >= 0 (seconds)"),
            ("--margin", args.margin, lambda v: v >= 0, "a finite number >= 0 (metres)"),
            *(("--heights", h, lambda v: v > 0, "finite heights > 0 above the table (metres)") for h in args.heights),
            *(("--marker-offset", o, lambda v: True, "three finite numbers (metres)") for o in args.marker_offset)):
        if not (math.isfinite(value) and ok(value)):
            raise ValueError(f"{flag}: got {value!r}, expected {expected}")
    # Checked here, before the cell is opened: found during the grid it would stop the run with the arm out.
    if args.marker == "aruco":
        dictionary = getattr(cv2.aruco, args.aruco_dict, None) if args.aruco_dict.startswith("DICT_") else None
        if not isinstance(dictionary, int):
            raise ValueError(f"--aruco-dict: got {args.aruco_dict!r}, expected an OpenCV ArUco dictionary name "
                             f"such as DICT_4X4_50")
        size = cv2.aruco.getPredefinedDictionary(dictionary).bytesList.shape[0]
        if not 0 <= args.aruco_id < size:
            raise ValueError(f"--aruco-id: got {args.aruco_id}, expected 0..{size - 1} for {args.aruco_dict}")
    return CalibrationOptions(marker=args.marker, aruco_dict=args.aruco_dict, aruco_id=args.aruco_id,
                              checkerboard=(int(m.group(1)), int(m.group(2))),
                              marker_offset=tuple(args.marker_offset), grid=tuple(args.grid),
                              heights=tuple(args.heights), margin=args.margin, settle=args.settle,
                              max_residual_mm=args.max_residual_mm)


def _open_real_cell(config: CellConfig) -> Cell:
    from flgd.hardware.ur5e_cell import UR5eCell

    return UR5eCell(config, require_width=False)  # calibration never judges a grasp


def main(argv: list[str] | None = None, *, cell_factory: Callable[[CellConfig], Any] = _open_real_cell,
         sleep: Callable[[float], None] = time.sleep) -> int:
    """Run the calibration; 0 = written (or dry run ok), 1 = refused or the cell failed, 2 = bad input."""
    args = _parser().parse_args(argv)
    try:
        options = _options(args)
        config = load_config(args.config)
    except (ValueError, ConfigError) as exc:
        print(f"flgd calibrate: {exc}", file=sys.stderr)
        return 2
    try:
        lock_fd: int | None = lock_state_dir(config.state_dir, create=False)
    except StateDirBusy as exc:
        print(f"flgd calibrate: {exc}: it drives this arm and camera. Stop it first (systemctl stop flgd), "
              "then calibrate", file=sys.stderr)
        return 1
    except FileNotFoundError:
        lock_fd = None  # no daemon has used this state directory
    except OSError as exc:
        print(f"flgd calibrate: warning: cannot check whether flgd is running ({exc}); make sure it is stopped",
              file=sys.stderr)
        lock_fd = None
    try:
        return _calibrate(args, options, config, cell_factory, sleep)
    finally:
        if lock_fd is not None:
            os.close(lock_fd)


def _calibrate(args: argparse.Namespace, options: CalibrationOptions, config: CellConfig,
               cell_factory: Callable[[CellConfig], Any], sleep: Callable[[float], None]) -> int:
    try:
        cell = cell_factory(config)
    except CellFault as exc:
        print(f"flgd calibrate: cannot open the cell of {args.config}: {exc}", file=sys.stderr)
        return 1
    try:
        tool_pose = cell.arm.tcp_pose
        cam, tcp, rot = collect_points(cell, options, tool_pose=tool_pose, sleep=sleep)
    except (CellFault, PlanRefused) as exc:
        print(f"flgd calibrate: stopped: {exc}", file=sys.stderr)
        return 1
    finally:
        cell.close()
    try:
        fit = fit_camera_pose_and_offset(cam, tcp, rot, options.marker_offset)
    except CalibrationError as exc:
        print(f"flgd calibrate: refused: {exc} ({len(cam)} detections)", file=sys.stderr)
        return 1
    rpy = matrix_to_rpy(fit.camera_pose[:3, :3])
    print(f"camera position {np.round(fit.camera_pose[:3, 3], 4).tolist()} m, rpy "
          f"{[round(math.degrees(a), 2) for a in rpy]} deg, depth-scale correction "
          f"{fit.depth_scale_correction:.4f}; RMS residual {fit.rms_mm:.2f} mm (max {fit.max_mm:.2f} mm) over "
          f"{fit.used} of {len(cam)} points")
    print(f"marker offset (tool frame): given {_fmt_offset(np.asarray(options.marker_offset, dtype=float))} m, "
          f"estimated {_fmt_offset(fit.marker_offset)} m (x, y estimated; z is the given one, not observable "
          f"with top-down poses)")
    why = check_fit(fit, options)
    if why:
        print(f"flgd calibrate: refused, {args.config} left unchanged: {why}", file=sys.stderr)
        return 1
    if args.dry_run:
        print("dry run: config not written")
        return 0
    try:
        write_calibration(args.config, fit)
    except (OSError, ConfigError, yaml.YAMLError) as exc:
        print(f"flgd calibrate: measured, but could not write {args.config} (left unchanged): {exc}",
              file=sys.stderr)
        return 1
    print(f"wrote camera.pose and camera.depth_scale_correction to {args.config}")
    return 0
