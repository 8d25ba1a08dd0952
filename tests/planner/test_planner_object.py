"""Which object the run bags: the coordinator takes V and the object's height from the run's freshest
marker detection (perception/object) when it names the run's object, else the scenario's, and says
which in the run's result. Pure: synthetic detections, a fake clock, no Zenoh."""

from __future__ import annotations

import numpy as np
import pytest
from test_planner_coordinator import T0, sample_g0, soi, started

from bagit.common.messages import Goal, ObjectDetection
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.planner.coordinator import CoordinatorConfig, compute_plan

SHIFT = np.array([0.012, -0.009, 0.0])  # the object stands 15 mm away from where the scenario says


def detection(c, t_frame: float, shift=SHIFT, marker_id: int | None = None, height: float = 0.2) -> ObjectDetection:
    o = c.run.scenario.object
    T = o.bottom_frame()
    T[:3, 3] += shift
    return ObjectDetection(source_stamp=t_frame, marker_id=o.marker.id if marker_id is None else marker_id, name="pineapple tin",
                           vertices=o.bottom_vertices() + shift, T_world_object=T, T_world_marker=T, height=height)


def failure(t_frame: float, error: str = "no known object in view: no ArUco marker in the image") -> ObjectDetection:
    return ObjectDetection(source_stamp=t_frame, ok=False, error=error)


def test_a_detection_of_the_runs_object_gives_v_and_height_and_the_result_says_marker():
    c = started()
    V_sc = c.run.scenario.object.bottom_vertices()
    assert c.on_object(detection(c, T0 + 0.8), T0 + 0.9) == []
    (eff,) = c.on_soi(soi(sample_g0(c.run.scenario), T0 + 1.0), T0 + 1.05)
    assert c.state.stage == "goal"
    job_obj = eff.job.scenario.object
    assert np.allclose(job_obj.bottom_vertices(), V_sc + SHIFT) and job_obj.effective_height() == 0.2
    assert np.allclose(c.run.scenario.object.bottom_vertices(), V_sc)  # the run's scenario (and run/state's doc) unchanged
    c.stop(T0 + 2.0)
    res = c.state.result
    assert res["object_from"] == "marker" and res["object_reason"] is None and res["marker"]["marker_id"] == c.run.scenario.object.marker.id
    assert res["marker"]["marker_v_error_m"] == pytest.approx(np.linalg.norm(SHIFT), abs=1e-5)
    assert res["marker"]["marker_height_m"] == 0.2


def test_the_plan_uses_the_marker_v():
    """compute_plan (the real goal) gets the marker's V: the goal message carries it."""
    c = started()
    small = np.array([0.004, 0.003, 0.0])
    c.on_object(detection(c, T0 + 0.8, shift=small, height=float(c.run.scenario.object.effective_height())), T0 + 0.9)
    (eff,) = c.on_soi(soi(sample_g0(c.run.scenario), T0 + 1.0), T0 + 1.05)
    goals: list[Goal] = []
    out = compute_plan(eff.job, on_goal=goals.append)
    assert goals, out.reason
    assert np.allclose(goals[0].vertices, c.run.scenario.object.bottom_vertices() + small)


def test_a_g0_waits_for_the_marker_and_goes_on_when_it_arrives():
    c = started()
    c.on_object(failure(T0 - 5.0), T0 - 4.9)  # perception publishes detections (this one of before the run: ignored)
    assert c.run.detection is None and c.run.detection_note is None
    assert c.on_soi(soi(sample_g0(c.run.scenario), T0 + 1.0), T0 + 1.05) == []
    assert c.state.stage == "perceiving" and c.run.waiting_soi is not None
    assert c.tick(T0 + 2.0) == [] and c.state.stage == "perceiving"
    (eff,) = c.on_object(detection(c, T0 + 1.9), T0 + 2.1)
    assert eff.kind == "plan" and c.state.stage == "goal"
    assert np.allclose(eff.job.scenario.object.bottom_vertices(), c.run.scenario.object.bottom_vertices() + SHIFT)
    assert c.run.extra["object"]["object_from"] == "marker"


def test_no_usable_detection_falls_back_to_the_scenario_with_the_reason():
    c = started()
    V_sc = c.run.scenario.object.bottom_vertices()
    c.on_object(failure(T0 + 0.7), T0 + 0.8)
    c.on_soi(soi(sample_g0(c.run.scenario), T0 + 1.0), T0 + 1.05)
    assert c.state.stage == "perceiving"
    (eff,) = c.tick(T0 + 0.5 + 3.0)  # settle_s + marker_wait_s
    assert c.state.stage == "goal" and np.allclose(eff.job.scenario.object.bottom_vertices(), V_sc)
    info = c.run.extra["object"]
    assert info["object_from"] == "scenario" and "no ArUco marker" in info["object_reason"] and "marker_v_error_m" not in info
    c.stop(T0 + 4.0)
    assert c.state.result["object_from"] == "scenario"


