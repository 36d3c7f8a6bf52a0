"""Bad input never crashes the daemon, moves the arm or corrupts stored data: diverged (NaN/Inf) policies and
learner updates, policy paths that are not regular files or are huge, policy file permissions and the
systemd sandbox hint, the signal handler's locking, flgctl's stop message, and cross-key config checks."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from flgd.actions import Action
from flgd.config import CellConfig, ConfigError, config_from_dict, load_config
from flgd.daemon.notify import Notifier
from flgd.daemon.state import State, StateMachine
from flgd.learning import policy_file
from flgd.learning.learner import Learner, resolve_device
from flgd.learning.networks import build_network
from flgd.learning.policy_file import MAX_POLICY_BYTES, PolicyFileError, load_policy, read_metadata, save_policy
from flgd.learning.replay import PrioritizedReplay, Transition
from flgd.perception import Heightmaps
from flgd.store import CheckpointDir

REPO = Path(__file__).resolve().parents[1]
SIM = REPO / "cell_config" / "sim.yaml"


@pytest.fixture(autouse=True)
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def small_net(seed: int = 0):
    return build_network("fast", 16, seed=seed).eval()


def save_unchecked(path: Path, net, monkeypatch) -> None:
    """Save ``net`` as an older flgd (without the finiteness check) would have: valid checksums, bad weights."""
    with monkeypatch.context() as m:
        m.setattr(policy_file, "first_non_finite", lambda *a: None)
        save_policy(path, net, {"training_steps": 1})


def poisoned(value: float, seed: int = 0) -> tuple[object, str]:
    """A network with one ``value`` (nan/inf) in its second floating-point tensor, and that tensor's name."""
    net = small_net(seed)
    names = [k for k, v in net.state_dict().items() if v.is_floating_point()]
    name = names[1]
    with torch.no_grad():
        net.state_dict()[name].view(-1)[0] = value
    return net, name


# =========================================================================== 1. non-finite policies

@pytest.mark.parametrize("value, kind", [(float("nan"), "NaN"), (float("inf"), "Inf"), (float("-inf"), "Inf")])
def test_a_policy_file_with_a_non_finite_weight_is_refused_naming_file_and_tensor(tmp_path, monkeypatch, value,
                                                                                    kind):
    net, name = poisoned(value)
    path = tmp_path / "diverged.safetensors"
    save_unchecked(path, net, monkeypatch)
    with pytest.raises(PolicyFileError) as err:
        load_policy(path, expected_variant="fast")
    msg = str(err.value)
    assert str(path) in msg and repr(name) in msg and kind in msg and "diverged" in msg, msg


def test_saving_a_diverged_network_is_refused_and_writes_nothing(tmp_path):
    net, name = poisoned(float("nan"))
    path = tmp_path / "p.safetensors"
    with pytest.raises(PolicyFileError, match="diverged") as err:
        save_policy(path, net, {})
    assert repr(name) in str(err.value)
    assert list(tmp_path.iterdir()) == []  # no file, no temp file


def test_a_diverged_checkpoint_is_skipped_and_the_daemon_resumes_from_the_older_good_one(tmp_path, monkeypatch):
    from flgd.wiring import starting_network

    ckpts = CheckpointDir(tmp_path / "checkpoints", keep=3)
    ckpts.write(lambda p: save_policy(p, small_net(1), {}), 100)
    bad, _ = poisoned(float("nan"), seed=2)
    ckpts.write(lambda p: save_unchecked(p, bad, monkeypatch), 200)
    cfg = dataclasses.replace(CellConfig(), learning=dataclasses.replace(CellConfig().learning, init_trunk=""))
    start = starting_network(cfg, ckpts, None)
    assert start.checkpoint == ckpts.path_for(100) and start.resumed_from_updates == 100
    assert all(torch.isfinite(v).all() for v in start.network.state_dict().values() if v.is_floating_point())


def _controller(tmp_path: Path):
    from flgd.daemon.controller import Controller

    cfg = dataclasses.replace(CellConfig(), state_dir=str(tmp_path / "state"))
    return Controller(cfg)


