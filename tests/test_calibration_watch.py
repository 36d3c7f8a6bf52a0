"""The calibration watch: the table plane in each frame says when the camera has moved from ``camera.pose``.

Pure functions on synthetic points and frames (a known tilt and offset are recovered, objects and holes are
ignored); the verdict's smoothing on made-up estimate sequences; then sim_cell with a moved camera (a drift
within 20 frames) and unmoved (none over changing scenes; 1,000 frames in benchmarks/calibration_watch.py), and
the daemon's event, status line and metrics.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from flgd.calibration_watch import (CLEAR_FRACTION, REMEDY, CalibrationWatch, TablePlane, fit_table_plane,
                                    table_points)
from flgd.config import CalibrationWatchConfig, CameraPoseErrorConfig, ConfigError, config_from_dict, load_config
from flgd.geometry import pose_matrix, rpy_to_matrix
from flgd.perception import make_heightmaps

REPO = Path(__file__).resolve().parents[1]
CFG = load_config(REPO / "cell_config" / "sim.yaml")
WS = CFG.workspace
ONE_DEGREE = math.radians(1.0)


# ------------------------------------------------------------------ the plane fit, on synthetic points

def synthetic_points(slope_x: float, slope_y: float, offset: float, *, covered: float = 0.35, seed: int = 0,
                     noise: float = 0.002) -> tuple[np.ndarray, float]:
    """Points of a table z = slope . (p - centre) + offset seen at ~2.2 mm spacing with ``noise`` (m), boxes 2-6 cm
    tall on about ``covered`` of it (their edges smeared: mixed pixels at any height between table and top), a
    10 cm disc and 5 % of single points without a reading.  Also returns the share the boxes cover."""
    rng = np.random.default_rng(seed)
    xs = np.arange(WS.x[0] + 0.001, WS.x[1], 0.0022)
    ys = np.arange(WS.y[0] + 0.001, WS.y[1], 0.0022)
    x, y = (a.ravel() for a in np.meshgrid(xs, ys))
    xc, yc = (WS.x[0] + WS.x[1]) / 2, (WS.y[0] + WS.y[1]) / 2
    z = slope_x * (x - xc) + slope_y * (y - yc) + offset + rng.normal(0.0, noise, x.size)
    on_box = np.zeros(x.size, dtype=bool)
    while on_box.mean() < covered:
        bx, by = rng.uniform(WS.x[0], WS.x[1]), rng.uniform(WS.y[0], WS.y[1])
        hx, hy, top = rng.uniform(0.015, 0.04), rng.uniform(0.015, 0.04), rng.uniform(0.02, 0.06)
        inside = (np.abs(x - bx) < hx) & (np.abs(y - by) < hy)
        edge = (np.abs(x - bx) < hx + 0.003) & (np.abs(y - by) < hy + 0.003) & ~inside
        z[inside] += top
        z[edge] += rng.uniform(0.0, top, int(edge.sum()))
        on_box |= inside | edge
    hole = np.hypot(x - (WS.x[0] + 0.1), y - (WS.y[1] - 0.1)) < 0.05
    keep = ~hole & (rng.random(x.size) > 0.05)
    return np.column_stack([x, y, z])[keep], float(on_box.mean())


@pytest.mark.parametrize("slope_x, slope_y, offset, covered", [
    (0.0, 0.0, 0.0, 0.35),
    (math.tan(ONE_DEGREE), 0.0, -0.010, 0.35),        # 1 degree and 1 cm low
    (0.006, -0.012, 0.008, 0.35),
    (0.0, -math.tan(ONE_DEGREE), 0.004, 0.6),        # most of the table under objects
])
def test_a_known_tilt_and_offset_are_recovered_with_objects_and_holes_ignored(slope_x, slope_y, offset, covered):
    points, share = synthetic_points(slope_x, slope_y, offset, covered=covered)
    plane = fit_table_plane(points, WS, CFG.rewards)
    assert plane is not None
    true_tilt = math.degrees(math.atan(math.hypot(slope_x, slope_y)))
    assert abs(plane.tilt_degrees - true_tilt) < 0.03, (plane, true_tilt)
    assert abs(plane.offset - offset) < 0.0003, (plane, offset)
    assert abs(plane.rms - 0.002) < 0.0005            # only table points: their scatter is the noise
    # the objects matter: a plain least-squares plane through every point is centimetres off
    a = np.column_stack([points[:, 0] - (WS.x[0] + WS.x[1]) / 2, points[:, 1] - (WS.y[0] + WS.y[1]) / 2,
                         np.ones(len(points))])
    naive = np.linalg.lstsq(a, points[:, 2], rcond=None)[0]
    assert naive[2] - offset > 0.005 and share >= covered


def test_too_little_table_is_not_judged():
    points, _ = synthetic_points(0.0, 0.0, 0.0, covered=0.0)
    corner = points[(points[:, 0] < WS.x[0] + 0.15) & (points[:, 1] < WS.y[0] + 0.15)]
    assert fit_table_plane(points, WS, CFG.rewards) is not None
    assert fit_table_plane(corner, WS, CFG.rewards) is None      # a tilt measured in one corner is a guess
    assert fit_table_plane(points[:500], WS, CFG.rewards) is None


# ------------------------------------------------------------------ the projection, on synthetic frames

def table_frame(true_pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(raw uint16 depth, intrinsics) of the bare table z = workspace.z[0] seen from ``true_pose``."""
    it = CFG.camera.intrinsics
    k = np.array([[it.fx, 0.0, it.cx], [0.0, it.fy, it.cy], [0.0, 0.0, 1.0]])
    v, u = np.mgrid[0:it.height, 0:it.width].astype(np.float64)
    rays = np.stack([(u - it.cx) / it.fx, (v - it.cy) / it.fy, np.ones_like(u)])   # camera z = 1
    dz = np.tensordot(true_pose[2, :3], rays, axes=1)
    along = (WS.table_z - true_pose[2, 3]) / dz                                      # camera z at the table
    return np.round(along / CFG.camera.depth_scale).astype(np.uint16), k


