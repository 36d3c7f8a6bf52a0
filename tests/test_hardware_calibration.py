"""Camera-to-base calibration: the SVD fit, marker detection, the config write-back, and the whole command."""

from __future__ import annotations

import errno
import math
import os
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from flgd.cell import ExecutionResult, Frame
from flgd.config import load_config
from flgd.geometry import pose_matrix, rpy_to_matrix
from flgd.hardware import calibration
from flgd.hardware.calibration import (CALIBRATION_YAWS, OFFSET_TOLERANCE_MM, CalibrationOptions, check_fit,
                                       find_marker, grid_poses, main, write_calibration)
from flgd.hardware.calibration_math import (CalibrationError, CalibrationFit, fit_camera_pose,
                                            fit_camera_pose_and_offset)
from sim_cell.emulator.marker import marker_image

ROOT = Path(__file__).resolve().parents[1]
REAL_CONFIG = ROOT / "cell_config" / "ur5e-d415.yaml"


def rotation_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    r = a.T @ b
    return math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(r) - 1) / 2))))


def true_camera_pose() -> np.ndarray:
    return pose_matrix((0.512, -0.008, 0.693), rpy_to_matrix(math.pi - 0.02, 0.015, 0.03))


def synthetic_detections(pose: np.ndarray, scale: float, rng, sigma_xy=0.0003, sigma_z=0.001):
    """Marker points on a 4x4x2 grid over the workspace, seen by a camera at ``pose`` with noisy depth.

    ``scale``: the true depth is ``scale`` times what the device reports.  The default noise is that of a
    D415 reading at 0.5-0.6 m taken as the median of a small window (about 1 mm along the optical axis).
    """
    xs, ys, zs = np.meshgrid(np.linspace(0.33, 0.67, 4), np.linspace(-0.17, 0.17, 4), [0.08, 0.18])
    base = np.stack([xs.ravel(), ys.ravel(), zs.ravel()], axis=1)
    cam_true = (base - pose[:3, 3]) @ pose[:3, :3]             # inverse rigid transform
    noise = rng.normal(0, 1, cam_true.shape) * np.array([sigma_xy, sigma_xy, sigma_z])
    return (cam_true + noise) / scale, base


@pytest.mark.parametrize("seed", range(5))
def test_fit_recovers_a_known_transform_from_noisy_detections(seed):
    rng = np.random.default_rng(seed)
    pose = true_camera_pose()
    cam, base = synthetic_detections(pose, 1.02, rng)
    fit = fit_camera_pose(cam, base)
    assert np.linalg.norm(fit.camera_pose[:3, 3] - pose[:3, 3]) < 0.002
    assert rotation_error_deg(fit.camera_pose[:3, :3], pose[:3, :3]) < 0.5
    assert fit.depth_scale_correction == pytest.approx(1.02, abs=0.005)
    assert 0.2 < fit.rms_mm < 3.0 and fit.used == len(cam)
    assert check_fit(fit, CalibrationOptions()) is None


def test_a_misdetection_is_dropped_and_the_fit_still_holds():
    rng = np.random.default_rng(7)
    pose = true_camera_pose()
    cam, base = synthetic_detections(pose, 1.0, rng)
    cam[5] += (0.04, -0.03, 0.05)   # a reflection detected as the marker
    fit = fit_camera_pose(cam, base)
    assert not fit.inliers[5] and fit.used == len(cam) - 1
    assert np.linalg.norm(fit.camera_pose[:3, 3] - pose[:3, 3]) < 0.002
    assert rotation_error_deg(fit.camera_pose[:3, :3], pose[:3, :3]) < 0.5


def test_a_poor_residual_is_refused():
    rng = np.random.default_rng(1)
    cam, base = synthetic_detections(true_camera_pose(), 1.0, rng, sigma_xy=0.008, sigma_z=0.012)
    fit = fit_camera_pose(cam, base)
    why = check_fit(fit, CalibrationOptions(max_residual_mm=5.0))
    assert why is not None and "RMS residual" in why and "above --max-residual-mm 5.0" in why


