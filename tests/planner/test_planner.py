"""SOI planning: every node of returned paths checked by code independent of the planner's own."""

import numpy as np
import pytest
from scipy.spatial import Delaunay

from bagit.common.errors import InfeasibleGoal
from bagit.common.geometry import closed_polyline_length
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario, list_scenarios
from bagit.services.planner import PLANNERS, plan_scenario
from bagit.services.planner.collision import rim_gap
from bagit.services.planner.plan import check_scenario_goal, collision_model

SAMPLES_PER_SEGMENT = 24


def dense_rim(rim: np.ndarray) -> np.ndarray:
    """Points along the closed polyline (not just the SOI points)."""
    s = np.linspace(0, 1, SAMPLES_PER_SEGMENT, endpoint=False)[:, None, None]
    nxt = np.roll(rim, -1, axis=0)
    return (rim[None] + s * (nxt - rim)[None]).reshape(-1, 3)


def inside_object(points: np.ndarray, scenario: Scenario, up: np.ndarray) -> np.ndarray:
    v = scenario.object.bottom_vertices()
    solid = Delaunay(np.vstack([v, v + scenario.object.effective_height() * up]))
    return solid.find_simplex(points) >= 0


def inside_obstacles(points: np.ndarray, scenario: Scenario) -> np.ndarray:
    hit = np.zeros(len(points), bool)
    for ob in scenario.obstacles:
        c, s = np.cos(ob.yaw), np.sin(ob.yaw)
        d = points - np.asarray(ob.center)
        local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], 1)
        hit |= np.all(np.abs(local) < np.asarray(ob.size) / 2, axis=1)
    return hit


def check_path(res, scenario: Scenario) -> None:
    assert res.success, res.reason
    path = res.path
    R = scenario.bag.rim_perimeter
    up = res.goal.frame[:3, 2]
    assert np.allclose(path[0], scenario.bag.g0())
    assert np.allclose(path[res.dagger_index], res.goal.g_dagger)
    assert np.allclose(path[-1], res.goal.g_star)
    for k, rim in enumerate(path):
        perim = np.linalg.norm(np.roll(rim, -1, 0) - rim, axis=1).sum()
        assert abs(perim / R - 1) <= 0.05 + 1e-9, f"node {k}: perimeter {perim:.3f} vs R {R:.3f}"
        pts = dense_rim(rim)
        assert not inside_object(pts, scenario, up).any(), f"node {k} cuts the object"
        assert not inside_obstacles(pts, scenario).any(), f"node {k} cuts an obstacle"
    steps = np.linalg.norm(np.diff(path, axis=0), axis=2).max(axis=1)
    assert steps.max() <= 0.05 + 1e-9, f"a rim point moves {steps.max():.3f} m between nodes"
    # halfway between nodes too: the motion the controller will follow stays clear
    mids = 0.5 * (path[1:] + path[:-1])
    for rim in mids:
        pts = dense_rim(rim)
        assert not inside_object(pts, scenario, up).any() and not inside_obstacles(pts, scenario).any()


@pytest.mark.slow
@pytest.mark.parametrize("path", list_scenarios(), ids=lambda p: p.stem)
def test_cbirrt_plans_every_paper_scenario(path):
    s = Scenario.from_file(path)
    for seed in (0, 1):
        check_path(plan_scenario(s, "cbirrt", seed), s)


@pytest.mark.slow
@pytest.mark.parametrize("planner", sorted(PLANNERS))
@pytest.mark.parametrize("name", ["obstacles-a-coffee-box", "exp11-two-bound-tilted", "exp06-work-bin-tilted"])
def test_every_planner_same_checks(planner, name):
    s = Scenario.from_file(find_scenario(name))
    check_path(plan_scenario(s, planner, seed=3), s)


def test_same_seed_same_path():
    s = Scenario.from_file(find_scenario("exp04"))
    a, b = plan_scenario(s, "cbirrt", 5), plan_scenario(s, "cbirrt", 5)
    assert np.array_equal(a.path, b.path)


def test_unreachable_goal_fails_before_any_search_with_reason():
    s = Scenario.from_file(find_scenario("exp01"))
    # A slab through the bagging plane: g† itself is in collision.
    doc = s.model_dump(exclude_none=True)
    doc["obstacles"] = [{"center": [0.0, 0.0, 0.5], "size": [0.6, 0.6, 0.02]}]
    blocked = Scenario.from_dict(doc)
    res = plan_scenario(blocked, "cbirrt", 0)
    assert not res.success and "touches" in res.reason and res.iterations == 0  # refused before any search


def test_a_bag_the_object_does_not_fit_is_refused_before_anything_moves_by_the_planners_own_rule():
    s = Scenario.from_file(find_scenario("exp12"))
    check_scenario_goal(s)  # the bundled bag fits
    rim = s.bag.g0()
    c = rim.mean(axis=0)
    tight = c + (rim - c) * (0.568 / closed_polyline_length(rim))  # a bag whose ellipse holds V under C1, barely
    doc = s.model_dump(exclude_none=True)
    doc["bag"].update(initial_rim=tight.tolist(), rim_perimeter=0.568)
    small = Scenario.from_dict(doc)
    with pytest.raises(InfeasibleGoal, match=r"does not fit the bag: from the start rim, g\* touches the object"):
        check_scenario_goal(small)
    res = plan_scenario(small, "cbirrt", 0)  # the planner, from the same rim, by the same rule
    assert not res.success and res.reason.startswith("g* touches the object") and res.iterations == 0