CONFIGURED = pose_matrix(CFG.camera.pose.position, rpy_to_matrix(*CFG.camera.pose.rpy))


@pytest.mark.parametrize("position, rpy, tilt, offset", [
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0, 0.0),
    ((0.0, 0.0, 0.01), (0.0, 0.0, 0.0), 0.0, -0.01),           # raised 1 cm: the table seems 1 cm low
    ((0.0, 0.0, -0.01), (0.0, 0.0, 0.0), 0.0, 0.01),
    ((0.0, 0.0, 0.0), (ONE_DEGREE, 0.0, 0.0), 1.0, 0.0),       # rolled 1 degree: the table seems tilted 1 degree
    ((0.0, 0.0, 0.0), (0.0, ONE_DEGREE, 0.0), 1.0, 0.0),
])
def test_table_points_put_the_table_where_the_configured_pose_says(position, rpy, tilt, offset):
    true_pose = pose_matrix(CONFIGURED[:3, 3] + np.asarray(position), CONFIGURED[:3, :3] @ rpy_to_matrix(*rpy))
    depth, k = table_frame(true_pose)
    points = table_points(depth, CFG.camera.depth_scale, k, CONFIGURED, WS, CFG.camera.depth_range)
    plane = fit_table_plane(points, WS, CFG.rewards)
    assert plane is not None
    assert abs(plane.tilt_degrees - tilt) < 0.02 and abs(plane.offset - offset) < 0.0004, plane
    if offset < 0:
        # why the watch projects the frame itself: the heightmap clamps the sunken table to a flat 0
        hm = make_heightmaps(np.zeros((*depth.shape, 3), np.uint8), depth, k, CFG.camera.depth_scale, CONFIGURED,
                             WS, CFG.camera.depth_range)
        assert float(np.abs(hm.height[~hm.unknown]).max()) == 0.0


# ------------------------------------------------------------------ the verdict, on made-up estimates

WATCH_CFG = CalibrationWatchConfig()


