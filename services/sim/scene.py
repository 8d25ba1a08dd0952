"""The MJCF of the rig's world, built from a scenario: the fabric bag (a MuJoCo flex), its two
mounts, the object, the obstacles, the table and the camera.

The bag is an open-top shell: `n_around` vertices per ring, `n_rings` rings from the rim down, and a
closed bottom. Its membrane elasticity (flex <elasticity>, stretch only: a fabric does not resist
bending) holds its shape; its rim vertices near each handle are welded to a mocap mount, so the
arms shape the rim only through the mounts. A red tube (a dim-1 flex through the rim vertices, no
contacts) marks the rim for the camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bagit.common.geometry import matrix_to_rpy, ramanujan_perimeter
from bagit.common.rig import RigConfig
from bagit.common.scenario import Scenario
from bagit.common.shapes import Box, Bundle, Cylinder, Prism, Sphere

N_AROUND = 24
N_RINGS = 5
HANDLE_HALF_ANGLE = 0.8  # rad: each mount clamps the rim within this of its side (about a quarter of the rim each)
TIMESTEP = 0.004
BAG_MASS_KG = 0.08
YOUNG_PA = 8e6  # with 1 mm thickness: a light fabric that stretches little
RIM_RGBA = "0.85 0.05 0.05 1"
RED_RIM_RADIUS = 0.006


@dataclass
class BagLayout:
    """Where the bag starts and which of its vertices are what."""

    vertices: np.ndarray  # (n, 3) world, at rest
    elements: np.ndarray  # (m, 3) triangles
    rim: np.ndarray  # (N_AROUND,) vertex ids of the rim, counter-clockwise from above
    handles: dict[str, np.ndarray]  # 'left'/'right' -> rim vertex ids clamped by that mount
    mount_home: dict[str, np.ndarray]  # 'left'/'right' -> (4, 4) world <- mount


def bag_layout(perimeter: float, depth: float, rim_center: np.ndarray, aspect: float = 1.3) -> BagLayout:
    """An open-top bag whose rim is an ellipse (long axis along y, the handles) of the given perimeter."""
    b = perimeter / ramanujan_perimeter(aspect, 1.0)  # semi-axis along x
    a = aspect * b  # along y
    verts = []
    for r in range(N_RINGS):
        f = r / (N_RINGS - 1)
        shrink = 1.0 - 0.15 * f**2
        z = -depth * 0.9 * f
        t = 2 * np.pi * np.arange(N_AROUND) / N_AROUND
        verts.append(np.stack([b * shrink * np.cos(t), a * shrink * np.sin(t), np.full(N_AROUND, z)], 1))
    verts.append(np.array([[0.0, 0.0, -depth]]))
    v = np.vstack(verts) + rim_center
    tris = []
    for r in range(N_RINGS - 1):
        for k in range(N_AROUND):
            i, j = r * N_AROUND + k, r * N_AROUND + (k + 1) % N_AROUND
            p, q = i + N_AROUND, j + N_AROUND
            tris += [[i, p, j], [j, p, q]]
    c = len(v) - 1
    last = (N_RINGS - 1) * N_AROUND
    tris += [[last + k, c, last + (k + 1) % N_AROUND] for k in range(N_AROUND)]
    rim = np.arange(N_AROUND)
    t = 2 * np.pi * rim / N_AROUND
    handles, home = {}, {}
    for name, side in (("left", -np.pi / 2), ("right", np.pi / 2)):
        ids = rim[np.abs(np.angle(np.exp(1j * (t - side)))) <= HANDLE_HALF_ANGLE]
        handles[name] = ids
        T = np.eye(4)
        T[:3, 3] = v[ids].mean(axis=0)
        home[name] = T
    return BagLayout(v, np.asarray(tris), rim, handles, home)


def _pose_attrs(position, rpy) -> str:
    return f'pos="{_v(position)}" euler="{_v(rpy)}"'


def _v(x) -> str:
    return " ".join(f"{float(c):.6g}" for c in np.ravel(x))


def _shape_geoms(shape, name: str, rgba: str) -> tuple[str, list[str]]:
    """Geoms (XML) of a scenario shape in its parent frame, and mesh assets it needs."""
    common = f'rgba="{rgba}" condim="3" friction="0.6"'
    if isinstance(shape, Box):
        return f'<geom name="{name}" type="box" size="{_v(np.asarray(shape.size) / 2)}" {_pose_attrs(shape.position, shape.rpy)} {common}/>', []
    if isinstance(shape, Cylinder):
        return f'<geom name="{name}" type="cylinder" size="{shape.radius} {shape.height / 2}" {_pose_attrs(shape.position, shape.rpy)} {common}/>', []
    if isinstance(shape, Sphere):
        return f'<geom name="{name}" type="sphere" size="{shape.radius}" {_pose_attrs(shape.position, shape.rpy)} {common}/>', []
    if isinstance(shape, Prism):
        pts = shape.local_hull_points()
        asset = f'<mesh name="{name}_mesh" vertex="{_v(pts)}"/>'
        return f'<geom name="{name}" type="mesh" mesh="{name}_mesh" {_pose_attrs(shape.position, shape.rpy)} {common}/>', [asset]
    if isinstance(shape, Bundle):
        parts, assets = [], []
        for k, p in enumerate(shape.parts):
            g, a = _shape_geoms(p, f"{name}_{k}", rgba)
            parts.append(g)
            assets += a
        return f'<body name="{name}_bundle" {_pose_attrs(shape.position, shape.rpy)}>{"".join(parts)}</body>', assets
    raise ValueError(f"unknown shape {type(shape).__name__}")


def _object_xml(scenario: Scenario) -> tuple[str, list[str]]:
    obj = scenario.object
    rgba = "0.85 0.65 0.25 1"
    if obj.shape is not None:
        geoms, assets = _shape_geoms(obj.shape, "object", rgba)
        top = obj.shape.hull_points()
    else:  # only V known: V extruded upward as a convex mesh
        v = obj.bottom_vertices()
        n = np.cross(v[1] - v[0], v[2] - v[0])
        up = n / np.linalg.norm(n) * (1 if n[2] >= 0 else -1)
        pts = np.vstack([v, v + obj.effective_height() * up])
        assets = [f'<mesh name="object_mesh" vertex="{_v(pts)}"/>']
        geoms = f'<geom name="object" type="mesh" mesh="object_mesh" rgba="{rgba}"/>'
        top = pts
    # The object hangs still from a thin rod above it, as in the experiments (no contacts).
    c = top.mean(axis=0)
    z0 = top[:, 2].max()
    rod = f'<geom name="rod" type="cylinder" fromto="{_v([c[0], c[1], z0])} {_v([c[0], c[1], z0 + 0.6])}" size="0.003" contype="0" conaffinity="0" rgba="0.6 0.6 0.6 1"/>'
    return f'<body name="object_body">{geoms}{rod}</body>', assets


def build_mjcf(scenario: Scenario, rig: RigConfig, layout: BagLayout) -> str:
    """The whole world as an MJCF string."""
    cam = rig.camera
    Tc = cam.T_world_camera()
    # MuJoCo cameras look along their -z with y up; ours (OpenCV) along +z with y down.
    xaxis, yaxis = Tc[:3, 0], -Tc[:3, 1]
    fovy = np.degrees(2 * np.arctan(cam.height / 2 / cam.fy))
    obj_xml, assets = _object_xml(scenario)
    obstacles = "".join(
        f'<geom name="obstacle_{k}" type="box" size="{_v(np.asarray(o.size) / 2)}" pos="{_v(o.center)}" euler="0 0 {o.yaw}" rgba="0.15 0.15 0.15 1"/>'
        for k, o in enumerate(scenario.obstacles)
    )
    mounts = ""
    for name, T in layout.mount_home.items():
        sign = -1 if name == "left" else 1
        arc = "".join(
            f'<geom type="capsule" fromto="{_v([0.03 * np.cos(a0), sign * 0.012 * np.cos(a0) - sign * 0.012, 0])} '
            f'{_v([0.03 * np.cos(a1), sign * 0.012 * np.cos(a1) - sign * 0.012, 0])}" size="0.008" contype="0" conaffinity="0" rgba="0.25 0.25 0.28 1"/>'
            for a0, a1 in ((-1.2, 0.0), (0.0, 1.2))
        )
        mounts += f'<body name="mount_{name}" mocap="true" pos="{_v(T[:3, 3])}" euler="{_v(matrix_to_rpy(T[:3, :3]))}">{arc}</body>'
    bag = scenario.bag
    body_rgba = _v(bag.color) + " 1"
    rim_rgba = RIM_RGBA if bag.kind == "red-edged" else body_rgba
    welds = "".join(
        f'<weld body1="bag_{i}" body2="mount_{name}" solref="0.004 1"/>' for name, ids in layout.handles.items() for i in ids
    )
    rim_bodies = " ".join(f"bag_{i}" for i in layout.rim)
    rim_edges = " ".join(f"{k} {(k + 1) % len(layout.rim)}" for k in range(len(layout.rim)))
    return f"""<mujoco model="bagit-rig">
  <compiler angle="radian"/>
  <option timestep="{TIMESTEP}" integrator="discrete" gravity="0 0 -9.81"/>
  <visual><global offwidth="{max(cam.width, 640)}" offheight="{max(cam.height, 480)}"/><quality shadowsize="0"/></visual>
  <asset>{"".join(assets)}</asset>
  <worldbody>
    <light pos="0 0 2.5" dir="0 0 -1" diffuse="0.8 0.8 0.8"/>
    <light pos="1 1 2" dir="-0.5 -0.5 -1" diffuse="0.4 0.4 0.4"/>
    <geom name="table" type="plane" size="1.5 1.5 0.05" pos="0 0 {rig.table_height}" rgba="0.55 0.55 0.52 1"/>
    <camera name="rgbd" pos="{_v(Tc[:3, 3])}" xyaxes="{_v(xaxis)} {_v(yaxis)}" fovy="{fovy:.6g}"/>
    {obj_xml}
    {obstacles}
    {mounts}
    <flexcomp name="bag" type="direct" dim="2" radius="0.003" mass="{BAG_MASS_KG}" rgba="{body_rgba}"
      point="{_v(layout.vertices)}" element="{_v(layout.elements)}">
      <elasticity young="{YOUNG_PA}" poisson="0.3" thickness="0.001" damping="0.002" elastic2d="stretch"/>
      <contact selfcollide="none" condim="3" solref="0.005 1" friction="0.5"/>
    </flexcomp>
  </worldbody>
  <deformable>
    <flex name="rim_band" dim="1" radius="{RED_RIM_RADIUS}" rgba="{rim_rgba}" body="{rim_bodies}" vertex="{' '.join(['0 0 0'] * len(layout.rim))}" element="{rim_edges}">
      <contact contype="0" conaffinity="0"/>
    </flex>
  </deformable>
  <equality>{welds}</equality>
</mujoco>"""
