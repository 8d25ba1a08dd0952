"""The dashboard's pure parts: colours, meshes, arm geometry, intake, health, history, parameters, series."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bagit.common import cr5
from bagit.common.errors import BadScenario, BadVertices, SafetyViolation
from bagit.common.geometry import pose_to_matrix
from bagit.common.messages import RunState
from bagit.common.params import PARAM_PATHS, MethodParams
from bagit.common.results import RunResult
from bagit.common.scenario import Obstacle, Scenario
from bagit.common.shapes import Box, Bundle, Cylinder, Prism, Sphere
from bagit.dashboard import style
from bagit.dashboard.arms import command_speeds, commanded_matrix, link_lengths, link_segments, segment_pose, tool_matrix
from bagit.dashboard.health import HealthBoard, health_markdown
from bagit.dashboard.history import RunHistory, history_markdown
from bagit.dashboard.intake import LatestSlots
from bagit.dashboard.meshes import (
    box_mesh,
    cylinder_mesh,
    extrude_polygon,
    mesh_volume,
    obstacle_mesh,
    outline_prism,
    shape_meshes,
    sphere_mesh,
    triangulate_polygon,
)
from bagit.dashboard.params import FIELD_NAMES, overrides, validate_params
from bagit.dashboard.scene import closed_segments, fan_indices
from bagit.dashboard.series import Series


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


# --- colours ----------------------------------------------------------------------------------


def test_fan_colours_run_orange_to_blue_to_red():
    c = style.fan_colors(11, 4).astype(int)
    assert c.shape == (11, 3)
    assert np.array_equal(c[0], style.ORANGE.astype(int))
    assert np.array_equal(c[4], style.BLUE.astype(int))  # g† is pure blue
    assert np.array_equal(c[-1], style.RED.astype(int))
    # blue grows over pre-bagging, red grows over bagging
    assert np.all(np.diff(c[:5, 2]) > 0) and np.all(np.diff(c[4:, 0]) > 0)


@pytest.mark.parametrize("n,d", [(1, 0), (2, 0), (2, 1), (5, 0), (5, 4), (5, 99)])
def test_fan_colours_edge_cases(n, d):
    c = style.fan_colors(n, d)
    assert c.shape == (n, 3) and c.dtype == np.uint8
    assert np.array_equal(c[min(d, n - 1)], style.BLUE.astype(np.uint8))


def test_fade_moves_toward_white_and_height_ramp_is_ordered():
    f = style.fade(np.array([[0, 0, 0], [200, 100, 0]]), 0.5)
    assert np.array_equal(f, [[128, 128, 128], [228, 178, 128]])
    h = style.height_colors(np.array([0.0, 0.5, 1.0]))
    assert np.array_equal(h[0], [68, 1, 84]) and np.array_equal(h[-1], [253, 231, 37])
    assert style.height_colors(np.zeros(3)).shape == (3, 3)
    assert style.height_colors(np.zeros(0)).shape == (0, 3)


# --- meshes -----------------------------------------------------------------------------------


def _closed(faces: np.ndarray) -> bool:
    """Every edge is shared by exactly two faces, once in each direction."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    fwd = {tuple(e) for e in edges}
    return len(fwd) == len(edges) and all((b, a) in fwd for a, b in fwd)


def test_box_cylinder_sphere_are_closed_outward_with_the_right_volume():
    v, f = box_mesh((0.12, 0.08, 0.15))
    assert _closed(f) and mesh_volume(v, f) == pytest.approx(0.12 * 0.08 * 0.15)
    v, f = cylinder_mesh(0.05, 0.2, segments=64)
    assert _closed(f) and mesh_volume(v, f) == pytest.approx(np.pi * 0.05**2 * 0.2, rel=0.01)
    v, f = sphere_mesh(0.1, rings=24, segments=48)
    assert _closed(f) and mesh_volume(v, f) == pytest.approx(4 / 3 * np.pi * 0.1**3, rel=0.02)


