"""The MJCF of the rig's world, built from a scenario and a rig config: the fabric bag (a MuJoCo
flex), its two mounts, the object, the obstacles, the table and the camera.

The bag is a dim-2 flex shell (services/sim/bag.py) with membrane elasticity only (a fabric resists
stretching, hardly bending), light and damped, colliding with the object, the obstacles and the
table, and with itself so that its walls do not pass through each other; contacts are
penetration-free (MuJoCo's IPC contact mode) and frictionless. Its rim vertices near
each handle are clamped to a mocap body, the mount: a rigid arc like the paper's 3D-printed
connector, bolted to the arm's tool flange, so the arms shape the rim only through the mounts.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from bagit.common.bag import RIM_TUBE_RADIUS_M, LightSpec
from bagit.common.rig import CameraConfig, RigConfig
from bagit.common.scenario import Scenario
from bagit.services.sim.bag import BagLayout
from bagit.services.sim.objects import object_files, object_mjcf

CAMERA_NAME = "rgbd"
TIMESTEP = 0.004  # s, the physics step (discrete integrator, as flex elasticity requires)
# The fabric's stiffness, mass, damping and friction, and the binding's bending and colour, come from
# the scenario (bag.fabric, bag.rim; defaults in common/bag.py: the bag of every earlier run). The
# membrane is a shell of THICKNESS_M whose Young's modulus gives the scenario's stretch stiffness E*t.
POISSON = 0.3
THICKNESS_M = 0.001
FLEX_RADIUS_M = 0.003  # collision and rendering half-thickness of the fabric
# Fabric contact uses MuJoCo's IPC mode (penetration-free, verified by continuous collision detection,
# frictionless): soft constraint contacts let a taut, light fabric be cut by an object's edge between
# its vertices. IPC resolves flex contacts with planes, spheres, capsules, boxes and meshes, so round
# objects go in as fine convex meshes. The soft-contact parameters below apply only with IPC off.
IPC = True
ARENA = "128M"  # MuJoCo arena: contacts, constraints and solver stack
CONTACT_SOLREF = "0.008 1"  # as stiff as the 4 ms step allows
CONTACT_SOLIMP = "0.95 0.99 0.002"
CLAMP_SOLREF = "0.008 1"
CLAMP_SOLIMP = "0.9999 0.9999 0.001"  # near-hard: a clamped vertex gives < 1 mm under the arms' pull
# The binding along the opening is a hem, a rod (dim-1 flex of radius RIM_TUBE_RADIUS_M through the
# rim vertices, no contacts) with a little bending stiffness: EI = E pi r^4 / 4 (bag.rim.bending_nm2;
# by default ~1e-4 N m^2, a doubled fabric strip's). It keeps the opening rounded under its own
# weight; compressed, it buckles and sags.
MOUNT_RGBA = "0.2 0.2 0.22 1"
MOUNT_ARC_DROP_M = 0.014  # the connector arc runs this far under the rim
FLANGE_RGBA = "0.75 0.75 0.78 1"
OBSTACLE_RGBA = "0.15 0.15 0.15 1"
TABLE_RGBA = "0.55 0.55 0.52 1"
# The lights at sim.light.intensity 1: a key lamp 2.5 m from the table's origin along -sim.light.direction,
# a fill lamp, and the camera's headlight (MuJoCo's defaults); all scale with the intensity.
KEY_LIGHT_DISTANCE_M = 2.5
KEY_LIGHT_DIFFUSE = 0.8
FILL_LIGHT_DIFFUSE = 0.4
HEADLIGHT_AMBIENT = 0.1
HEADLIGHT_DIFFUSE = 0.4


def _v(x) -> str:
    return " ".join(f"{float(c):.9g}" for c in np.ravel(x))


def _quat(R: np.ndarray) -> np.ndarray:
    """MuJoCo quaternion (w, x, y, z) of a rotation matrix."""
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def camera_mjcf(cam: CameraConfig, T_world_camera: np.ndarray) -> str:
    """The MJCF <camera> with the rig camera's pose and exact pinhole intrinsics."""
    info = cam.info()
    # MuJoCo cameras look along their -z with y up; ours (OpenCV) along +z with y down.
    xaxis, yaxis = T_world_camera[:3, 0], -T_world_camera[:3, 1]
    # principalpixel is the offset of the image centre from the principal point (checked by test).
    ppx = (info.width - 1) / 2 - info.cx
    ppy = (info.height - 1) / 2 - info.cy
    return (
        f'<camera name="{CAMERA_NAME}" pos="{_v(T_world_camera[:3, 3])}" xyaxes="{_v(xaxis)} {_v(yaxis)}" '
        f'resolution="{info.width} {info.height}" focalpixel="{_v([info.fx, info.fy])}" principalpixel="{_v([ppx, ppy])}" '
        f'sensorsize="{_v([info.width * 1e-5, info.height * 1e-5])}"/>'
    )


