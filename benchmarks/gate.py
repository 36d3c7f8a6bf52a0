"""``flgd bench gate``: the champion/challenger gate's error rates, by simulation with Bernoulli outcomes.

Each trial plays the daemon's schedule with the config's gate settings: every action is the challenger's with
probability ``gate.share`` (rising to ``gate.max_share`` with the evidence, when set), else the champion's; its outcome is a successful grasp with the policy's rate; the gate
looks after every action (``flgd.gate.statistics``, the functions the daemon runs).  Printed per case: how often a
challenger is promoted, dropped early as worse, and after how many of its actions; how often a champion that falls
below its predecessor's record is rolled back.  tests/test_gate_statistics.py asserts the issue's bounds with the same
functions.

    flgd bench gate [--config cell_config/sim.yaml] [--trials 1000] [--rate 0.75] [--max-share S]
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from flgd.gate.statistics import GateSettings, Tally, challenger_decision, challenger_share, rollback_decision

REPO = Path(__file__).resolve().parents[1]


def challenger_trial(rng: np.random.Generator, p_champion: float, p_challenger: float,
                     s: GateSettings) -> tuple[str, int, int]:
    """(how the test of one challenger ended, its actions then, all actions (cycles) then)."""
    champion, challenger = Tally(), Tally()
    share = s.share
    while True:  # drawn in blocks for speed; max_attempts ends every trial
        assign = rng.random(512)
        u = rng.random(512)
        for k in range(512):
            if assign[k] < share:
                challenger = challenger.add(u[k] < p_challenger, True)
            else:
                champion = champion.add(u[k] < p_champion, True)
            kind, _ = challenger_decision(champion, challenger, s)
            if kind != "testing":
                return kind, challenger.actions, challenger.actions + champion.actions
            share = challenger_share(champion, challenger, s)


def rollback_trial(rng: np.random.Generator, predecessor: Tally, p_live: float, s: GateSettings,
                   horizon: int) -> int | None:
    """The champion action at which it was rolled back, or None within ``horizon``."""
    live = Tally()
    for n, u in enumerate(rng.random(horizon), start=1):
        live = live.add(u < p_live, True)
        if rollback_decision(live, predecessor, s)[0] == "rollback":
            return n
    return None


def main(argv: list[str]) -> int:
    from flgd.config import load_config
    from flgd.gate.keeper import gate_settings

    p = argparse.ArgumentParser(prog="flgd bench gate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", type=Path, default=REPO / "cell_config" / "sim.yaml")
    p.add_argument("--trials", type=int, default=1000)
    p.add_argument("--rate", type=float, default=0.75, help="the champion's successful grasps per action")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-share", type=float, default=None, help="gate.max_share instead of the config's")
    args = p.parse_args(argv)
    s = gate_settings(load_config(args.config))
    if args.max_share is not None:
        if not (args.max_share == 0 or s.share <= args.max_share < 1):
            p.error(f"--max-share: got {args.max_share}, expected 0 (off) or gate.share ({s.share}) .. < 1")
        s = dataclasses.replace(s, max_share=args.max_share)
    rng = np.random.default_rng(args.seed)
    r0 = args.rate
    print(f"gate settings: {s}\nchampion at {r0:.2f} successful grasps per action, {args.trials} trials per case")
    for delta in (-0.10, -0.05, -0.02, 0.0, 0.02, 0.05, 0.10):
        runs = [challenger_trial(rng, r0, r0 + delta, s) for _ in range(args.trials)]
        promoted = [n for kind, n, _ in runs if kind == "promote"]
        cycles = [c for kind, _, c in runs if kind == "promote"]
        early = sum(kind == "drop-worse" for kind, _, _ in runs) / args.trials
        dropped = [n for kind, n, _ in runs if kind != "promote"]
        q = (f"median {np.median(promoted):.0f}, 90 % within {np.percentile(promoted, 90):.0f} of its actions, "
             f"median {np.median(cycles):.0f} cycles" if promoted else "-")
        print(f"challenger {delta:+.2f}: promoted {100 * len(promoted) / args.trials:5.1f} % ({q}); "
              f"dropped early as worse {100 * early:5.1f} %, drops after a median "
              f"{np.median(dropped) if dropped else float('nan'):.0f} of its actions")
    for n_pred in (150, 500):
        pred = Tally(n_pred, int(round(r0 * n_pred)), n_pred)
        for delta in (-0.10, -0.05, 0.0):
            at = [rollback_trial(rng, pred, r0 + delta, s, 600) for _ in range(args.trials)]
            hits = [a for a in at if a is not None]
            print(f"champion {delta:+.2f} below a predecessor's record of {n_pred} actions: rolled back "
                  f"{100 * len(hits) / args.trials:5.1f} % within 600 of its actions"
                  + (f" (median {np.median(hits):.0f})" if hits else ""))
    return 0
