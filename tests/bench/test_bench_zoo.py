"""`bagit bench zoo`: bags drawn reproducibly from the documented core ranges, each a valid scenario."""

import math

import pytest

from bagit.bench import zoo
from bagit.common.bag import FABRIC_DAMPING_S, RIM_BENDING_NM2
from bagit.common.errors import BagItError
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario


def test_bag_i_is_the_same_whatever_the_zoo_size_and_differs_by_seed():
    a = zoo.zoo_bag(zoo.zoo_name("core", 0, 3))
    assert a == zoo.zoo_bag("zoo-core-0-3")
    assert a["values"] != zoo.zoo_bag("zoo-core-1-3")["values"] and a["values"] != zoo.zoo_bag("zoo-core-0-4")["values"]
    with pytest.raises(BagItError):
        zoo.zoo_bag("zoo-nowhere-0-1")


def test_bags_lie_in_the_core_ranges_with_distinct_hues():
    for i in range(40):
        b = zoo.zoo_bag(f"zoo-core-7-{i}")
        for k, r in zoo.CORE.items():
            assert r.lo <= b["values"][k] <= r.hi, (i, k)
        obj = zoo._hue_deg(zoo.OBJECT_RGB)
        if b["kind"] == "solid":
            assert b["binding_color"] is None and "solid" in b["classes"]
            assert zoo._hue_gap(zoo._hue_deg(b["fabric_color"]), obj) >= zoo.MIN_HUE_GAP_DEG
        else:
            h = zoo._hue_deg(b["binding_color"])
            assert zoo._hue_gap(h, obj) >= zoo.MIN_HUE_GAP_DEG and zoo._hue_gap(h, zoo._hue_deg(b["fabric_color"])) >= zoo.MIN_HUE_GAP_DEG


def test_a_range_names_the_classes_of_its_tails():
    r = zoo.CORE["stretch_n_per_m"]
    assert r.classes(1000.0) == ["soft"] and r.classes(64000.0) == ["stiff"] and r.classes(8000.0) == []
    assert zoo.CORE["mass_kg"].classes(0.03) == []


def test_a_zoo_bag_is_a_scenario_of_its_values():
    sc, b = zoo.zoo_scenario("zoo-core-0-2")
    v = b["values"]
    assert sc.name == "zoo-core-0-2" and sc.bag.kind == b["kind"]
    assert sc.bag.fabric.stretch_n_per_m == v["stretch_n_per_m"] and sc.bag.fabric.mass_kg == v["mass_kg"]
    assert math.isclose(sc.bag.fabric.damping_s, v["damping_x"] * FABRIC_DAMPING_S)
    assert math.isclose(sc.bag.rim.bending_nm2, v["bending_x"] * RIM_BENDING_NM2)
    assert sc.sim.light.intensity == v["light_x"] and sc.sim.camera.depth_noise == v["depth_noise_x"]
    assert math.isclose(sc.bag.rim_perimeter, b["perimeter_m"]) and zoo.CORE["perimeter_m"].lo <= b["perimeter_m"] <= zoo.CORE["perimeter_m"].hi
    rim_z = sum(p[2] for p in sc.bag.initial_rim) / len(sc.bag.initial_rim)
    assert sc.bag.depth <= rim_z - zoo.DEPTH_CLEARANCE_M + 1e-9  # hangs clear of the table
    el = math.degrees(math.asin(-sc.sim.light.unit_direction()[2]))
    assert zoo.CORE["light_elevation_deg"].lo - 1e-6 <= el <= zoo.CORE["light_elevation_deg"].hi + 1e-6


def test_a_perimeter_is_drawn_again_where_the_object_does_not_fit_from_the_start_rim():
    from bagit.services.planner.plan import check_scenario_goal

    b = zoo.zoo_bag("zoo-core-0-23")  # exp12's object; its first draw (0.568 m) leaves g* on the object
    first = zoo._apply(Scenario.from_file(find_scenario("exp12")), b, b["perimeter_draws"][0])
    with pytest.raises(BagItError, match="does not fit"):
        check_scenario_goal(first)
    sc, bag = zoo.zoo_scenario("zoo-core-0-23")
    assert bag["fit_draws"] > 1 and bag["perimeter_m"] == b["perimeter_draws"][bag["fit_draws"] - 1]
    check_scenario_goal(sc)