def test_walled_in_start_gives_up_at_its_budget():
    s = Scenario.from_file(find_scenario("exp02"))
    g0 = s.bag.g0()
    # a thin wall, as wide and tall as the workspace, between the bag (x > 0.06) and the object
    assert g0[:, 0].min() > 0.06
    doc = s.model_dump(exclude_none=True)
    doc["obstacles"] = [{"center": [0.057, 0.0, 0.5], "size": [0.004, 2.0, 2.0]}]
    res = plan_scenario(Scenario.from_dict(doc), "cbirrt", 0, time_budget_s=1.0)
    assert not res.success
    assert res.reason and ("time budget" in res.reason or "touches" in res.reason)  # gave up, at its budget or before


def test_a_failed_search_leaves_the_straight_motion_when_it_is_free(monkeypatch):
    """The fallback of a search that failed (round the tightest bags, CBiRRT never tries to join its trees):
    the straight motion between the stage's ends, checked here by the test's own geometry; never through
    an obstacle."""
    s = Scenario.from_file(find_scenario("exp01"))
    monkeypatch.setitem(PLANNERS, "cbirrt", lambda space, a, b, eps, max_iter, deadline: (None, max_iter))
    res = plan_scenario(s, "cbirrt", 0)
    check_path(res, s)
    assert res.iterations == 2 * s.params.planner.max_iterations  # both searches failed, both stages are straight
    g0, gd = res.path[0], res.path[res.dagger_index]
    for rim in res.path[1 : res.dagger_index]:  # every point on its own line from g0 to g† (up to the perimeter's scaling)
        d, along = rim - g0, gd - g0
        assert np.abs(np.cross(d, along)).max() <= 0.01 * np.linalg.norm(along, axis=1).max()
    # a box in the middle of that motion (clear of g0 and g†): no straight motion, the search's failure stands
    doc = s.model_dump(exclude_none=True)
    doc["obstacles"] = [{"center": (0.5 * (g0[0] + gd[0])).tolist(), "size": [0.03, 0.03, 0.03]}]
    res = plan_scenario(Scenario.from_dict(doc), "cbirrt", 0)
    assert not res.success and res.reason == "cbirrt found no pre-bagging path within its 4000 iterations"


def test_plan_message_round_trip():
    from bagit.common import wire
    from bagit.common.messages import Path

    s = Scenario.from_file(find_scenario("exp03"))
    res = plan_scenario(s, "cbirrt", 0)
    msg = wire.decode(wire.encode(res.to_message("run-1")), Path)
    assert msg.nodes.shape == res.path.shape and msg.dagger_index == res.dagger_index


def _chamfer(a, b):
    d = np.linalg.norm(a[:, None] - b[None], axis=2)
    return d.min(1).mean() + d.min(0).mean()


def _noisy_ellipse(rng, n=32, noise=0.006, bunched=False):
    t = np.sort(rng.uniform(0, 2 * np.pi, n)) if bunched else 2 * np.pi * np.arange(n) / n + rng.normal(0, 0.05, n)
    if bunched:  # most points on one side: the best ellipse's centre is far from their centroid
        t = np.sort(np.concatenate([rng.uniform(-0.6, 0.6, n - 6), rng.uniform(0, 2 * np.pi, 6)]))
    u, v = np.linalg.qr(rng.normal(size=(3, 2)))[0].T
    return np.array([0.1, 0.0, 0.5]) + np.outer(0.12 * np.cos(t), u) + np.outer(0.07 * np.sin(t), v) + rng.normal(0, noise, (n, 3))


@pytest.mark.parametrize("seed", range(4))
def test_regularize_is_a_planar_ellipse_under_c4_c5(seed):
    from bagit.services.planner.space import regularize

    rng = np.random.default_rng(seed)
    x = _noisy_ellipse(rng, bunched=seed % 2 == 1)
    y = regularize(x, 0.002, 0.021)
    r_x = np.linalg.norm(np.roll(x, -1, 0) - x, axis=1).sum()
    r_y = np.linalg.norm(np.roll(y, -1, 0) - y, axis=1).sum()
    assert abs(r_x / r_y - 1) <= 0.002 + 1e-9  # C4
    # y = c + A [cos t, sin t] on a uniform t grid: its centre is its mean, and it lies in a plane
    assert np.linalg.norm(y.mean(0) - x.mean(0)) <= 0.021 + 1e-9  # C5
    sv = np.linalg.svd(y - y.mean(0), compute_uv=False)
    assert sv[2] < 1e-9 * sv[0]
    # and an ellipse: its points fit a conic in their plane exactly
    _, _, vt = np.linalg.svd(y - y.mean(0))
    p = (y - y.mean(0)) @ vt[:2].T
    M = np.column_stack([p[:, 0] ** 2, p[:, 0] * p[:, 1], p[:, 1] ** 2, p[:, 0], p[:, 1], np.ones(len(p))])
    s = np.linalg.svd(M, compute_uv=False)
    assert s[-1] < 1e-9 * s[0]


