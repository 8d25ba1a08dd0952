"""The transport benchmark's machinery works (numbers are for `python -m bagit.bench.zenoh`, not asserts)."""

from __future__ import annotations

import pytest

from bagit.bench import zenoh as zbench


@pytest.mark.parametrize("where", ["in-process", "cross-process"])
def test_benchmark_scenario_delivers_frames_and_soi(where):
    r = zbench._scenario(where, 0.5, 30.0, 30.0)
    for k in ("rgbd", "soi"):
        assert r[k]["sent"] >= 10
        assert r[k]["received"] >= 1 and r[k]["latency"]["n"] == r[k]["received"]
        assert 0 <= r[k]["latency"]["min_ms"] <= r[k]["latency"]["median_ms"] <= r[k]["latency"]["p99_ms"]
    assert r["malformed"] == 0