def test_ear_clipping_handles_concave_and_clockwise_outlines():
    L = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], dtype=float)  # area 3
    for poly in (L, L[::-1]):
        faces = triangulate_polygon(poly)
        assert faces.shape == (4, 3)
        a = poly[faces[:, 0]]
        b = poly[faces[:, 1]]
        c = poly[faces[:, 2]]
        areas = 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
        assert np.all(areas > 0) and areas.sum() == pytest.approx(3.0)
    v, f = extrude_polygon(L, 0.0, 0.5)
    assert _closed(f) and mesh_volume(v, f) == pytest.approx(1.5)
    with pytest.raises(BadVertices):
        triangulate_polygon(np.array([[0, 0], [1, 1], [2, 2]], dtype=float))


def test_shape_meshes_sit_where_the_scenario_puts_them():
    box = Box(size=(0.12, 0.08, 0.15), position=(0.0, 0.0, 0.575), rpy=(0, 0, 0.2))
    (v, f), = shape_meshes(box)
    assert v[:, 2].min() == pytest.approx(0.5) and v[:, 2].max() == pytest.approx(0.65)
    # the mesh's bottom corners are the shape's V
    bottom = v[np.isclose(v[:, 2], 0.5)]
    V = box.bottom_vertices()
    assert max(np.min(np.linalg.norm(bottom - p, axis=1)) for p in V) < 1e-12
    tilted = Cylinder(radius=0.05, height=0.1, position=(0.1, 0.0, 0.5), rpy=(0.3, 0, 0))
    (v, f), = shape_meshes(tilted)
    assert mesh_volume(v, f) > 0  # a rigid motion keeps the faces outward
    bundle = Bundle(parts=[Box(size=(0.1, 0.1, 0.1)), Sphere(radius=0.05, position=(0.1, 0, 0)),
                           Prism(outline=[(0, 0), (0.1, 0), (0, 0.1)], height=0.05, position=(0, 0.1, 0))],
                    position=(0.0, 0.0, 0.5))
    parts = shape_meshes(bundle)
    assert len(parts) == 3
    assert all(mesh_volume(v, f) > 0 for v, f in parts)
    assert parts[1][0].mean(axis=0) == pytest.approx([0.1, 0.0, 0.5], abs=1e-9)


def test_obstacle_and_outline_prism():
    v, f = obstacle_mesh(Obstacle(center=(0.3, 0.0, 0.5), size=(0.1, 0.2, 0.3), yaw=np.pi / 2))
    assert np.ptp(v[:, 0]) == pytest.approx(0.2) and np.ptp(v[:, 1]) == pytest.approx(0.1)
    V = np.array([[0.1, 0.1, 0.5], [-0.1, 0.1, 0.5], [-0.1, -0.1, 0.5], [0.1, -0.1, 0.5]])
    v, f = outline_prism(V, np.array([0, 0, 1.0]), 0.2)
    assert _closed(f) and mesh_volume(v, f) == pytest.approx(0.2 * 0.2 * 0.2)
    assert v[:, 2].min() == pytest.approx(0.5) and v[:, 2].max() == pytest.approx(0.7)
    with pytest.raises(BadVertices):
        outline_prism(V[:2], np.array([0, 0, 1.0]), 0.2)
    with pytest.raises(BadVertices):
        outline_prism(np.full((4, 3), np.nan), np.array([0, 0, 1.0]), 0.2)


# --- arms -------------------------------------------------------------------------------------


def test_link_segments_follow_the_cr5_chain_in_the_world():
    rng = np.random.default_rng(3)
    T_wb = pose_to_matrix([0.0, -0.6, 0.0], [0, 0, np.pi / 2])
    for _ in range(5):
        q = rng.uniform(-np.pi, np.pi, 6)
        segs = link_segments(T_wb, q)
        assert segs.shape == (6, 2, 3)
        # consecutive, starting at the base, ending at the flange
        assert np.allclose(segs[1:, 0], segs[:-1, 1])
        assert np.allclose(segs[0, 0], [0.0, -0.6, 0.0])
        assert np.allclose(segs[-1, 1], (T_wb @ cr5.fk(q))[:3, 3])
        # rigid links: constant lengths
        assert np.allclose(np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1), link_lengths())
    with pytest.raises(SafetyViolation):
        link_segments(T_wb, np.full(6, np.nan))
    with pytest.raises(SafetyViolation):
        link_segments(T_wb, np.zeros(5))


