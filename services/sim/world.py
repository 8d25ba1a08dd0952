"""The simulated world: physics of the fabric bag, its two mounts, the object and the obstacles, the
RGB-D camera, and the ground truth that only tests and benchmarks may read.

The arms (services/sim/rig_sim.py, or any caller) move the mounts with `set_mount_targets`; within
each `step(dt)` a mount travels to its target at a steady pace (as an arm tracks a servo setpoint
over a control period), never faster than MAX_MOUNT_SPEED_MPS / MAX_MOUNT_SPEED_RPS, so no command
can make the fabric explode. Same scenario, rig, seed and calls: the same run, frames included.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass

import mujoco
import numpy as np

from bagit.common.errors import BadControlInput, BadScenario, SimulationFailed, WallLimitReached
from bagit.common.geometry import closed_polyline_length, make_transform, resample_closed
from bagit.common.messages import RgbdFrame
from bagit.common.mounts import rim_frame
from bagit.common.rig import ARMS, ArmName, RigConfig
from bagit.common.scenario import Scenario
from bagit.services.sim.bag import BagLayout, bag_layout
from bagit.services.sim.camera import DepthNoise, DrawsAhead, RgbdRenderer, add_depth_noise, depth_units
from bagit.services.sim.objects import object_mesh, object_parts, object_pose
from bagit.services.sim.scene import TIMESTEP, build_mjcf, scene_files
from bagit.services.sim.truth import GroundTruth, PenetrationMonitor

RIM_BELOW_OBJECT_M = 0.12  # default start: the rim this far below the object's lowest point ...
RIM_BESIDE_OBJECT_M = 0.15  # ... and this far beside it (towards +x, the camera's side)
MAX_MOUNT_SPEED_MPS = 1.5  # an arm's flange cannot move faster than this ...
MAX_MOUNT_SPEED_RPS = 3.0  # ... nor turn faster
# MuJoCo's warnings that the integration went unstable (each is followed by an automatic reset)
FAR_M = 20.0  # a bag vertex this far from the world origin has been flung off by an unstable step
INSTABILITY_WARNINGS = (mujoco.mjtWarning.mjWARN_BADQACC, mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL)


def _quat_of(R: np.ndarray) -> np.ndarray:
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=float).ravel())
    return q


def _mat_of(q: np.ndarray) -> np.ndarray:
    R = np.empty(9)
    mujoco.mju_quat2Mat(R, q)
    return R.reshape(3, 3)


def _slerp(q0: np.ndarray, q1: np.ndarray, f: float) -> np.ndarray:
    d = float(q0 @ q1)
    if d < 0:
        q1, d = -q1, -d
    if d > 1.0 - 1e-12:
        q = q0 + f * (q1 - q0)
    else:
        th = np.arccos(min(d, 1.0))
        q = (np.sin((1 - f) * th) * q0 + np.sin(f * th) * q1) / np.sin(th)
    return q / np.linalg.norm(q)


def _quat_angle(q0: np.ndarray, q1: np.ndarray) -> float:
    return 2.0 * float(np.arccos(min(abs(float(q0 @ q1)), 1.0)))


@dataclass(frozen=True)
class WorldState:
    """A snapshot of a SimWorld (physics state, mount targets, penetration record)."""

    data: mujoco.MjData
    target_pos: dict[ArmName, np.ndarray]
    target_quat: dict[ArmName, np.ndarray]
    max_depth: float
    passed: bool


class SimWorld:
    """MuJoCo world built from a scenario and a rig. Deterministic for a given scenario and seed.

    `model` and `data` are the MuJoCo objects (for the rig simulation and viewers); `layout` says
    which bag vertices are the rim and the handles.
    """

    def __init__(self, scenario: Scenario, rig: RigConfig | None = None, seed: int = 0, camera: bool = True):
        self.scenario = scenario
        self.rig = rig or RigConfig()
        self.seed = int(seed)
        R = scenario.bag.perimeter_m()
        g0 = scenario.bag.g0()
        if g0 is not None:
            # At g0's centroid, level: the bag hangs from mounts at one height (perception's solid-bag
            # segmenter expects a level rim, so g0's own tilt is not reproduced).
            frame = rim_frame(g0.mean(axis=0))
        else:
            pts = np.vstack([p.points for p in object_parts(scenario.object)])
            c = pts[:, :2].mean(axis=0) + [RIM_BESIDE_OBJECT_M, 0.0]
            frame = rim_frame(np.append(c, pts[:, 2].min() - RIM_BELOW_OBJECT_M))
        self.layout: BagLayout = bag_layout(R, scenario.bag.depth, frame)
        self._check_start(scenario)
        self.model = mujoco.MjModel.from_xml_string(build_mjcf(scenario, self.rig, self.layout), assets=scene_files(scenario))
        self.data = mujoco.MjData(self.model)
        self._mocap = {name: int(self.model.body(f"mount_{name}").mocapid[0]) for name in ARMS}
        self._target_pos = {n: self.data.mocap_pos[i].copy() for n, i in self._mocap.items()}
        self._target_quat = {n: self.data.mocap_quat[i].copy() for n, i in self._mocap.items()}
        flex_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_FLEX, "bag")
        self._vert_adr = int(self.model.flex_vertadr[flex_id])
        self._nvert = int(self.model.flex_vertnum[flex_id])
        self._monitor = PenetrationMonitor(object_parts(scenario.object), self.layout.elements)
        # which clamp (connect constraint) belongs to which mount, for mount_forces()
        mount_body = {int(self.model.body(f"mount_{n}").id): n for n in ARMS}
        self._eq_mount = np.array([mount_body.get(int(b), "") for b in self.model.eq_obj1id])
        self._camera_enabled = camera
        self._renderer: RgbdRenderer | None = None
        self._draws = DrawsAhead()  # the next frame's noise draws, made while the world steps
        self.noise = DepthNoise().scaled(scenario.sim.camera.depth_noise)
        self.failure: str | None = None  # why the physics went unstable (then step() refuses to go on)
        # A host's wall-clock deadline (time.perf_counter()): step() stops at the physics step that passes it.
        # MuJoCo's contact solver can crawl for seconds a step on a bunched-up stiff bag, and a host that
        # checks its wall limit only between its own steps would wait out the whole of a long one.
        self.wall_deadline: float | None = None
        # live views of MuJoCo's instability warning counters (indexing data.warning anew costs ~20 us a step)
        self._warnings = [self.data.warning[w] for w in INSTABILITY_WARNINGS]
        mujoco.mj_forward(self.model, self.data)

    def _check_start(self, scenario: Scenario) -> None:
        """The bag must start clear of the table and of the object, or nothing that follows is physical."""
        v = self.layout.vertices
        if v[:, 2].min() < self.rig.table_height + 0.005:
            raise BadScenario(
                f"{scenario.name}: the bag ({scenario.bag.depth:.2f} m deep) hanging from its start rim at z = "
                f"{v[self.layout.rim, 2].mean():.2f} m would reach through the table at z = {self.rig.table_height:.2f} m"
            )
        inside = max(float(p.depth(v).max()) for p in object_parts(scenario.object))
        if inside > 0:
            raise BadScenario(f"{scenario.name}: the bag's start shape cuts {inside * 1000:.0f} mm into the object; start the rim clear of it")

    # -- physics -----------------------------------------------------------------------------

    @property
    def time(self) -> float:
        """Simulated seconds since the start."""
        return float(self.data.time)

    def step(self, dt: float) -> None:
        """Advance `dt` seconds of simulated time, in whole physics steps of TIMESTEP (at least one for dt > 0)."""
        if not np.isfinite(dt) or dt < 0 or dt > 3600:
            raise BadControlInput(f"step needs a finite dt in [0, 3600] s, got {dt}")
        if self.failure is not None:
            raise SimulationFailed(f"the simulation failed earlier and cannot go on: {self.failure}")
        n = int(round(dt / TIMESTEP))
        if n == 0 and dt > 0:
            n = 1
        before = self._warning_counts()
        for k in range(n):
            self._advance_mounts(n - k)
            try:
                mujoco.mj_step(self.model, self.data)
            except mujoco.FatalError as e:  # e.g. the contact solver's arena overflowing on a bunched-up bag
                self.failure = f"the simulation stopped at t = {self.time:.3f} s: MuJoCo: {str(e).splitlines()[0]}"
                raise SimulationFailed(self.failure) from None
            verts = self.data.flexvert_xpos[self._vert_adr : self._vert_adr + self._nvert]
            # MuJoCo answers bad accelerations, positions or velocities by resetting the world and
            # carrying on; a reset or non-finite world must end the run, not feed it a teleported bag.
            # (a non-finite vertex makes the largest |coordinate| NaN or inf: not <= FAR_M)
            now = self._warning_counts()
            if now != before or not np.abs(verts).max() <= FAR_M or not np.isfinite(self.data.qvel).all():
                self.failure = self._describe_failure(before, now)
                raise SimulationFailed(self.failure)
            self._monitor.update(verts)
            if self.wall_deadline is not None and time.perf_counter() > self.wall_deadline:
                raise WallLimitReached(f"the wall-time limit passed at t = {self.time:.3f} s simulated (the contact solver crawls?)")

    def pass_time(self, dt: float) -> None:
        """Advance the clock by `dt` (whole steps of TIMESTEP, as `step` counts them) with nothing moving:
        the world at rest (`SimRig.idle`)."""
        for _ in range(max(1, int(round(dt / TIMESTEP)))):
            self.data.time += TIMESTEP

    def set_time(self, t: float) -> None:
        """The clock at `t` with nothing moving: a settled world begun again (`SimRig.resettle`)."""
        self.data.time = float(t)

    def _warning_counts(self) -> tuple[int, ...]:
        return tuple(int(w.number) for w in self._warnings)

    def _describe_failure(self, before: tuple[int, ...], now: tuple[int, ...]) -> str:
        fired = [w.name.removeprefix("mjWARN_") for w, a, b in zip(INSTABILITY_WARNINGS, before, now, strict=False) if b != a]
        verts = self.bag_vertices()
        if fired:
            what = f"MuJoCo warned of {', '.join(fired)}"
        elif np.all(np.isfinite(verts)) and np.abs(verts).max() > FAR_M:
            what = f"a bag vertex flew {np.abs(verts).max():.0f} m away"
        else:
            what = "the state became non-finite"
        return f"the simulated fabric went unstable at t = {self.time:.3f} s ({what}; torn by the mounts?)"

    def _advance_mounts(self, remaining: int) -> None:
        """Move each mount 1/remaining of the way to its target, within the speed limits."""
        for name, i in self._mocap.items():
            pos, quat = self.data.mocap_pos[i], self.data.mocap_quat[i]
            dp = self._target_pos[name] - pos
            dist = float(np.linalg.norm(dp))
            if dist > 0:
                step = min(dist / remaining, MAX_MOUNT_SPEED_MPS * TIMESTEP)
                self.data.mocap_pos[i] = self._target_pos[name] if step >= dist else pos + dp * (step / dist)
            ang = _quat_angle(quat, self._target_quat[name])
            if ang > 0:
                turn = min(ang / remaining, MAX_MOUNT_SPEED_RPS * TIMESTEP)
                self.data.mocap_quat[i] = self._target_quat[name] if turn >= ang else _slerp(quat.copy(), self._target_quat[name], turn / ang)

    def save_state(self) -> WorldState:
        """A snapshot to branch from (e.g. to try several mount moves from one bag state)."""
        data = mujoco.MjData(self.model)
        mujoco.mj_copyData(data, self.model, self.data)
        return WorldState(
            data,
            {k: v.copy() for k, v in self._target_pos.items()},
            {k: v.copy() for k, v in self._target_quat.items()},
            self._monitor.max_depth,
            self._monitor.passed,
        )

    def restore_state(self, state: WorldState) -> None:
        """Go back to a snapshot from `save_state` of this world; stepping on replays exactly."""
        mujoco.mj_copyData(self.data, self.model, state.data)
        self._target_pos = {k: v.copy() for k, v in state.target_pos.items()}
        self._target_quat = {k: v.copy() for k, v in state.target_quat.items()}
        self._monitor.max_depth, self._monitor.passed = state.max_depth, state.passed
        self.failure = None  # a snapshot is a world that was still stable

    def mount_home_poses(self) -> dict[ArmName, np.ndarray]:
        """Where the mounts start: 'left'/'right' -> (4, 4) world <- mount (tool axis z into the bag)."""
        return {k: v.copy() for k, v in self.layout.mount_home.items()}

    def set_mount_targets(self, T_world_mount: Mapping[ArmName, np.ndarray]) -> None:
        """The mounts go to these poses ('left'/'right' -> (4, 4) world <- mount) over the next step."""
        checked: dict[ArmName, np.ndarray] = {}
        for name, T in T_world_mount.items():
            if name not in self._mocap:
                raise BadControlInput(f"no mount named {name!r} (have {', '.join(self._mocap)})")
            T = np.asarray(T, dtype=float)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise BadControlInput(f"mount target for {name} must be a finite 4x4 transform")
            R = T[:3, :3]
            if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0 or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
                raise BadControlInput(f"mount target for {name} is not a rigid transform")
            checked[name] = T
        for name, T in checked.items():
            self._target_pos[name] = T[:3, 3].copy()
            self._target_quat[name] = _quat_of(T[:3, :3])

    def mount_poses(self) -> dict[ArmName, np.ndarray]:
        """Where the mounts are now: 'left'/'right' -> (4, 4) world <- mount."""
        return {n: make_transform(_mat_of(self.data.mocap_quat[i]), self.data.mocap_pos[i].copy()) for n, i in self._mocap.items()}

    def mount_forces(self) -> dict[ArmName, np.ndarray]:
        """'left'/'right' -> (3,) the force (N, world) the bag pulls on each mount with, through its
        clamps: what an arm's joint torques would feel (about the bag's weight at rest; far more once
        the arms stretch the rim taut)."""
        d = self.data
        rows = np.nonzero(np.asarray(d.efc_type) == mujoco.mjtConstraint.mjCNSTR_EQUALITY)[0]
        out: dict[ArmName, np.ndarray] = {}
        for name in ARMS:
            mine = rows[self._eq_mount[np.asarray(d.efc_id)[rows]] == name]
            out[name] = np.asarray(d.efc_force)[mine].reshape(-1, 3).sum(axis=0) if len(mine) else np.zeros(3)
        return out

    def bag_vertices(self) -> np.ndarray:
        """All bag vertices `(n, 3)`, world frame."""
        return self.data.flexvert_xpos[self._vert_adr : self._vert_adr + self._nvert].copy()

    # -- ground truth (tests and benchmarks only) --------------------------------------------

    def true_rim(self, n_x: int | None = None) -> np.ndarray:
        """The true rim `(N_AROUND, 3)` (its vertices in order), or resampled to `(n_x, 3)` by arc length."""
        rim = self.data.flexvert_xpos[self._vert_adr + self.layout.rim].copy()
        return rim if n_x is None else resample_closed(rim, n_x)

    def ground_truth(self) -> GroundTruth:
        rim = self.true_rim()
        return GroundTruth(
            time=self.time,
            rim=rim,
            rim_centroid=rim.mean(axis=0),
            rim_perimeter=closed_polyline_length(rim),
            object_pose=object_pose(self.scenario.object),
            object_vertices=self.scenario.object.bottom_vertices(),
            passed_through=self._monitor.passed,
            max_penetration_m=max(self._monitor.max_depth, 0.0),
            clearance_m=-self._clearance_depth(),
            mount_poses=self.mount_poses(),
        )

    def _clearance_depth(self) -> float:
        """The fabric's deepest point inside the object now: the monitor's from the last physics step (the
        vertices move only in `step`), measured afresh before the first."""
        d = self._monitor.last_depth
        return self._monitor.depth(self.bag_vertices()) if d is None else d

    def object_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """The object for display: vertices `(n, 3)` (world) and triangles `(m, 3)`."""
        return object_mesh(self.scenario.object)

    # -- camera ------------------------------------------------------------------------------

    def render_rgbd(self, seq: int = 0) -> RgbdFrame:
        """A noisy RGB-D frame from the rig's camera (colour RGB uint8, depth uint16 in depth_scale units,
        0 = no return), stamped with the simulated time; the noise is seeded by (world seed, seq)."""
        color, z = self.render_true()
        info = self.rig.camera.info()
        depth = depth_units(self.noisy_depth(z, seq), info.depth_scale)
        return RgbdFrame(seq=int(seq), camera=info, color=color, depth=depth, stamp=self.time)

    def render_true(self) -> tuple[np.ndarray, np.ndarray]:
        """The camera's render: colour `(H, W, 3)` uint8 and noise-free metric depth `(H, W)` float32."""
        if not self._camera_enabled:
            raise RuntimeError("this world was built without a camera (camera=False)")
        if self._renderer is None:
            self._renderer = RgbdRenderer(self.model, self.rig.camera)
        return self._renderer.render(self.data)

    def noisy_depth(self, z: np.ndarray, seq: int) -> np.ndarray:
        """Frame `seq`'s noisy metric depth `(H, W)` float32 from `render_true`'s depth `z (H, W)`, drawn from
        np.random.default_rng([world seed, seq]); the draws of frame seq + 1 are then made while the world steps."""
        if self._renderer is None:
            raise RuntimeError("render_true first: the noise needs the camera's rays")
        if not self.noise.enabled:
            return add_depth_noise(z, self.noise, None, self._renderer.rays)
        draws = self._draws.take(self.seed, int(seq), z.shape)
        out = add_depth_noise(z, self.noise, None, self._renderer.rays, draws)
        self._draws.ahead(self.seed, int(seq) + 1, z.shape)  # after the noise, whose bands share the worker
        return out

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> SimWorld:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