def test_summary_per_class_and_files_only_when_asked(tmp_path, monkeypatch):
    names = [zoo.zoo_name("core", 0, i) for i in range(3)]
    runs = [{"scenario": n, "success": i != 1, "error_cm": 0.5 * (i + 1), "duration_s": 10.0 + i, "stage_reached": "done"}
            for i, n in enumerate(names)]
    monkeypatch.setattr(zoo, "sweep", lambda keys, jsonl, *a: [dict(r) for r in runs][: len(keys)])
    monkeypatch.setattr(zoo, "RESULTS_DIR", tmp_path / "results")
    r = zoo.run(3)
    assert "files" not in r and not (tmp_path / "results").exists()
    s = r["summary"]["all"]
    assert (s["success"], s["of"]) == (2, 3) and math.isclose(s["error_cm_mean"], 1.0) and math.isclose(s["time_s_mean"], 11.0)
    for c, row in r["summary"].items():
        assert row["of"] == sum(c == "all" or c in x["zoo_bag"]["classes"] for x in r["runs"])
    q = zoo.run(3, quick=True)
    assert q["files"]["markdown"].startswith(str(tmp_path / "results" / "quick"))
    rec = zoo.run(3, record=True)
    assert rec["files"]["json"] == str(tmp_path / "results" / "zoo-core-0.json")


def test_envelope_bags_lie_in_its_ranges_with_a_calibration_error_of_the_sets_size():
    for set_name, ranges in (("core", zoo.CORE), ("envelope", zoo.ENVELOPE)):
        cal = zoo.CALIBRATION_SETS[set_name]
        for i in range(20):
            b = zoo.zoo_bag(zoo.zoo_name(set_name, 3, i))
            for k, r in {**ranges, **cal}.items():
                assert r.lo <= b["values"][k] <= r.hi, (set_name, i, k)
            off, turn = (math.dist(b["calibration_error"][k], (0, 0, 0)) for k in ("offset_m", "turn_deg"))
            assert math.isclose(off, b["values"]["calibration_offset_m"], abs_tol=1e-5)
            assert math.isclose(turn, b["values"]["calibration_turn_deg"], abs_tol=1e-5)
            tail = any(v >= r.lo + (1 - zoo.TAIL) * (r.hi - r.lo) for v, r in ((off, cal["calibration_offset_m"]), (turn, cal["calibration_turn_deg"])))
            assert (zoo.CALIBRATION_CLASS in b["classes"]) == tail
    assert zoo.ENVELOPE_CALIBRATION["calibration_offset_m"].hi == 0.03 and zoo.ENVELOPE_CALIBRATION["calibration_turn_deg"].hi == 2.0
    sc, b = zoo.zoo_scenario("zoo-envelope-0-5")
    assert sc.sim.camera.calibration_error.offset_m == tuple(b["calibration_error"]["offset_m"])


def test_a_failed_run_is_blamed_on_the_part_its_stage_and_reason_name():
    def rec(stage, reason, success=False):
        return {"success": success, "stage_reached": stage, "reason": reason}

    assert zoo.cause(rec("done", None, True)) is None
    assert zoo.cause(rec("bagging", "perception lost the rim: no SOI for 5.1 s in bagging (the controller held)")) == "perception"
    assert zoo.cause(rec("perceiving", "no fresh SOI from perception within 30 s")) == "perception"
    assert zoo.cause(rec("goal", "no bagging ellipse")) == "goal" and zoo.cause(rec("planning", "no path")) == "plan"
    assert zoo.cause(rec("bagging", "simulator: too slow, 900 s of wall time")) == "physics"
    assert zoo.cause(rec("bagging", "time limit of 40 s reached in bagging")) == "control"
    assert zoo.cause(rec("done", "the final rim does not go round the object")) == "outcome"
    assert zoo.cause(rec("idle", "timed out: no result within 900 s of wall time")) == "harness"