def test_flgctl_policy_load_of_a_diverged_file_is_an_error_reply_and_the_running_policy_stays(tmp_path,
                                                                                              monkeypatch):
    from flgd.daemon.commands import policy_load
    from flgd.daemon.protocol import ProtocolError

    net, name = poisoned(float("nan"))
    path = tmp_path / "diverged.safetensors"
    save_unchecked(path, net, monkeypatch)
    ctl = _controller(tmp_path)
    ctl.learner = None  # never reached: the file is refused before the learner sees any weight
    with pytest.raises(ProtocolError) as err:
        policy_load(ctl, str(path))
    assert err.value.code == "failed" and "running policy stays" in err.value.message
    assert str(path) in err.value.message and repr(name) in err.value.message


# =========================================================================== 1b. the learner's NaN guard

N = 32


def scene(seed: int) -> Heightmaps:
    rng = np.random.default_rng(seed)
    h = np.zeros((N, N), np.float32)
    r, c = rng.integers(2, N - 8, 2)
    h[r:r + 6, c:c + 6] = 0.03
    color = np.full((N, N, 3), 90, np.uint8)
    return Heightmaps(color, h)


def make_learner(calls: list) -> Learner:
    cfg = CellConfig()
    cfg = dataclasses.replace(cfg, learning=dataclasses.replace(cfg.learning, batch_size=2, device="cpu",
                                                                checkpoint_every=1))
    replay = PrioritizedReplay.from_config(cfg.learning)
    for i in range(3):
        replay.add(Transition(scene(i), Action("grasp", 10, 12, i), 1.0, scene(i + 1), False))
    return Learner(cfg, small_net(), replay, checkpoint_callback=lambda net, n: calls.append(n))


class _InfGrad(torch.autograd.Function):
    """Identity forward, infinite gradient backward: a finite loss whose step would still wreck the weights."""

    @staticmethod
    def forward(ctx, x):
        return x.clone()

    @staticmethod
    def backward(ctx, grad):
        return grad * float("inf")


@pytest.mark.parametrize("poison", ["nan_loss", "inf_gradient"])
def test_a_non_finite_update_is_skipped_counted_and_reported_and_nothing_is_checkpointed(poison):
    calls: list[int] = []
    lrn = make_learner(calls)
    real = lrn.loss_terms

    def diverging(transitions, weights):
        terms = real(transitions, weights)
        terms.loss = terms.loss * float("nan") if poison == "nan_loss" else _InfGrad.apply(terms.loss)
        return terms

    before = {k: v.clone() for k, v in lrn.online.state_dict().items()}
    priorities = [lrn.replay.priority(i) for i in range(3)]
    lrn.loss_terms = diverging
    assert lrn.update() is None
    after = lrn.online.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before), "a non-finite update changed the weights"
    assert lrn.optimizer.state == {} and lrn.updates == 0 and calls == []
    assert [lrn.replay.priority(i) for i in range(3)] == priorities
    assert lrn.skipped_updates == 1 and "update 1 skipped" in lrn.last_error
    assert ("loss is nan" if poison == "nan_loss" else "gradient of") in lrn.last_error, lrn.last_error
    # learning goes on once the updates are finite again
    lrn.loss_terms = real
    stats = lrn.update()
    assert stats is not None and lrn.updates == 1 and calls == [1] and lrn.skipped_updates == 1
    assert all(torch.isfinite(v).all() for v in lrn.online.state_dict().values() if v.is_floating_point())


def test_the_background_learner_reports_skipped_updates_through_last_error():
    calls: list[int] = []
    lrn = make_learner(calls)
    real = lrn.loss_terms

    def nan_loss(transitions, weights):
        terms = real(transitions, weights)
        terms.loss = terms.loss * float("nan")
        return terms

    lrn.loss_terms = nan_loss
    lrn.start()
    try:
        lrn.notify_new_transition()
        assert lrn.wait_idle(120)
    finally:
        lrn.stop(30)
    assert lrn.skipped_updates >= 1 and lrn.failed_updates == 0 and lrn.updates == 0
    assert lrn.last_error and "skipped" in lrn.last_error


# =========================================================================== 2. what a policy path may be

