"""The champion/challenger gatekeeper: which policy acts, on what evidence, kept in the state directory.

The statistics are in ``flgd.gate.statistics`` (a pure function of counts); this
module holds the state around them and keeps it across restarts:

* every policy the gate knows is a policy file in ``<state_dir>/gate/`` (written
  atomically) and a row of the store's ``policies`` table: the **champion** (the
  one that acts), at most one **challenger** (the learner's weights of one
  hand-over, acting on a share of decisions), **retired** champions (kept for
  rollbacks, each with the record of its tenure), and dropped / rolled-back ones
  (records only; their files are deleted);
* every change of the acting policy -- the initial one, a promotion, a drop, a
  rollback, a policy load, a manual override, a fall-back from an unusable file --
  is a ``gate_events`` row with its evidence and who asked;
* the tallies are not stored apart: each action-log row names the policy whose
  greedy decision it was (``actions.policy``, written in the cycle's own
  transaction), so after a ``kill -9`` or a power cut the tallies are recounted
  from exactly the actions that were committed.

A restart acts with the stored champion, never with a learner checkpoint.

How the files are kept, and what a file that cannot be read or used does to a
start (it is set aside, or the start is refused): ``flgd.gate.storage``.

Only the daemon's run loop calls the methods that change state (they swap the
agent's networks); ``status`` and ``history`` may be called from any thread.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import threading
from pathlib import Path
import sqlite3
from typing import TYPE_CHECKING, Any, Callable

from flgd.config import CellConfig
from flgd.cycle_record import CycleOutcome
from flgd.gate.storage import (KEEP_UNUSABLE, READ_RETRY_DELAYS, GateDirUnwritable,
                               GateError, GateFileUnreadable, GateStorage, PolicyRecord, insert_record, tally_json,
                               write_event)
from flgd.learning.agent import WeightsMailbox
from flgd.gate.statistics import GateSettings, Tally, Verdict, challenger_share, challenger_verdict, rollback_verdict
from flgd.store import Store

if TYPE_CHECKING:
    from flgd.cycle_record import CycleRecord
    from flgd.learning.agent import Agent
    from flgd.learning.networks import QMapNetwork

__all__ = ["Gatekeeper", "GateError", "GateFileUnreadable", "PolicyRecord", "gate_settings", "CREDITED_OUTCOMES"]

log = logging.getLogger("flgd")

# Outcomes that are the deciding policy's doing: a refused plan is its failure too; an unstable simulation,
# a stop or a cell fault is not.
CREDITED_OUTCOMES = (CycleOutcome.EXECUTED, CycleOutcome.REFUSED)
# events that make a policy the champion, and whether a champion made so is rolled back automatically
_CROWNING = {"initial": False, "promote": True, "manual-promote": True, "rollback": False,
             "manual-rollback": False, "load": False, "fallback": False}


def gate_settings(config: CellConfig) -> GateSettings:
    """The config's gate section as the statistics' settings (same names)."""
    return GateSettings(**{f.name: getattr(config.gate, f.name) for f in dataclasses.fields(GateSettings)})


class Gatekeeper:
    """The gate's state: champion, challenger, their tallies; the agent's networks follow it."""

    def __init__(self, config: CellConfig, store: Store, agent: Agent, state_dir: str | Path,
                 keep_champions: int | None = None, keep_unusable: int = KEEP_UNUSABLE,
                 read_retry_delays: tuple[float, ...] = READ_RETRY_DELAYS, *,
                 handovers: WeightsMailbox | None = None, on_champion: Callable[[QMapNetwork], None] | None = None,
                 reset_learner: Callable[[QMapNetwork], object] | None = None) -> None:
        self.config = config
        self.settings = gate_settings(config)
        self.enabled = bool(config.gate.enabled)
        self.keep_champions = config.gate.keep_champions if keep_champions is None else keep_champions
        self.store = store
        self.agent = agent
        self.state_dir = Path(state_dir)
        # the learner posts here when the gate is on (the learning stack gives the learner this mailbox)
        self.handovers = WeightsMailbox() if handovers is None else handovers
        self.champion: PolicyRecord | None = None
        self.challenger: PolicyRecord | None = None
        self.champion_live = Tally()   # the champion's actions since it became champion
        self.champion_during_test = Tally()  # ... since the challenger under test came
        self.challenger_tally = Tally()
        self.by_promotion = False  # the champion came in by a promotion: it is rolled back automatically
        self.verdict: Verdict | None = None  # on the challenger under test
        self.champion_verdict: Verdict | None = None  # on a promoted champion (rollback or keep)
        # called with the champion's network after a rollback or a drop as worse: the learner starts again
        # from what acts, instead of going on along the line of weights just rejected
        self.reset_learner = reset_learner
        # called with the champion's network whenever the acting policy changes (restore, promotion, rollback,
        # load): the learner's L2-SP anchor (``learning.anchor_weight``) follows what acts
        self.on_champion = on_champion
        self.files = GateStorage(config, store, state_dir, keep_unusable=keep_unusable,
                                 read_retry_delays=read_retry_delays)
        self._lock = threading.RLock()
        self._unwritten: tuple[Any, int] | None = None  # a hand-over whose file the gate directory refused

    # ------------------------------------------------------------------ tallies
    def _tally(self, policy_id: int, since_step: int) -> Tally:
        rows = self.store.query(
            "SELECT COUNT(*), COALESCE(SUM(success = 1), 0), COALESCE(SUM(primitive = 'grasp'), 0) FROM actions "
            f"WHERE policy=? AND step>=? AND outcome IN ({', '.join('?' * len(CREDITED_OUTCOMES))})",
            (int(policy_id), int(since_step), *CREDITED_OUTCOMES))
        n, s, g = rows[0]
        return Tally(int(n), int(s), int(g))

    # ------------------------------------------------------------------ start-up
    def restore(self, step: int, configured: Callable[[], tuple[Any, dict, str] | None],
                fresh: Callable[[], tuple[Any, dict, str]]) -> str:
        """Make the agent act with the stored champion (and test the stored challenger); returns a summary.

        ``configured`` gives (network, metadata, origin) of the configured policy, or None when there is
        none; it is called only when no stored champion is usable (first start, or every file unusable).
        ``fresh`` gives the network a daemon without any policy starts from; it is used only on a first
        start without a configured policy (training from scratch), never as a fall-back.
        """
        from flgd.learning.policy_file import PolicyFileError

        with self._lock:
            self.files.remove_strays()
            self.files.set_aside_earlier_unusable()
            note = ""
            first_start = int(self.store.query("SELECT COUNT(*) FROM policies")[0][0]) == 0
            champion = self.files.by_role("champion")
            network = None
            unusable: list[tuple[PolicyRecord, PolicyFileError]] = []
            cur = champion
            while cur is not None:
                try:
                    network = self.files.load(cur)  # a GateError (unreadable now) refuses the start: nothing recorded
                    break
                except PolicyFileError as exc:  # its content: the file named, the next one tried
                    unusable.append((cur, exc))
                    cur = self.files.row(cur.predecessor) if cur.predecessor is not None else None
            tried = [str(exc) for _, exc in unusable]
            if network is not None and cur is not None and champion is not None and cur.id != champion.id:
                self._crown(cur, step, "fallback", "flgd", f"champion #{champion.id} unusable; policy #{cur.id} "
                                                           f"acts again", {"unusable": tried},
                            also=self.files.set_aside(unusable, step))
                note = f"fell back to policy #{cur.id} ({'; '.join(tried)})"
            if network is None:
                got = configured()
                if got is None and first_start:
                    got = fresh()
                if got is None:
                    raise GateError("no usable champion and no configured policy: " + "; ".join(tried) +
                                    " (set `policy:` in the config to a policy file to act with)")
                net, meta, origin = got
                kind = "initial" if first_start else "fallback"
                cur = self._register_champion(net, meta, origin, step, kind, "flgd",
                                              {"unusable": tried} if tried else {},
                                              also=self.files.set_aside(unusable, step))
                network = net
                if tried:
                    note = f"fell back to the configured policy ({'; '.join(tried)})"
            self.files.prune_unusable()
            assert cur is not None and network is not None  # found, or registered from the configured policy
            self._act_with_champion(cur, network)
            self._restore_challenger(step)
            self._recount()
            return note or f"champion #{cur.id} ({cur.origin})"

    def _restore_challenger(self, step: int) -> None:
        rec = self.files.by_role("challenger")
        if rec is None:
            self.agent.set_challenger(None)
            return
        from flgd.learning.policy_file import PolicyFileError

        try:
            net = self.files.load(rec)  # a GateError (unreadable now) refuses the start: nothing recorded
        except PolicyFileError as exc:  # its content: kept for inspection, the challenger dropped
            self.challenger = rec
            rel = self.files.move_aside(rec)
            where = "" if rel is None else f" (moved to {self.state_dir / rel})"
            self._drop(step, "flgd", f"its file cannot be used: {exc}{where}", {"error": str(exc), "moved_to": rel},
                       kind="drop", also=None if rel is None else lambda db: db.execute(
                           "UPDATE policies SET file=? WHERE id=?", (rel, rec.id)))
            return
        self.challenger = rec
        self.agent.set_challenger(net, rec.id, -1, self.settings.share if self.enabled else 0.0)

    def _recount(self) -> None:
        ch = self.champion
        assert ch is not None
        self.champion_live = self._tally(ch.id, ch.since_step)
        if self.challenger is not None:
            self.challenger_tally = self._tally(self.challenger.id, self.challenger.since_step)
            self.champion_during_test = self._tally(ch.id, self.challenger.since_step)
        else:
            self.challenger_tally = Tally()
            self.champion_during_test = Tally()
        rows = self.store.query("SELECT kind FROM gate_events WHERE policy=? AND kind IN (%s) ORDER BY id DESC "
                                "LIMIT 1" % ", ".join("?" * len(_CROWNING)), (ch.id, *_CROWNING))
        self.by_promotion = bool(rows) and _CROWNING.get(rows[0][0], False)
        self._evaluate_only()
        self._set_share()

    def _set_share(self) -> None:
        """The challenger under test makes its share of the next decisions (rising with ``gate.max_share``)."""
        if self.enabled and self.challenger is not None and self.verdict is not None and self.verdict.kind == "testing":
            self.agent.set_challenger_share(challenger_share(self.champion_during_test, self.challenger_tally,
                                                             self.settings))

    # ------------------------------------------------------------------ changes of the acting policy
    def _act_with_champion(self, record: PolicyRecord, network: QMapNetwork) -> None:
        self.champion = record
        # a learner update count for the cached double-DQN argmax; only the learner's own weights have one
        self.agent.act_with(network.state_dict(), record.id if self.enabled else None,
                            record.learner_updates if record.learner_updates is not None else -1)
        if self.on_champion is not None:
            try:
                self.on_champion(self.agent.network)
            except Exception as exc:  # the anchor is a hint to the learner: acting goes on without it
                log.warning("gate: the learner's anchor did not follow champion #%d: %s", record.id, exc)

    def _register_champion(self, network: QMapNetwork, meta: dict, origin: str, step: int, kind: str, who: str,
                           evidence: dict, also: Callable[[Any], None] | None = None) -> PolicyRecord:
        pid = self.files.next_id()
        steps = int(meta.get("training_steps", 0) or 0)
        rel, sha = self.files.write_file(pid, network, {"training_steps": steps, "cell": self.config.name or
                                                   self.config.backend, "source": origin, "gate_policy": pid})
        old = self.champion
        record = PolicyRecord(pid, "champion", rel, sha, origin, None if old is None else old.id, None, steps,
                              int(step), None)

        def write(db: sqlite3.Connection) -> None:
            if also is not None:
                also(db)
            if old is not None:
                db.execute("UPDATE policies SET role='retired', record=? WHERE id=?",
                           (tally_json(self.champion_live), old.id))
            insert_record(db, record)
            write_event(db, kind, step, pid, record.predecessor, who, f"policy #{pid} is the champion: {origin}",
                        evidence)
        self.store.transaction(write)
        log.info("gate: policy #%d is the champion (%s: %s)", pid, kind, origin)
        self.by_promotion = False
        return record

    def _crowned(self) -> PolicyRecord:
        """The champion just crowned (``_crown`` always sets one)."""
        if self.champion is None:
            raise GateError("no champion after a crowning: the gate's records are inconsistent")
        return self.champion

    def _crown(self, record: PolicyRecord, step: int, kind: str, who: str, message: str, evidence: dict,
               retire_as: str = "retired", also: Callable[[Any], None] | None = None) -> None:
        """``record`` (a stored policy) becomes the champion; the current one is retired (or rolled back).
        ``also`` writes more in the same transaction."""
        old = self.champion

        def write(db: sqlite3.Connection) -> None:
            if also is not None:
                also(db)
            if old is not None and old.id != record.id:
                db.execute("UPDATE policies SET role=?, record=? WHERE id=?",
                           (retire_as, tally_json(self.champion_live), old.id))
            if kind in ("promote", "manual-promote"):
                db.execute("UPDATE policies SET role='champion', predecessor=?, since_step=? WHERE id=?",
                           (None if old is None else old.id, int(step), record.id))
            else:
                db.execute("UPDATE policies SET role='champion', since_step=? WHERE id=?", (int(step), record.id))
            write_event(db, kind, step, record.id, None if old is None else old.id, who, message, evidence)
        self.store.transaction(write)
        refreshed = self.files.row(record.id)
        assert refreshed is not None
        self.champion = refreshed
        self.by_promotion = _CROWNING[kind]
        log.info("gate: %s", message)

    def _drop(self, step: int, who: str, why: str, evidence: dict, kind: str = "drop",
              also: Callable[[Any], None] | None = None) -> None:
        ch = self.challenger
        if ch is None:
            return

        def write(db: sqlite3.Connection) -> None:
            if also is not None:
                also(db)
            db.execute("UPDATE policies SET role='dropped', record=? WHERE id=?",
                       (tally_json(self.challenger_tally), ch.id))
            write_event(db, kind, step, ch.id, None if self.champion is None else self.champion.id, who,
                        f"challenger #{ch.id} dropped: {why}", evidence)
        self.store.transaction(write)
        self.files.remove_file(ch)
        log.info("gate: challenger #%d dropped: %s", ch.id, why)
        self.challenger = None
        self.challenger_tally = Tally()
        self.champion_during_test = Tally()
        self.agent.set_challenger(None)

    def _evidence(self) -> dict:
        return {"champion": None if self.champion is None else self.champion.id,
                "challenger": None if self.challenger is None else self.challenger.id,
                "champion_during_test": self.champion_during_test.as_dict(),
                "challenger_tally": self.challenger_tally.as_dict(),
                "champion_live": self.champion_live.as_dict(),
                "p_better": None if self.verdict is None else self.verdict.p_better,
                "settings": self.settings.__dict__}

    def promote(self, step: int, who: str, reason: str) -> dict:
        with self._lock:
            ch = self.challenger
            if ch is None:
                raise GateError("no challenger to promote")
            if self.agent.challenger is None:
                raise GateError(f"challenger #{ch.id} is not loaded in the agent")
            network = copy.deepcopy(self.agent.challenger)
            kind = "promote" if who == "gate" else "manual-promote"
            evidence = self._evidence()
            self._crown(ch, step, kind, who, f"challenger #{ch.id} promoted: {reason}", evidence)
            self.challenger = None
            self.agent.set_challenger(None)
            champion = self._crowned()
            self._act_with_champion(champion, network)
            self.champion_live, self.challenger_tally, self.champion_during_test = Tally(), Tally(), Tally()
            self.files.prune_retired(champion, self.keep_champions)
            self.verdict = None
            return {"champion": champion.id, "reason": reason}

    def reject(self, step: int, who: str) -> dict:
        with self._lock:
            if self.challenger is None:
                raise GateError("no challenger to reject")
            pid = self.challenger.id
            self._drop(step, who, f"rejected by {who}", self._evidence(), kind="reject")
            self.verdict = None
            return {"rejected": pid}

    def rollback(self, step: int, who: str, reason: str) -> dict:
        """The champion's predecessor acts again; the champion and any challenger are dropped."""
        with self._lock:
            ch = self.champion
            if ch is None or ch.predecessor is None:
                raise GateError("the champion has no predecessor to roll back to")
            pred = self.files.row(ch.predecessor)
            if pred is None:
                raise GateError(f"predecessor #{ch.predecessor} is not in the store")
            try:
                network = self.files.load(pred)
            except Exception as exc:
                raise GateError(f"predecessor #{pred.id} cannot be used: {exc}") from None
            if self.challenger is not None:
                self._drop(step, who, f"its champion #{ch.id} was rolled back", self._evidence())
            kind = "rollback" if who == "gate" else "manual-rollback"
            evidence = self._evidence()
            evidence["predecessor_record"] = None if pred.record is None else pred.record.as_dict()
            self._crown(pred, step, kind, who, f"champion #{ch.id} rolled back to #{pred.id}: {reason}", evidence,
                        retire_as="rolled_back")
            self.files.remove_file(ch)
            self._act_with_champion(self._crowned(), network)
            self.champion_live = Tally()
            self.verdict = None
            return {"champion": pred.id, "rolled_back": ch.id, "reason": reason}

    def load_champion(self, network: QMapNetwork, meta: dict, origin: str, step: int, who: str) -> dict:
        """A policy file loaded by the operator becomes the champion (any challenger is dropped)."""
        with self._lock:
            if self.challenger is not None:
                self._drop(step, who, "a policy was loaded", self._evidence())
            self.handovers.take()  # weights handed over before the load are of the line it replaces
            self._unwritten = None
            rec = self._register_champion(network, meta, origin, step, "load", who, {"metadata": {
                k: v for k, v in meta.items() if isinstance(v, (str, int, float, bool, type(None)))}})
            self._act_with_champion(rec, network)
            self.champion_live = Tally()
            self.files.prune_retired(self.champion, self.keep_champions)
            self.verdict = None
            return {"champion": rec.id}

    # ------------------------------------------------------------------ the cycle's side
    def take_handover(self, step: int) -> bool:
        """With no challenger under test, the learner's newest handed-over weights become the challenger."""
        if not self.enabled:
            return False
        with self._lock:
            if self.challenger is not None:
                return False
            posted = self.handovers.take()
            if posted is None:  # none newer: the one whose file could not be written, if any, is tried again
                posted, self._unwritten = self._unwritten, None
            else:
                self._unwritten = None  # newer weights supersede it
            if posted is None:
                return False
            from flgd.learning.policy_file import PolicyFileError

            weights, version = posted
            network = copy.deepcopy(self.agent.network)
            network.load_state_dict(weights)
            network.eval()
            pid = self.files.next_id()
            origin = f"learner update {version}"
            steps = self.agent.policy_steps(step)  # the policy's own count
            try:
                rel, sha = self.files.write_file(pid, network, {"training_steps": steps, "cell": self.config.name or
                                                           self.config.backend, "source": origin,
                                                           "learner_updates": int(version), "gate_policy": pid})
            except GateDirUnwritable as exc:  # kept until the directory takes it (after a reset, or newer)
                self._unwritten = posted
                log.error("gate: hand-over of learner update %s not taken: %s", version, exc)
                raise GateDirUnwritable(f"{exc} Then flgctl reset: learner update {version} is kept and becomes "
                                        "the challenger.") from None
            except PolicyFileError as exc:  # e.g. non-finite weights: never tested, never acting
                why = str(exc)
                self.store.transaction(lambda db: write_event(
                    db, "refused", step, None, None, "gate", f"hand-over of learner update {version} refused: {why}",
                    {"error": why}))
                log.error("gate: hand-over of learner update %s refused: %s", version, exc)
                return False
            rec = PolicyRecord(pid, "challenger", rel, sha, origin, None, int(version), steps, int(step), None)
            champion = self.champion

            def write(db: sqlite3.Connection) -> None:
                insert_record(db, rec)
                write_event(db, "challenger", step, pid, None if champion is None else champion.id, "gate",
                            f"policy #{pid} ({origin}) is the challenger", {"share": self.settings.share,
                                                                             "training_steps": steps})
            self.store.transaction(write)
            self.challenger = rec
            self.challenger_tally, self.champion_during_test = Tally(), Tally()
            self.agent.set_challenger(network, pid, int(version), self.settings.share)
            log.info("gate: policy #%d (%s) is the challenger", pid, origin)
            self.verdict = None
            return True

    def after_cycle(self, record: CycleRecord) -> Verdict | None:
        """Credit the cycle's outcome to the policy that decided it, apply the gate's verdict, take a hand-over.

        Returns the verdict that changed something (promote, drop, rollback), else None.
        """
        if not self.enabled:
            return None
        step = int(record.step) + 1 if record.step is not None else self._step_now()
        with self._lock:
            pid = record.policy
            if pid is not None and record.outcome in CREDITED_OUTCOMES:
                success = bool(record.success) if record.primitive == "grasp" else False
                grasp = record.primitive == "grasp"
                if self.champion is not None and pid == self.champion.id:
                    self.champion_live = self.champion_live.add(success, grasp)
                    if self.challenger is not None:
                        self.champion_during_test = self.champion_during_test.add(success, grasp)
                elif self.challenger is not None and pid == self.challenger.id:
                    self.challenger_tally = self.challenger_tally.add(success, grasp)
            acted = self._apply_verdict(step)
            self.take_handover(step)
            return acted

    def _step_now(self) -> int:
        return int(self.store.next_step())

    def _rollback_check(self) -> Verdict | None:
        """The verdict on a champion that came in by promotion: keep it, or roll it back (None otherwise)."""
        ch = self.champion
        if not self.by_promotion or ch is None or ch.predecessor is None:
            return None
        pred = self.files.row(ch.predecessor)
        if pred is None or pred.record is None or pred.record.actions == 0:
            return None
        return rollback_verdict(self.champion_live, pred.record, self.settings)

    def _evaluate_only(self) -> None:
        self.champion_verdict = self._rollback_check()
        self.verdict = None if self.challenger is None else challenger_verdict(
            self.champion_during_test, self.challenger_tally, self.settings)

    def _restart_learner_from_champion(self, why: str) -> None:
        self.handovers.take()  # of the rejected line too
        self._unwritten = None
        if self.reset_learner is None:
            return
        try:
            self.reset_learner(self.agent.network)
            log.info("gate: the learner starts again from the champion (%s)", why)
        except Exception as exc:  # the learner busy for long: it goes on from its own weights
            log.warning("gate: the learner could not be reset to the champion (%s): %s", why, exc)

    def _apply_verdict(self, step: int) -> Verdict | None:
        """Rollback first (checked on every cycle, with or without a challenger), then the challenger's verdict;
        a challenger still under test gets its share for the next decisions (``gate.max_share``)."""
        acted = self._judge(step)
        self._set_share()
        return acted

    def _judge(self, step: int) -> Verdict | None:
        self._evaluate_only()
        rv = self.champion_verdict
        if rv is not None and rv.kind == "rollback":
            try:
                self.rollback(step, "gate", rv.reason)
            except GateError as exc:
                log.error("gate: rollback not possible: %s", exc)
                self.by_promotion = False  # do not retry every cycle; the operator sees the event
                why, champion_id = str(exc), None if self.champion is None else self.champion.id
                self.store.transaction(lambda db: write_event(
                    db, "rollback-failed", step, champion_id, None, "gate", f"rollback not possible: {why}",
                    {"verdict": rv.reason}))
                return None
            self._restart_learner_from_champion("rollback")
            return rv
        v = self.verdict
        if v is None:
            return None
        if v.kind == "promote":
            self.promote(step, "gate", v.reason)
            return v
        if v.kind == "drop":
            worse = v.p_better is not None and 1.0 - v.p_better >= self.settings.drop_confidence
            self._drop(step, "gate", v.reason, self._evidence())
            self.verdict = None
            if worse:
                self._restart_learner_from_champion("challenger dropped as worse")
            return v
        return None

    # ------------------------------------------------------------------ reading
    def status(self) -> dict:
        with self._lock:
            ch, cl, v = self.champion, self.challenger, self.verdict
            share = getattr(self.agent, "challenger_share", 0.0) if cl is not None else self.settings.share
            out: dict[str, Any] = {"enabled": self.enabled, "share": share if self.enabled else 0.0}
            out["champion"] = None if ch is None else {
                **ch.as_dict(), "live": self.champion_live.as_dict(), "file": str(self.files.path(ch)),
                "rolled_back_automatically": self.by_promotion}
            out["challenger"] = None if cl is None else {
                **cl.as_dict(), "tally": self.challenger_tally.as_dict(), "file": str(self.files.path(cl)),
                "champion_during_test": self.champion_during_test.as_dict()}
            out["verdict"] = None if v is None else {"kind": v.kind, "p_better": v.p_better, "reason": v.reason}
            cv = self.champion_verdict
            out["champion_verdict"] = None if cv is None else {"kind": cv.kind, "p_better": cv.p_better,
                                                                "reason": cv.reason}
            out["handover_waiting"] = self.handovers.waiting or self._unwritten is not None
            return out

    def history(self, limit: int = 50) -> list[dict]:
        rows = self.store.query("SELECT id, time, step, kind, policy, other, who, message, evidence FROM gate_events "
                                "ORDER BY id DESC LIMIT ?", (int(limit),))
        out = []
        for r in reversed(rows):
            d = dict(zip(("id", "time", "step", "kind", "policy", "other", "who", "message", "evidence"), r))
            d["evidence"] = json.loads(d["evidence"])
            out.append(d)
        return out
