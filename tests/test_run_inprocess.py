"""The whole run in one process, on the simulator: camera -> SOI -> goal -> plan -> servo.

A short headless run: every stage is exercised through its real path, perception sees only
rendered frames, and every command stays inside C7. (Success of whole runs is measured by the
benchmark, not asserted here.)
"""

import json

import numpy as np
import pytest

from bagit.cli import main
from bagit.common.params import MethodParams
from bagit.common.scenario import Scenario
from bagit.pipeline import judge, run_bagging
from bagit.scenarios import find_scenario


@pytest.mark.slow
def test_short_run_goes_through_every_stage_within_limits():
    s = Scenario.from_file(find_scenario("exp02-canned-pineapple"))
    r = run_bagging(s, "mpc", "cbirrt", seed=0, time_limit_s=3.0)
    assert r.planning_time_s > 0 and r.path_nodes >= 2  # perceived g0, made a goal, planned
    assert r.ticks >= 80  # servoed (exploration first) for the whole 3 s at 30 Hz
    assert r.final_rim.shape[1] == 3 and np.all(np.isfinite(r.final_rim))
    assert not r.passed_through
    assert r.reason  # 3 s is too short to bag: the result says why it did not succeed
    u = np.asarray(r.history["u_norm"])
    p = MethodParams()
    lim = np.linalg.norm([p.max_linear_speed_mps / p.control_rate_hz] * 6 + [p.max_angular_speed_rps / p.control_rate_hz] * 6)
    assert u.max() <= lim + 1e-12


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


def test_run_cli_json_fields(capsys):
    code = main(["run", "exp08-plastic-packing", "--time-limit", "1", "--json"])
    out = json.loads(capsys.readouterr().out)
    for key in ("success", "error_cm", "duration_s", "planning_time_s", "ticks", "stage_reached", "final_rim", "object_vertices"):
        assert key in out
    assert code == (0 if out["success"] else 1)


@pytest.mark.slow
def test_a_whole_simulated_bagging_run_succeeds():
    """The canned pineapple, end to end from camera frames: judged on the simulator's ground truth."""
    s = Scenario.from_file(find_scenario("exp02-canned-pineapple"))
    r = run_bagging(s, "mpc", "cbirrt", seed=0, time_limit_s=40.0)
    assert r.success, (r.stage_reached, r.reason)
    assert r.stage_reached == "done" and not r.passed_through
    assert r.error_cm < 2.0 and r.duration_s < 40.0
    # the true rim went round V with room to spare when the lift from g† began (cm)
    assert r.lift_margin_cm is not None and r.lift_margin_cm > 1.0, r.lift_margin_cm
