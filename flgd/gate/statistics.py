"""The champion/challenger gate: when learned weights may act, as a pure function of outcome counts.

The acting policy is the *champion*; the learner's newest weights, handed over on
a schedule, become the *challenger*, which acts greedily on a randomised share of
decisions.  Each policy's greedy actions are tallied apart (epsilon-random actions
are credited to neither), and the gate compares them on **successful grasps per
action** -- a Bernoulli outcome per action whose rate is what picks per hour
follows (a move counts as an action without a pick).

The test.  Both rates get a Beta(1 + successes, 1 + failures) posterior (a uniform
prior); the gate uses P(challenger's rate > champion's rate), in the normal
approximation of the two posteriors (their difference has mean m_c - m_0 and
variance v_c + v_0).  Why Bayesian with fixed thresholds rather than a
fixed-sample test: the gate looks after every action and must stop as soon as the
evidence is clear either way, and the posterior probability is meaningful at every
look; its error rates under repeated looks are not the nominal ones, so they were
measured by simulation (tests/test_gate_statistics.py; the README states them).

* **promote** when the challenger has at least ``min_attempts`` actions and
  P(better) >= ``promote_confidence``;
* **drop** when it has at least ``drop_min_attempts`` actions and
  P(worse) >= ``drop_confidence`` (clearly worse: stop testing it early), or when
  it reached ``max_attempts`` without being promoted (not shown better: make room
  for a newer challenger);
* **roll back** a champion that came in by promotion when, after at least
  ``rollback_min_attempts`` of its own actions as champion, P(its live rate <
  its predecessor's recorded rate) >= ``rollback_confidence``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["Tally", "GateSettings", "Verdict", "challenger_verdict", "rollback_verdict", "p_better",
           "challenger_decision", "rollback_decision", "challenger_share"]


@dataclass(frozen=True)
class Tally:
    """Greedy actions a policy took and what they gave."""

    actions: int = 0
    successes: int = 0  # successful grasps
    grasps: int = 0

    def add(self, success: bool, grasp: bool) -> "Tally":
        return Tally(self.actions + 1, self.successes + int(bool(success)), self.grasps + int(bool(grasp)))

    def __add__(self, other: "Tally") -> "Tally":
        return Tally(self.actions + other.actions, self.successes + other.successes, self.grasps + other.grasps)

    @property
    def per_action(self) -> float | None:
        """Successful grasps per action (None before the first action)."""
        return None if self.actions == 0 else self.successes / self.actions

    @property
    def grasp_success(self) -> float | None:
        return None if self.grasps == 0 else self.successes / self.grasps

    def as_dict(self) -> dict:
        return {"actions": self.actions, "successes": self.successes, "grasps": self.grasps,
                "per_action": self.per_action, "grasp_success": self.grasp_success}


@dataclass(frozen=True)
class GateSettings:
    share: float = 0.5  # the shipped settings (GateConfig's defaults; docs/learning-on-the-cell.md)
    max_share: float = 0.0  # 0 (or <= share): the challenger's share stays ``share``
    min_attempts: int = 60
    max_attempts: int = 100
    promote_confidence: float = 0.98
    drop_min_attempts: int = 40
    drop_confidence: float = 0.99
    rollback_min_attempts: int = 60
    rollback_confidence: float = 0.99


@dataclass(frozen=True)
class Verdict:
    kind: str  # "testing", "promote", "drop" (challenger); "keep", "rollback" (champion)
    p_better: float | None  # P(challenger better than champion) or P(champion live better than predecessor)
    reason: str


def _posterior(t: Tally) -> tuple[float, float]:
    """Mean and variance of the Beta(1 + s, 1 + f) posterior of a tally's success-per-action rate."""
    a, b = 1.0 + t.successes, 1.0 + (t.actions - t.successes)
    n = a + b
    return a / n, a * b / (n * n * (n + 1.0))


