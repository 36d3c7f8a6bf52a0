"""One decision (``Agent.decide``: 16 rotations x 2 maps, masks, choice) with and without
``exploration.side_taper`` on the same stored states, one torch thread, the two interleaved.
Usage: python decision_time.py STATE_DB LIMIT_M [STATES]"""

from __future__ import annotations

import dataclasses
import json
import sqlite3
import sys
import time

import numpy as np
import torch

from flgd.config import load_config
from flgd.learning.agent import Agent
from flgd.learning.policy_file import load_policy
from flgd.store.replay_rows import decode_heightmaps

if __name__ == "__main__":
    torch.set_num_threads(1)
    db, limit = sys.argv[1], float(sys.argv[2])
    count = int(sys.argv[3]) if len(sys.argv) > 3 else 40
    base = load_config("cell_config/sim.yaml")
    network = load_policy(base.policy).network
    states = [decode_heightmaps(*r) for r in sqlite3.connect(db).execute(
        "select rows, cols, color, height from states order by id limit ?", (count,))]
    configs = {"off": base, "on": dataclasses.replace(base, exploration=dataclasses.replace(
        base.exploration, side_taper=limit, epsilon_start=0.0, epsilon_end=0.0))}
    configs["off"] = dataclasses.replace(base, exploration=dataclasses.replace(
        base.exploration, epsilon_start=0.0, epsilon_end=0.0))
    agents = {k: Agent(c, network, seed=0) for k, c in configs.items()}
    times: dict[str, list[float]] = {k: [] for k in agents}
    for i, s in enumerate(states):
        for k, agent in agents.items():
            t0 = time.perf_counter()
            agent.decide(s, 10_000 + i)
            times[k].append(time.perf_counter() - t0)
    print(json.dumps({k: {"median_s": round(float(np.median(v)), 4), "p90_s": round(float(np.percentile(v, 90)), 4),
                          "states": len(v)} for k, v in times.items()}))
