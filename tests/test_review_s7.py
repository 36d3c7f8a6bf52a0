"""Review s7: bad input to calibration, perception, flgctl and the config loader is a clear error, never a crash
or a silently wrong result."""

from __future__ import annotations

import base64
import errno
import json
import shutil
import socket
import tempfile
import threading
from pathlib import Path

import numpy as np
import pytest

from flgd import ctl
from flgd.config import ConfigError, WorkspaceConfig, load_config
from flgd.hardware import calibration
from flgd.hardware.calibration import CalibrationOptions, check_fit, main as calibrate_main
from flgd.hardware.calibration_math import CalibrationError, CalibrationFit, fit_camera_pose
from flgd.perception import make_heightmaps
from tests.synthetic_scene import camera_looking_down, intrinsics_matrix
from tests.test_hardware_calibration import REAL_CONFIG, FakeCalibrationCell, true_camera_pose


# --------------------------------------------------------------------------- calibration

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
    code = calibrate_main(["--config", str(REAL_CONFIG), *args], cell_factory=pytest.fail)
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
    code = calibrate_main(["--config", str(path)], cell_factory=lambda cfg: cell, sleep=lambda s: None)
    err = capsys.readouterr().err
    assert code == 1 and str(path) in err and "Read-only file system" in err
    assert path.read_bytes() == before and cell.closed


# --------------------------------------------------------------------------- config loading

def _load(tmp_path: Path, text: str):
    path = tmp_path / "cell.yaml"
    path.write_text(text)
    return load_config(path), path


@pytest.mark.parametrize("text, expect", [
    ("? [a, b]\n: 1\n", "cannot be a key"),                               # was TypeError: unhashable
    ("camera:\n  depth_scale: " + "1" * 400 + "\n", "camera.depth_scale"),  # was OverflowError
    ("[" * 5000 + "]" * 5000 + "\n", "nested too deeply"),               # was RecursionError
    ("camera:\n  serial: 819612070593\n", "quote the value"),
])
def test_malformed_config_is_a_config_error_naming_the_file(tmp_path, text, expect):
    with pytest.raises(ConfigError) as info:
        _load(tmp_path, text)
    assert str(tmp_path / "cell.yaml") in str(info.value) and expect in str(info.value)


# --------------------------------------------------------------------------- perception

def _frame(h: int = 30, w: int = 30):
    k = intrinsics_matrix()
    k = k.copy()
    k[0, 2], k[1, 2] = w / 2, h / 2
    pose = camera_looking_down(-0.5, 0.0, 0.7)
    return np.zeros((h, w, 3), np.uint8), np.full((h, w), 700, np.uint16), k, pose


def test_rgba_colour_is_refused_not_scrambled():
    color, depth, k, pose = _frame()
    rgba = np.zeros((30, 30, 4), np.uint8)  # 30*30*4 bytes divide by 3: the old byte view silently misread it
    with pytest.raises(ValueError, match="color"):
        make_heightmaps(rgba, depth, k, 0.001, pose, WorkspaceConfig())
    with pytest.raises(ValueError, match="color"):
        make_heightmaps(color.astype(np.float32), depth, k, 0.001, pose, WorkspaceConfig())


@pytest.mark.parametrize("what", ["pose", "intrinsics", "depth_scale", "depth"])
def test_non_finite_camera_model_is_refused_not_an_empty_heightmap(what):
    color, depth, k, pose = _frame()
    scale = 0.001
    if what == "pose":
        pose = pose.copy()
        pose[0, 3] = np.nan
    elif what == "intrinsics":
        k[0, 0] = 0.0
    elif what == "depth_scale":
        scale = float("nan")
    else:
        depth = depth[None]
    with pytest.raises(ValueError, match=what):
        make_heightmaps(color, depth, k, scale, pose, WorkspaceConfig())


# --------------------------------------------------------------------------- flgctl

@pytest.mark.parametrize("value", ["-1", "0", "nan", "inf", "soon"])
def test_bad_timeout_is_a_usage_error(value, capsys):
    assert ctl.main(["--socket", "/nonexistent/flgd.sock", "--timeout", value, "status"]) == ctl.EXIT_USAGE
    assert "--timeout" in capsys.readouterr().err


class _OneReplyDaemon:
    """A control socket that answers every request line with ``reply`` (bytes, newline added)."""

    def __init__(self, reply: bytes):
        self.dir = Path(tempfile.mkdtemp(prefix="flgd-s7-", dir="/tmp"))
        self.path = self.dir / "s.sock"
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.bind(str(self.path))
        self.sock.listen(1)
        self.reply = reply
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        conn, _ = self.sock.accept()
        with conn:
            buf = b""
            while b"\n" not in buf:
                chunk = conn.recv(65536)
                if not chunk:
                    return
                buf += chunk
            conn.sendall(self.reply + b"\n")

    def close(self) -> None:
        self.sock.close()
        self.thread.join(5)
        shutil.rmtree(self.dir, ignore_errors=True)


def test_json_output_reports_a_snapshot_that_cannot_be_written(tmp_path, capsys):
    png = base64.b64encode(b"\x89PNG fake").decode()
    daemon = _OneReplyDaemon(json.dumps({"ok": True, "state": "IDLE",
                                         "result": {"png_base64": png, "source": "last", "action": None}}).encode())
    try:
        code = ctl.main(["--socket", str(daemon.path), "--json", "snapshot", str(tmp_path / "no-dir" / "s.png")])
    finally:
        daemon.close()
    out = capsys.readouterr()
    assert code == ctl.EXIT_FAILED
    reply = json.loads(out.out)  # a script reading stdout must not see an empty output (or a success)
    assert reply["ok"] is False and "no-dir" in reply["error"]["message"]


def test_a_reply_that_is_not_utf8_is_exit_1_not_a_traceback(capsys):
    daemon = _OneReplyDaemon(b'{"ok": true, "result": "\xff"}')  # JSON-looking, not UTF-8
    try:
        code = ctl.main(["--socket", str(daemon.path), "status"])
    finally:
        daemon.close()
    assert code == ctl.EXIT_FAILED and "unreadable reply" in capsys.readouterr().err
