"""`bagit bench paper --quick` writes a report whose tables agree with its JSON, and its figures."""

from __future__ import annotations

import json
import re

import pytest

from bagit.bench import paper
from bagit.cli import main


def _cells(md: str, first: str) -> list[list[str]]:
    """Table rows of the report whose first cell starts with `first`."""
    return [[c.strip() for c in line.strip("|").split("|")] for line in md.splitlines() if line.startswith(f"| {first}")]


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper")
    # one closed-loop record file: with the CR5s a run that succeeded and one that failed, for exp01 / mpc;
    # with floating grippers (the ablation) one that succeeded; one autobag run (Table I)
    runs = out / "closed-loop-test.jsonl"
    prov = {"commit": "abc1234def", "host": "test", "params": {}}
    runs.write_text(
        json.dumps({"scenario": "exp01-coffee-box", "controller": "mpc", "planner": "cbirrt", "seed": 0, "arms": "cr5", "success": True,
                    "error_cm": 0.8, "duration_s": 16.0, "stage_reached": "done", "reason": None, "wall_s": 30.0,
                    "arm_events": {"slowed": 3}, "provenance": prov}) + "\n"
        + json.dumps({"scenario": "exp01-coffee-box", "controller": "mpc", "planner": "cbirrt", "seed": 1, "arms": "cr5", "success": False,
                      "error_cm": 4.0, "duration_s": 40.0, "stage_reached": "bagging", "reason": "time limit", "wall_s": 30.0,
                      "provenance": prov}) + "\n"
        + json.dumps({"scenario": "exp01-coffee-box", "controller": "mpc", "planner": "cbirrt", "seed": 0, "arms": "ideal", "success": True,
                      "error_cm": 0.5, "duration_s": 12.0, "stage_reached": "done", "reason": None, "wall_s": 20.0, "provenance": prov}) + "\n"
        + json.dumps({"scenario": "exp01-coffee-box", "controller": "autobag", "planner": "cbirrt", "seed": 0, "arms": "cr5", "success": True,
                      "error_cm": 0.3, "duration_s": 6.0, "stage_reached": "done", "reason": None, "wall_s": 20.0, "provenance": prov}) + "\n"
    )
    rc = main(["bench", "paper", "--quick", "--out", str(out)])
    assert rc == 0
    return out, json.loads((out / "paper.json").read_text()), (out / "paper.md").read_text()


@pytest.mark.slow
def test_quick_report_matches_json(quick):
    out, r, md = quick
    assert r["quick"] and r["seeds"] == 3
    assert set(r["planning"]) == {p.stem for p in paper.scenarios(True)}
    n = 0
    for stem, row in r["planning"].items():
        for planner, c in row.items():
            # the report's success count is the JSON's, which is the count of the raw runs
            raw = [x for x in r["planning_runs"] if x["scenario"] == stem and x["planner"] == planner]
            assert c["success"] == sum(x["success"] for x in raw) and c["of"] == len(raw) == 3
            rows = [cells for cells in _cells(md, stem) if cells[1] == planner and re.fullmatch(r"\d+/\d+", cells[2])]
            assert rows and rows[0][2] == f"{c['success']}/{c['of']}"
            if c["time_mean_s"] is not None:
                assert rows[0][5].startswith(f"{c['time_mean_s']:.3f} ± ")
            n += 1
    assert n == 9
    # the paper's own numbers are beside ours
    assert "| exp01-coffee-box | cbirrt | " in md and "| 9/10 |" in md and "5.13 ± 1.26" in md


