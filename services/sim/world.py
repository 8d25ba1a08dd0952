"""The simulated world: physics of the bag, the mounts, the object and the obstacles, plus the
camera and the ground truth that only tests and benchmarks may read.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

from dataclasses import dataclass  # noqa: E402

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial import ConvexHull  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from bagit.common.geometry import closed_polyline_length, make_transform, resample_closed  # noqa: E402
from bagit.common.messages import RgbdFrame  # noqa: E402
from bagit.common.rig import RigConfig  # noqa: E402
from bagit.common.scenario import Scenario  # noqa: E402
from bagit.services.sim.camera import DepthNoise, add_depth_noise  # noqa: E402
from bagit.services.sim.scene import TIMESTEP, BagLayout, bag_layout, build_mjcf  # noqa: E402

PENETRATION_TOL_M = 0.008  # a fabric vertex deeper than this inside the object: the fabric went through (flex radius 3 mm + soft-contact give)
RIM_BELOW_OBJECT_M = 0.12  # default start: the rim this far below the object's lowest point


@dataclass
class GroundTruth:
    """What really happened (tests and benchmarks only). rim: (N_AROUND, 3) in order; object_pose: (4, 4)."""

    time: float
    rim: np.ndarray
    rim_centroid: np.ndarray
    rim_perimeter: float
    object_pose: np.ndarray
    passed_through: bool
    max_penetration_m: float


class SimWorld:
    """MuJoCo world built from a scenario and a rig. Deterministic for a given scenario and seed."""

    def __init__(self, scenario: Scenario, rig: RigConfig | None = None, seed: int = 0, camera: bool = True):
        self.scenario = scenario
        self.rig = rig or RigConfig()
        self.seed = seed
        R = scenario.bag.rim_perimeter or 0.68
        g0 = scenario.bag.g0()
        if g0 is not None:
            center = g0.mean(axis=0)
        else:
            lowest = self._object_points()[:, 2].min()
            center = np.append(self._object_points()[:, :2].mean(axis=0) + [0.15, 0.0], lowest - RIM_BELOW_OBJECT_M)
        self.layout: BagLayout = bag_layout(R, scenario.bag.depth, center)
        self.model = mujoco.MjModel.from_xml_string(build_mjcf(scenario, self.rig, self.layout))
        self.data = mujoco.MjData(self.model)
        self._mocap = {name: self.model.body(f"mount_{name}").mocapid[0] for name in ("left", "right")}
        self._flex_adr = self.model.flex_vertadr[mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_FLEX, "bag")]
        self._hull = self._object_halfspaces()
        self._passed = False
        self._max_pen = 0.0
        self._renderer: mujoco.Renderer | None = None
        self._camera_enabled = camera
        self.noise = DepthNoise()
        mujoco.mj_forward(self.model, self.data)

    # -- physics -----------------------------------------------------------------------------

    @property
    def time(self) -> float:
        return float(self.data.time)

    def step(self, dt: float) -> None:
        """Advance by `dt` seconds of simulated time (whole internal steps of TIMESTEP)."""
        n = max(int(round(dt / TIMESTEP)), 1)
        for _ in range(n):
            mujoco.mj_step(self.model, self.data)
        self._check_penetration()

    def mount_home_poses(self) -> dict[str, np.ndarray]:
        """Where the mounts start: 'left'/'right' -> (4, 4) world <- mount."""
        return {k: v.copy() for k, v in self.layout.mount_home.items()}

    def set_mount_targets(self, T_world_mount: dict[str, np.ndarray]) -> None:
        """The mounts follow these poses from the next step on (they are bolted to the arms' flanges)."""
        for name, T in T_world_mount.items():
            T = np.asarray(T, dtype=float)
            if name not in self._mocap:
                raise ValueError(f"no mount named {name!r}")
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise ValueError(f"mount target for {name} must be a finite 4x4 transform")
            i = self._mocap[name]
            self.data.mocap_pos[i] = T[:3, 3]
            q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x y z w
            self.data.mocap_quat[i] = [q[3], q[0], q[1], q[2]]

    def mount_poses(self) -> dict[str, np.ndarray]:
        out = {}
        for name, i in self._mocap.items():
            w, x, y, z = self.data.mocap_quat[i]
            out[name] = make_transform(Rotation.from_quat([x, y, z, w]).as_matrix(), self.data.mocap_pos[i].copy())
        return out

    def bag_vertices(self) -> np.ndarray:
        """All bag vertices `(n, 3)` (world)."""
        n = len(self.layout.vertices)
        return self.data.flexvert_xpos[self._flex_adr : self._flex_adr + n].copy()

    # -- ground truth ------------------------------------------------------------------------

    def true_rim(self, n_x: int | None = None) -> np.ndarray:
        rim = self.bag_vertices()[self.layout.rim]
        return rim if n_x is None else resample_closed(rim, n_x)

    def ground_truth(self) -> GroundTruth:
        rim = self.true_rim()
        return GroundTruth(
            time=self.time,
            rim=rim,
            rim_centroid=rim.mean(axis=0),
            rim_perimeter=closed_polyline_length(rim),
            object_pose=self._object_pose(),
            passed_through=self._passed,
            max_penetration_m=self._max_pen,
        )

    def _object_points(self) -> np.ndarray:
        obj = self.scenario.object
        if obj.shape is not None:
            return obj.shape.hull_points()
        v = obj.bottom_vertices()
        return np.vstack([v, v + [0.0, 0.0, obj.effective_height()]])

    def _object_pose(self) -> np.ndarray:
        s = self.scenario.object.shape
        return s.pose() if s is not None else make_transform(None, self.scenario.object.bottom_vertices().mean(axis=0))

    def _object_halfspaces(self) -> np.ndarray:
        return ConvexHull(self._object_points()).equations  # (m, 4): n.p + d <= 0 inside

    def _check_penetration(self) -> None:
        v = self.bag_vertices()
        depth = -(v @ self._hull[:, :3].T + self._hull[:, 3]).max(axis=1)  # > 0 inside, = distance to the nearest face
        pen = float(depth.max())
        self._max_pen = max(self._max_pen, pen)
        if pen > PENETRATION_TOL_M:
            self._passed = True

    # -- camera ------------------------------------------------------------------------------

    def render_rgbd(self, seq: int = 0) -> RgbdFrame:
        """A noisy RGB-D frame from the rig's camera (colour RGB uint8, depth uint16 in depth_scale units)."""
        if not self._camera_enabled:
            raise RuntimeError("this world was built without a camera")
        cam = self.rig.camera
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, cam.height, cam.width)
        r = self._renderer
        r.update_scene(self.data, camera="rgbd")
        r.disable_depth_rendering()
        color = r.render().copy()
        r.enable_depth_rendering()
        depth = r.render().astype(np.float64)
        r.disable_depth_rendering()
        rng = np.random.default_rng([self.seed, seq])
        depth = add_depth_noise(depth, self.noise, rng)
        info = cam.info()
        d = np.clip(np.round(depth / info.depth_scale), 0, 65535).astype(np.uint16)
        return RgbdFrame(seq=seq, camera=info, color=color, depth=d, stamp=self.time)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
