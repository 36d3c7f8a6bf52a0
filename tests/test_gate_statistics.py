"""The champion/challenger gate's error rates, by simulation with Bernoulli outcomes (apart from any cell).

Each trial plays the daemon's schedule: every action is the challenger's with probability ``share``, else
the champion's; the outcome is a successful grasp with the policy's rate; the gate looks after every action.
The rates are successful grasps per action around 0.75 (the shipped policy's level on the simulated cell,
with its share of moves).  The numbers the README states come from these cases.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flgd.config import CellConfig
from flgd.gate.keeper import gate_settings
from flgd.gate.statistics import Tally, challenger_verdict, p_better

from benchmarks.gate import challenger_trial, rollback_trial

TRIALS = 1000
SHIPPED = gate_settings(CellConfig())  # the defaults a user gets: share 0.5, at most 100 actions
# the long test of the first table in docs/learning-on-the-cell.md: a fifth of the decisions, up to 800 actions
SETTINGS = dataclasses.replace(SHIPPED, share=0.2, max_attempts=800)


def test_p_better_is_a_probability_that_follows_the_evidence():
    even = p_better(Tally(100, 75, 100), Tally(100, 75, 100))
    assert even == pytest.approx(0.5)
    assert p_better(Tally(400, 320, 400), Tally(400, 280, 400)) > 0.99  # 0.80 vs 0.70 on 400 each
    assert p_better(Tally(10, 8, 10), Tally(10, 7, 10)) < 0.8  # the same rates on 10 each: not convincing
    assert p_better(Tally(400, 280, 400), Tally(400, 320, 400)) < 0.01


def test_a_challenger_5_points_worse_is_promoted_in_at_most_5_percent_of_trials():
    rng = np.random.default_rng(11)
    ends = [challenger_trial(rng, 0.75, 0.70, SETTINGS)[0] for _ in range(TRIALS)]
    promoted = ends.count("promote") / TRIALS
    assert promoted <= 0.05, promoted
    assert ends.count("drop-worse") / TRIALS >= 0.5  # and most are dropped early, as clearly worse


def test_a_challenger_5_points_better_is_promoted_in_at_least_80_percent_within_max_attempts():
    rng = np.random.default_rng(12)
    runs = [challenger_trial(rng, 0.75, 0.80, SETTINGS) for _ in range(TRIALS)]
    promoted = [n for kind, n, _ in runs if kind == "promote"]
    assert len(promoted) / TRIALS >= 0.80, len(promoted) / TRIALS
    assert np.percentile(promoted, 90) <= 600  # the stated number: 90 % of the promotions within 600 of its actions


@pytest.mark.parametrize("challenger, at_most, at_least", [
    (0.70, 0.03, 0.0),   # 5 points worse: rarely promoted (docs: 1.1 %)
    (0.75, 0.08, 0.0),   # as good: docs 5.1 %
    (0.80, 0.35, 0.12),  # 5 points better: docs 21.3 %; the next weights are tested after 100 actions
    (0.85, 0.65, 0.38),  # 10 points better: docs 50.9 %
])
def test_the_shipped_gate_decides_within_100_actions_at_the_documented_rates(challenger, at_most, at_least):
    rng = np.random.default_rng(21)
    runs = [challenger_trial(rng, 0.75, challenger, SHIPPED) for _ in range(TRIALS)]
    promoted = sum(kind == "promote" for kind, _, _ in runs) / TRIALS
    assert at_least <= promoted <= at_most, promoted
    assert max(n for _, n, _ in runs) <= SHIPPED.max_attempts


def test_a_champion_10_points_below_its_predecessors_record_is_rolled_back_in_90_percent():
    rng = np.random.default_rng(13)
    predecessor = Tally(500, 375, 500)  # the record of a champion that acted 500 times at 0.75
    rolled = sum(rollback_trial(rng, predecessor, 0.65, SETTINGS, 600) is not None for _ in range(TRIALS))
    assert rolled / TRIALS >= 0.90, rolled / TRIALS
    # ... while one as good as its predecessor is rarely rolled back over the same horizon
    kept = sum(rollback_trial(rng, predecessor, 0.75, SETTINGS, 600) is None for _ in range(300))
    assert kept / 300 >= 0.95


def test_the_verdict_names_its_evidence():
    v = challenger_verdict(Tally(300, 210, 290), Tally(80, 40, 78), SETTINGS)
    assert v.kind == "drop" and "40/80" in v.reason and "210/300" in v.reason
    v = challenger_verdict(Tally(30, 20, 30), Tally(5, 4, 5), SETTINGS)
    assert v.kind == "testing" and f"{SETTINGS.min_attempts - 5} more actions" in v.reason


def test_the_challengers_share_rises_with_the_evidence_that_it_is_better_and_only_then():
    from flgd.gate.statistics import challenger_share

    s = dataclasses.replace(SETTINGS, share=0.2, max_share=0.5, drop_min_attempts=40)
    champion = Tally(400, 300, 400)                                              # 0.75
    assert challenger_share(champion, Tally(30, 30, 30), s) == 0.2               # too few actions yet
    assert challenger_share(champion, Tally(100, 90, 100), s) == 0.5             # clearly better: the most
    assert challenger_share(champion, Tally(100, 60, 100), s) == 0.2             # worse: never above share
    between = challenger_share(champion, Tally(100, 79, 100), s)                 # P(better) ~0.8
    assert 0.2 < between < 0.5
    # off: max_share 0 (the default) or not above share
    assert challenger_share(champion, Tally(100, 90, 100), dataclasses.replace(s, max_share=0.0)) == 0.2
    assert challenger_share(champion, Tally(100, 90, 100), dataclasses.replace(s, max_share=0.1)) == 0.2


def test_with_a_rising_share_a_worse_challenger_is_still_rarely_promoted_and_a_better_one_sooner():
    s = dataclasses.replace(SETTINGS, max_share=0.5)
    rng = np.random.default_rng(21)
    worse = [challenger_trial(rng, 0.75, 0.70, s)[0] for _ in range(TRIALS)]
    assert worse.count("promote") / TRIALS <= 0.05
    rng = np.random.default_rng(22)
    fixed = [c for kind, _, c in (challenger_trial(rng, 0.75, 0.85, SETTINGS) for _ in range(300)) if kind == "promote"]
    rising = [c for kind, _, c in (challenger_trial(rng, 0.75, 0.85, s) for _ in range(300)) if kind == "promote"]
    assert np.median(rising) < 0.8 * np.median(fixed)     # cycles until a 10-point-better challenger is promoted
