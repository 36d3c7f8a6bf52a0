"""Prometheus metrics of a running daemon (``flgd run --metrics HOST:PORT``), for the plant's dashboards.

Why a collector read at scrape time, not counters kept alongside: the numbers
then are, by construction, the ones ``flgctl status`` and ``flgctl stats``
show (both read the controller and the store), they survive a restart (the
store's counts do), and no code path in the cycle has to remember to bump a
metric.  Everything a scrape reports is built in one function,
``cell_metric_families``; a new metric goes there.

Off by default; the server binds only where it is told (give a loopback or a
plant-network address, not 0.0.0.0, unless the port is firewalled: the page
names the policy file and the config path).
"""

from __future__ import annotations

import logging
import time
from typing import Any, TYPE_CHECKING, Callable, Iterator

from prometheus_client import CollectorRegistry
from prometheus_client.core import (CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily,
                                    InfoMetricFamily, Metric)
from prometheus_client.platform_collector import PlatformCollector
from prometheus_client.process_collector import ProcessCollector
from prometheus_client.registry import Collector

from flgd.daemon.metrics import PhaseHistograms, compute_stats, fault_counts
from flgd.daemon.metrics_http import MetricsHTTPServer
from flgd.daemon.state import State
from flgd.store import StoreError

if TYPE_CHECKING:
    from flgd.daemon.controller import Controller

__all__ = ["MetricsServer", "CellCollector", "cell_metric_families", "STATES"]

log = logging.getLogger("flgd.metrics")

# Every state a scrape can report: the daemon's, and STARTING while it sets up.
STATES = ("STARTING", *(s.value for s in State))


def _counter(name: str, doc: str, value: float, labels: dict[str, str] | None = None) -> CounterMetricFamily:
    fam = CounterMetricFamily(name, doc, labels=list(labels or {}))
    fam.add_metric(list((labels or {}).values()), value)
    return fam


def _gauge(name: str, doc: str, value: float | None) -> GaugeMetricFamily | None:
    if value is None:  # unknown (no grasp yet, no cycle time yet): no sample rather than a made-up 0
        return None
    return GaugeMetricFamily(name, doc, value=value)


def _gate_families(gate: dict[str, Any] | None) -> Iterator[Metric]:
    """The champion/challenger gate: which policies act and their tallies (absent while there is no gate)."""
    if not gate:
        return
    yield GaugeMetricFamily("flgd_gate_enabled", "1 when learned weights act only after the gate promotes them",
                            value=1.0 if gate.get("enabled") else 0.0)
    roles = [("champion", gate.get("champion"), "live"), ("challenger", gate.get("challenger"), "tally")]
    ids = GaugeMetricFamily("flgd_gate_policy_id", "the gate's id of the policy in each role", labels=["role"])
    actions = CounterMetricFamily("flgd_gate_actions", "greedy actions credited to the policy in each role "
                                                       "(the champion: since it became champion)", labels=["role"])
    picks = CounterMetricFamily("flgd_gate_successes", "successful grasps credited to the policy in each role",
                                labels=["role"])
    for role, rec, key in roles:
        if rec:
            ids.add_metric([role], float(rec["id"]))
            actions.add_metric([role], float(rec[key]["actions"]))
            picks.add_metric([role], float(rec[key]["successes"]))
    yield ids
    yield actions
    yield picks
    verdict = gate.get("verdict")
    if verdict and verdict.get("p_better") is not None:
        yield GaugeMetricFamily("flgd_gate_challenger_p_better", "P(challenger better than the champion)",
                                value=float(verdict["p_better"]))