def p_better(x: Tally, y: Tally) -> float:
    """P(rate of x > rate of y) under the two posteriors (normal approximation of their difference)."""
    mx, vx = _posterior(x)
    my, vy = _posterior(y)
    sd = math.sqrt(vx + vy)
    if sd == 0.0:
        return 0.5
    return 0.5 * (1.0 + math.erf((mx - my) / (sd * math.sqrt(2.0))))


def _rate(t: Tally) -> str:
    return "-" if t.per_action is None else f"{t.per_action:.3f}"


def challenger_decision(champion: Tally, challenger: Tally, s: GateSettings) -> tuple[str, float]:
    """(kind, P(better)): "promote", "drop-worse", "drop-timeout" or "testing" (the rule, without any text)."""
    p = p_better(challenger, champion)
    n = challenger.actions
    if n >= s.min_attempts and p >= s.promote_confidence:
        return "promote", p
    if n >= s.drop_min_attempts and 1.0 - p >= s.drop_confidence:
        return "drop-worse", p
    if n >= s.max_attempts:
        return "drop-timeout", p
    return "testing", p


# P(better) at which the share starts to rise above ``share``, and at which it reaches ``max_share``
SHARE_RISE_FROM, SHARE_RISE_TO = 0.5, 0.9


def challenger_share(champion: Tally, challenger: Tally, s: GateSettings) -> float:
    """The share of greedy decisions the challenger makes now.

    ``share`` until the challenger has ``drop_min_attempts`` actions; then it rises linearly with P(better), from
    ``share`` at P 0.5 to ``max_share`` at P 0.9.  Why: a challenger that is doing better gathers its evidence (and
    its picks) sooner, while one that is not keeps costing at most ``share`` of the decisions.  Off (always
    ``share``) when ``max_share`` is not above ``share``.
    """
    if s.max_share <= s.share or challenger.actions < s.drop_min_attempts:
        return s.share
    rise = (p_better(challenger, champion) - SHARE_RISE_FROM) / (SHARE_RISE_TO - SHARE_RISE_FROM)
    return s.share + (s.max_share - s.share) * min(1.0, max(0.0, rise))


def rollback_decision(live: Tally, predecessor: Tally, s: GateSettings) -> tuple[str, float]:
    """(kind, P(live better than the predecessor's record)): "rollback" or "keep"."""
    p = p_better(live, predecessor)
    if live.actions >= s.rollback_min_attempts and 1.0 - p >= s.rollback_confidence:
        return "rollback", p
    return "keep", p


def challenger_verdict(champion: Tally, challenger: Tally, s: GateSettings) -> Verdict:
    """Promote, drop or keep testing a challenger, from its tally and the champion's over the same time."""
    kind, p = challenger_decision(champion, challenger, s)
    summary = (f"challenger {challenger.successes}/{challenger.actions} = {_rate(challenger)} vs champion "
               f"{champion.successes}/{champion.actions} = {_rate(champion)} successful grasps per action, "
               f"P(better) {p:.3f}")
    if kind == "promote":
        return Verdict("promote", p, f"{summary} >= {s.promote_confidence} after >= {s.min_attempts} actions")
    if kind == "drop-worse":
        return Verdict("drop", p, f"{summary}: worse with P {1.0 - p:.3f} >= {s.drop_confidence}")
    if kind == "drop-timeout":
        return Verdict("drop", p, f"{summary}: not shown better within {s.max_attempts} actions")
    need = max(0, s.min_attempts - challenger.actions)
    return Verdict("testing", p, summary + (f"; {need} more actions before a promotion is possible" if need else ""))


def rollback_verdict(live: Tally, predecessor: Tally, s: GateSettings) -> Verdict:
    """Roll back a promoted champion whose live rate is clearly below its predecessor's recorded one."""
    kind, p = rollback_decision(live, predecessor, s)
    summary = (f"champion live {live.successes}/{live.actions} = {_rate(live)} vs predecessor's record "
               f"{predecessor.successes}/{predecessor.actions} = {_rate(predecessor)}, P(worse) {1.0 - p:.3f}")
    if kind == "rollback":
        return Verdict("rollback", p, f"{summary} >= {s.rollback_confidence}")
    return Verdict("keep", p, summary)