def test_degenerate_point_sets_are_errors():
    line = np.stack([np.linspace(0.3, 0.6, 8), np.zeros(8), np.full(8, 0.1)], axis=1)
    with pytest.raises(CalibrationError, match="collinear"):
        fit_camera_pose(line + 0.001, line)
    with pytest.raises(CalibrationError, match="at least 4"):
        fit_camera_pose(line[:3], line[:3])
    with pytest.raises(CalibrationError, match="matched"):
        fit_camera_pose(line, line[:5])
    bad = line.copy()
    bad[2, 1] = np.nan
    with pytest.raises(CalibrationError, match="NaN"):
        fit_camera_pose(bad, line)


def test_fit_and_refusal_of_few_detections():
    rng = np.random.default_rng(2)
    cam, base = synthetic_detections(true_camera_pose(), 1.0, rng)
    fit = fit_camera_pose(cam[:5], base[:5] + [0, 0, 0])
    assert "only 5 usable" in check_fit(fit, CalibrationOptions())
    far = CalibrationFit(np.eye(4), 1.3, 1.0, 1.0, np.ones(10, bool))
    assert "implausible" in check_fit(far, CalibrationOptions())


# --------------------------------------------------------------------------- rendering a marker

MARKER_SIDE = 0.05  # m including its white quiet zone


def _marker_texture(options: CalibrationOptions) -> np.ndarray:
    return marker_image(options.marker, aruco_dict=options.aruco_dict, aruco_id=options.aruco_id,
                        checkerboard=options.checkerboard)  # what the emulator prints on its gripper, too


def render_marker_frame(camera_pose: np.ndarray, k: np.ndarray, centre: np.ndarray, options: CalibrationOptions,
                        table_z: float, depth_unit: float, size=(640, 480), yaw=0.0):
    """Colour + raw depth of a flat, upward-facing marker centred at ``centre`` above a grey table."""
    w, h = size
    half = MARKER_SIDE / 2
    c, s = math.cos(yaw), math.sin(yaw)
    corners = np.array([centre + (c * dx - s * dy, s * dx + c * dy, 0.0)
                        for dx, dy in ((-half, half), (half, half), (half, -half), (-half, -half))])  # printed image, seen from above
    cam = (corners - camera_pose[:3, 3]) @ camera_pose[:3, :3]
    px = (cam[:, :2] / cam[:, 2:3]) * (k[0, 0], k[1, 1]) + (k[0, 2], k[1, 2])
    tex = _marker_texture(options)
    th, tw = tex.shape
    src = np.float32([[0, 0], [tw, 0], [tw, th], [0, th]])
    hom = cv2.getPerspectiveTransform(src, px.astype(np.float32))
    gray = np.full((h, w), 110, np.uint8)
    warped = cv2.warpPerspective(tex, hom, (w, h), flags=cv2.INTER_LINEAR, borderValue=0)
    mask = cv2.warpPerspective(np.full_like(tex, 255), hom, (w, h), flags=cv2.INTER_NEAREST) > 0
    gray[mask] = warped[mask]
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    rays = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], -1) @ camera_pose[:3, :3].T
    o = camera_pose[:3, 3]
    plane_z = np.where(mask, centre[2], table_z)
    z_cam = (plane_z - o[2]) / rays[..., 2]          # rays have unit camera-z, so this is the depth
    depth = np.round(z_cam / depth_unit).astype(np.uint16)
    return np.repeat(gray[..., None], 3, axis=2), depth


@pytest.mark.parametrize("marker", ["aruco", "checkerboard"])
def test_marker_centre_is_found_to_a_fraction_of_a_pixel(marker):
    options = CalibrationOptions(marker=marker)
    pose = true_camera_pose()
    k = np.array([[615.0, 0, 320.0], [0, 615.0, 240.0], [0, 0, 1]])
    centre = np.array([0.45, 0.06, 0.12])
    color, _ = render_marker_frame(pose, k, centre, options, table_z=-0.02, depth_unit=0.001, yaw=0.4)
    cam = (centre - pose[:3, 3]) @ pose[:3, :3]
    expected = cam[:2] / cam[2] * 615.0 + (320.0, 240.0)
    uv = find_marker(color, options)
    assert uv is not None and np.linalg.norm(np.array(uv) - expected) < 0.5
    assert find_marker(np.full_like(color, 110), options) is None
    if marker == "aruco":
        assert find_marker(color, CalibrationOptions(marker="aruco", aruco_id=7)) is None, "another tag id"