@pytest.mark.parametrize("d", [[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0.3, -0.4, 0.2]])
def test_segment_pose_turns_z_onto_the_segment(d):
    a = np.array([0.1, 0.2, 0.3])
    b = a + np.asarray(d)
    pos, q = segment_pose(a, b)
    R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
    assert np.allclose(pos, (a + b) / 2)
    assert np.allclose(R[:, 2], np.asarray(d) / np.linalg.norm(d))


def test_tool_and_commanded_poses():
    T = tool_matrix(np.array([0.1, 0.2, 0.3, 0.0, 0.0, np.pi / 2]))
    assert np.allclose(T[:3, 3], [0.1, 0.2, 0.3]) and np.allclose(T[:3, 0], [0, 1, 0])
    u = np.array([0.01, 0.0, -0.02, 0.0, 0.0, 0.1])
    C = commanded_matrix(T, u)
    assert np.allclose(C[:3, 3], [0.11, 0.2, 0.28])
    assert np.allclose(C[:3, :3], Rotation.from_rotvec([0, 0, 0.1]).as_matrix() @ T[:3, :3])
    with pytest.raises(SafetyViolation):
        tool_matrix(np.array([0, 0, np.inf, 0, 0, 0]))
    ll, rl, la, ra = command_speeds(np.r_[0.003, 0.004, 0, 0, 0, 0.01, 0, 0, 0, 0, 0, 0], 0.1)
    assert (ll, rl, la, ra) == pytest.approx((0.05, 0.0, 0.1, 0.0))


def test_closed_segments_and_fan_indices():
    p = np.arange(12.0).reshape(4, 3)
    s = closed_segments(p)
    assert s.shape == (4, 2, 3) and np.array_equal(s[-1], [p[3], p[0]])
    assert np.array_equal(fan_indices(10, 4), np.arange(10))
    idx = fan_indices(500, 333, max_rims=60)
    assert {0, 333, 499} <= set(idx.tolist()) and len(idx) <= 63 and np.all(np.diff(idx) > 0)


# --- intake -----------------------------------------------------------------------------------


def test_slots_are_latest_wins_and_rate_limited():
    clock = FakeClock()
    s = LatestSlots({"cloud": 0.1, "arm": 1 / 30}, default_period_s=0.0, clock=clock)
    for i in range(5):
        s.put("cloud", i)
    s.put("arm:left", "L")
    s.put("goal", "g")
    got = s.take_due()
    assert {k: v.value for k, v in got.items()} == {"cloud": 4, "arm:left": "L", "goal": "g"}
    s.put("cloud", 5)
    clock.t += 0.05
    assert s.take_due() == {}  # cloud not due for another 50 ms
    assert s.next_due_in() == pytest.approx(0.05)
    clock.t += 0.051
    assert s.take_due()["cloud"].value == 5
    assert s.next_due_in() is None and not s.wake.is_set()
    st = s.stats()["cloud"]
    assert st == {"received": 6, "coalesced": 4, "taken": 2}
    s.put("cloud", 6)
    assert s.take_due(force=True)["cloud"].value == 6  # force ignores the period


# --- health -----------------------------------------------------------------------------------


def test_health_rates_last_seen_and_loss_warnings():
    clock = FakeClock()
    h = HealthBoard(clock=clock, window_s=2.0)
    for _ in range(61):  # 30 Hz for two seconds
        h.note("perception/soi")
        clock.t += 1 / 30
    assert h.service_changed("perception", True) is False
    assert h.service_changed("controller", False) is False  # never seen up: no loss
    (row,) = h.streams()
    assert row.rate_hz == pytest.approx(30.0, rel=0.05) and row.count == 61
    assert row.last_seen_s == pytest.approx(1 / 30)
    clock.t += 5.0
    assert h.streams()[0].rate_hz == 0.0  # silence: the rate falls to zero
    assert h.services()[1].streams == ["perception/soi"]
    assert h.service_changed("perception", False) is True
    clock.t += 3.0
    assert h.warnings() == ["perception went away 3 s ago"]
    md = health_markdown(h)
    assert "| perception | **DOWN** |" in md and "perception/soi" in md
    h.service_changed("perception", True)
    assert h.warnings() == [] and h.is_up("perception") is True


