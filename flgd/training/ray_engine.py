"""Ray as the engine of runs on many simulated cells: start a local cluster or join one, and leave nothing behind.

``flgd train --workers N``, ``flgd eval --workers N`` and ``flgd bench finetune --jobs N`` start here.  Without
``--address`` a local cluster is started for the run (``ray.init``) and stopped with it; with one the run joins
an existing cluster (``ray start --head`` on one machine, ``ray start --address=HEAD:6379`` on the others;
docs/training-and-evaluation.md).  Ray's usage reporting is off unless the environment turns it on, a local
cluster starts without its dashboard, and Ray's token authentication is on (Ray's default for a local
cluster; asked for when joining one, unless ``RAY_AUTH_MODE`` says otherwise).  The daemon never imports this module: a cell PC needs no Ray.

Why a reaper: a local cluster's processes are children of the driver, and Ray stops them on a clean exit, but
when the driver is killed (``kill -9``, the OOM killer) some of them (its dashboard and runtime-env agents)
outlive it for good.  ``LocalClusterReaper`` is a small process that notes the driver's descendants every
second and kills those that are Ray's once the driver's pipe to it closes -- which the kernel does however the
driver ends.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass
from typing import Any

__all__ = ["EngineError", "Engine", "start_engine", "remote_class", "worker_lost_errors"]


class EngineError(RuntimeError):
    """Ray is missing or the cluster cannot be started or joined; the message says what to do."""


@dataclass
class Engine:
    """A started or joined Ray cluster; ``stop`` ends what this run started."""

    ray: Any
    address: str  # '' = a local cluster started for this run
    cpus: float
    reaper: subprocess.Popen | None = None

    @property
    def local(self) -> bool:
        return not self.address

    def stop(self) -> None:
        clean = False
        try:
            self.ray.shutdown()
            clean = True
        finally:
            if self.reaper is not None:  # a shutdown that failed leaves the reaper to kill what is left
                _close_reaper(self.reaper, keep=clean)
                self.reaper = None


def start_engine(address: str | None, workers: int) -> Engine:
    """Start a local cluster with at least ``workers`` CPUs (one per worker), or join the one at ``address``."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    # Token authentication (a shared secret, ~/.ray/auth_token or RAY_AUTH_TOKEN): Ray gives a local cluster its
    # own; to join a cluster started with it (docs/training-and-evaluation.md) the driver must ask for it too.
    # Ray reads the mode when it is imported, so only a first import here can take this default.
    if address and "ray" not in sys.modules:
        os.environ.setdefault("RAY_AUTH_MODE", "token")
    try:
        import ray
    except ImportError as exc:
        raise EngineError(f"Ray is not installed ({exc}); install it with `pip install -e '.[train]'` (or run "
                          f"`bash .ci/install.sh`), or train in one process without --workers") from None
    if address:
        _check_reachable(address)
    if ray.is_initialized():
        ray.shutdown()
    reaper = None
    # ray.init installs a SIGTERM handler of its own (exit at once): the caller's (a checkpoint, a report first)
    # is put back
    keep_sigterm = threading.current_thread() is threading.main_thread()
    sigterm = signal.getsignal(signal.SIGTERM) if keep_sigterm else None
    try:
        if address:
            ray.init(address=address, logging_level="ERROR", log_to_driver=False)
        else:
            reaper = _start_reaper()
            ray.init(num_cpus=max(os.cpu_count() or 1, workers), include_dashboard=False, logging_level="ERROR",
                     log_to_driver=False)
    except Exception as exc:  # ConnectionError, RuntimeError, ValueError ... from ray.init
        if reaper is not None:
            _close_reaper(reaper, keep=False)
        where = f"the Ray cluster at {address!r}" if address else "a local Ray cluster"
        hint = ("; is it running (`ray status`), and do this machine and every node share its auth token "
                "(RAY_AUTH_MODE=token, the head's ~/.ray/auth_token or RAY_AUTH_TOKEN)?") if address else ""
        raise EngineError(f"could not start or join {where}: {type(exc).__name__}: {exc}{hint}") from None
    finally:
        if keep_sigterm and sigterm is not None:
            signal.signal(signal.SIGTERM, sigterm)
    cpus = float(ray.cluster_resources().get("CPU", 0.0))
    return Engine(ray, address or "", cpus, reaper)


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """EngineError at once when nothing listens at a HOST:PORT address (ray.init would retry for minutes)."""
    import socket

    host, sep, port = address.rpartition(":")
    if not sep or "://" in address or not port.isdigit():
        return  # "auto", a ray:// client address ...: Ray's to judge
    try:
        with socket.create_connection((host or "127.0.0.1", int(port)), timeout=timeout):
            pass
    except OSError as exc:
        raise EngineError(f"--address {address}: no Ray cluster answers there ({exc.strerror or exc}); start one "
                          f"with `ray start --head --port={port}` on that machine (docs/training-and-evaluation.md) "
                          f"or leave --address out for a local cluster") from None


def remote_class(ray: Any, cls: type, cpus: float = 1.0) -> Any:
    """``cls`` as a Ray actor class taking ``cpus`` CPUs; a dead actor is not restarted by Ray (the caller
    replaces it with a fresh one and says so)."""
    return ray.remote(num_cpus=cpus, max_restarts=0)(cls)


def worker_lost_errors(ray: Any) -> tuple[type[BaseException], ...]:
    """The exceptions that mean a worker (an actor, or a task's process) or its node died -- not an error raised
    by the code it ran, which Ray raises as a ``RayTaskError`` carrying it."""
    exc = ray.exceptions
    names = ("RayActorError", "WorkerCrashedError", "ObjectLostError", "NodeDiedError", "OutOfMemoryError")
    return tuple(e for e in (getattr(exc, n, None) for n in names) if isinstance(e, type))


# ---------------------------------------------------------------------- reaper

def _start_reaper() -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "flgd.training.ray_reaper", str(os.getpid())],
                            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, close_fds=True,
                            start_new_session=True)


def _close_reaper(reaper: subprocess.Popen, keep: bool) -> None:
    """Tell the reaper the driver ends cleanly (``keep``: Ray stopped its own processes) and let it go."""
    try:
        if reaper.stdin is not None:
            if keep:
                reaper.stdin.write(b"clean\n")
            reaper.stdin.close()
        reaper.wait(timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        reaper.kill()
