"""`bagit run`: the deployed stack's logic in one process, on the simulator's clock.

Short headless runs: every stage goes through the coordinator, perception sees only rendered
frames, the arms are the two simulated CR5s behind the arm driver's rules, and a run is
deterministic. (Success of whole runs is measured by the benchmark, not asserted here, but one.)
"""

import json

import numpy as np
import pytest

from bagit.cli import main
from bagit.common.results import RunResult
from bagit.common.scenario import Scenario
from bagit.inprocess import RunOptions, run_inprocess
from bagit.scenarios import find_scenario
from bagit.services.sim.judge import judge


@pytest.mark.slow
def test_a_short_run_goes_through_the_coordinators_stages_with_the_cr5s():
    s = Scenario.from_file(find_scenario("exp02-canned-pineapple"))
    stages = []
    r = run_inprocess(RunOptions(scenario=s, seed=0, time_limit_s=3.0, on_state=lambda st: stages.append(st.stage)))
    assert stages == ["perceiving", "goal", "planning", "pre-bagging", "failed"], stages  # the run/state a dashboard would see
    assert r.arms == "cr5" and r.stage_reached == "pre-bagging" and "time limit" in r.reason
    assert r.planning_time_s > 0 and r.path_nodes >= 2 and r.ticks >= 80  # perceived g0, planned, servoed 3 s at 30 Hz
    assert r.object_from == "marker" and r.marker["marker_id"] == 2  # V from the object's marker, as deployed
    assert np.asarray(r.final_rim).shape == (s.bag.n_x, 3) and r.truth is not None and not r.truth.passed_through
    assert r.arm_events["faults"] == 0 and r.arm_events["alarms"] == 0 and r.arm_events["watchdog_stops"] == 0
    assert r.provenance.commit and r.provenance.params["control_rate_hz"] == s.params.controller.control_rate_hz


@pytest.mark.slow
def test_a_camera_slower_than_the_keep_alive_pace_gets_keep_alive_ticks_not_watchdog_stops():
    """At 10 frames/s a control tick per frame leaves 100 ms between commands, over the watchdog's 90 ms
    gap: the host ticks the controller on the last SOI in between (keep-alives), as the node does."""
    s = Scenario.from_file(find_scenario("exp02-canned-pineapple"))
    r = run_inprocess(RunOptions(scenario=s, seed=0, time_limit_s=2.0, fps=10.0))
    assert r.stage_reached == "pre-bagging" and r.ticks >= 15  # servoed, a control tick per frame
    assert r.arm_events["watchdog_stops"] == 0 and r.arm_events["faults"] == 0, r.arm_events


@pytest.mark.slow
def test_two_runs_with_one_seed_are_the_same_bit_for_bit():
    s = Scenario.from_file(find_scenario("exp10-printed-cuboid"))
    a, b = (run_inprocess(RunOptions(scenario=s, seed=3, time_limit_s=2.0)) for _ in range(2))
    assert a.ticks == b.ticks and a.final_rim == b.final_rim and a.truth.error_cm == b.truth.error_cm
    assert a.perceived_error_cm == b.perceived_error_cm and a.arm_events == b.arm_events


@pytest.mark.slow
def test_the_ideal_arms_ablation_moves_floating_grippers():
    s = Scenario.from_file(find_scenario("exp02-canned-pineapple"))
    r = run_inprocess(RunOptions(scenario=s, seed=0, time_limit_s=1.5, arms="ideal"))
    assert r.arms == "ideal" and r.ticks >= 40 and r.arm_events == dict.fromkeys(r.arm_events, 0)


def test_judge_on_constructed_rims():
    s = Scenario.from_file(find_scenario("exp02-canned-pineapple"))
    v = s.object.bottom_vertices()
    c = v.mean(axis=0)
    t = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    ring = np.stack([0.1 * np.cos(t), 0.1 * np.sin(t), np.zeros(32)], 1) + c
    up = np.array([0.0, 0.0, 1.0])
    ok, err, _ = judge(ring + [0, 0, 0.04], s, 0.055, up)
    assert ok and err < 0.01
    ok, _, why = judge(ring + [0, 0, 0.01], s, 0.055, up)
    assert not ok and "above the bottom" in why
    ok, _, why = judge(ring + [0.2, 0, 0.04], s, 0.055, up)
    assert not ok and "round" in why