# --------------------------------------------------------------------------- the config file

def test_write_back_changes_only_the_pose_lines(tmp_path):
    path = tmp_path / "cell.yaml"
    shutil.copy(REAL_CONFIG, path)
    before = path.read_text().splitlines()
    pose = true_camera_pose()
    fit = CalibrationFit(pose, 1.0123, 1.7, 3.2, np.ones(32, bool))
    cfg = write_calibration(path, fit)
    np.testing.assert_allclose(cfg.camera.pose.position, pose[:3, 3], atol=1e-6)
    assert rotation_error_deg(rpy_to_matrix(*cfg.camera.pose.rpy), pose[:3, :3]) < 1e-5
    assert cfg.camera.depth_scale_correction == pytest.approx(1.0123)
    after = path.read_text().splitlines()
    removed = [ln for ln in before if ln not in after]
    added = [ln for ln in after if ln not in before]
    keys = ("pose:", "position:", "rpy:", "depth_scale_correction:")
    assert 3 <= len(removed) <= 4 and all(any(k in ln for k in keys) for ln in removed)
    assert len(added) == 4 and "RMS residual 1.70 mm over 32 points" in added[0]
    assert [ln for ln in after if ln in before] == [ln for ln in before if ln in after], "order kept"
    # Written twice: replaced in place, not duplicated.
    write_calibration(path, fit)
    assert path.read_text().count("depth_scale_correction") == 1 and path.read_text().count("  pose:") == 1


@pytest.mark.parametrize("camera_block", [
    "camera:\n  serial: ''\n  pose: {position: [0.5, 0.0, 0.7], rpy: [3.14, 0.0, 0.0]}\n  fps: 30\n",
    "camera:\n  serial: ''\n  fps: 30\n",
    "",
])
def test_write_back_handles_flow_style_and_missing_pose(tmp_path, camera_block):
    text = REAL_CONFIG.read_text()
    start = text.index("\ncamera:") + 1
    end = text.index("\nrobot:") + 1
    path = tmp_path / "cell.yaml"
    path.write_text(text[:start] + camera_block + "\n" + text[end:])
    fit = CalibrationFit(true_camera_pose(), 0.995, 1.0, 2.0, np.ones(20, bool))
    cfg = write_calibration(path, fit)
    np.testing.assert_allclose(cfg.camera.pose.position, true_camera_pose()[:3, 3], atol=1e-6)
    assert cfg.robot.host == "192.168.1.10", "the rest of the file still loads as before"


# --------------------------------------------------------------------------- the whole command

class FakeCalibrationCell:
    """Stands in for the UR5e cell: records the checked moves, renders the marker where the tool is.

    The scene is seen by a camera at ``true_pose`` whose depth reads ``1/depth_error`` of the truth; the
    config's camera pose is only a first guess, as on a real cell.
    """

    def __init__(self, config, true_pose, depth_error=1.015, marker_offset=(0.0, 0.0, 0.0),
                 options=CalibrationOptions(), tool_noise=0.0002, seed=0):
        self.config = config
        self.true_pose, self.depth_error = true_pose, depth_error
        self.offset, self.options = np.asarray(marker_offset), options
        self.rng = np.random.default_rng(seed)
        self.tool_noise = tool_noise
        self.moves: list = []
        self.closed = False
        self.arm = self
        it = config.camera.intrinsics
        self.k = np.array([[it.fx, 0, it.cx], [0, it.fy, it.cy], [0, 0, 1.0]])

    def execute(self, checked):
        plan = checked.verify(self.config)
        self.moves.append(plan.poses[-1])
        return ExecutionResult(True)

    def tcp_pose(self):
        pose = self.moves[-1]
        return [*(np.asarray(pose.position) + self.rng.normal(0, self.tool_noise, 3)), *pose.rotvec]

    def capture(self) -> Frame:
        pose = self.moves[-1]
        centre = np.asarray(pose.position) + pose.matrix @ self.offset
        unit = 0.001 * self.depth_error                  # the depth the device reports is off by depth_error
        yaw = math.atan2(pose.matrix[1, 0], pose.matrix[0, 0])   # the marker turns with the tool
        color, depth = render_marker_frame(self.true_pose, self.k, centre, self.options,
                                           self.config.workspace.table_z, unit, yaw=yaw)
        cam = self.config.camera
        return Frame(color=color, depth=depth, depth_scale=0.001 * cam.depth_scale_correction,
                     intrinsics=self.k, camera_pose=pose_matrix(cam.pose.position, rpy_to_matrix(*cam.pose.rpy)))

    def close(self):
        self.closed = True