def test_dev_zero_is_refused_at_once_without_reading_it():
    start = time.monotonic()
    for fn in (lambda: load_policy("/dev/zero"), lambda: read_metadata("/dev/zero")):
        with pytest.raises(PolicyFileError, match="character device") as err:
            fn()
        assert "/dev/zero" in str(err.value) and "regular" in str(err.value)
    assert time.monotonic() - start < 5


def test_a_fifo_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "policy.safetensors"
    os.mkfifo(fifo)
    result: list = []

    def load():
        try:
            load_policy(fifo)
        except PolicyFileError as exc:
            result.append(str(exc))

    t = threading.Thread(target=load, daemon=True)
    t.start()
    t.join(10)
    if t.is_alive():  # unblock the thread before failing (open a writer)
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail("load_policy blocked on a FIFO")
    assert result and "FIFO" in result[0] and str(fifo) in result[0]


def test_a_directory_is_refused(tmp_path):
    with pytest.raises(PolicyFileError, match="is a directory"):
        load_policy(tmp_path)


def test_a_file_over_the_size_cap_is_refused_before_it_is_read(tmp_path):
    big = tmp_path / "huge.safetensors"
    with open(big, "wb") as f:  # sparse: takes no disk space
        f.truncate(MAX_POLICY_BYTES + 1)
    start = time.monotonic()
    with pytest.raises(PolicyFileError) as err:
        load_policy(big)
    assert time.monotonic() - start < 5
    msg = str(err.value)
    assert str(big) in msg and "512.0 MB" in msg and "expected at most" in msg


def test_the_shipped_policy_still_loads():
    shipped = sorted((REPO / "policies").glob("*.safetensors"))
    policies = [p for p in shipped if not p.name.startswith("trunk")]
    assert policies
    for p in policies:
        assert load_policy(p).network is not None


# =========================================================================== 3. permissions and the sandbox hint

def test_saved_policies_and_checkpoints_are_group_readable_whatever_the_umask(tmp_path):
    old = os.umask(0o077)
    try:
        save_policy(tmp_path / "p.safetensors", small_net(), {})
        ckpt = CheckpointDir(tmp_path / "ckpt").write(lambda p: save_policy(p, small_net(), {}), 5)
    finally:
        os.umask(old)
    for p in (tmp_path / "p.safetensors", ckpt):
        assert stat.S_IMODE(p.stat().st_mode) == 0o640, oct(p.stat().st_mode)


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("setpriv") is None, reason="needs root and setpriv")
def test_flgctl_policy_save_copy_works_for_a_group_member_who_is_not_the_daemons_user():
    """The daemon (here root) saves into a 0750 state directory; flgctl runs as another uid in its group."""
    base = Path(tempfile.mkdtemp(prefix="flgd-perm-", dir="/tmp"))
    try:
        os.chmod(base, 0o755)
        state = base / "state"
        state.mkdir(mode=0o750)
        os.chmod(state, 0o750)
        saved = state / "policies" / "policy-x.safetensors"
        old = os.umask(0o027)  # the unit's UMask
        try:
            save_policy(saved, small_net(), {})
        finally:
            os.umask(old)
        out = base / "out"
        out.mkdir()
        os.chown(out, 65534, 0)
        sock_path = base / "flgd.sock"
        srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        srv.bind(str(sock_path))
        os.chmod(sock_path, 0o666)
        srv.listen(1)

        def serve():
            conn, _ = srv.accept()
            with conn:
                conn.recv(65536)
                conn.sendall((json.dumps({"ok": True, "state": "IDLE", "result": {"saved": str(saved),
                                                                                   "learner_updates": 3}})
                              + "\n").encode())

        threading.Thread(target=serve, daemon=True).start()
        dest = out / "mine.safetensors"
        p = subprocess.run(["setpriv", "--reuid=65534", "--regid=0", "--clear-groups", sys.executable, "-m",
                            "flgd.ctl", "--socket", str(sock_path), "policy", "save", str(dest)],
                           capture_output=True, text=True, timeout=120, cwd=REPO)
        srv.close()
        assert p.returncode == 0, p.stderr
        assert dest.read_bytes() == saved.read_bytes()
        assert "policy saved" in p.stdout
    finally:
        shutil.rmtree(base, ignore_errors=True)


@pytest.mark.parametrize("where", ["/tmp/flgd-no-such-policy.safetensors", "/home/op/flgd-no-such.safetensors",
                                   "/var/tmp/flgd-no-such.safetensors"])