def test_judge_takes_the_section_the_rim_lies_against():
    """A rim resting on a grapefruit above its equator is round it though it lies inside V seen from
    above; on a box the same rim is not (a box's section is V at every height)."""
    sphere = Scenario.from_file(find_scenario("exp03-grapefruit"))  # r = 6 cm, V its equator, lambda_d 3 cm
    v = sphere.object.bottom_vertices()
    c, up = v.mean(axis=0), np.array([0.0, 0.0, 1.0])
    t = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    circle = lambda r, h: np.stack([r * np.cos(t), r * np.sin(t), np.full(32, h)], 1) + c  # noqa: E731
    r_at_goal = np.sqrt(0.06**2 - 0.03**2)  # the sphere's section 3 cm above the equator: 5.2 cm
    ok, err, why = judge(circle(0.056, 0.03), sphere, 0.03, up)
    assert ok and err < 0.01, why
    ok, _, why = judge(circle(r_at_goal - 0.004, 0.03), sphere, 0.03, up)  # inside the section: not round it
    assert not ok and "round" in why
    box = Scenario.from_file(find_scenario("exp08-plastic-packing"))  # 10 x 7 cm bottom
    cb = box.object.bottom_vertices().mean(axis=0)
    ring = lambda r: np.stack([r * np.cos(t), r * np.sin(t), np.full(32, 0.03)], 1) + cb  # noqa: E731
    assert judge(ring(0.07), box, 0.03, up)[0]
    ok, _, why = judge(ring(0.055), box, 0.03, up)  # cuts the box's corners: not round it
    assert not ok and "round" in why


@pytest.mark.slow
def test_run_cli_json_is_the_run_result(capsys):
    code = main(["run", "exp08-plastic-packing", "--time-limit", "1", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert set(out) == set(RunResult.model_fields)  # the same top-level keys as `bagit up --json`
    assert RunResult.model_validate(out).arms == "cr5"
    assert code == (0 if out["success"] else 1)


@pytest.mark.parametrize("bad", [["--time-limit", "-1"], ["--time-limit", "nan"], ["--wall-limit", "inf"], ["--seed", "-1"],
                                 ["--params", "[1]"], ["--arms", "floating"]])
def test_run_cli_refuses_bad_numbers_with_one_line(bad, capsys):
    assert main(["run", "exp08-plastic-packing", *bad]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "error:" in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
@pytest.mark.parametrize("controller", ["autobag", "shakingbot"])
def test_the_primitive_baselines_run_through_the_one_run_path_to_a_judged_end(controller, capsys):
    """`bagit run exp01 --controller autobag|shakingbot --json`: the coordinator's stages with the CR5s,
    the primitives' pre-bagging then bagging, and a result judged on the truth with the keys of every run."""
    stages: list[str] = []
    s = Scenario.from_file(find_scenario("exp01-coffee-box"))
    r = run_inprocess(RunOptions(scenario=s, controller=controller, seed=0, on_state=lambda st: stages.append(st.stage)))
    assert stages == ["perceiving", "goal", "planning", "pre-bagging", "bagging", "done"], (stages, r.reason)
    assert r.controller == controller and r.arms == "cr5" and r.truth is not None and r.error_cm is not None
    assert r.success == r.truth.success and (r.success or r.reason)  # a failure says why
    assert r.arm_events["faults"] == 0 and r.arm_events["alarms"] == 0 and r.arm_events["watchdog_stops"] == 0
    assert main(["run", "exp01", "--controller", controller, "--time-limit", "0.5", "--json"]) in (0, 1)
    out = json.loads(capsys.readouterr().out)
    assert set(out) == set(RunResult.model_fields) and out["controller"] == controller
