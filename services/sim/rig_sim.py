"""The simulated rig: the physics world with its two CR5 controllers bolted to the bag's mounts.

`SimRig(scenario, rig, seed)` builds the world (bagit.services.sim.world.SimWorld), puts each arm
in the joint configuration that holds its mount where the world starts it (T_world_base @ fk(q) @
T_flange_mount == the mount's home pose), and from then on the mounts follow the arms' flanges:
each physics step first advances both controllers, then sets the mount targets from their
flanges, then steps the world. With `with_servers=True` each arm is also reachable over Dobot's
TCP/IP protocol V4 on the rig config's ports (or free ports with `ephemeral_ports=True`), so an
arm driver can talk to it as to a real CR5. `run_realtime(speed)` paces the loop to the wall
clock (speed 2 = twice real time) for such clients.

The Python API (`arms['left'].servo_p(...)`, `step`, `render_rgbd`, `ground_truth`) serves tests
and the in-process pipeline; ground truth is for tests and benchmarks only.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from bagit.common import cr5
from bagit.common.clock import SIM_EPOCH0_S, next_epoch, sim_time
from bagit.common.errors import BadScenario
from bagit.common.geometry import invert_transform
from bagit.common.messages import RgbdFrame
from bagit.common.rig import ARMS, ArmName, RigConfig
from bagit.common.scenario import Scenario
from bagit.services.sim.cr5_sim import SimulatedCR5
from bagit.services.sim.dobot_server import DobotControllerServer
from bagit.services.sim.scene import TIMESTEP as WORLD_STEP_S

SETTLE_S = 1.0  # simulated seconds the bag hangs still after a (re)set before the camera's first frame
REST_AFTER_S = SETTLE_S  # between runs in lockstep: the physics steps on this long after an arm last moved (`idle`)
SETTLE_CHUNK_STEPS = 10  # `SimRig.settle` with a `between`: world steps between its calls
WALL_FPS = 10.0  # on the wall clock: camera frames per simulated second a 2-core machine keeps up with beside every service


def camera_fps(fps: float | None, lockstep: bool, rate_hz: float) -> float:
    """Camera frames per simulated second: `fps` when given; else in lockstep the run's control rate
    `rate_hz` (a frame per control tick, as `bagit run` takes them), WALL_FPS on the wall clock."""
    return fps or (rate_hz if lockstep else WALL_FPS)


class World(Protocol):
    """What SimRig needs of the physics world (SimWorld provides it)."""

    wall_deadline: float | None  # a host's wall-clock deadline (time.perf_counter()): step() stops past it

    @property
    def time(self) -> float: ...

    def step(self, dt: float) -> None: ...
    def pass_time(self, dt: float) -> None: ...
    def set_time(self, t: float) -> None: ...
    def mount_home_poses(self) -> dict[ArmName, np.ndarray]: ...
    def set_mount_targets(self, T_world_mount: Mapping[ArmName, np.ndarray]) -> None: ...
    def mount_poses(self) -> dict[ArmName, np.ndarray]: ...
    def render_rgbd(self, seq: int = 0) -> RgbdFrame: ...
    def ground_truth(self) -> Any: ...
    def true_rim(self, n_x: int | None = None) -> np.ndarray: ...  # ground truth too (the in-process host's result)
    def close(self) -> None: ...


def natural_ik(T_base_flange: np.ndarray) -> np.ndarray | None:
    """The joint angles an operator would pick to hold a flange pose: shoulder facing the target,
    elbow above the shoulder, no self-collision, then the least-wound of those; None if unreachable.
    """
    sols = cr5.ik_all(T_base_flange)
    if len(sols) == 0:
        return None
    p = T_base_flange[:3, 3]
    facing = np.arctan2(p[1], p[0])
    best, best_cost = None, np.inf
    for q in sols:
        F = cr5.link_frames(q)
        if cr5.self_collision(q) or not cr5.within_limits(q):
            continue
        # the upper arm's direction (shoulder -> elbow) and the target's bearing
        elbow = F[2][:3, 3]
        bearing = np.arctan2(elbow[1], elbow[0]) if np.hypot(elbow[0], elbow[1]) > 1e-6 else facing
        turned = abs(np.angle(np.exp(1j * (bearing - facing)))) > np.pi / 2
        low_elbow = elbow[2] < cr5.D1
        cost = 100.0 * turned + 10.0 * low_elbow + float(np.sum(q**2))
        if cost < best_cost:
            best, best_cost = q, cost
    return best


@dataclass
class RealtimeStats:
    sim_s: float
    wall_s: float
    realtime_factor: float
    frames: int


def _world_key(scenario: Scenario | None, seed: int) -> tuple[str, int] | None:
    """What a world is built from (the rig aside, which a SimRig keeps): its scenario, whole, and its seed."""
    return None if scenario is None else (scenario.model_dump_json(), int(seed))


@dataclass(frozen=True)
class _Settled:
    """A world just built, as `SimRig.settle` left it: what it was built from, the settle, the world's time
    and physics steps after it, and where the arms held."""

    key: tuple[str, int]
    dt: float
    world_t: float
    physics_steps: int
    start: dict[ArmName, np.ndarray]


class SimRig:
    """The world plus two SimulatedCR5s (and, optionally, their TCP servers)."""

    def __init__(
        self,
        scenario: Scenario | None = None,
        rig: RigConfig | None = None,
        seed: int = 0,
        camera: bool = True,
        with_servers: bool = False,
        ephemeral_ports: bool = False,
        world: World | None = None,
    ):
        self.rig = rig or RigConfig()
        self._built = _world_key(scenario, seed) if world is None else None  # the world's scenario and seed (None: given a world)
        if world is None:
            if scenario is None:
                raise BadScenario("SimRig needs a scenario or a world")
            from bagit.services.sim.world import SimWorld  # MuJoCo loads only when a real world is wanted

            world = SimWorld(scenario, self.rig, seed, camera=camera)
        self.world: World = world
        self.camera = camera
        self.arms: dict[ArmName, SimulatedCR5] = {}
        try:
            start = self._start_angles(self.world)
        except BadScenario:
            self.world.close()
            raise
        for name in ARMS:
            self.arms[name] = SimulatedCR5(self.rig.arms[name], q0=start[name], name=name)
        self.servers: dict[ArmName, DobotControllerServer] = {}
        self.epoch = SIM_EPOCH0_S  # the rig's clock when this world's time began (see `clock_s`)
        self._stamp_feedback = False
        self._on_servo: Callable[[], None] | None = None
        self._loop_lock = threading.Lock()
        self._synced_q: dict[ArmName, np.ndarray] = {}
        self._physics_steps = 0  # the world's physics steps since it was built
        self._settled: _Settled | None = None  # how `settle` left a world just built (`resettle`)
        if with_servers:
            self.start_servers(ephemeral_ports)
        self._sync_mounts()
        self._still_s = REST_AFTER_S  # simulated seconds since an arm last moved (`idle`): a world just built is at rest

    def _start_angles(self, world: World) -> dict[ArmName, np.ndarray]:
        """Each arm's joints holding its mount where `world` starts it; BadScenario if out of reach."""
        homes = world.mount_home_poses()
        out: dict[ArmName, np.ndarray] = {}
        for name in ARMS:
            arm = self.rig.arms[name]
            T_bf = invert_transform(arm.T_world_base()) @ homes[name] @ invert_transform(arm.T_flange_mount())
            q = natural_ik(T_bf)
            if q is None:
                d = np.linalg.norm(T_bf[:3, 3])
                raise BadScenario(f"the {name} mount starts {d:.2f} m from its CR5's base, out of the arm's reach; move the base in the rig config")
            out[name] = q
        return out

    def reset(self, scenario: Scenario, seed: int = 0, world: World | None = None) -> None:
        """A new world for `scenario` with the arms re-placed at its start; the controllers and
        their TCP servers (and their clients' connections) stay. On BadScenario the old world stays."""
        built = world is None
        if world is None:
            from bagit.services.sim.world import SimWorld

            world = SimWorld(scenario, self.rig, seed, camera=self.camera)
        try:
            start = self._start_angles(world)
        except BadScenario:
            world.close()
            raise
        with self._loop_lock:
            old, self.world = self.world, world
            self._begin(start)
            self._built = _world_key(scenario, seed) if built else None
            self._physics_steps, self._settled = 0, None
        old.close()

    def _begin(self, start: Mapping[ArmName, np.ndarray]) -> None:
        """(With the loop lock held.) The world's time begins again: a new epoch, the arms re-placed at
        `start`, their clocks stamped from the world's time 0, the mounts on them."""
        self.epoch = next_epoch(self.clock_s)  # the new world's time begins at 0: the clock goes on
        for name, q in start.items():
            self.arms[name].teleport(q)
        self._sync_clock_offsets(0.0)
        self._synced_q = {}
        self._sync_mounts()
        self._still_s = REST_AFTER_S

    def settle(self, dt: float, between: Callable[[], None] | None = None) -> None:
        """`step(dt)` after a (re)set: the bag comes to hang still from the held arms. A world built and
        settled so, and not stepped since, can stand in for a reset to it and its settle (`resettle`).
        `between()` is called every SETTLE_CHUNK_STEPS steps (the same steps; a lockstep simulator at start
        pushes the controllers' feedback, which an arm driver bringing its arms up waits for)."""
        key, start = self._built, None
        if key is not None and self._physics_steps == 0 and self.world.time == 0.0:  # built and untouched
            start = self._start_angles(self.world)  # where a reset to this world puts the arms
        n = max(1, int(round(dt / WORLD_STEP_S)))
        chunk = n if between is None else SETTLE_CHUNK_STEPS
        for k in range(0, n, chunk):
            self._advance(min(chunk, n - k) * WORLD_STEP_S, rest=False)
            if between is not None:
                between()
        if key is not None and start is not None and self._held(start):
            self._settled = _Settled(key, dt, self.world.time, self._physics_steps, start)

    def _held(self, q: Mapping[ArmName, np.ndarray]) -> bool:
        """Both arms at `q` now, and their mounts set from there (`_sync_mounts`)."""
        return all(n in self._synced_q and np.array_equal(self._synced_q[n], q[n]) and np.array_equal(self.arms[n].q, q[n]) for n in ARMS)

    def resettle(self, scenario: Scenario, seed: int, dt: float) -> bool:
        """`reset(scenario, seed)` then `settle(dt)`, the world's part already done: True if this world is
        `scenario` at `seed`, settled `dt` right after it was built and not stepped since (the simulator
        settles the world it starts with, which `bagit up SCENARIO` runs first, while the services start).
        The world is then as the reset and settle would leave it, bit for bit: a held arm does not move
        after its teleport, so its mount stood still through the world's settle whenever that ran, and the
        arms' controllers step now as they would have stepped beside it. False, nothing done, otherwise."""
        s = self._settled
        if s is None or s.key != _world_key(scenario, seed) or s.dt != dt or s.physics_steps != self._physics_steps:
            return False
        with self._loop_lock:
            self._settled = None
            self._begin(s.start)
            moved = False
            for _ in range(max(1, int(round(dt / WORLD_STEP_S)))):  # `_advance`'s steps, the world's left out
                for robot in self.arms.values():
                    robot.step(WORLD_STEP_S)
                moved = self._sync_mounts() or moved
                self._still_s += WORLD_STEP_S
            self.world.set_time(s.world_t)
        if moved:  # an arm moved while its controller stepped (a command came): the settle was not this one
            self.reset(scenario, seed)
            self.step(dt)
        return True

    # -- servers ---------------------------------------------------------------------------------

    def start_servers(self, ephemeral_ports: bool = False) -> dict[ArmName, tuple[int, int]]:
        """Serve both arms over TCP; returns 'left'/'right' -> (dashboard port, feedback port)."""
        for name, robot in self.arms.items():
            if name in self.servers:
                continue
            arm = self.rig.arms[name]
            ports = (0, 0) if ephemeral_ports else (arm.dashboard_port, arm.feedback_port)
            try:
                self.servers[name] = DobotControllerServer(robot, arm.host, *ports).start()
            except OSError:
                self.stop_servers()
                raise
        self._configure_servers()
        return self.ports()

    def _configure_servers(self) -> None:
        """Lockstep: feedback only when the world steps (`push_feedback`), and who hears of a servo command."""
        for server in self.servers.values():
            server.periodic_push = not self._stamp_feedback
            server.on_servo = self._on_servo

    def ports(self) -> dict[ArmName, tuple[int, int]]:
        return {name: (s.dashboard_port, s.feedback_port) for name, s in self.servers.items()}

    def stop_servers(self) -> None:
        for s in self.servers.values():
            s.stop()
        self.servers.clear()

    # -- simulation ------------------------------------------------------------------------------

    @property
    def time(self) -> float:
        """The world's time (back to 0 at each reset)."""
        return float(self.world.time)

    @property
    def clock_s(self) -> float:
        """The rig's clock: the world's time from this world's epoch (`sim_time`), which never goes back."""
        return sim_time(float(self.world.time), self.epoch)

    def stamp_feedback(self, on: bool = True, on_servo: Callable[[], None] | None = None) -> None:
        """Have the simulated controllers stamp their feedback on the rig's clock (lockstep) or the wall's;
        in lockstep their feedback goes out after each step only, and `on_servo` hears of each servo command."""
        self._stamp_feedback = on
        self._on_servo = on_servo
        self._sync_clock_offsets()
        self._configure_servers()

    def _sync_clock_offsets(self, world_t: float | None = None) -> None:
        """Each controller's stamps on the rig's clock (lockstep): the world at `world_t` (None: now) is its time now."""
        t = float(self.world.time) if world_t is None else world_t
        for robot in self.arms.values():
            robot.clock_offset = (self.epoch + t - robot.time) if self._stamp_feedback else None

    def servo_counts(self) -> dict[str, int]:
        """Each simulated controller's servo commands (ServoP/ServoJ) received so far."""
        return {name: robot.servo_commands for name, robot in self.arms.items()}

    def push_feedback(self) -> None:
        """Each served controller's feedback packet now (a lockstep step is over: its driver may cycle)."""
        for server in self.servers.values():
            server.push_feedback()

    def _sync_mounts(self) -> bool:
        """Mount targets from the flanges; only the arms whose joints moved are sent (setting one is not free);
        an arm that moved restarts the count of `idle`'s stillness. True if one moved."""
        moved: dict[ArmName, np.ndarray] = {}
        for name, robot in self.arms.items():
            q = robot.q
            if name not in self._synced_q or not np.array_equal(q, self._synced_q[name]):
                self._synced_q[name] = q
                moved[name] = robot.mount_pose_world()
        if moved:
            self.world.set_mount_targets(moved)
            self._still_s = 0.0
        return bool(moved)

    def step(self, dt: float) -> None:
        """Advance `dt` seconds (rounded to whole world steps): controllers, then mounts, then physics."""
        self._advance(dt, rest=False)

    def idle(self, dt: float) -> None:
        """`step` between runs in lockstep, where nothing waits on the world: once no arm has moved for
        REST_AFTER_S (and in a world just built) the world is at rest, and only the controllers and the
        world's clock go on; the physics steps again from the step an arm moves. Its contact solver took
        ~0.6 of a core at real time (a 2-core VM) to move a bag hanging from still mounts, while the
        services start beside it; a run's reset builds its world anew."""
        self._advance(dt, rest=True)

    def _advance(self, dt: float, rest: bool) -> None:
        n = max(1, int(round(dt / WORLD_STEP_S)))
        with self._loop_lock:
            for _ in range(n):
                for robot in self.arms.values():
                    robot.step(WORLD_STEP_S)
                self._sync_mounts()
                if rest and self._still_s >= REST_AFTER_S:
                    self.world.pass_time(WORLD_STEP_S)
                else:
                    self.world.step(WORLD_STEP_S)
                    self._still_s += WORLD_STEP_S
                    self._physics_steps += 1

    def render_rgbd(self, seq: int = 0) -> RgbdFrame:
        """A camera frame, stamped on the rig's clock (`clock_s`)."""
        frame = self.world.render_rgbd(seq)
        frame.stamp = self.clock_s
        return frame

    def ground_truth(self) -> Any:
        """The world's ground truth (tests and benchmarks only)."""
        return self.world.ground_truth()

    def flange_poses(self) -> dict[ArmName, np.ndarray]:
        """'left'/'right' -> 4x4 world <- flange (the perception benchmark moves the bag by them)."""
        return {name: robot.flange_pose_world() for name, robot in self.arms.items()}

    def run_realtime(
        self,
        speed: float = 1.0,
        duration: float | None = None,
        stop: threading.Event | None = None,
        on_frame: Callable[[RgbdFrame], None] | None = None,
        on_progress: Callable[[RealtimeStats], None] | None = None,
        chunk_s: float = 0.02,
        progress_every_s: float = 1.0,
        fps: float | None = None,
    ) -> RealtimeStats:
        """Step in chunks paced so that simulated time runs `speed` times the wall clock.

        If the machine cannot keep up, the loop runs flat out and the returned realtime factor says
        so. `on_frame` gets a camera frame `fps` times per simulated second (default: the camera's
        rate); `stop` ends the loop.
        """
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        stop = stop or threading.Event()
        fps = fps or self.rig.camera.fps
        t_sim0, t_wall0 = self.time, time.monotonic()
        next_frame, next_report, frames = self.time, self.time + progress_every_s, 0

        def stats() -> RealtimeStats:
            sim, wall = self.time - t_sim0, time.monotonic() - t_wall0
            return RealtimeStats(sim, wall, sim / wall if wall > 0 else 0.0, frames)

        while not stop.is_set() and (duration is None or self.time - t_sim0 < duration - 1e-9):
            self.step(chunk_s)
            if on_frame is not None and self.time >= next_frame - 1e-9:
                on_frame(self.render_rgbd(frames))
                frames += 1
                next_frame += 1.0 / fps
            if on_progress is not None and self.time >= next_report:
                on_progress(stats())
                next_report += progress_every_s
            ahead = (self.time - t_sim0) / speed - (time.monotonic() - t_wall0)
            if ahead > 0:
                stop.wait(ahead)
        return stats()

    def close(self) -> None:
        self.stop_servers()
        self.world.close()

    def __enter__(self) -> SimRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