def test_not_found_under_a_sandboxed_path_explains_protecthome_and_privatetmp(where):
    with pytest.raises(PolicyFileError) as err:
        load_policy(where)
    msg = str(err.value)
    assert where in msg and "No such file or directory" in msg
    assert "PrivateTmp" in msg and "ProtectHome" in msg and "/var/lib/flgd/policies" in msg


def test_not_found_elsewhere_has_no_sandbox_hint():
    # A fixed path outside every sandboxed prefix: the repository itself may be checked out under /tmp or /home.
    missing = Path("/var/lib/flgd-test-no-such-dir/no-such-policy.safetensors")
    assert not missing.exists()
    with pytest.raises(PolicyFileError) as err:
        load_policy(missing)
    assert "No such file or directory" in str(err.value) and "PrivateTmp" not in str(err.value)


def test_the_unit_state_directory_is_where_the_hint_points():
    unit = (REPO / "systemd" / "flgd.service").read_text()
    assert "StateDirectory=flgd\n" in unit and "ProtectHome=yes" in unit and "PrivateTmp=yes" in unit
    assert "UMask=0027" in unit  # saved policies (0640) and their directory (0750) stay group-readable


def test_write_atomically_sets_the_mode_before_the_file_appears(tmp_path):
    from flgd.atomic_file import write_atomically

    target = tmp_path / "f"
    write_atomically(target, b"x", mode=0o640)
    assert stat.S_IMODE(target.stat().st_mode) == 0o640
    write_atomically(target, b"y")
    assert stat.S_IMODE(target.stat().st_mode) == 0o600 and target.read_bytes() == b"y"


# =========================================================================== 4. the signal handler

class _FakeRunner:
    def __init__(self):
        self.halts = 0

    def request_stop(self):
        self.halts += 1


class _FakeController:
    """The parts of Controller the signal path touches, with the real (non-reentrant) locks."""

    def __init__(self):
        self.state = StateMachine(State.RUNNING)
        self.notifier = Notifier({})
        self.runner = _FakeRunner()
        self.state.add_listener(lambda change: self.notifier.send(f"STATUS={change.new.value}"))

    def request_stop(self, cause: str) -> None:  # what Controller.request_stop does
        self.state.transition(State.STOPPING, cause)
        if self.runner is not None:
            self.runner.request_stop()


def test_the_handler_halts_the_motion_but_leaves_the_state_change_to_the_loop():
    from flgd.daemon.run import _SignalStop

    ctl = _FakeController()
    stop = _SignalStop(ctl)
    assert stop.poll() is False
    stop.on_signal(signal.SIGTERM)
    assert ctl.runner.halts == 1 and ctl.state.state is State.RUNNING
    assert stop.poll() is True
    assert ctl.state.state is State.STOPPING and ctl.state.cause == "signal SIGTERM"
    assert stop.poll() is True and ctl.state.cause == "signal SIGTERM"  # polled again: no second transition


@pytest.mark.parametrize("lock", ["state", "notifier"])
def test_a_signal_while_the_main_thread_holds_a_lock_does_not_deadlock(lock):
    """A real SIGTERM delivered while this (the main) thread holds the lock, as in the daemon."""
    from flgd.daemon.run import _SignalStop

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals are delivered to the main thread only")
    ctl = _FakeController()
    stop = _SignalStop(ctl)
    held = ctl.state._lock if lock == "state" else ctl.notifier._lock

    def alarm(_s, _f):  # a deadlocked handler is interrupted here instead of hanging the test run
        raise TimeoutError("the signal handler deadlocked")

    prev_term = signal.signal(signal.SIGTERM, stop.on_signal)
    prev_alarm = signal.signal(signal.SIGALRM, alarm)
    try:
        signal.setitimer(signal.ITIMER_REAL, 5.0)
        with held:
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(100):  # the handler runs between bytecodes of this thread
                if stop.seen:
                    break
                time.sleep(0.01)
        signal.setitimer(signal.ITIMER_REAL, 0)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGTERM, prev_term)
        signal.signal(signal.SIGALRM, prev_alarm)
    assert stop.seen == [signal.SIGTERM] and ctl.runner.halts == 1
    assert stop.poll() and ctl.state.state is State.STOPPING