def test_calibrate_command_measures_and_writes_the_camera_pose(tmp_path, capsys):
    path = tmp_path / "cell.yaml"
    shutil.copy(REAL_CONFIG, path)
    cells = []

    def factory(cfg):
        cells.append(FakeCalibrationCell(cfg, true_camera_pose(), marker_offset=(0.0, 0.03, -0.02)))
        return cells[0]

    code = main(["--config", str(path), "--marker-offset", "0", "0.03", "-0.02"], cell_factory=factory,
                sleep=lambda s: None)
    out = capsys.readouterr()
    assert code == 0, out.err
    assert cells[0].closed and len(cells[0].moves) == 32
    cfg = load_config(path)
    got = pose_matrix(cfg.camera.pose.position, rpy_to_matrix(*cfg.camera.pose.rpy))
    assert np.linalg.norm(got[:3, 3] - true_camera_pose()[:3, 3]) < 0.002
    assert rotation_error_deg(got[:3, :3], true_camera_pose()[:3, :3]) < 0.5
    assert cfg.camera.depth_scale_correction == pytest.approx(1.015, abs=0.005)
    assert "RMS residual" in out.out
    m = re.search(r"estimated \((-?[\d.]+), (-?[\d.]+), (-?[\d.]+)\)", out.out)
    assert m and np.allclose([float(g) for g in m.groups()], (0.0, 0.03, -0.02), atol=0.001)
    assert len({round(math.atan2(p.matrix[1, 0], p.matrix[0, 0]), 6) for p in cells[0].moves}) == 3


def test_calibrate_command_refuses_a_poor_fit_and_leaves_the_file(tmp_path, capsys):
    path = tmp_path / "cell.yaml"
    shutil.copy(REAL_CONFIG, path)
    before = path.read_bytes()
    # The marker wobbles on its mount (positions off by ~6 mm): no transform fits within 2 mm.
    factory = lambda cfg: FakeCalibrationCell(cfg, true_camera_pose(), marker_offset=(0.0, 0.0, 0.0),  # noqa: E731
                                              tool_noise=0.006)
    code = main(["--config", str(path), "--max-residual-mm", "2"], cell_factory=factory, sleep=lambda s: None)
    err = capsys.readouterr().err
    assert code == 1 and "refused" in err and "left unchanged" in err
    assert path.read_bytes() == before


def test_calibrate_command_rejects_bad_input(tmp_path, capsys):
    assert main(["--config", str(tmp_path / "missing.yaml")], cell_factory=pytest.fail) == 2
    assert "file not found" in capsys.readouterr().err
    assert main(["--config", str(REAL_CONFIG), "--checkerboard", "4by3"], cell_factory=pytest.fail) == 2
    assert "expected COLSxROWS" in capsys.readouterr().err


def test_every_grid_pose_passes_the_envelope_of_the_shipped_config():
    from flgd.plans import MoveL, Plan
    from flgd.safety import check_plan

    cfg = load_config(REAL_CONFIG)
    poses = grid_poses(cfg, CalibrationOptions())
    assert len(poses) == 32
    for pose in poses:
        check_plan(Plan("calibrate", (MoveL(pose, cfg.robot.speed, cfg.robot.acceleration),)), cfg)


