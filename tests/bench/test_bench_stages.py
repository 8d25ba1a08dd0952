"""`bagit bench stages`: every listed stage is a benchmark module, and the arm driver's measures Ruckig alone."""

from __future__ import annotations

import importlib

import numpy as np

from bagit.bench import arm_driver
from bagit.commands.bench import STAGES


def test_every_stage_is_a_benchmark_module_with_run() -> None:
    for name in STAGES:
        mod = importlib.import_module(f"bagit.bench.{name}")
        assert callable(getattr(mod, "run", None)), name


def test_the_arm_driver_benchmark_times_one_12_axis_ruckig_update_and_the_cycle_around_it() -> None:
    r = arm_driver._offline(30)  # noqa: SLF001
    assert {"ruckig", "pipeline", "format", "reach", "cycle"} <= set(r)
    for name, s in r.items():
        assert s["n"] == 30 and np.isfinite(s["median_ms"]) and 0 < s["min_ms"] <= s["median_ms"], name
    # the pipeline runs one Ruckig update per cycle and more besides
    assert r["pipeline"]["median_ms"] > r["ruckig"]["median_ms"]


def test_up_wall_times_each_frame_once_from_its_publication_and_from_its_stamp_and_tables_the_record() -> None:
    """Frame -> command latency pairs a command with its frame by the frame's stamp: the first command
    of a frame only (a keep-alive carries the same stamp later), from the frame's arrival and from the
    stamp (the image taken); commands outside a run or before the window are not timed."""
    from types import SimpleNamespace as NS

    from bagit.bench import up_wall

    t = up_wall._Timings()  # noqa: SLF001
    t.frames = {100.0: 100.020, 100.1: 100.125, 99.0: 99.02}
    t.cmds = {100.0: 100.030, 100.1: 100.160, 99.0: 99.05}
    t.on_cmd(NS(mode="servo", source_stamp=100.0, run_id="r"))  # a keep-alive on frame 100.0, later: not timed again
    t.on_cmd(NS(mode="hold", source_stamp=0.0, run_id="r"))  # no frame: counted, not timed
    lat = t.latency(since=99.5)
    assert lat["commands"] == 2 and lat["frames"] == 2 and t.modes == {"servo": 1, "hold": 1}
    pub, taken = lat["from_published"], lat["from_taken"]
    assert np.isclose(pub["p50_ms"], 22.5) and np.isclose(pub["max_ms"], 35.0)
    assert np.isclose(taken["max_ms"], 60.0) and taken["n"] == 2
    rec = {"machine": {"commit": "abc", "host": "h", "cpu": "c", "cores": 2, "when": "now"}, "load_before": [1.0, 1.0, 1.0],
           "load_after": [1.2, 1.0, 1.0], "params": {"camera": "640x480", "camera_fps": 10.0}, "run": {"stage": "done", "realtime_factor": 1.01},
           "servo": {"realtime_factor": 1.0}, "watchdog_stops": 0, "arm_events": {"watchdog_stops": 0}, "latency": lat,
           "cpu_s_per_sim_s": {"sim": 0.6, "total": 1.0}, "cpu_s_whole_life": {"sim": 30.0}, "goal": {"p99_ms": False}}
    md = up_wall.markdown(rec)
    assert "| commit | abc |" in md and "camera 640x480" in md and "22.5 /" in md and "p99_ms no" in md and "sim 0.600" in md