def _calibration_families(watch: dict[str, Any] | None) -> Iterator[Metric]:
    """The calibration watch: the table plane the camera sees, and whether it says the camera moved (absent when
    the watch is off; the estimates are absent before the first frame with enough table)."""
    if not watch:
        return
    if watch.get("table_tilt_degrees") is not None:
        yield GaugeMetricFamily("flgd_calibration_table_tilt_degrees", "tilt of the table plane in the heightmap "
                                "(median of the newest frames; 0 with a calibrated camera)",
                                value=float(watch["table_tilt_degrees"]))
        yield GaugeMetricFamily("flgd_calibration_table_offset_meters", "height of the table plane at the "
                                "workspace centre above workspace.z[0] (median of the newest frames; 0 with a "
                                "calibrated camera)", value=float(watch["table_offset_m"]))
    yield GaugeMetricFamily("flgd_calibration_drift", "1 while the table plane says the camera has moved from "
                            "camera.pose (remedy: flgd calibrate)", value=1.0 if watch.get("drift") else 0.0)


def cell_metric_families(controller: Controller, state_name: Callable[[], str],
                         histograms: PhaseHistograms) -> Iterator[Metric]:
    """Every metric of one scrape, read from the controller's status and the store's statistics."""
    state = state_name()
    fam = GaugeMetricFamily("flgd_state", "1 for the daemon's current state, 0 for the others", labels=["state"])
    for name in STATES:
        fam.add_metric([name], 1.0 if name == state else 0.0)
    yield fam
    yield GaugeMetricFamily("flgd_state_since_timestamp_seconds", "Unix time the current state was entered",
                            value=float(controller.state.since))

    status = controller.status()
    yield InfoMetricFamily("flgd_policy", "the policy the cell acts with", value={
        "source": str(status.get("policy") or ""), "last_checkpoint": str(status.get("last_checkpoint") or "")})
    yield InfoMetricFamily("flgd_cell", "the cell this daemon drives", value={
        "backend": str(status.get("backend") or ""), "name": str(controller.config.name or ""),
        "config": str(status.get("config") or "")})

    yield _counter("flgd_learner_updates", "learner updates applied (continues across restarts from the "
                                           "checkpoint)", float(status.get("learner_updates") or 0))
    yield GaugeMetricFamily("flgd_learner_backlog", "scheduled learner updates not run yet",
                            value=float(status.get("learner_backlog") or 0))
    yield _counter("flgd_learner_dropped_updates", "scheduled updates dropped because the backlog was full "
                                                   "(since start)", float(status.get("learner_dropped") or 0))
    yield _counter("flgd_learner_skipped_updates", "updates not applied because the loss or gradients were not "
                                                   "finite (since start)",
                   float(status.get("learner_skipped") or 0))
    yield GaugeMetricFamily("flgd_learner_running", "1 while the background learner thread runs",
                            value=1.0 if status.get("learner_running") else 0.0)
    yield GaugeMetricFamily("flgd_replay_transitions", "transitions in the replay memory",
                            value=float(status.get("replay_size") or 0))
    yield from _gate_families(status.get("gate"))
    yield from _calibration_families(status.get("calibration"))

    store = getattr(controller, "store", None)
    readable = store is not None
    if store is not None:
        try:
            stats = compute_stats(store)
            faults = fault_counts(store)
            phases = histograms.read(store)
        except StoreError as exc:
            log.warning("metrics: the store cannot be read: %s", exc)
            readable = False
    yield GaugeMetricFamily("flgd_store_readable", "1 if the statistics could be read from the store",
                            value=1.0 if readable else 0.0)
    if not readable:
        return

    yield _counter("flgd_cycles", "cycles logged (decided actions, whatever their outcome)", stats["cycles"])
    yield _counter("flgd_grasp_attempts", "executed grasps", stats["grasp_attempts"])
    yield _counter("flgd_grasp_successes", "executed grasps that held an object", stats["grasp_successes"])
    fam = GaugeMetricFamily("flgd_grasp_success_ratio", "share of the last N grasp attempts that succeeded",
                            labels=["window"])
    for n in (50, 200):
        value = stats.get(f"grasp_success_last_{n}")
        if value is not None:
            fam.add_metric([str(n)], value)
    yield fam
    picks = _gauge("flgd_picks_per_hour", "successful grasps per hour of cycle time (pauses do not count)",
                   stats["picks_per_hour"])
    if picks is not None:
        yield picks
    moves = CounterMetricFamily("flgd_moves", "executed moves by kind", labels=["kind"])
    for kind, n in sorted(stats["moves"].items()):
        moves.add_metric([kind], n)
    yield moves
    faults_family = CounterMetricFamily("flgd_faults", "faults recorded, by kind", labels=["kind"])
    for kind, n in faults.items():
        faults_family.add_metric([kind], n)
    yield faults_family
    yield _counter("flgd_frames_refused", "pictures refused because the tool stood between the camera and the "
                                          "workspace (never decided on)", stats["frames_refused"])
    yield _counter("flgd_plans_refused", "plans the safety envelope refused (never sent to the cell)",
                   stats["plans_refused"])
    yield _counter("flgd_stuck", "times the cell declared itself stuck (exploration.stuck_after actions without a "
                                 "successful grasp, or nothing left to try)", stats["stuck_events"])
    yield GaugeMetricFamily("flgd_actions_since_pick", "actions decided since the last successful grasp",
                            value=float(stats["actions_since_pick"]))
    fam = GaugeMetricFamily("flgd_cycle_split_seconds", "median over the recent cycles of a cycle's parts on the "
                            "cell's clock: motion, gripper, and waiting (the arm still while the controller works)",
                            labels=["part"])
    for part in ("motion", "gripper", "waiting"):
        value = stats["timing_median"].get(part)
        if value is not None:
            fam.add_metric([part], value)
    yield fam
    hidden = _gauge("flgd_decide_hidden_ratio", "share of the recent decision time spent while the arm carried the "
                                                "previous pick home or placed it", stats["decide_hidden_share"])
    if hidden is not None:
        yield hidden
    phase_family = HistogramMetricFamily("flgd_cycle_phase_seconds", "duration of each phase of a cycle, and of "
                                         "the whole cycle (phase=\"cycle\")", labels=["phase"])
    for phase, (counts, total, n) in phases.items():
        buckets = [(repr(float(b)), c) for b, c in zip(histograms.buckets, counts)] + [("+Inf", n)]
        phase_family.add_metric([phase], buckets, sum_value=total)
    yield phase_family


