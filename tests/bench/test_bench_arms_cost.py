"""bench/arms_cost.py's report: ratios from the records, pairs matched by scenario and seed."""

from bagit.bench.arms_cost import summary


def _row(sc: str, arms: str, cpu: float, ticks: int) -> dict:
    return {"scenario": sc, "seed": 0, "arms": arms, "cpu_s": cpu, "ticks": ticks, "provenance": {"commit": "abc"}}


def test_summary_divides_cr5_by_ideal_per_run_and_per_tick():
    rows = [_row("exp01", "cr5", 30.0, 450), _row("exp01", "ideal", 20.0, 300), _row("exp04", "cr5", 10.0, 100)]
    text = summary(rows)
    assert "| exp01 | 0 | 30.0 | 20.0 | 1.50 | 450 | 300 | 1.00 |" in text
    assert "exp04" not in text  # no ideal run to pair it with
    assert "| all | | 30.0 | 20.0 | 1.50 |" in text
