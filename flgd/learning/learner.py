"""The learner: the DQN update (``flgd.learning.dqn_update``) trained continually in a background thread.

``Learner`` is the update's scheduler.  Each transition added schedules
``updates_per_action`` updates (``notify_new_transition``; at most
``max_backlog`` stay owed), and the background thread runs them one at a time.
``flgd train`` uses the synchronous mode instead of the thread
(``update_pending`` after each cycle, same updates), so that a training run is
reproducible.  The learner trains its own copy of the network given to it, so the acting
network is never touched mid-decision.

One publish rule for both modes: the learner hands its weights over (posts them to its
``WeightsMailbox``: the gate's, or with the gate off the agent's) after every
``gate.handover_every``-th update, whatever its backlog -- on a cell whose cycles outrun
the learner the backlog never drains, and weights handed over only then would never reach
anyone.  A synchronous run also ends with a hand-over (unless its last update just made
one): its caller decides next, with the weights of every update it waited for.
``paused`` holds the thread between two updates (for a policy swap) without stopping it,
so nothing a command does can leave the daemon without its learner.  The background thread lowers
its own CPU priority (``thread_nice``, Linux per-thread nice) so that on a
small cell PC a decision preempts training instead of sharing the cores.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from typing import Any, Iterator

import torch

from flgd.config import CellConfig
from flgd.learning.agent import WeightsMailbox
from flgd.learning.dqn_update import (CheckpointCallback, DQNUpdate, LossTerms, PrioritySink, UpdateStats,
                                      resolve_device)
from flgd.learning.networks import QMapNetwork
from flgd.learning.prior_sample import PriorSample
from flgd.learning.replay import PrioritizedReplay

__all__ = ["Learner", "LearnerBusy", "UpdateStats", "LossTerms", "resolve_device", "no_learner_status"]

log = logging.getLogger(__name__)


class LearnerBusy(RuntimeError):
    """The learner's update in progress did not finish in time (the learner itself goes on)."""