def test_grid_poses_vary_the_tool_yaw_top_down_on_the_same_layout():
    from flgd.plans import MoveL, Plan
    from flgd.safety import check_plan

    cfg = load_config(REAL_CONFIG)
    options = CalibrationOptions()
    poses = grid_poses(cfg, options)
    ws = cfg.workspace
    xs = np.linspace(ws.x[0] + options.margin, ws.x[1] - options.margin, 4)
    ys = np.linspace(ws.y[0] + options.margin, ws.y[1] - options.margin, 4)
    layout = [(x, y, ws.table_z + h) for h in options.heights for x in xs for y in ys]
    np.testing.assert_allclose([p.position for p in poses], layout, atol=1e-12)   # grid and count unchanged
    yaws = np.array([math.atan2(p.matrix[1, 0], p.matrix[0, 0]) for p in poses])
    for pose in poses:
        np.testing.assert_allclose(pose.matrix[:, 2], (0, 0, -1), atol=1e-12)      # top-down
        check_plan(Plan("calibrate", (MoveL(pose, cfg.robot.speed, cfg.robot.acceleration),)), cfg)
    assert len(set(np.round(yaws, 6))) == 3 and np.all(np.abs(yaws) < math.radians(90) - 1e-6)
    # every move turns the wrist the short way through 0, under 180 deg, so it swings back and forth
    assert np.all(np.abs(np.diff(yaws)) < math.radians(170) + 1e-9)
    for layer in (yaws[:16], yaws[16:]):
        assert len(set(np.round(layer, 6))) == 3, "every height sees every yaw"
    for column in range(4):                                      # yaw is not tied to a row or column of the grid
        assert len(set(np.round(yaws.reshape(2, 4, 4)[:, :, column].ravel(), 6))) > 1
        assert len(set(np.round(yaws.reshape(2, 4, 4)[:, column, :].ravel(), 6))) > 1


def synthetic_tool_detections(pose, scale, offset, rng, yaws=CALIBRATION_YAWS, sigma_xy=0.0003, sigma_z=0.001):
    """Camera points of a marker at ``offset`` on a tool moved top-down over the 4x4x2 grid, yaw cycling."""
    from flgd.geometry import top_down_rotation

    xs, ys, zs = np.meshgrid(np.linspace(0.33, 0.67, 4), np.linspace(-0.17, 0.17, 4), [0.08, 0.18])
    tcp = np.stack([xs.ravel(), ys.ravel(), zs.ravel()], axis=1)
    rot = np.array([top_down_rotation(yaws[i % len(yaws)]) for i in range(len(tcp))])
    marker = tcp + rot @ np.asarray(offset, dtype=float)
    cam_true = (marker - pose[:3, 3]) @ pose[:3, :3]
    noise = rng.normal(0, 1, cam_true.shape) * np.array([sigma_xy, sigma_xy, sigma_z])
    return (cam_true + noise) / scale, tcp, rot


@pytest.mark.parametrize("seed", range(3))
def test_the_marker_offset_x_y_is_estimated_with_the_camera_pose(seed):
    rng = np.random.default_rng(seed)
    pose, truth = true_camera_pose(), np.array([0.0, 0.03, -0.02])
    cam, tcp, rot = synthetic_tool_detections(pose, 1.02, truth, rng)
    for given in ((0.0, 0.0, -0.02), (0.0, 0.03, -0.02), (-0.04, 0.01, -0.02)):
        fit = fit_camera_pose_and_offset(cam, tcp, rot, given)
        np.testing.assert_allclose(fit.marker_offset, truth, atol=0.001)
        assert np.linalg.norm(fit.camera_pose[:3, 3] - pose[:3, 3]) < 0.002
        assert rotation_error_deg(fit.camera_pose[:3, :3], pose[:3, :3]) < 0.5
        assert fit.depth_scale_correction == pytest.approx(1.02, abs=0.005) and fit.rms_mm < 3.0
    # Why the yaw is varied: at one yaw, a fit with the wrong offset has a low residual and a camera off by
    # the offset's error (the review's finding); at varied yaws the plain fit can no longer hide it.
    cam1, tcp1, rot1 = synthetic_tool_detections(pose, 1.02, truth, rng, yaws=(0.0,))
    plain = fit_camera_pose(cam1, tcp1 + rot1 @ np.array([0.0, 0.0, -0.02]))
    assert plain.rms_mm < 3.0 and np.linalg.norm(plain.camera_pose[:3, 3] - pose[:3, 3]) > 0.025
    assert fit_camera_pose(cam, tcp + rot @ np.array([0.0, 0.0, -0.02])).rms_mm > 10.0