def test_the_map_bins_each_parameter_and_names_where_success_falls_off():
    bags = {n: zoo.zoo_scenario(n)[1] for n in (zoo.zoo_name("envelope", 0, i) for i in range(6))}
    runs = [{"scenario": n, "success": b["values"]["stretch_n_per_m"] < 16000, "stage_reached": "done", "error_cm": 0.5, "duration_s": 12.0,
             "reason": "the final rim does not go round the object", "zoo_bag": b} for n, b in bags.items()]
    m = zoo.envelope_map(runs, "envelope")
    assert set(m) == set(zoo.ENVELOPE) | set(zoo.ENVELOPE_CALIBRATION)
    for k, bins in m.items():
        assert sum(b["of"] for b in bins) == len(runs) and len(bins) == zoo.MAP_BINS
        assert math.isclose(bins[0]["lo"], zoo.ENVELOPE.get(k, zoo.ENVELOPE_CALIBRATION.get(k)).lo)
    stiff = m["stretch_n_per_m"]
    assert 0 < sum(r["success"] for r in runs) < len(runs)  # bags on both sides of the made-up fall-off
    assert all(b["success"] == b["of"] for b in stiff if b["hi"] <= 16000)
    assert all(b["success"] == 0 and b["causes"] == ({"outcome": b["of"]} if b["of"] else {}) for b in stiff if b["lo"] >= 16000)
    text = zoo.markdown({"machine": {}, "bags": 6, "set": "envelope", "zoo_seed": 0, "load_before": 0, "load_after": 0, "params": {},
                         "summary": zoo.summary(runs, bags), "map": m, "runs": [{**r, "cause": zoo.cause(r)} for r in runs]})
    row = next(line for line in text.splitlines() if line.startswith("| stretch_n_per_m"))
    assert all(f"{b['lo']:.3g}-{b['hi']:.3g} (outcome {b['of']})" in row for b in stiff if b["lo"] >= 16000 and b["of"])  # each bin its own causes
    assert "slowed" not in text  # no run has arm_events: none is listed as slowed


def test_the_report_names_the_runs_the_arm_driver_slowed():
    bags = {n: zoo.zoo_scenario(n)[1] for n in (zoo.zoo_name("core", 0, i) for i in range(3))}
    slowed = [0, 7, 583]
    runs = [{"scenario": n, "success": i < 2, "stage_reached": "done" if i < 2 else "bagging", "error_cm": 0.5, "duration_s": 12.0,
             "reason": None if i < 2 else "time limit of 40 s reached in bagging", "arm_events": {"slowed": s, "clipped": 0},
             "zoo_bag": b} for i, ((n, b), s) in enumerate(zip(bags.items(), slowed, strict=True))]
    text = zoo.markdown({"machine": {}, "bags": 3, "set": "core", "zoo_seed": 0, "load_before": 0, "load_after": 0, "params": {},
                         "summary": zoo.summary(runs, bags), "map": {}, "runs": [{**r, "cause": zoo.cause(r)} for r in runs]})
    fail = next(line for line in text.splitlines() if line.startswith("- zoo-core-0-2 "))
    assert fail.endswith("control: bagging: time limit of 40 s reached in bagging (arms slowed 583 periods)")
    listed = next(line for line in text.splitlines() if line.startswith("Runs the arm driver slowed"))
    assert "zoo-core-0-1 (7, success)" in listed and "zoo-core-0-2 (583, failed)" in listed and "zoo-core-0-0" not in listed


def test_a_zoo_bag_written_as_a_scenario_file_reads_back_as_the_same_scenario(tmp_path):
    from bagit.common.scenario import Scenario

    out = zoo.write_bag("zoo-envelope-0-2", tmp_path)
    assert out["scenario"] == str(tmp_path / "zoo-envelope-0-2.yaml") and out["seed"] == 2
    assert Scenario.from_file(out["scenario"]) == zoo.zoo_scenario("zoo-envelope-0-2")[0]
    assert zoo._stem("core", 0, {"jacobian_update": "frozen"}) == "zoo-core-0-jacobian_update-frozen" and zoo._stem("core", 0, None) == "zoo-core-0"
