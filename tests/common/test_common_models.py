import json
from datetime import UTC

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bagit.common import wire
from bagit.common.errors import BadMessage, BadScenario, BagItError
from bagit.common.messages import MESSAGE_TYPES, Command, RgbdFrame, SoiState
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario, list_scenarios


def box_doc(**kw):
    doc = {"name": "t", "object": {"shape": {"type": "box", "size": [0.1, 0.07, 0.12], "position": [0, 0, 0.5]}}}
    doc.update(kw)
    return doc


def test_box_bottom_vertices_and_height():
    s = Scenario.from_dict(box_doc())
    v = s.object.bottom_vertices()
    assert v.shape == (4, 3) and np.allclose(v[:, 2], 0.44)
    assert s.object.height == pytest.approx(0.12)
    assert s.lambda_d() == pytest.approx(0.06)


def test_tilted_cylinder_outline_is_tilted_circle():
    s = Scenario.from_dict(
        {"name": "c", "object": {"shape": {"type": "cylinder", "radius": 0.04, "height": 0.1, "rpy": [0.3, 0, 0]}}}
    )
    v = s.object.bottom_vertices()
    assert np.allclose(np.linalg.norm(v - v.mean(0), axis=1), 0.04)
    assert np.ptp(v[:, 2]) > 0.02  # the bottom is no longer horizontal


def test_sphere_and_prism_and_bundle():
    sph = Scenario.from_dict({"name": "s", "object": {"shape": {"type": "sphere", "radius": 0.05}}})
    assert sph.object.height == pytest.approx(0.05)
    pr = Scenario.from_dict(
        {"name": "p", "object": {"shape": {"type": "prism", "outline": [[0, 0], [0.1, 0], [0.05, 0.08]], "height": 0.1}}}
    )
    assert len(pr.object.vertices) == 3
    bun = Scenario.from_dict(
        {
            "name": "b",
            "object": {
                "shape": {
                    "type": "bundle",
                    "parts": [
                        {"type": "box", "size": [0.1, 0.1, 0.1], "position": [0.05, 0, 0]},
                        {"type": "box", "size": [0.1, 0.1, 0.2], "position": [-0.05, 0, 0.05]},
                    ],
                }
            },
        }
    )
    v = bun.object.bottom_vertices()
    assert np.ptp(v[:, 0]) == pytest.approx(0.2) and bun.object.height == pytest.approx(0.2)


def test_rim_perimeter_measured_from_initial_rim():
    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    rim = np.stack([0.1 * np.cos(t), 0.1 * np.sin(t), 0.3 + 0 * t], axis=1)
    s = Scenario.from_dict(box_doc(bag={"initial_rim": rim.tolist(), "n_x": 16}))
    assert s.bag.rim_perimeter == pytest.approx(2 * np.pi * 0.1, rel=0.01)
    assert s.bag.g0().shape == (16, 3)


@pytest.mark.parametrize(
    "doc, word",
    [
        ({"name": "x"}, "object"),
        ({"name": "x", "object": {}}, "vertices"),
        ({"name": "x", "object": {"vertices": [[0, 0, float("nan")]] * 3}}, "NaN"),
        (box_doc(params={"lambda_1": 1.5}), "lambda_1"),
        (box_doc(params={"lamda_1": 0.5}), "lamda_1"),
        (box_doc(obstacles=[{"center": [0, 0, 0], "size": [0, 1, 1]}]), "size"),
        ([1, 2, 3], "mapping"),
    ],
)
def test_bad_scenarios_are_one_line_errors(doc, word):
    with pytest.raises(BadScenario) as e:
        Scenario.from_dict(doc)
    assert word in str(e.value) and "\n" not in str(e.value)


def test_scenario_file_round_trip(tmp_path):
    s = Scenario.from_dict(box_doc())
    p = tmp_path / "s.yaml"
    p.write_text(s.to_yaml())
    assert np.allclose(Scenario.from_file(p).object.bottom_vertices(), s.object.bottom_vertices())
    (tmp_path / "s.json").write_text(json.dumps(box_doc()))
    assert Scenario.from_file(tmp_path / "s.json").name == "t"
    with pytest.raises(BadScenario):
        Scenario.from_file(tmp_path / "missing.yaml")
    (tmp_path / "bad.yaml").write_text("name: [unclosed")
    with pytest.raises(BadScenario):
        Scenario.from_file(tmp_path / "bad.yaml")


def test_bundled_scenarios_all_load():
    for p in list_scenarios():
        Scenario.from_file(p)
    with pytest.raises(BadScenario):
        find_scenario("no-such-scenario")