def test_the_marker_offset_z_is_not_observable_and_stays_as_given():
    rng = np.random.default_rng(3)
    pose, truth = true_camera_pose(), np.array([0.01, 0.03, -0.02])
    cam, tcp, rot = synthetic_tool_detections(pose, 1.0, truth, rng)
    fit = fit_camera_pose_and_offset(cam, tcp, rot, (0.01, 0.03, -0.03))        # z given 1 cm wrong
    assert fit.marker_offset[2] == -0.03 and fit.rms_mm < 3.0
    np.testing.assert_allclose(fit.marker_offset[:2], truth[:2], atol=0.001)
    assert fit.camera_pose[2, 3] - pose[2, 3] == pytest.approx(0.01, abs=0.002), "z error goes into the camera"


def test_the_marker_offset_cannot_be_checked_from_one_yaw():
    rng = np.random.default_rng(4)
    cam, tcp, rot = synthetic_tool_detections(true_camera_pose(), 1.0, (0, 0.03, -0.02), rng, yaws=(0.0,))
    with pytest.raises(CalibrationError, match="yaws"):
        fit_camera_pose_and_offset(cam, tcp, rot, (0, 0.03, -0.02))


def test_check_fit_refuses_an_offset_that_disagrees_with_the_estimate():
    options = CalibrationOptions(marker_offset=(0.0, 0.0, -0.02))
    near = CalibrationFit(true_camera_pose(), 1.0, 1.0, 2.0, np.ones(20, bool), np.array([0.003, -0.003, -0.02]))
    assert check_fit(near, options) is None
    far = CalibrationFit(true_camera_pose(), 1.0, 1.0, 2.0, np.ones(20, bool), np.array([0.0, 0.03, -0.02]))
    why = check_fit(far, options)
    assert why is not None and "given (0.0000, 0.0000, -0.0200)" in why and "estimated (0.0000, 0.0300, -0.0200)" in why
    assert f"tolerance {OFFSET_TOLERANCE_MM} mm" in why and "--marker-offset" in why


def test_calibrate_command_refuses_a_wrong_marker_offset(tmp_path, capsys):
    """The review's reproduction: marker at (0, 0.03, -0.02) on the tool, run with --marker-offset 0 0 0.

    Before the yaw was varied this wrote a camera pose ~3 cm off with an RMS of 0.5 mm and exit 0.
    """
    path = tmp_path / "cell.yaml"
    shutil.copy(REAL_CONFIG, path)
    before = path.read_bytes()
    factory = lambda cfg: FakeCalibrationCell(cfg, true_camera_pose(), marker_offset=(0.0, 0.03, -0.02))  # noqa: E731
    code = main(["--config", str(path), "--marker-offset", "0", "0", "0"], cell_factory=factory,
                sleep=lambda s: None)
    out = capsys.readouterr()
    assert code == 1 and "refused" in out.err and "left unchanged" in out.err
    assert path.read_bytes() == before
    assert "given (0.0000, 0.0000, 0.0000)" in out.err
    m = re.search(r"estimated \((-?[\d.]+), (-?[\d.]+), (-?[\d.]+)\)", out.err)
    assert m and abs(float(m.group(1))) < 0.001 and abs(float(m.group(2)) - 0.03) < 0.001
    assert "--marker-offset" in out.err and "z cannot be estimated" in out.err
    # --dry-run reports the same refusal
    assert main(["--config", str(path), "--dry-run"], cell_factory=factory, sleep=lambda s: None) == 1
    assert path.read_bytes() == before


