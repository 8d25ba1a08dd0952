"""A solid-colour bag (no red edge): the rim is the local top of the bag's colour, level or tilted."""

import numpy as np

from bagit.common.geometry import points_to_polyline_distance
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.perception import extract_soi, rim_cloud
from bagit.services.perception.rgbd import local_top, solid_rim_segmenter
from bagit.services.sim.world import SimWorld


def test_solid_bag_rim_from_its_top_band():
    s = Scenario.from_file(find_scenario("exp09-tea-bucket-solid-bag"))
    assert s.bag.kind == "solid"
    w = SimWorld(s, seed=0)
    w.step(0.5)
    frame = w.render_rgbd(0)
    assert len(rim_cloud(frame)) < 50  # no red edge to find
    cloud = rim_cloud(frame, solid_rim_segmenter(s.bag.color))
    soi = extract_soi(cloud, 32)
    d = points_to_polyline_distance(soi, w.true_rim())
    assert d.mean() < 0.012 and d.max() < 0.03
    w.close()


def test_solid_bag_rim_when_the_grippers_tilt_it():
    """One mount 6 cm above the other tilts the rim far beyond a global top band; its local top still
    finds the whole rim."""
    s = Scenario.from_file(find_scenario("exp09-tea-bucket-solid-bag"))
    w = SimWorld(s, seed=0)
    w.step(0.5)
    mounts = w.mount_home_poses()
    mounts["left"][2, 3] += 0.03
    mounts["right"][2, 3] -= 0.03
    for _ in range(40):  # the mounts move at their speed limit: step towards the targets
        w.set_mount_targets(mounts)
        w.step(0.05)
    rim = w.true_rim()
    assert np.ptp(rim[:, 2]) > 0.04  # tilted well past the 1.5 cm band
    cloud = rim_cloud(w.render_rgbd(0), solid_rim_segmenter(s.bag.color))
    soi = extract_soi(cloud, 32)
    d = points_to_polyline_distance(soi, rim)
    assert d.mean() < 0.012 and d.max() < 0.03
    w.close()


def test_a_few_flying_pixels_do_not_raise_the_local_top():
    """At an object's silhouette a few pixels carry the bag's colour with the object's (nearer) depth;
    they must not make the rim next to them look like hanging fabric."""
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 2 * np.pi, 4000)
    rim = np.column_stack([0.09 * np.cos(a), 0.09 * np.sin(a), np.full_like(a, 0.50)])
    wall = np.column_stack([0.09 * np.cos(a), 0.09 * np.sin(a), rng.uniform(0.40, 0.49, a.size)])
    flyers = np.array([[0.09, 0.0, 0.55], [0.088, 0.01, 0.56], [0.0, 0.09, 0.545], [0.0, 0.091, 0.55]])
    pts = np.vstack([rim, wall, flyers])
    top = local_top(pts[:, :2], pts[:, 2], 0.03)
    kept = pts[:, 2] >= top - 0.015
    assert kept[: len(rim)].all()  # the whole rim, the arcs next to the flyers included
    assert not kept[len(rim) : len(rim) + len(wall)][wall[:, 2] < 0.48].any()  # and not the wall below it