@settings(max_examples=150, suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(
    st.recursive(
        st.none() | st.booleans() | st.floats(allow_nan=True) | st.integers() | st.text(max_size=5),
        lambda c: st.lists(c, max_size=4) | st.dictionaries(
            st.sampled_from(["name", "object", "bag", "shape", "type", "vertices", "size", "height", "params", "obstacles", "x"]), c, max_size=4),
        max_leaves=20,
    )
)
def test_arbitrary_documents_give_scenario_or_bad_scenario(doc):
    try:
        Scenario.from_dict(doc)
    except BadScenario:
        pass


def _example(kind):
    arr = np.arange(96, dtype=float).reshape(32, 3) / 100
    ex = {
        "rgbd": dict(color=np.zeros((4, 5, 3), np.uint8), depth=np.ones((4, 5), np.uint16)),
        "cloud": dict(points=arr.astype(np.float32)),
        "soi": dict(rim=arr),
        "goal": dict(
            g_dagger=arr, g_star=arr, frame=np.eye(4), ellipse={"center": (0, 0), "a": 1, "b": 1, "alpha": 0},
            perimeter=0.68, c1=0.8, c2=0.0, c3=1.0, vertices=arr[:4],
        ),
        "path": dict(nodes=np.stack([arr, arr]), dagger_index=1),
        "cmd": dict(u=np.zeros(12)),
        "controller_status": dict(mode="servo", error_to_goal=0.01, solve_ms=2.5),
        "arm_state": dict(arm="left", q=np.zeros(6), qd=np.zeros(6), tool_pose=np.zeros(6)),
        "run_state": dict(stage="planning", progress=0.5),
        "run_control": dict(action="start", scenario="exp01"),
        "run_control_reply": dict(accepted=False, reason="busy"),
        "estop": dict(source="test"),
        "object": dict(marker_id=3, name="bin", vertices=arr[:4], T_world_object=np.eye(4), height=0.2),
        "sim_truth": dict(rim=arr, sim_time=1.0),
        "clock": dict(t=1073741825.5, servo_tick=3, run_id="r1"),
        "ack": dict(service="controller", run_id="r1", frame=1073741825.5, cmd_seq=7, status_seq=7),
        "recorder_status": dict(messages=10, lost=2, errors=1, error="disk full"),
    }
    return MESSAGE_TYPES[kind](**ex[kind])


@pytest.mark.parametrize("kind", sorted(MESSAGE_TYPES))
def test_wire_round_trip_every_message(kind):
    msg = _example(kind)
    back = wire.decode(wire.encode(msg), type(msg))
    for name in type(msg).model_fields:
        a, b = getattr(msg, name), getattr(back, name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b)
        else:
            assert a == b


def test_arrays_travel_as_raw_bytes_not_json():
    frame = RgbdFrame(color=np.zeros((480, 640, 3), np.uint8), depth=np.zeros((480, 640), np.uint16))
    payload = wire.encode(frame)
    assert len(payload) < 480 * 640 * 5 + 2000


def test_malformed_payloads_raise_bad_message():
    good = wire.encode(SoiState(rim=np.zeros((8, 3))))
    bad = [b"", b"junk", good[:20], good[:-8], good.replace(b'"soi"', b'"zzz"'), good.replace(b'"v": 1', b'"v": 9')]
    for p in bad:
        with pytest.raises(BadMessage):
            wire.decode(p)
    with pytest.raises(BadMessage):
        wire.decode(good, Command)
    huge = good.replace(b"[8, 3]", b"[80000000, 3]")
    with pytest.raises(BadMessage):
        wire.decode(huge)


def test_messages_reject_non_finite_and_bad_shapes():
    with pytest.raises(ValueError):
        Command(u=np.full(12, np.nan))
    with pytest.raises(ValueError):
        Command(u=np.zeros(6))
    with pytest.raises(ValueError):
        SoiState(rim=np.zeros((5, 2)))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400))
def test_arbitrary_bytes_decode_or_bad_message(data):
    try:
        wire.decode(b"BGT1" + data)
    except BadMessage:
        pass


def test_error_hierarchy():
    from bagit.common.errors import BadCloud, InfeasibleGoal

    assert issubclass(BadCloud, ValueError) and issubclass(InfeasibleGoal, ValueError)
    assert issubclass(BadCloud, BagItError) and issubclass(InfeasibleGoal, BagItError)


def test_object_detection_failure_round_trips_and_incomplete_success_is_refused():
    from bagit.common.messages import ObjectDetection

    fail = ObjectDetection(ok=False, error="no ArUco marker in the image", others=[9], source_stamp=3.0)
    back = wire.decode(wire.encode(fail), ObjectDetection)
    assert back.ok is False and back.vertices is None and back.error == fail.error and back.others == [9]
    with pytest.raises(ValueError, match="needs marker_id"):
        ObjectDetection(marker_id=1, vertices=np.zeros((4, 3)), height=0.1)  # no T_world_object
    with pytest.raises(ValueError, match="needs its error"):
        ObjectDetection(ok=False)
    with pytest.raises(ValueError):
        ObjectDetection(marker_id=1, vertices=np.full((4, 3), np.nan), T_world_object=np.eye(4), height=0.1)
    with pytest.raises(ValueError):
        ObjectDetection(marker_id=1, vertices=np.zeros((4, 3)), T_world_object=np.eye(3), height=0.1)


def test_every_name_is_defined_once_and_the_registries_follow_it():
    """The controllers and planners the code can run are exactly the names the CLI, the coordinator and the benchmark offer."""
    from bagit.common.messages import RunState
    from bagit.common.names import CONTROLLER_NAMES, PLANNER_NAMES, STAGES
    from bagit.services.controller.controller import CONTROLLERS
    from bagit.services.planner.rrt import PLANNERS

    assert tuple(CONTROLLERS) == CONTROLLER_NAMES and tuple(PLANNERS) == PLANNER_NAMES
    assert set(STAGES) == set(RunState.model_fields["stage"].annotation.__args__)


def test_a_fresh_provenance_names_the_commit_host_date_and_parameters():
    from datetime import datetime, timedelta

    from bagit.common.results import provenance

    p = provenance({"horizon": 10})
    assert p.commit and p.host and p.params == {"horizon": 10}
    assert p.date is not None and abs(datetime.now(UTC) - datetime.fromisoformat(p.date)) < timedelta(minutes=1)