@pytest.mark.parametrize("seed", range(3))
def test_regularize_is_near_the_chamfer_optimum(seed):
    """Against a generic optimiser (SLSQP) of the same problem, eq. 13 with C5, written here."""
    from scipy.optimize import minimize

    from bagit.services.planner.space import FIT_OVERSAMPLE, fit_ellipse

    rng = np.random.default_rng(10 + seed)
    x = _noisy_ellipse(rng, noise=0.01)
    m = FIT_OVERSAMPLE * len(x)
    t = 2 * np.pi * np.arange(m) / m

    def cd(p):
        return _chamfer(p[:3] + np.column_stack([np.cos(t), np.sin(t)]) @ p[3:].reshape(3, 2).T, x)

    c, A = fit_ellipse(x, 0.021)
    ours = cd(np.concatenate([c, A.ravel()]))
    # start SLSQP from PCA axes through the centroid, not from our answer
    _, _, vt = np.linalg.svd(x - x.mean(0))
    ext = (x - x.mean(0)) @ vt[:2].T
    p0 = np.concatenate([x.mean(0), (vt[:2].T * np.abs(ext).max(0)).ravel()])
    cons = [{"type": "ineq", "fun": lambda p: 0.021 - np.linalg.norm(p[:3] - x.mean(0))}]
    ref = minimize(cd, p0, method="SLSQP", constraints=cons, options={"maxiter": 400})
    assert np.linalg.norm(c - x.mean(0)) <= 0.021 + 1e-9
    assert ours <= 1.03 * ref.fun, (ours, ref.fun)


def test_plan_accepts_a_name_and_an_explicit_g0():
    from bagit.services.planner import plan

    s = Scenario.from_file(find_scenario("exp08"))
    g0 = np.roll(s.bag.g0(), 5, axis=0)[::-1]  # perception may start the rim anywhere, either way round
    res = plan("exp08", seed=2, g0=g0)
    assert res.success and np.allclose(res.path[0], g0)
    # point i means the same place on the rim in every node: neighbours in the path stay close pointwise
    assert np.linalg.norm(np.diff(res.path, axis=0), axis=2).max() <= 0.05 + 1e-9


@pytest.mark.parametrize(
    "g0, word", [(np.full((32, 3), np.nan), "NaN"), (np.zeros((3, 3)), "at least 4"), (np.zeros((32, 2)), "shape")]
)
def test_bad_g0_is_a_clear_error(g0, word):
    from bagit.common.errors import BadCloud
    from bagit.services.planner import plan

    with pytest.raises(BadCloud, match=word):
        plan("exp01", g0=g0)


def _exp01_with_flat_bag(perimeter: float, rim_z: float) -> Scenario:
    """exp01 with a flat round bag of `perimeter` centred under its opening's old centre, at height `rim_z`
    (exp01's box has its bottom at z = 0.5 and reaches over x in [-0.067, 0.067])."""
    s = Scenario.from_file(find_scenario("exp01"))
    t = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    r = perimeter / (32 * 2 * np.sin(np.pi / 32))  # the 32-gon's circumradius
    rim = np.column_stack([0.15 + r * np.cos(t), r * np.sin(t), np.full(32, rim_z)])
    doc = s.model_dump(exclude_none=True)
    doc["bag"].update(initial_rim=rim.tolist(), rim_perimeter=perimeter)
    return Scenario.from_dict(doc)


def test_a_start_rim_within_the_margin_under_the_object_is_left_along_a_growing_clearance():
    # a large bag hanging 1.5 cm under the box's bottom, its rim passing under the box (the envelope zoo's
    # exp01 bags): inside the planner's 2 cm margin, touching nothing
    s = _exp01_with_flat_bag(1.1, 0.485)
    res = plan_scenario(s, "cbirrt", 0)
    check_path(res, s)  # starts at g0 exactly, no node or midpoint in the object
    goal = res.goal
    coll = collision_model(s, goal.up, s.params.planner.clearance_m, goal.g_dagger)
    margin = coll.margins[0]
    gaps = [rim_gap(rim, coll.polytopes[0]) for rim in res.path]
    assert 0 < gaps[0] <= margin  # g0 within the margin: refused before
    first_clear = next(k for k, g in enumerate(gaps) if g > margin)
    assert np.all(np.diff(gaps[: first_clear + 1]) > 0)  # the clearance grows until the margin is met
    assert all(not coll.touched(rim) for rim in res.path[first_clear:])  # and the margin holds from there


def test_a_start_rim_through_the_object_is_still_refused():
    s = _exp01_with_flat_bag(1.1, 0.52)  # the same bag 2 cm up: its rim passes through the box
    res = plan_scenario(s, "cbirrt", 0)
    assert not res.success and res.reason.startswith("g0 touches the object") and res.iterations == 0
