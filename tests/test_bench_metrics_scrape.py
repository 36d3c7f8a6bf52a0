"""``flgd bench metrics-scrape`` measures scrapes of the log it wrote (not of an empty store)."""

from __future__ import annotations

from benchmarks import metrics_scrape


def test_the_benchmark_scrapes_the_synthetic_log(monkeypatch):
    import prometheus_client  # measure() imports generate_latest when it runs: patch it at the source

    texts: list[bytes] = []

    original = prometheus_client.generate_latest

    def spy(registry):
        texts.append(original(registry))
        return texts[-1]

    monkeypatch.setattr(prometheus_client, "generate_latest", spy)
    row = metrics_scrape.measure(300, scrapes=2)
    assert row["cycles"] == 300 and len(texts) == 3
    assert b"flgd_cycles_total 300.0" in texts[0]
    assert b'flgd_faults_total{kind="cell"} 0.0' in texts[0]  # 300 // 1000 fault events
    assert b'flgd_cycle_phase_seconds_count{phase="cycle"} 299.0' in texts[-1]
