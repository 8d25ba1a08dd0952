"""`bagit bench verify`: the sample it draws, what counts as bit for bit, its statistics against known values,
and a tiny record file re-run through the sweep's own path (bench/isolated.py)."""

from __future__ import annotations

import copy
import json

import pytest

from bagit import cli
from bagit.bench import isolated, verify

# The cheapest real run: one second of simulated time with floating grippers (tests/test_bench_cluster.py's).
KEY = ("exp02-canned-pineapple", "mpc", "cbirrt", 0, "ideal")
TIME_LIMIT_S = 1.0


def test_the_sample_is_the_seeds_own_distinct_and_in_order():
    a = verify.sample_indices(120, 20, seed=0)
    assert a == verify.sample_indices(120, 20, seed=0)
    assert len(set(a)) == 20 and a == sorted(a) and 0 <= a[0] and a[-1] < 120
    assert verify.sample_indices(120, 20, seed=1) != a
    assert verify.sample_indices(5, None, seed=3) == verify.sample_indices(5, 9, seed=3) == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="at least one"):
        verify.sample_indices(5, 0, seed=0)


def _record(ticks: int = 300, error: float = 0.4, duration: float = 10.0, success: bool = True) -> dict:
    return {"scenario": "exp01-coffee-box", "controller": "mpc", "planner": "cbirrt", "seed": 1, "arms": "cr5", "success": success,
            "ticks": ticks, "error_cm": error, "duration_s": duration, "final_rim": [[0.1, 0.2, 0.3], [0.1, 0.25, 0.3]],
            "wall_s": 17.0, "provenance": {"host": "a"}}


def test_bit_for_bit_is_every_number_of_the_run_and_not_the_machines():
    old = _record()
    new = dict(copy.deepcopy(old), wall_s=25.0, provenance={"host": "b"})
    assert verify.bit_for_bit(old, new)
    assert not verify.bit_for_bit(old, dict(new, ticks=301))
    assert not verify.bit_for_bit(old, dict(new, error_cm=0.4000001))
    rim = copy.deepcopy(new)
    rim["final_rim"][1][2] = 0.30001
    assert not verify.bit_for_bit(old, rim)


def test_identical_runs_agree_with_every_p_one():
    old = [_record(300 + i, 0.3 + 0.01 * i, 10.0 + i) for i in range(8)]
    t = verify.compare_distributions(old, copy.deepcopy(old))
    assert t["agrees"]
    assert t["success"]["fisher_p"] == t["success"]["mcnemar_p"] == 1.0
    assert t["error_cm"]["wilcoxon_p"] == t["error_cm"]["mannwhitney_p"] == 1.0 and t["error_cm"]["median_diff"] == 0.0


def test_the_tests_give_their_known_p_values():
    # Fisher's exact test on 8/10 against 2/10 successes: two-sided p = 0.0230 (R: fisher.test(matrix(c(8,2,2,8),2))).
    old = [_record(success=i < 8) for i in range(10)]
    new = [_record(success=i < 2) for i in range(10)]
    s = verify.compare_distributions(old, new)["success"]
    assert s["fisher_p"] == pytest.approx(0.02301, abs=1e-4)
    # McNemar's exact test: 6 pairs succeeded only in the record, none only in the re-run: p = 2 * 0.5**6.
    assert (s["only_old"], s["only_new"]) == (6, 0) and s["mcnemar_p"] == pytest.approx(2 * 0.5**6)
    # Wilcoxon's signed-rank test, six pairs all larger in the re-run: exact two-sided p = 2 / 2**6.
    pairs = [(1.0, 1.0 + 0.1 * (i + 1)) for i in range(6)]
    assert verify.paired_tests(pairs)["wilcoxon_p"] == pytest.approx(2 / 2**6)


def test_a_shifted_error_is_found_and_the_distribution_differs():
    old = [_record(300 + i, 0.3 + 0.01 * i, 10.0 + 0.5 * i) for i in range(20)]
    new = [dict(r, error_cm=r["error_cm"] + 1.0) for r in old]
    t = verify.compare_distributions(old, new)
    assert t["error_cm"]["wilcoxon_p"] < 1e-4 and t["error_cm"]["median_diff"] == pytest.approx(1.0)
    assert t["duration_s"]["wilcoxon_p"] == 1.0
    assert not t["agrees"]


def test_only_runs_that_succeeded_both_times_enter_the_error_and_time_tests():
    old = [_record(error=0.3 + 0.01 * i) for i in range(6)]
    new = copy.deepcopy(old)
    new[0] = dict(new[0], success=False, error_cm=None)
    t = verify.compare_distributions(old, new)
    assert t["error_cm"]["n"] == t["duration_s"]["n"] == 5
    assert (t["success"]["only_old"], t["success"]["only_new"]) == (1, 0)


@pytest.mark.slow
def test_a_record_file_re_run_through_the_sweeps_path(tmp_path):
    rec = isolated.run_isolated(KEY, TIME_LIMIT_S, None, 120.0)
    assert rec.get("ticks"), rec.get("reason")
    changed = dict(rec, ticks=rec["ticks"] + 1)
    records = tmp_path / "tiny.jsonl"
    records.write_text(json.dumps(rec) + "\n" + json.dumps(changed) + "\n")
    r = verify.verify([records], sample=None, seed=0, time_limit_s=TIME_LIMIT_S, timeout_s=120.0, out_dir=tmp_path / "out")
    assert [row["bit_for_bit"] for row in r["rows"]] == [True, False]
    assert r["bit_for_bit"] == 1 and r["sample"] == r["of"] == 2 and r["rows"][0]["same_params"]
    assert r["provenance"]["numerics"]["libraries"]["numpy"]
    written = json.loads((tmp_path / "out" / r["written"]["json"].rsplit("/", 1)[-1]).read_text())
    assert written["bit_for_bit"] == 1 and len(written["runs"]) == 2
    assert "Bit for bit: 1/2" in (tmp_path / "out" / r["written"]["markdown"].rsplit("/", 1)[-1]).read_text()


def test_verify_without_a_record_file_is_a_one_line_error(capsys):
    assert cli.main(["bench", "verify"]) == 2
    assert "record files" in capsys.readouterr().err