def plane(tilt_degrees: float = 0.0, offset_mm: float = 0.0) -> TablePlane:
    return TablePlane(slope_x=math.tan(math.radians(tilt_degrees)), slope_y=0.0, offset=offset_mm / 1000.0,
                      points=20000, rms=0.002)


def feed(watch: CalibrationWatch, planes) -> list[tuple[int, str]]:
    """(frame index, kind) of every event the planes raise."""
    return [(i, e.kind) for i, p in enumerate(planes) if (e := watch.observe(p, now=float(i))) is not None]


def test_a_lasting_drift_raises_one_event_and_its_end_one_more():
    watch = CalibrationWatch(WATCH_CFG, WS, CFG.rewards)
    planes = [plane()] * 10 + [plane(offset_mm=-10.0)] * 40 + [plane()] * 20
    events = feed(watch, planes)
    assert [k for _, k in events] == ["calibration_drift", "calibration_ok"]
    # the median of 5 turns at the 3rd moved frame, and 3 frames confirm it
    assert events[0][0] == 10 + 2 + WATCH_CFG.confirm_frames - 1
    assert events[1][0] == 50 + 2 + WATCH_CFG.confirm_frames - 1
    assert not watch.drift and watch.status()["since"] == float(events[1][0])


def test_the_drift_message_names_the_estimate_the_limits_and_the_remedy():
    watch = CalibrationWatch(WATCH_CFG, WS, CFG.rewards)
    event = [e for p in [plane(tilt_degrees=1.0, offset_mm=0.4)] * 10 if (e := watch.observe(p))][0]
    assert "tilted 1.00 deg (limit 0.5)" in event.message and "+0.4 mm" in event.message
    assert "(limit 5 mm)" in event.message and REMEDY in event.message
    status = watch.status()
    assert status["drift"] and abs(status["table_tilt_degrees"] - 1.0) < 1e-9


def test_noise_and_single_bad_frames_never_raise_a_drift():
    rng = np.random.default_rng(3)
    watch = CalibrationWatch(WATCH_CFG, WS, CFG.rewards)
    planes = []
    for i in range(2000):
        if i % 4 == 0:  # every 4th frame wildly off (an arm in view, a packed scene read as table)
            planes.append(plane(tilt_degrees=3.0, offset_mm=30.0))
        elif i % 9 == 0:
            planes.append(None)  # too little table: not judged
        else:
            planes.append(plane(abs(rng.normal(0.0, 0.1)), rng.normal(0.0, 1.0)))
    assert feed(watch, planes) == []
    assert watch.unjudged > 0


def test_an_estimate_hovering_just_inside_the_limit_does_not_clear_a_drift():
    watch = CalibrationWatch(WATCH_CFG, WS, CFG.rewards)
    hovering = 0.5 * (1.0 + CLEAR_FRACTION) * WATCH_CFG.max_offset_mm
    events = feed(watch, [plane(offset_mm=8.0)] * 10 + [plane(offset_mm=hovering)] * 50)
    assert [k for _, k in events] == ["calibration_drift"] and watch.drift


def test_bad_config_values_are_refused_with_the_key():
    for key, value in (("max_tilt_degrees", 0.0), ("max_offset_mm", -1.0), ("window", 0)):
        with pytest.raises(ConfigError, match=f"calibration_watch.{key}: got"):
            config_from_dict({"calibration_watch": {key: value}}, source="t.yaml")


# ------------------------------------------------------------------ sim_cell: frames only (capture, no motion)

def sim_config(error: CameraPoseErrorConfig, **sim):
    return dataclasses.replace(CFG, sim=dataclasses.replace(CFG.sim, camera_pose_error=error, **sim))


def watch_frames(cfg, frames: int, new_scene_every: int) -> tuple[CalibrationWatch, list[tuple[int, str]]]:
    """Feed ``frames`` captures of a sim cell to a watch, laying out a new scene every ``new_scene_every``."""
    from sim_cell.cell import SimCell

    watch = CalibrationWatch(cfg.calibration_watch, cfg.workspace, cfg.rewards, cfg.camera.depth_range)
    events = []
    with SimCell(cfg) as cell:
        for i in range(frames):
            if i and i % new_scene_every == 0:
                cell.reset_scene()
            event = watch.observe_frame(cell.capture())
            if event is not None:
                events.append((i, event.kind))
    return watch, events


