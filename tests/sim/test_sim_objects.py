"""The object and the obstacles in the simulated world are where, and what, the scenario says."""

import mujoco
import numpy as np
import pytest
from scipy.spatial import ConvexHull, cKDTree

from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.sim.objects import object_mjcf, object_parts
from bagit.services.sim.scene import IPC
from bagit.services.sim.world import SimWorld

ALL = [
    "exp01-coffee-box", "exp02-canned-pineapple", "exp03-grapefruit", "exp04-triangular-prism", "exp05-tea-caddy",
    "exp06-work-bin-tilted", "exp07-tea-bucket", "exp08-plastic-packing", "exp09-tea-bucket-solid-bag",
    "exp10-printed-cuboid", "exp11-two-bound-tilted", "exp12-three-bound-tilted", "obstacles-a-coffee-box",
    "obstacles-b-canned-pineapple", "obstacles-c-grapefruit",
]  # fmt: skip


def geom_points(m: mujoco.MjModel, d: mujoco.MjData, g: int) -> np.ndarray:
    """World points that pin down geom g: a box's corners, a mesh's vertices, a sphere's centre."""
    R, p = d.geom_xmat[g].reshape(3, 3), d.geom_xpos[g]
    t = m.geom_type[g]
    if t == mujoco.mjtGeom.mjGEOM_BOX:
        s = m.geom_size[g]
        local = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * s
    elif t == mujoco.mjtGeom.mjGEOM_MESH:
        mid = m.geom_dataid[g]
        local = m.mesh_vert[m.mesh_vertadr[mid] : m.mesh_vertadr[mid] + m.mesh_vertnum[mid]]
    elif t == mujoco.mjtGeom.mjGEOM_SPHERE:
        local = np.zeros((1, 3))
    else:
        raise AssertionError(f"unexpected geom type {t}")
    return local @ R.T + p


@pytest.mark.parametrize("name", ALL)
def test_object_geometry_matches_the_scenario(name):
    s = Scenario.from_file(find_scenario(name))
    w = SimWorld(s, seed=0, camera=False)
    w.step(0.1)  # and every bundled scenario simulates
    assert np.all(np.isfinite(w.bag_vertices()))
    parts = object_parts(s.object)
    names = object_mjcf(s.object, round_as_mesh=IPC)[2]
    assert len(names) == len(parts)
    for gname, part in zip(names, parts, strict=False):
        g = mujoco.mj_name2id(w.model, mujoco.mjtObj.mjOBJ_GEOM, gname)
        pts = geom_points(w.model, w.data, g)
        if part.kind == "sphere":
            assert np.allclose(pts[0], part.center, atol=1e-9)
            assert w.model.geom_size[g][0] == pytest.approx(part.radius)
            continue
        # the geom's corners / vertices are the part's hull points, both ways round
        assert cKDTree(part.points).query(pts)[0].max() < 1e-6
        assert cKDTree(pts).query(part.points)[0].max() < 1e-6
    # V, the scenario's bottom outline, lies on the object's surface
    V = s.object.bottom_vertices()
    depth = np.max([p.depth(V) for p in parts], axis=0)
    assert np.all(np.abs(depth) < 1e-6) or s.object.shape.type in ("sphere", "bundle")
    assert np.all(depth > -1e-6)  # never outside it


def test_an_object_given_only_by_its_outline_is_extruded():
    s = Scenario.from_file(find_scenario("exp01-coffee-box"))
    data = s.model_dump()
    data["object"] = {"vertices": s.object.bottom_vertices().tolist(), "height": 0.12}
    s2 = Scenario.from_dict(data)
    w = SimWorld(s2, seed=0, camera=False)
    assert len(object_parts(s2.object)) == 1
    verts, faces = w.object_mesh()
    assert ConvexHull(verts).volume == pytest.approx(0.12 * 0.08 * 0.12, rel=1e-6)
    assert faces.min() == 0 and faces.max() == len(verts) - 1
    assert np.allclose(w.ground_truth().object_pose[:3, 3], s2.object.bottom_vertices().mean(axis=0))


def test_object_mesh_volumes():
    box = Scenario.from_file(find_scenario("exp10-printed-cuboid"))
    can = Scenario.from_file(find_scenario("exp02-canned-pineapple"))
    for s, volume in (
        (box, float(np.prod(box.object.shape.size))),
        (can, np.pi * can.object.shape.radius**2 * can.object.shape.height),
    ):
        w = SimWorld(s, seed=0, camera=False)
        verts, faces = w.object_mesh()
        tri = verts[faces]
        signed = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
        assert abs(signed) == pytest.approx(volume, rel=0.01)  # a closed surface of the right size


def test_obstacles_are_static_boxes_where_the_scenario_puts_them():
    s = Scenario.from_file(find_scenario("obstacles-a-coffee-box"))
    data = s.model_dump()
    data["obstacles"][0]["yaw"] = 0.4
    s = Scenario.from_dict(data)
    w = SimWorld(s, seed=0, camera=False)
    for k, o in enumerate(s.obstacles):
        g = mujoco.mj_name2id(w.model, mujoco.mjtObj.mjOBJ_GEOM, f"obstacle_{k}")
        assert np.allclose(w.data.geom_xpos[g], o.center)
        assert np.allclose(w.model.geom_size[g], np.asarray(o.size) / 2)
        R = w.data.geom_xmat[g].reshape(3, 3)
        assert np.allclose(R[:, 0], [np.cos(o.yaw), np.sin(o.yaw), 0], atol=1e-9)
        assert w.model.body_dofnum[w.model.geom_bodyid[g]] == 0  # static