class Learner(DQNUpdate):
    """The DQN update run on a schedule: a background thread (or synchronous runs) and the weights' hand-over."""

    def __init__(self, config: CellConfig, network: QMapNetwork, replay: PrioritizedReplay,
                 device: str | torch.device | None = None, mailbox: WeightsMailbox | None = None,
                 checkpoint_callback: CheckpointCallback | None = None, thread_nice: int = 10,
                 priority_sink: PrioritySink | None = None, prior: PriorSample | None = None,
                 prior_share: float = 0.0, updates: int = 0) -> None:
        super().__init__(config, network, replay, device=device, checkpoint_callback=checkpoint_callback,
                         priority_sink=priority_sink, prior=prior, prior_share=prior_share, updates=updates)
        self.mailbox = mailbox
        self.thread_nice = thread_nice
        self.handover_every = config.gate.handover_every
        self.handovers = 0  # weight sets posted to the mailbox
        self.stopped_why = "not started"
        self.failed_updates = 0
        self.dropped_updates = 0  # scheduled updates dropped because the backlog was full (max_backlog)
        self._cond = threading.Condition()
        self._pending = 0
        self._busy = False
        self._stop = False
        self._thread: threading.Thread | None = None
        self._exited = True  # the thread (if any) has left its loop; guarded by _cond

    # ------------------------------------------------------------------ hand-over

    def _handover_due(self, stats: UpdateStats | None) -> bool:
        """The publish rule (module docstring): after every ``handover_every``-th update."""
        return stats is not None and stats.update % self.handover_every == 0

    def publish(self) -> bool:
        """Post the online weights to the mailbox (if one is attached)."""
        if self.mailbox is None:
            return False
        with self._update_lock:
            self.mailbox.post(self.online.state_dict(), version=self.updates)
            self.handovers += 1
        return True

    @contextlib.contextmanager
    def paused(self, timeout: float) -> Iterator[None]:
        """Hold the learner between two updates while the body runs (the thread lives on and resumes after).

        Raises ``LearnerBusy`` when the update in progress does not finish within ``timeout`` seconds; the
        learner is then untouched and keeps running.
        """
        if not self._update_lock.acquire(timeout=timeout):
            raise LearnerBusy(f"the learner did not finish its update in progress within {timeout:.0f} s")
        try:
            yield
        finally:
            self._update_lock.release()

    def drop_backlog(self) -> int:
        """Forget the scheduled updates (they were owed to weights just replaced); counted as dropped."""
        with self._cond:
            owed, self._pending = self._pending, 0
            self.dropped_updates += owed
            self._cond.notify_all()
        return owed

    def load_weights(self, network: QMapNetwork, publish: bool = True) -> None:
        """Replace online and target weights (a policy loaded at run time) and, by default, publish them.

        Call it inside ``paused`` or with the thread stopped (the update lock is taken here too)."""
        self.replace_weights(network)
        if publish:
            self.publish()

    def status(self) -> dict[str, Any]:
        """What the daemon's status shows of the learner, read at once (``flgctl status``, the metrics page)."""
        running = self.running
        return {
            "learner_updates": self.updates,
            "learner_running": running,
            "learner_stopped_why": "" if running else self.stopped_why,
            "learner_handovers": self.handovers,
            "learner_prior": None if self.prior is None else {
                "path": self.prior.path, "transitions": len(self.prior), "share": self.prior_share,
                "drawn": self.prior_drawn},
            "learner_backlog": self.pending,  # scheduled updates not run yet
            "learner_dropped": self.dropped_updates,  # backlog was full
            "learner_skipped": self.skipped_updates,  # not finite: not applied
            "learner_error": self.last_error,
        }

    # ------------------------------------------------------------------ background thread

    def notify_new_transition(self) -> None:
        """A transition was added: schedule ``updates_per_action`` updates (none while the replay holds fewer
        than ``min_replay`` transitions).

        With ``max_backlog`` > 0 at most that many (and never fewer than one action's) stay owed: on a cell
        whose cycles are faster than the learner (the simulator) the backlog would otherwise grow without
        end, and the updates would be of ever older data.  The dropped ones are counted.
        """
        lc = self.config.learning
        if len(self.replay) < lc.min_replay:
            return  # too few transitions yet: updates now would fit these few (they are not made up later)
        with self._cond:
            self._pending += lc.updates_per_action
            if lc.max_backlog > 0:
                cap = max(lc.max_backlog, lc.updates_per_action)
                if self._pending > cap:
                    self.dropped_updates += self._pending - cap
                    self._pending = cap
            self._cond.notify_all()

    @property
    def pending(self) -> int:
        with self._cond:
            return self._pending

    def start(self) -> None:
        """Run updates in the background thread; never two threads.

        Why the care: a ``stop`` whose join timed out leaves its thread inside a long update.  If that
        thread has not yet seen the stop it simply carries on (the stop is withdrawn here); only a
        thread that has left its loop is replaced.
        """
        with self._cond:
            self._stop = False
            self.stopped_why = ""
            old = self._thread
            if old is not None and old.is_alive() and not self._exited:
                return
            self._exited = False
            self._thread = threading.Thread(target=self._run, name="flgd-learner", daemon=True)
            self._thread.start()

    def stop(self, timeout: float | None = None, why: str = "stopped") -> None:
        """Finish the update in progress, drop the pending ones and join the thread."""
        with self._cond:
            self._stop = True
            self.stopped_why = why
            self._pending = 0
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)
            if not self._thread.is_alive():  # a timed-out join keeps it: start() must not add a second one
                self._thread = None

    def update_pending(self) -> list[UpdateStats]:
        """Synchronous mode: run the scheduled updates in the caller's thread, handing over as the thread does,
        and at the end.

        ``flgd train`` calls this after each cycle instead of starting the
        thread, so a run's results do not depend on thread timing; it is the
        same update as the thread's.  Errors propagate (a training run should
        stop on a broken update rather than log and go on).
        """
        if self.running:
            raise RuntimeError("update_pending: the background learner thread is running; use one mode")
        done: list[UpdateStats] = []
        while True:
            with self._cond:
                if self._pending == 0:
                    break
                self._pending -= 1
            stats = self.update()
            if stats is not None:
                done.append(stats)
                if self._handover_due(stats):
                    self.publish()
        if not done or not self._handover_due(done[-1]):  # else these weights were handed over just now
            self.publish()
        return done

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until no update is pending or running; False on timeout.

        Updates scheduled after the thread left its loop are not waited for: nothing would run them."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while self._busy or (self._pending > 0 and not self._exited):
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return False
                self._cond.wait(remaining)
        return True

    def _lower_priority(self) -> None:
        """Renice the learner thread (Linux nice values are per thread) so a decision preempts training."""
        if self.thread_nice <= 0 or not hasattr(os, "setpriority"):
            return
        try:
            tid = threading.get_native_id()
            os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + self.thread_nice))
        except OSError as exc:  # not permitted or not supported: train at normal priority
            log.warning("could not lower the learner thread's priority: %s", exc)

    def _run(self) -> None:
        self._lower_priority()
        while True:
            with self._cond:
                while not self._stop and self._pending == 0:
                    self._cond.wait()
                if self._stop:
                    self._exited = True
                    return
                self._pending -= 1
                self._busy = True
            stats = None
            try:
                stats = self.update()
            except Exception as exc:  # keep the daemon alive; the error is reported through status
                self.failed_updates += 1
                self.last_error = f"update {self.updates + 1}: {type(exc).__name__}: {exc}"
                log.exception("learner update failed")
            if self._handover_due(stats):
                try:
                    self.publish()
                except Exception as exc:
                    self.last_error = f"publish: {type(exc).__name__}: {exc}"
                    log.exception("publishing weights failed")
            with self._cond:
                self._busy = False
                self._cond.notify_all()


def no_learner_status() -> dict[str, Any]:
    """``Learner.status``'s keys for a daemon that has no learner (yet)."""
    return {"learner_updates": 0, "learner_running": False, "learner_stopped_why": "", "learner_handovers": 0,
            "learner_prior": None, "learner_backlog": 0, "learner_dropped": 0, "learner_skipped": 0,
            "learner_error": None}
