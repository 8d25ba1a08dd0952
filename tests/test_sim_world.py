"""The simulated world: a fabric bag that behaves like one, an object it must not pass through, a camera."""

import numpy as np
import pytest

from bagit.common.geometry import points_to_polyline_distance
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.perception import rim_cloud
from bagit.services.sim.world import SimWorld


@pytest.fixture(scope="module")
def scenario():
    return Scenario.from_file(find_scenario("exp01-coffee-box"))


def move_mounts(w: SimWorld, offsets: dict, seconds: float, settle: float = 0.5) -> None:
    start = w.mount_poses()
    steps = int(seconds / 0.02)
    for k in range(1, steps + 1):
        s = 0.5 - 0.5 * np.cos(np.pi * k / steps)  # smooth start and stop
        targets = {}
        for name, T in start.items():
            T2 = T.copy()
            T2[:3, 3] += s * np.asarray(offsets[name])
            targets[name] = T2
        w.set_mount_targets(targets)
        w.step(0.02)
    w.step(settle)


def free_sag(w: SimWorld) -> float:
    """How far the rim's free stretches (between the mounts) hang below the clamped ones."""
    rim_ids = w.layout.rim
    clamped = np.isin(rim_ids, np.concatenate(list(w.layout.handles.values())))
    z = w.true_rim()[:, 2]
    return float(z[clamped].mean() - z[~clamped].min())


def test_apart_tightens_and_together_slackens(scenario):
    """Pulled apart, the rim's free stretches straighten and it barely stretches; pushed together they sag."""
    w = SimWorld(scenario, seed=0, camera=False)
    w.step(0.5)
    base_sag, R = free_sag(w), w.ground_truth().rim_perimeter
    move_mounts(w, {"left": [0, -0.04, 0], "right": [0, 0.04, 0]}, 1.0)
    apart_sag, apart_R = free_sag(w), w.ground_truth().rim_perimeter
    move_mounts(w, {"left": [0, 0.09, 0], "right": [0, -0.09, 0]}, 1.0)
    together_sag = free_sag(w)
    assert apart_sag < base_sag - 0.003, (base_sag, apart_sag)
    assert together_sag > base_sag + 0.004, (base_sag, together_sag)
    assert abs(apart_R / R - 1) < 0.1  # fabric, not rubber
    assert np.all(np.isfinite(w.bag_vertices()))


def test_raising_around_the_object_wraps_without_passing_through():
    scenario = Scenario.from_file(find_scenario("exp02-canned-pineapple"))
    w = SimWorld(scenario, seed=0, camera=False)
    w.step(0.5)
    c = w.true_rim().mean(axis=0)
    bottom = scenario.object.bottom_vertices()[:, 2].min()
    # lower the rim clear of the object, centre it under it, then lift it 4 cm past the object's bottom
    down = min(0.0, bottom - 0.06 - w.true_rim()[:, 2].max())
    move_mounts(w, {"left": [0, 0, down], "right": [0, 0, down]}, 0.8)
    move_mounts(w, {"left": [-c[0], -c[1], 0], "right": [-c[0], -c[1], 0]}, 1.5)
    lift = bottom + 0.04 - w.true_rim()[:, 2].mean()
    move_mounts(w, {"left": [0, 0, lift], "right": [0, 0, lift]}, 2.0)
    gt = w.ground_truth()
    assert not gt.passed_through, gt.max_penetration_m
    assert gt.rim[:, 2].mean() > bottom + 0.01  # the rim is above the object's bottom ...
    v = scenario.object.bottom_vertices()
    rim_xy = gt.rim[:, :2]
    from matplotlib.path import Path as MplPath

    assert MplPath(rim_xy).contains_points(v[:, :2]).all()  # ... and goes round it


def test_pushing_the_rim_into_the_object_is_detected(scenario):
    w = SimWorld(scenario, seed=0, camera=False)
    w.step(0.3)
    c = w.true_rim().mean(axis=0)
    bottom = scenario.object.bottom_vertices()[:, 2].min()
    # bring the bag straight up beside the object so the fabric hits it
    move_mounts(w, {"left": [-c[0] + 0.12, 0, bottom + 0.08 - c[2]], "right": [-c[0] + 0.12, 0, bottom + 0.08 - c[2]]}, 1.0, settle=0.2)
    move_mounts(w, {"left": [-0.2, 0, 0], "right": [-0.2, 0, 0]}, 0.6, settle=0.1)
    assert w.ground_truth().max_penetration_m > 0.0


def test_determinism(scenario):
    rims, frames = [], []
    for _ in range(2):
        w = SimWorld(scenario, seed=3)
        move_mounts(w, {"left": [0.02, 0, 0.02], "right": [0.02, 0, 0.02]}, 0.4, settle=0.2)
        rims.append(w.true_rim())
        frames.append(w.render_rgbd(seq=5))
        w.close()
    assert np.array_equal(rims[0], rims[1])
    assert np.array_equal(frames[0].depth, frames[1].depth) and np.array_equal(frames[0].color, frames[1].color)


def test_camera_depth_matches_geometry_and_rim_pixels_fall_on_the_rim(scenario):
    w = SimWorld(scenario, seed=1)
    w.step(0.5)
    f = w.render_rgbd(seq=0)
    assert f.color.shape == (480, 640, 3) and f.depth.shape == (480, 640)
    from bagit.common.geometry import transform_points
    from bagit.services.perception.rgbd import back_project

    pts = transform_points(f.camera.extrinsics(), back_project(f.depth * f.camera.depth_scale, f.camera))
    table = pts[np.abs(pts[:, 2]) < 0.02]
    assert len(table) > 0.3 * len(pts)  # most of the view is the table at z = 0 ...
    assert np.median(np.abs(table[:, 2])) < 0.003  # ... where the depth puts it
    rim_pts = rim_cloud(f)
    assert len(rim_pts) > 200
    d = points_to_polyline_distance(rim_pts[::5], w.true_rim())
    assert np.median(d) < 0.012  # the red tube is 6 mm thick around the rim's centre line
    w.close()


def test_bad_targets_are_rejected(scenario):
    w = SimWorld(scenario, seed=0, camera=False)
    T = np.eye(4)
    T[0, 3] = np.nan
    with pytest.raises(ValueError):
        w.set_mount_targets({"left": T})
    with pytest.raises(ValueError):
        w.set_mount_targets({"middle": np.eye(4)})