def test_quick_placements_and_closed_loop(quick):
    out, r, md = quick
    s = r["placements"]
    assert s["placements"] == 100 and s["shapes"] == 12 and s["valid"] == len([x for x in r["placement_runs"] if x["valid"]])
    assert f"| ours, all | {s['all']['c1_mean']:.3f} |" in md
    assert any(x["tilt_deg"] > 10 for x in r["placement_runs"])
    # closed loop: the file's two runs are 1/2 for exp01 mpc; everything else is "not run"
    m = r["manipulation"]["exp01-coffee-box"]["mpc"]
    assert (m["success"], m["of"], m["error_cm_mean"]) == (1, 2, 0.8)
    assert r["manipulation"]["exp01-coffee-box"]["mpc/ideal"]["success"] == 1
    # Table II: with the CR5s, the arm side's events (and the deployed stack's column: no `bagit bench deployed`
    # records in this folder); the ablation's table: cr5 and ideal side by side, the wall-time ratio between them
    row = [c for c in _cells(md, "exp01-coffee-box") if c[1] == "mpc" and len(c) == 8]
    assert [(c[3], c[4], c[6], c[7]) for c in row] == [("1/2", "0.80 ± 0.00", "slowed 3", "not run")]
    assert [c[3] for c in _cells(md, "exp06-work-bin-tilted") if c[1] == "mpc" and len(c) == 8] == ["not run"]
    ablation = [c for c in _cells(md, "exp01-coffee-box") if c[1] == "mpc" and len(c) == 9]
    assert [(c[2], c[3], c[5], c[6], c[8]) for c in ablation] == [("1/2", "0.80 ± 0.00", "1/1", "0.50 ± 0.00", "1.50")]
    assert not [c for c in _cells(md, "exp06-work-bin-tilted") if len(c) == 9]  # no ablation run there
    assert "commit abc1234def" in md
    # each method over every experiment, cr5 against ideal, and where they differ
    assert "| mpc | cr5 | 1/2 | 0.80 | 16.0 | 30.0 | slowed 3 |" in md and "| mpc | ideal | 1/1 | 0.50 | 12.0 | 20.0 | none |" in md
    assert "- exp01-coffee-box / mpc: cr5 1/2, ideal 1/1; cr5 failures: bagging: time limit" in md
    # Table I: the paper's four methods beside ours from the records, Table II's other servos after them
    assert "| Ours | `mpc` | 8/8 | 53.09 ± 2.92 | 2.10 ± 0.77 | 1/2 | 16.0 ± 0.0 | 0.80 ± 0.00 |" in md
    assert "| AutoBag | `autobag` | 6/8 | 32.54 ± 4.11 | 5.36 ± 0.87 | 1/1 | 6.0 ± 0.0 | 0.30 ± 0.00 |" in md
    assert "| ShakingBot | `shakingbot` | 4/8 | 39.86 ± 3.74 | 6.47 ± 1.13 | not run | — | — |" in md
    assert "| BimaManip. | `bimamanip` | 7/8 | 44.21 ± 5.81 | 3.50 ± 0.93 | not run | — | — |" in md
    assert "| (ibvs, Table II) | `ibvs` | — | — | — | not run | — | — |" in md and "not reimplemented" not in md
    assert not [c for c in _cells(md, "exp01-coffee-box") if c[1] == "autobag"]  # Table II has the shape servos only


def test_quick_figures_exist_and_are_small(quick):
    out, r, md = quick
    names = {p.rsplit("/", 1)[-1] for p in r["figures"]}
    assert {"planning_times.png", "planning_vs_paper.png", "paths.png", "soi_c1.png", "manipulation.png"} <= names
    total = 0
    for f in r["figures"]:
        p = out / f
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"]({f})" in md
        total += p.stat().st_size
    assert total < 600_000


@pytest.mark.slow
def test_reuse_keeps_runs_and_rejects_other_files(quick, tmp_path):
    out, r, _ = quick
    again = paper.run(quick=True, reuse=out / "paper.json", closed_loop=[], out_dir=tmp_path, figures=False)
    assert again["planning_runs"] == r["planning_runs"] and again["manipulation"] == {}
    assert again["placements"]["all"]["c1_mean"] == pytest.approx(r["placements"]["all"]["c1_mean"])  # seeded
    assert "| exp01-coffee-box | mpc | 8/8 | not run |" in (tmp_path / "paper.md").read_text()
    bad = tmp_path / "other.json"
    bad.write_text('{"stages": {}}')
    with pytest.raises(ValueError, match="not a `bagit bench paper` result"):
        paper.run(quick=True, reuse=bad, out_dir=tmp_path, figures=False)
    broken = tmp_path / "closed-loop-broken.jsonl"
    broken.write_text('{"scenario": "exp01"}\n')
    with pytest.raises(ValueError, match="without scenario/success"):
        paper.run(quick=True, reuse=out / "paper.json", closed_loop=[broken], out_dir=tmp_path, figures=False)


def test_the_deployed_column_comes_from_the_deployed_records():
    from bagit.bench.deployed import markdown, summary
    from bagit.bench.paper_report import _deployed

    rec = {"scenario": "exp02-canned-pineapple", "seed": 0, "controller": "mpc", "identical": True, "within": True, "d_error_cm": 0.0,
           "run": {"success": True, "error_cm": 0.63, "ticks": 522}, "up": {"success": True, "error_cm": 0.63, "ticks": 522},
           "wall_s": {"run": 20.0, "up": 40.0}, "provenance": {"commit": "abc1234def0", "host": "vm", "cpu": "x", "cores": 2}}
    other = {**rec, "seed": 1, "identical": False, "within": False, "d_error_cm": 0.5}
    s = summary([rec, other])["exp02-canned-pineapple"]
    assert (s["pairs"], s["identical"], s["within"], s["max_d_error_cm"]) == (2, 1, 1, 0.5)
    assert _deployed(s) == "1/2 bit for bit, 1/2 within 0.2 cm" and _deployed(None) == "not run"
    md = markdown([rec, other])
    assert "Bit for bit: 1/2" in md and "| exp02-canned-pineapple | 1 |" in md and "abc1234def" in md