# --- history ----------------------------------------------------------------------------------


def test_history_records_params_and_final_results():
    h = RunHistory(max_runs=3)
    h.started("r1", "exp01-coffee-box", {"horizon": 12})
    h.update(RunState(run_id="r1", scenario="exp01-coffee-box", stage="bagging", progress=0.5, elapsed_s=4.0))
    result = RunResult(run_id="r1", success=True, stage_reached="done", perceived_error_cm=0.42).model_dump(mode="json")
    h.update(RunState(run_id="r1", stage="done", progress=1.0, elapsed_s=9.0, result=result))
    h.update(RunState(run_id="r1", stage="idle"))  # a late republish does not reopen it
    r = h.get("r1")
    assert (r.stage, r.elapsed_s, r.params, r.by_dashboard) == ("done", 9.0, {"horizon": 12}, True)
    assert r.result == RunResult.model_validate(result)  # the one result model, as the coordinator made it
    assert "**done**, 0.42 cm" in history_markdown(h)
    h.update(RunState(run_id="r2", scenario="x", stage="failed", reason="planner gave up"))
    assert h.get("r2").reason == "planner gave up" and not h.get("r2").by_dashboard
    assert h.update(RunState(stage="idle")) is None
    for i in range(3, 6):
        h.update(RunState(run_id=f"r{i}", stage="done"))
    assert [r.run_id for r in h.records()] == ["r5", "r4", "r3"]  # bounded, newest first
    md = history_markdown(h)
    assert md.count("\n") == 4 and "| r5 |" in md


# --- parameters -------------------------------------------------------------------------------


def test_parameter_overrides_are_only_the_changed_valid_fields():
    base = MethodParams(lambda_d=0.05, horizon=8)
    values = {name: base.get(name) for name in FIELD_NAMES}
    assert overrides(base, values) == {}
    values.update(horizon=12, lambda_1=0.9)
    assert overrides(base, values) == {"horizon": 12, "lambda_1": 0.9}
    values["lambda_d"] = None
    assert overrides(base, values)["lambda_d"] is None
    with pytest.raises(BadScenario, match="lambda_1"):
        validate_params(base, {"lambda_1": 1.5})
    with pytest.raises(BadScenario, match="horizon"):
        validate_params(base, {"horizon": 0})
    with pytest.raises(BadScenario, match="unknown parameter"):
        validate_params(base, {"lambda_9": 1})
    # every editable field exists on MethodParams
    assert set(FIELD_NAMES) <= set(PARAM_PATHS)
    # a scenario's own params are the base: its tuned value is not an override
    s = Scenario.from_text("name: t\nobject: {vertices: [[0,0,0],[1,0,0],[0,1,0]]}\nparams: {horizon: 20}")
    assert overrides(s.params, {"horizon": 20}) == {}


# --- series -----------------------------------------------------------------------------------


def test_series_is_bounded_relative_and_restarts_per_run():
    s = Series(("a", "b"), capacity=5)
    for i in range(8):
        s.add(50.0 + i, (i, None if i == 3 else -i), run_id="r1")
    t, a, b = s.arrays()
    assert len(t) == 5 and np.allclose(t, [3, 4, 5, 6, 7]) and np.isnan(b[0])
    v = s.version
    s.add(40.0, (1, 1), run_id="r1")  # older than the last sample: ignored
    assert s.version == v
    s.add(500.0, (1, 2), run_id="r2")
    t, a, b = s.arrays()
    assert list(t) == [0.0] and s.last() == (0.0, 1.0, 2.0)
    s.clear()
    assert len(s) == 0 and all(len(x) == 0 for x in s.arrays())