def test_a_failing_halt_never_raises_into_the_interrupted_code_and_is_logged_later(caplog):
    from flgd.daemon.run import _SignalStop

    ctl = _FakeController()
    calls = []

    def broken():  # the first halt (in the handler) fails; the loop's own stop later goes through
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("link gone")

    ctl.runner.request_stop = broken
    stop = _SignalStop(ctl)
    stop.on_signal(signal.SIGTERM)  # must not raise
    with caplog.at_level("ERROR"):
        assert stop.poll()
    assert "link gone" in caplog.text and ctl.state.state is State.STOPPING


def test_a_signal_during_setup_is_only_recorded():
    from flgd.daemon.run import _SignalStop

    ctl = _FakeController()
    ctl.runner = None
    stop = _SignalStop(ctl)
    stop.on_signal(signal.SIGINT)
    assert ctl.state.state is State.RUNNING and stop.poll() and ctl.state.cause == "signal SIGINT"


def test_a_second_ctrl_c_exits_at_once_with_130():
    code = ("import signal\n"
            "from flgd.daemon.run import _SignalStop\n"
            "class C:\n    runner = None\n"
            "s = _SignalStop(C())\n"
            "s.on_signal(signal.SIGINT)\n"
            "s.on_signal(signal.SIGINT)\n"
            "print('not reached')\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert p.returncode == 130 and "second interrupt" in p.stderr and "not reached" not in p.stdout


def test_run_docstring_no_longer_promises_the_motion_is_never_stopped():
    import flgd.daemon.run as run

    assert "never stopped mid-motion" not in run.__doc__ and "halts the motion in flight" in run.__doc__


# =========================================================================== 5. flgctl stop says what is known

def test_flgctl_stop_reports_a_request_not_a_finished_flush(tmp_path, capsys):
    from flgd import ctl

    sock_path = tmp_path / "s.sock"
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(str(sock_path))
    srv.listen(1)

    def serve():
        conn, _ = srv.accept()
        with conn:
            conn.recv(65536)
            conn.sendall(b'{"ok": true, "state": "STOPPING", "result": {"stopping": true}}\n')

    threading.Thread(target=serve, daemon=True).start()
    assert ctl.main(["--socket", str(sock_path), "stop"]) == 0
    out = capsys.readouterr().out
    srv.close()
    assert out.startswith("stop requested") and "flushed" not in out and "halted" not in out


def test_flgctl_policy_save_permission_error_names_the_group(tmp_path, capsys, monkeypatch):
    from flgd import ctl

    sock_path = tmp_path / "s.sock"
    saved = "/var/lib/flgd/policies/p.safetensors"
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(str(sock_path))
    srv.listen(1)

    def serve():
        conn, _ = srv.accept()
        with conn:
            conn.recv(65536)
            conn.sendall((json.dumps({"ok": True, "state": "IDLE", "result": {"saved": saved,
                                                                               "learner_updates": 1}})
                          + "\n").encode())

    threading.Thread(target=serve, daemon=True).start()

    def denied(src, dst):
        raise PermissionError(13, "Permission denied", src)

    monkeypatch.setattr(ctl.shutil, "copyfile", denied)
    assert ctl.main(["--socket", str(sock_path), "policy", "save", str(tmp_path / "x.safetensors")]) == 1
    srv.close()
    err = capsys.readouterr().err
    assert saved in err and "Permission denied" in err and "group flgd" in err


# =========================================================================== 6. cross-key config checks

def sim_data() -> dict:
    return yaml.safe_load(SIM.read_text())


def problems_of(data: dict) -> list[str]:
    with pytest.raises(ConfigError) as err:
        config_from_dict(data, "cell.yaml")
    return err.value.problems


def test_workspace_top_must_lie_inside_the_envelope():
    data = sim_data()
    data["workspace"]["z"] = [0.0, 0.9]
    (p,) = problems_of(data)
    assert p.startswith("workspace.z:") and "0.9" in p and "safety.envelope_z" in p and "0.45" in p


@pytest.mark.parametrize("pose", ["home", "place"])
def test_home_and_place_must_clear_the_table_floor(pose):
    data = sim_data()
    data["robot"][pose]["position"][2] = 0.002  # inside envelope_z [0, 0.45], below 0 + 0.004
    (p,) = problems_of(data)
    assert p.startswith(f"robot.{pose}.position:") and "0.002" in p and "clearance floor" in p \
        and "safety.min_table_clearance" in p


def test_home_and_place_have_no_tilt_to_configure():
    data = sim_data()
    data["robot"]["home"]["rpy"] = [0.3, 0.0, 0.0]
    (p,) = problems_of(data)
    assert p.startswith("robot.home.rpy: unknown key")


def test_unknown_backend_is_a_config_error_with_a_suggestion():
    data = sim_data()
    data["backend"] = "ur5"
    problems = problems_of(data)
    assert any(p.startswith("backend: got 'ur5'") and "'sim'" in p and "did you mean 'ur5e'" in p
               for p in problems), problems


def test_a_gripper_driver_the_backend_cannot_drive_is_a_config_error():
    data = yaml.safe_load((REPO / "cell_config" / "ur5e-d415.yaml").read_text())
    data["gripper"]["driver"] = "sim"
    (p,) = problems_of(data)
    assert p.startswith("gripper.driver: got 'sim'") and "'rg2_xmlrpc'" in p and "backend 'ur5e'" in p


def test_the_simulator_accepts_a_real_driver_so_a_real_config_can_swap_to_sim():
    data = sim_data()
    data["gripper"]["driver"] = "rg2_xmlrpc"
    config_from_dict(data, "cell.yaml")


def test_check_config_reports_the_new_problems(tmp_path, capsys):
    from flgd.check_config import main

    data = sim_data()
    data["workspace"]["z"] = [0.0, 0.9]
    data["backend"] = "nope"
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    assert main([str(path)]) == 1
    err = capsys.readouterr().err
    assert str(path) in err and "workspace.z" in err and "backend: got 'nope'" in err


def test_cuda_on_a_machine_without_cuda_is_a_config_error(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    data = sim_data()
    data["learning"]["device"] = "cuda"
    (p,) = problems_of(data)
    assert p.startswith("learning.device: got 'cuda'") and "no CUDA device" in p and "'cpu' or 'auto'" in p
    with pytest.raises(ConfigError, match="learning.device"):
        resolve_device("cuda", "cell.yaml")


@pytest.fixture
def keep_logging():
    """``flgd run`` in-process replaces the root log handlers with one on this test's (soon closed) stderr."""
    import logging

    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


def _cuda_config(tmp_path: Path) -> Path:
    data = sim_data()
    data["learning"]["device"] = "cuda"
    data["learning"]["init_trunk"] = ""
    data["policy"] = ""
    data["state_dir"] = str(tmp_path / "state")
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_flgd_run_with_cuda_but_no_cuda_exits_1_with_a_clear_message(tmp_path, monkeypatch, capsys, keep_logging):
    from flgd.daemon import run

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    path = _cuda_config(tmp_path)
    assert run.main(["--config", str(path), "--socket", str(tmp_path / "s.sock"), "--no-status-line"]) == 1
    err = capsys.readouterr().err
    assert str(path) in err and "learning.device" in err and "Traceback" not in err


def test_a_device_error_found_only_at_learner_construction_is_still_a_clear_exit_1(tmp_path, monkeypatch,
                                                                                  capsys, keep_logging):
    """Defence in depth: should the config check be bypassed, the learner's error is a ConfigError that
    ``flgd run`` reports (not a traceback) before anything moves."""
    import flgd.config.rules as config_rules
    from flgd.daemon import run

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(config_rules, "_check_device", lambda cfg, problems: None)
    path = _cuda_config(tmp_path)
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    assert run.main(["--config", str(path), "--socket", str(tmp_path / "s.sock"), "--no-status-line"]) == 1
    err = capsys.readouterr().err
    assert "learning.device" in err and "no CUDA device" in err and "Traceback" not in err
    assert not (tmp_path / "s.sock").exists()
    assert {sig: signal.getsignal(sig) for sig in before} == before


def test_shipped_configs_still_pass():
    for path in sorted((REPO / "cell_config").glob("*.yaml")):
        load_config(path)
