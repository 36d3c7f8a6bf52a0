"""flgd bench soak's summary: growth per 1,000 cycles after warm-up, from the last run's samples only."""

from __future__ import annotations

import pytest

from benchmarks.soak import summarise


def _sample(run: int, cycles: int, rss: int, store: int) -> dict:
    return {"run": run, "cycles": cycles, "rss_bytes": rss, "descriptors": 11, "threads": 12,
            "store_bytes": store, "wal_bytes": 4 << 20, "state_dir_bytes": store + (4 << 20), "scrape_seconds": 0.01}


def test_growth_after_warmup_is_the_slope_of_the_last_runs_samples():
    samples = [_sample(0, c, 500_000_000 + 100 * c, 36_000 * c) for c in range(0, 2001, 250)]
    # a restart at 2,000 cycles: RSS starts low again; only this run's samples after warm-up are judged
    samples += [_sample(1, c, 400_000_000, 36_000 * c) for c in range(2250, 5001, 250)]
    s = summarise(samples, warmup=1000)
    growth = s["after_warmup"]["growth_per_1000_cycles"]
    assert growth["rss_bytes"] == pytest.approx(0.0, abs=1e-6)
    assert growth["store_bytes"] == pytest.approx(36_000_000)
    assert growth["descriptors"] == pytest.approx(0.0)
    assert s["after_warmup"]["samples"] == 12 and s["runs"] == 2
    assert [row["cycles"] // 1000 for row in s["per_1000_cycles"]] == [0, 1, 2, 3, 4, 5]