def test_a_marker_of_another_object_is_not_used():
    c = started()
    other = c.run.scenario.object.marker.id + 1
    c.on_object(detection(c, T0 + 0.8, marker_id=other), T0 + 0.9)
    assert c.run.detection is None and f"id {other}" in c.run.detection_note
    c.on_soi(soi(sample_g0(c.run.scenario), T0 + 1.0), T0 + 1.05)
    (eff,) = c.tick(T0 + 3.6)
    info = c.run.extra["object"]
    assert info["object_from"] == "scenario" and "not the run's object" in info["object_reason"]


def test_an_object_without_a_marker_in_the_scenario_takes_any_detected_object():
    doc = Scenario.from_file(find_scenario("exp02")).model_dump(mode="json", exclude_none=True)
    del doc["object"]["marker"], doc["object"]["marker_id"]  # a scenario document that does not name the object's marker
    c = started(scenario=None, scenario_doc=doc)
    assert c.run.scenario.object.marker is None
    c.on_object(_det_any(c, 7), T0 + 0.9)
    (eff,) = c.on_soi(soi(sample_g0(c.run.scenario), T0 + 1.0), T0 + 1.05)
    assert c.run.extra["object"]["object_from"] == "marker" and c.run.extra["object"]["marker_id"] == 7


def _det_any(c, marker_id: int) -> ObjectDetection:
    o = c.run.scenario.object
    return ObjectDetection(source_stamp=T0 + 0.8, marker_id=marker_id, name="some box", vertices=o.bottom_vertices(),
                           T_world_object=o.bottom_frame(), height=0.1)


def test_without_detections_on_the_bus_g0_does_not_wait():
    c = started()
    (eff,) = c.on_soi(soi(sample_g0(c.run.scenario), T0 + 1.0), T0 + 1.05)
    assert c.run.extra["object"] == {"object_from": "scenario", "object_reason": "perception publishes no marker detections (perception/object)"}


def test_object_source_scenario_keeps_the_scenario_v_and_reports_the_marker_error():
    c = started(CoordinatorConfig(settle_s=0.5, object_source="scenario"))
    c.on_object(detection(c, T0 + 0.8), T0 + 0.9)
    (eff,) = c.on_soi(soi(sample_g0(c.run.scenario), T0 + 1.0), T0 + 1.05)
    assert np.allclose(eff.job.scenario.object.bottom_vertices(), c.run.scenario.object.bottom_vertices())
    info = c.run.extra["object"]
    assert info["object_from"] == "scenario" and info["object_reason"] == "object_source is scenario"
    assert info["marker_v_error_m"] == pytest.approx(np.linalg.norm(SHIFT), abs=1e-5)


def test_the_freshest_detection_wins_and_stale_ones_are_ignored():
    c = started()
    c.on_object(detection(c, T0 + 0.2), T0 + 0.3)  # before start + settle: a frame of the old world
    assert c.run.detection is None
    c.on_object(detection(c, T0 + 1.5, shift=np.zeros(3)), T0 + 1.6)
    c.on_object(detection(c, T0 + 0.9), T0 + 1.7)  # older frame, arriving late
    assert c.run.detection.source_stamp == T0 + 1.5


def test_the_planner_node_takes_the_object_from_perception_object_over_the_bus():
    """Wiring: a detection on perception/object reaches the coordinator; a g0 waiting for it goes on."""
    import time

    from bus_support import session_pair, wait_until

    from bagit.common.bus import Keys, LatestCache, Publisher, request_run_control
    from bagit.common.messages import RunControl, RunState, SoiState
    from bagit.services.planner.node import PlannerNode, PlannerServiceConfig

    for a, b in session_pair("plobj"):
        keys = Keys("plobj")
        cfg = PlannerServiceConfig(coordinator=CoordinatorConfig(settle_s=0.1, marker_wait_s=30.0), publish_hz=5)
        with PlannerNode(a, keys, cfg) as node:
            watch = LatestCache(b, keys.run_state, RunState)
            obj_pub = Publisher(b, keys.perception_object, ObjectDetection)
            soi_pub = Publisher(b, keys.perception_soi, SoiState)
            assert wait_until(lambda: obj_pub.matched and soi_pub.matched and watch.get() is not None)
            obj_pub.put(failure(time.time()))  # perception publishes detections: g0 will wait for one
            assert wait_until(lambda: node.coord.objects_heard)
            rep = request_run_control(b, keys, RunControl(action="start", scenario="exp02"))
            assert rep.accepted
            sc = node.coord.run.scenario
            time.sleep(0.15)  # past settle_s
            soi_pub.put(SoiState(rim=sample_g0(sc), source_stamp=time.time()))
            assert wait_until(lambda: node.coord.run.waiting_soi is not None)
            assert node.state.stage == "perceiving"
            with node._lock:
                det = detection(node.coord, time.time())
            obj_pub.put(det)
            assert wait_until(lambda: (s := watch.get()) is not None and s.stage in ("goal", "planning", "pre-bagging", "failed"))
            assert node.coord.run.extra["object"]["object_from"] == "marker"
            request_run_control(b, keys, RunControl(action="stop"))