class CellCollector(Collector):
    """The daemon's metrics, read from the controller at every scrape."""

    def __init__(self, controller: Controller, state_name: Callable[[], str] | None = None):
        self.controller = controller
        self.state_name = state_name or (lambda: controller.state.state.value)
        self.histograms = PhaseHistograms()

    def collect(self) -> Iterator[Metric]:
        started = time.monotonic()
        yield from cell_metric_families(self.controller, self.state_name, self.histograms)
        yield GaugeMetricFamily("flgd_scrape_duration_seconds", "time this scrape took to read the daemon",
                                value=time.monotonic() - started)

    def describe(self) -> list[Metric]:
        return []  # registering must not read the controller (it may not be set up yet)


class MetricsServer:
    """The HTTP endpoint: ``/metrics`` in the Prometheus text format, from a small fixed pool of threads.

    The connections are bounded and each has a deadline (``flgd.daemon.metrics_http``), so no number of
    slow or half-sent scrapes can take the descriptors the control socket needs.
    """

    def __init__(self, controller: Controller, host: str, port: int, state_name: Callable[[], str] | None = None):
        self.host = host
        self.port = port
        self.registry = CollectorRegistry()
        self.registry.register(CellCollector(controller, state_name))
        ProcessCollector(registry=self.registry)  # process_* : CPU, memory, open files, start time
        PlatformCollector(registry=self.registry)
        self._httpd: MetricsHTTPServer | None = None

    def start(self) -> None:
        """Bind and serve; OSError naming the address if it cannot (port in use, address not local)."""
        httpd = MetricsHTTPServer(self.registry, self.host, self.port)
        try:
            httpd.start()
        except OSError as exc:
            raise OSError(f"metrics: cannot listen on {self.host}:{self.port}: {exc.strerror or exc}") from None
        self._httpd = httpd
        self.port = httpd.port
        log.info("metrics: serving http://%s:%d/metrics", f"[{self.host}]" if ":" in self.host else self.host,
                 self.port)

    def stop(self) -> None:
        if self._httpd is not None:
            self._httpd.stop()
            self._httpd = None