def test_the_up_lockstep_record_reads_as_a_table_with_its_provenance_ratios_and_goals():
    from bagit.bench.up_lockstep import markdown

    r = {"machine": {"commit": "abc", "host": "h", "cpu": "AMD EPYC", "cores": 2, "when": "now"}, "load_before": [1.0], "load_after": [2.0],
         "params": {"scenario": "exp02", "hogs": 0},
         "run": {"exit": 0, "wall_s": 10.0, "cpu_s": 9.0, "result": {}},
         "up": {"exit": 0, "wall_s": 11.0, "cpu_s": 12.0, "exact": True, "inexact": [], "cpu_s_per_service": {"sim": 6.0},
                "cpu_s_per_sim_s": {"sim": 0.5}, "result": {}, "realtime_factor": 1.2,
                "own_cpu_s": {"bagit up": 1.5, "fork server": 0.7}},
         "bit_for_bit": True, "ratio": {"wall": 1.1, "cpu": 1.333},
         "goal": {"bit_for_bit": True, "wall_ratio": True, "cpu_ratio": False},
         "per_sim_second_at_10fps": {"fps": 10.0, "lockstep": {"cpu_s_per_sim_s": {"sim": 0.4}}, "wall": {"cpu_s_per_sim_s": {"sim": 0.6}}}}
    md = markdown(r)
    assert md.startswith("# `bagit up` in lockstep against `bagit run`")
    for text in ("| commit | abc |", "| up / run: wall, CPU | 1.1, 1.333", "bit_for_bit yes, wall_ratio yes, cpu_ratio no",
                 "lockstep, 10 frames/s | sim 0.400", "wall, 10 frames/s | sim 0.600",
                 "and of its fork server (whole life) | bagit up 1.5, fork server 0.7 |"):
        assert text in md, (text, md)


def test_the_up_lockstep_goals_judge_the_whole_life_and_the_run_alone_apart():
    from bagit.bench.up_lockstep import goals

    r = {"bit_for_bit": True, "ratio": {"wall": 1.4, "cpu": 1.7}, "ratio_the_run": {"wall": 1.05, "cpu": 1.35}}
    assert goals(r, exact=True) == {"bit_for_bit": True, "wall_ratio": False, "cpu_ratio": False,
                                    "wall_ratio_the_run": True, "cpu_ratio_the_run": False}
    assert goals({**r, "ratio_the_run": None}, exact=False)["bit_for_bit"] is False
    assert not goals({**r, "ratio_the_run": None}, exact=True)["wall_ratio_the_run"]


def test_up_lockstep_pairs_judge_the_goals_by_the_median_pair_and_bit_for_bit_by_every_one(monkeypatch):
    """`--pairs N`: the record is the median pair's, the ratios the medians of all pairs, bit for bit only if all are."""
    from bagit.bench import up_lockstep

    made = iter([(1.30, 1.50, True), (1.05, 1.25, True), (1.10, 1.28, False)])

    def measure(**_kw):
        wall, cpu, same = next(made)
        return {"machine": {"commit": "abc"}, "load_before": [1.0], "load_after": [2.0], "params": {"scenario": "exp02"},
                "run": {"wall_s": 10.0, "cpu_s": 10.0, "result": {}}, "bit_for_bit": same,
                "up": {"wall_s": 10 * wall, "cpu_s": 10 * cpu, "exact": True, "cpu_s_per_service": {}, "result": {}},
                "ratio": {"wall": wall, "cpu": cpu}, "ratio_the_run": {"wall": wall - 0.1, "cpu": cpu - 0.1}}

    monkeypatch.setattr(up_lockstep, "measure", measure)
    r = up_lockstep.measure_pairs(3, scenario="exp02")
    assert r["ratio"] == {"wall": 1.1, "cpu": 1.28} and r["up"]["cpu_s"] == 12.8  # the medians; the median CPU pair's details
    assert r["params"]["pairs"] == 3 and len(r["pairs"]) == 3 and r["bit_for_bit"] is False
    assert r["goal"] == {"bit_for_bit": False, "wall_ratio": True, "cpu_ratio": True, "wall_ratio_the_run": True, "cpu_ratio_the_run": True}
    md = up_lockstep.markdown(r)
    assert "| up / run: wall, CPU (the median of 3 pairs) | 1.1, 1.28" in md and "1.3, 1.5; 1.05, 1.25; 1.1, 1.28" in md, md


def test_the_cpu_lines_of_bagit_up_are_read_per_service_and_its_own_apart():
    from bagit.bench.deployed import cpu_per_service

    err = ("[sim] cpu s: not this one\n[up] cpu s: sim 12.3, perception 4.5, arm-driver 2.0\n"
           "[up] own cpu s: bagit up 1.2, fork server 0.6\n")
    assert cpu_per_service(err) == {"sim": 12.3, "perception": 4.5, "arm-driver": 2.0}
    assert cpu_per_service(err, "[up] own cpu s: ") == {"bagit up": 1.2, "fork server": 0.6}
    assert cpu_per_service("no such line") == {}
