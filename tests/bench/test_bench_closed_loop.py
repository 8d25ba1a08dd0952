"""The closed-loop sweep's machinery: a process per run on the sweep's Dask workers, failures as records, JSONL resume
(the engine itself, a running cluster, time-outs and interrupted sweeps: test_bench_cluster.py)."""

from __future__ import annotations

import json

import pytest

from bagit.bench import closed_loop
from bagit.bench.paper import load_closed_loop, manipulation_summary, same_runs_as_mpc
from bagit.common.results import RunResult


@pytest.mark.slow
def test_a_failing_run_is_a_record_and_a_resumed_sweep_skips_it(tmp_path):
    out = tmp_path / "closed-loop.jsonl"
    key = ("no-such-scenario", "mpc", "cbirrt", 0, "cr5")
    recs = closed_loop.sweep([key], out, timeout_s=300)
    assert len(recs) == 1 and recs[0]["success"] is False
    assert recs[0]["reason"].startswith("error: ") and "no-such-scenario" in recs[0]["reason"]
    assert recs[0]["provenance"]["host"] and recs[0]["arms"] == "cr5"  # a failed run's record names its machine too
    lines = out.read_text().splitlines()
    assert len(lines) == 1 and json.loads(lines[0])["scenario"] == "no-such-scenario"
    again = closed_loop.sweep([key], out)  # already there: not run again
    assert again == recs and len(out.read_text().splitlines()) == 1
    # bench paper reads the same file: 0/1 with the reason
    runs, rows = load_closed_loop([out])
    cell = manipulation_summary(runs, rows)["no-such-scenario"]["mpc"]
    assert (cell["success"], cell["of"]) == (0, 1) and "error: " in cell["failures"][0]


@pytest.mark.slow
def test_a_sweep_runs_bagit_runs_own_path_and_records_its_result(tmp_path):
    """One short run per arms mode through the sweep's worker: the records are RunResults with provenance."""
    out = tmp_path / "closed-loop.jsonl"
    keys = [("exp02-canned-pineapple", "mpc", "cbirrt", 0, "cr5"), ("exp02-canned-pineapple", "mpc", "cbirrt", 0, "ideal")]
    recs = closed_loop.sweep(keys, out, workers=2, time_limit_s=1.0)
    assert [r["arms"] for r in recs] == ["cr5", "ideal"]
    for r in recs:
        res = RunResult.model_validate(r)
        assert res.stage_reached == "pre-bagging" and "time limit" in res.reason and res.ticks > 20
        assert res.provenance.commit and res.provenance.params["horizon"] == 10


def test_planner_rows_that_repeat_mpcs_runs_are_counted():
    def run(planner, seed, ticks, err, ok=True, controller="mpc"):
        return {"scenario": "exp01", "controller": controller, "planner": planner, "seed": seed, "arms": "cr5", "ticks": ticks, "error_cm": err,
                "success": ok}

    runs = [
        run("cbirrt", 0, 300, 0.4), run("cbirrt", 1, 310, 0.5),
        run("ffg-rrt", 0, 300, 0.4), run("ffg-rrt", 1, 320, 0.5),  # seed 1 took another path: not the same run
        run("ts-rrt", 0, 300, 0.4), run("ts-rrt", 2, 300, 0.4),  # no mpc run with seed 2 to compare
        run("cbirrt", 0, 300, 0.4, controller="ibvs"),
    ]
    assert same_runs_as_mpc(runs) == {"mpc+ffg-rrt": [1, 2], "mpc+ts-rrt": [1, 1]}