def test_calibrate_refuses_while_a_daemon_holds_the_cell_and_runs_once_it_is_gone(tmp_path, capsys):
    """The daemon and calibrate would both drive the arm: calibrate checks the daemon's state-dir lock
    (the same flock on the state directory the daemon takes) before it opens anything."""
    from flgd.state_dir_lock import StateDirBusy, lock_state_dir

    state = tmp_path / "state"
    path = tmp_path / "cell.yaml"
    path.write_text(REAL_CONFIG.read_text().replace("state_dir: /var/lib/flgd", f"state_dir: {state}"))
    opened = []

    def factory(cfg):
        opened.append(FakeCalibrationCell(cfg, true_camera_pose()))
        return opened[-1]

    daemon_fd = lock_state_dir(state, create=True)  # what a running daemon holds
    try:
        code = main(["--config", str(path), "--dry-run"], cell_factory=factory, sleep=lambda s: None)
        err = capsys.readouterr().err
        assert code == 1 and not opened, err
        assert str(state) in err and "systemctl stop flgd" in err
    finally:
        os.close(daemon_fd)
    # the daemon gone: calibrate runs, and holds the lock meanwhile (a daemon started now would be refused)
    held = []

    def probing_factory(cfg):
        with pytest.raises(StateDirBusy):
            lock_state_dir(state, create=True)
        held.append(True)
        return factory(cfg)

    assert main(["--config", str(path), "--dry-run"], cell_factory=probing_factory, sleep=lambda s: None) == 0
    assert held and opened[-1].closed
    os.close(lock_state_dir(state, create=True))  # released afterwards


# --------------------------------------------------------------------------- calibration: bad input is a clear error

def _grid_points() -> np.ndarray:
    xs, ys, zs = np.meshgrid(np.linspace(0.33, 0.67, 4), np.linspace(-0.17, 0.17, 4), [0.08, 0.18])
    return np.stack([xs.ravel(), ys.ravel(), zs.ravel()], axis=1)


def test_coincident_camera_points_are_a_calibration_error_not_a_nan_pose():
    base = _grid_points()
    frozen = np.tile([0.01, -0.02, 0.6], (len(base), 1))  # the camera returned the same point every time
    with pytest.raises(CalibrationError, match="camera-side"):
        fit_camera_pose(frozen, base)


def test_a_nan_residual_is_never_accepted():
    fit = CalibrationFit(true_camera_pose(), 1.0, float("nan"), float("nan"), np.ones(20, bool))
    assert check_fit(fit, CalibrationOptions()) is not None


@pytest.mark.parametrize("args, flag", [
    (["--max-residual-mm", "nan"], "--max-residual-mm"),    # NaN would switch the residual gate off
    (["--settle", "nan"], "--settle"),
    (["--heights", "0.1", "-0.2"], "--heights"),
    (["--marker-offset", "0", "nan", "0"], "--marker-offset"),
    (["--aruco-dict", "DICT_NOPE"], "--aruco-dict"),        # used to stop the run with the arm out on the grid
    (["--aruco-id", "50"], "--aruco-id"),                   # DICT_4X4_50 has ids 0..49: never detected
])
def test_bad_calibrate_options_are_refused_before_the_cell_is_opened(args, flag, capsys):
    code = main(["--config", str(REAL_CONFIG), *args], cell_factory=pytest.fail)
    err = capsys.readouterr().err
    assert code == 2 and flag in err and "expected" in err


def test_a_config_that_cannot_be_written_is_exit_1_and_left_unchanged(tmp_path, monkeypatch, capsys):
    path = tmp_path / "cell.yaml"
    shutil.copy(REAL_CONFIG, path)
    before = path.read_bytes()

    def read_only(*_a, **_k):
        raise OSError(errno.EROFS, "Read-only file system", str(path))

    monkeypatch.setattr(calibration, "write_atomically", read_only)
    cell = FakeCalibrationCell(load_config(path), true_camera_pose())
    code = main(["--config", str(path)], cell_factory=lambda cfg: cell, sleep=lambda s: None)
    err = capsys.readouterr().err
    assert code == 1 and str(path) in err and "Read-only file system" in err
    assert path.read_bytes() == before and cell.closed