def _mount_body(name: str, T_home: np.ndarray, rim_local: np.ndarray, T_flange_mount: np.ndarray) -> str:
    """A mocap body at the mount's home pose: the connector arc through its clamped rim vertices
    (`rim_local (k, 3)` in the mount frame), a stem to the tool flange, the flange and the wrist."""
    # The arc runs just under the clamped fabric (mount y points down the rim normal), so the red
    # edge above it stays in view, as the bag's edge does over the paper's connectors.
    arc_pts = rim_local + [0.0, MOUNT_ARC_DROP_M, 0.0]
    arc = "".join(
        f'<geom type="capsule" fromto="{_v(a)} {_v(b)}" size="0.005" contype="0" conaffinity="0" rgba="{MOUNT_RGBA}"/>'
        for a, b in zip(arc_pts[:-1], arc_pts[1:], strict=False)
    )
    mid = arc_pts[len(arc_pts) // 2]
    T_mount_flange = np.linalg.inv(T_flange_mount)
    flange = T_mount_flange[:3, 3]
    axis = T_mount_flange[:3, 2]  # the tool axis, pointing from the flange to the mount
    stem = f'<geom type="capsule" fromto="{_v(mid)} {_v(flange)}" size="0.006" contype="0" conaffinity="0" rgba="{MOUNT_RGBA}"/>'
    disc = f'<geom type="cylinder" fromto="{_v(flange - 0.008 * axis)} {_v(flange)}" size="0.032" contype="0" conaffinity="0" rgba="{FLANGE_RGBA}"/>'
    wrist = (f'<geom type="cylinder" fromto="{_v(flange - 0.09 * axis)} {_v(flange - 0.008 * axis)}" size="0.045" '
             f'contype="0" conaffinity="0" rgba="{FLANGE_RGBA}"/>')
    return f'<body name="mount_{name}" mocap="true" pos="{_v(T_home[:3, 3])}" quat="{_v(_quat(T_home[:3, :3]))}">{arc}{stem}{disc}{wrist}</body>'


def lights_mjcf(light: LightSpec) -> tuple[str, str]:
    """The MJCF <headlight> (inside <visual>) and the <light>s of the world body for the scenario's light."""
    k = light.intensity
    d = light.unit_direction()
    pos = -KEY_LIGHT_DISTANCE_M * d + 0.0  # + 0.0: no negative zeros in the file

    def grey(x: float) -> str:
        return _v([x * k] * 3)

    head = f'<headlight ambient="{grey(HEADLIGHT_AMBIENT)}" diffuse="{grey(HEADLIGHT_DIFFUSE)}"/>'
    lamps = (f'<light pos="{_v(pos)}" dir="{_v(d + 0.0)}" diffuse="{grey(KEY_LIGHT_DIFFUSE)}"/>\n'
             f'    <light pos="1 1 2" dir="-0.5 -0.5 -1" diffuse="{grey(FILL_LIGHT_DIFFUSE)}"/>')
    return head, lamps


def rim_young_pa(bending_nm2: float) -> float:
    """The binding rod's Young's modulus (Pa) for a bending stiffness EI (N m^2): E = 4 EI / (pi r^4)."""
    return 4.0 * bending_nm2 / (np.pi * RIM_TUBE_RADIUS_M**4)


def scene_files(scenario: Scenario) -> dict[str, bytes]:
    """Files `build_mjcf`'s XML refers to (textures), for `MjModel.from_xml_string(xml, assets=...)`."""
    return object_files(scenario.object)


def build_mjcf(scenario: Scenario, rig: RigConfig, layout: BagLayout) -> str:
    """The whole world as an MJCF string."""
    cam = rig.camera
    obj_xml, assets, _ = object_mjcf(scenario.object, round_as_mesh=IPC)
    obstacles = "".join(
        f'<geom name="obstacle_{k}" type="box" size="{_v(np.asarray(o.size) / 2)}" pos="{_v(o.center)}" '
        f'quat="{_v([np.cos(o.yaw / 2), 0, 0, np.sin(o.yaw / 2)])}" rgba="{OBSTACLE_RGBA}"/>'
        for k, o in enumerate(scenario.obstacles)
    )
    mounts = ""
    for name, T in layout.mount_home.items():
        rim_local = (layout.vertices[layout.handles[name]] - T[:3, 3]) @ T[:3, :3]
        mounts += _mount_body(name, T, rim_local, rig.arms[name].T_flange_mount())
    # Each clamped vertex is held at a fixed point of its mount (a ball-joint "connect": body1 is the
    # mount, so the point turns with it; a weld to a vertex body would not, as vertices have no rotation).
    clamps = ""
    for name, ids in layout.handles.items():
        T = layout.mount_home[name]
        for i in ids:
            anchor = (layout.vertices[i] - T[:3, 3]) @ T[:3, :3]
            clamps += f'<connect body1="mount_{name}" body2="bag_{i}" anchor="{_v(anchor)}" solref="{CLAMP_SOLREF}" solimp="{CLAMP_SOLIMP}"/>'

    bag = scenario.bag
    fabric = bag.fabric
    body_rgba = _v(bag.color) + " 1"
    rim_rgba = (*(bag.rim.color if bag.kind == "red-edged" else bag.color), 1.0)
    headlight, lamps = lights_mjcf(scenario.sim.light)
    return f"""<mujoco model="bagit-rig">
  <compiler angle="radian"/>
  <size memory="{ARENA}"/>  <!-- room for the contacts of a crumpled bag (IPC); the default arena overflows -->
  <option timestep="{TIMESTEP}" integrator="discrete" gravity="0 0 -9.81">{'<flag ipc="enable"/>' if IPC else ''}</option>
  <statistic extent="2" center="0 0 0.4"/>
  <visual>
    <global offwidth="{max(cam.width, 640)}" offheight="{max(cam.height, 480)}"/>
    <map znear="0.01" zfar="5"/>
    <quality shadowsize="0" offsamples="0"/>  <!-- no multisampling: the software-rendered camera stays fast -->
    {headlight}
  </visual>
  <asset>{"".join(assets)}</asset>
  <worldbody>
    {lamps}
    <geom name="table" type="plane" size="3 3 0.05" pos="0 0 {rig.table_height}" rgba="{TABLE_RGBA}"/>
    {camera_mjcf(cam, scenario.sim.camera.calibration_error.true_pose(cam.T_world_camera()))}
    {obj_xml}
    {obstacles}
    {mounts}
    <flexcomp name="bag" type="direct" dim="2" radius="{FLEX_RADIUS_M}" mass="{fabric.mass_kg:.9g}" rgba="{body_rgba}"
      point="{_v(layout.vertices)}" element="{" ".join(str(int(i)) for i in layout.elements.ravel())}">
      <elasticity young="{fabric.stretch_n_per_m / THICKNESS_M:.9g}" poisson="{POISSON}" thickness="{THICKNESS_M}" damping="{fabric.damping_s:.9g}"
        elastic2d="stretch"/>
      <contact selfcollide="auto" condim="3" solref="{CONTACT_SOLREF}" solimp="{CONTACT_SOLIMP}" friction="{fabric.friction:.9g}"/>
    </flexcomp>
  </worldbody>
  <deformable>
    <flex name="rim" dim="1" radius="{RIM_TUBE_RADIUS_M}" rgba="{_v(rim_rgba)}" body="{" ".join(f"bag_{i}" for i in layout.rim)}"
      element="{" ".join(f"{k} {(k + 1) % len(layout.rim)}" for k in range(len(layout.rim)))}">
      <elasticity young="{rim_young_pa(bag.rim.bending_nm2):.9g}" poisson="0.3"/>
      <contact contype="0" conaffinity="0"/>
    </flex>
  </deformable>
  <equality>{clamps}</equality>
</mujoco>"""