SHIFTED = load_config(REPO / "cell_config" / "sim-shifted.yaml").sim.camera_pose_error


@pytest.mark.parametrize("error, tilt, offset_mm", [
    (CameraPoseErrorConfig(position=(0.0, 0.0, 0.01)), 0.0, -10.0),             # the mount slid 1 cm up
    (CameraPoseErrorConfig(position=(0.0, 0.0, -0.01)), 0.0, 10.0),
    (CameraPoseErrorConfig(rpy=(ONE_DEGREE, 0.0, 0.0)), 1.0, 0.0),              # knocked 1 degree
    (SHIFTED, 0.89, -4.1),                                                      # the second cell: 1.3 cm, 1.7 deg
], ids=["up-1cm", "down-1cm", "roll-1deg", "sim-shifted"])
def test_a_moved_camera_in_sim_cell_raises_a_drift_within_20_frames(error, tilt, offset_mm):
    watch, events = watch_frames(sim_config(error), frames=20, new_scene_every=7)
    assert [k for _, k in events] == ["calibration_drift"], events
    est_tilt, est_offset = watch.estimate()
    assert abs(est_tilt - tilt) < 0.05 and abs(1000 * est_offset - offset_mm) < 0.5, watch.status()


def test_the_unmoved_sim_cell_raises_no_drift_over_changing_scenes():
    """60 frames of 20 scenes (half of them packed edge to edge); benchmarks/calibration_watch.py runs 1,000."""
    cfg = sim_config(CameraPoseErrorConfig(), packed_scenes=0.5, objects=15, seed=7)
    watch, events = watch_frames(cfg, frames=60, new_scene_every=3)
    assert events == [] and not watch.drift
    assert watch.frames >= 55           # frames with too little table are few
    tilt, offset = watch.estimate()
    assert tilt < 0.1 * cfg.calibration_watch.max_tilt_degrees
    assert abs(offset) < 0.1 * cfg.calibration_watch.max_offset_mm / 1000


# ------------------------------------------------------------------ the daemon: event, status line, metrics

def test_the_daemon_reports_a_moved_camera_in_events_status_and_metrics(tmp_path):
    from prometheus_client import generate_latest
    from prometheus_client.registry import CollectorRegistry

    from flgd.ctl import _human
    from flgd.daemon.controller import Controller
    from flgd.daemon.prometheus import CellCollector
    from flgd.daemon.protocol import Request
    from tests.fakes.daemon import write_config

    path = write_config(tmp_path, tmp_path / "state", sim={"camera_pose_error": {"position": [0.0, 0.0, 0.01]}},
                        learning={"updates_per_action": 0})
    c = Controller(load_config(path))
    c.setup()
    try:
        c.handle(Request("start"))
        for cycles in range(1, 21):
            c._one_cycle()
            if c.status()["calibration"]["drift"]:
                break
        events = [e for e in c.store.events() if e["kind"].startswith("calibration")]
        assert [e["kind"] for e in events] == ["calibration_drift"] and cycles <= 20
        assert "-10.0 mm" in events[0]["message"] and "flgd calibrate" in events[0]["message"]
        text = _human("status", {"result": c.status()}, {})          # what `flgctl status` prints
        line = [ln for ln in text.splitlines() if ln.startswith("calibration")][0]
        assert "CAMERA MOVED" in line and "offset -10.0 mm" in line and "flgd calibrate" in line
        assert "camera moved: flgd calibrate" in c.status_text()
        registry = CollectorRegistry()
        registry.register(CellCollector(c))
        page = generate_latest(registry).decode()
        assert "flgd_calibration_drift 1.0" in page
        offset = [ln for ln in page.splitlines() if ln.startswith("flgd_calibration_table_offset_meters ")][0]
        assert abs(float(offset.split()[1]) + 0.010) < 0.0005
    finally:
        c.shutdown()
