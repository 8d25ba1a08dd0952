"""A simulated CR5 controller: its state machine, motion queue, servo tracking and feedback packet.

What it models, and why:
- States as Dobot reports them: disabled (4) after power-up, enabled and idle (5), running (7)
  while a queued motion or a servo target is being followed, error (9) while an alarm is latched.
  An emergency stop disables the arm and latches alarm 132 until it is released and cleared.
- MovJ/MovL are queued, get a command id, and run one after another: MovJ along a quintic in joint
  space, MovL along a straight line with the orientation slerped, both timed by the joint or
  Cartesian speed limits scaled by SpeedFactor and the command's `v`.
- ServoJ/ServoP set a target to reach in `t` seconds; the reference ramps there linearly (QTarget),
  and the joints follow it through a critically damped second-order loop whose bandwidth grows
  with `gain` (40 rad/s at 500) and which feeds forward `aheadtime`/100 of the reference velocity,
  clipped to the joint speed (180°/s) and acceleration (`cr5.JOINT_ACCEL_LIMIT`) limits. At the defaults a steady motion
  trails its reference by about 25 ms, on top of the `t` the target itself takes.
- Targets the arm cannot take raise the alarms a real controller raises and stop the arm:
  no inverse solution (17), a solution beyond the joint limits (18, or 64..75 for a joint target),
  the flange or tool against the arm's own body (77), a servo step faster than a joint can go
  (48..53). The command that asked for it is answered -1 (not executed).

All public methods are thread-safe (the TCP servers call them from their socket threads while the
simulation loop calls `step`). Angles on this API are radians unless a name says `_deg`; the
protocol's degrees and millimetres are converted by the server and `fill_feedback`.
"""

from __future__ import annotations

import threading
import time as _time
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from bagit.common import cr5
from bagit.common.dobot import Alarm, ErrorId, RobotMode, joint_limit_alarm, new_feedback, overspeed_alarm
from bagit.common.rig import ArmConfig
from bagit.common.so3 import matrix_to_quat_wxyz, so3_log

SUBSTEP_S = 0.002
MOVL_IK_PERIOD_S = 0.005  # the Cartesian line is solved at this rate and joint-interpolated between
MOVJ_ACCEL = 6.0  # rad/s^2 at 100 %
MOVL_SPEED = 1.0  # m/s at 100 %
MOVL_ACCEL = 2.5  # m/s^2 at 100 %
MOVL_ANGULAR_SPEED = np.pi  # rad/s at 100 %
SERVO_OMEGA = 40.0  # rad/s, servo loop bandwidth at gain 500
SETTLE_RAD = 1e-4
READY_POSE_DEG = (0.0, 0.0, -90.0, 0.0, 90.0, 0.0)


@dataclass
class _Segment:
    """A queued motion: joint (MovJ) or Cartesian (MovL) from `q0` to the target over `duration` seconds."""

    cmd_id: int
    kind: str  # "joint" | "linear"
    q_goal: np.ndarray
    speed: float  # v/100
    accel: float  # a/100
    q0: np.ndarray | None = None
    T0: np.ndarray | None = None
    T1: np.ndarray | None = None
    slerp: Slerp | None = None
    duration: float = 0.0
    elapsed: float = 0.0
    knots: tuple[float, np.ndarray, float, np.ndarray] | None = None  # (t0, q0, t1, q1) of the line's IK


@dataclass
class _Servo:
    """A streamed target: the reference moves from `start` to `goal` in `t` seconds."""

    start: np.ndarray
    goal: np.ndarray
    t: float
    elapsed: float
    omega: float
    feedforward: float


def _quintic(tau: float) -> tuple[float, float]:
    """Position and velocity (per unit duration) of the rest-to-rest quintic at tau in [0, 1]."""
    tau = min(max(tau, 0.0), 1.0)
    return 10 * tau**3 - 15 * tau**4 + 6 * tau**5, 30 * tau**2 - 60 * tau**3 + 30 * tau**4


class SimulatedCR5:
    """One CR5 controller and arm. `arm` places its base in the world; `q0 (6,)` rad is where it starts."""

    def __init__(self, arm: ArmConfig | None = None, q0: np.ndarray | None = None, name: str = "cr5"):
        self.arm = arm or ArmConfig(base_position=(0.0, 0.0, 0.0), base_rpy=(0.0, 0.0, 0.0))
        self.name = name
        self._lock = threading.RLock()
        q = np.radians(READY_POSE_DEG) if q0 is None else np.asarray(q0, dtype=float)
        if q.shape != (6,) or not cr5.within_limits(q):
            raise ValueError(f"{name}: start angles {np.degrees(q).round(1).tolist()} deg are not within the CR5's limits")
        self._q = q.copy()
        self._qd = np.zeros(6)
        self._q_ref = q.copy()
        self._q_ref_checked = q.copy()
        self._qd_ref = np.zeros(6)
        self._T_world_base = self.arm.T_world_base()
        self._T_flange_mount = self.arm.T_flange_mount()
        self._tool_offset = np.asarray(self.arm.mount_offset, dtype=float)
        self.time = 0.0
        self._boot_wall = _time.time()
        # On the rig's simulated clock (`bagit up`'s lockstep) the feedback's TimeStamp is the rig's
        # clock, this controller's time + `clock_offset`: the driver then knows which step a packet shows.
        self.clock_offset: float | None = None
        self.servo_commands = 0  # ServoP/ServoJ received: the simulator's lockstep waits for a tick's to land
        self._enabled = False
        self._estop = False
        self._alarms: list[int] = []
        # why each alarm was raised, for the operator's log (GetErrorID has only the ids): (sim time, id, detail)
        self.alarm_log: deque[tuple[float, int, str]] = deque(maxlen=50)
        self._speed_factor = int(self.arm.speed_factor)
        self._load = 0.0
        self._center = np.zeros(3)
        self._queue: deque[_Segment] = deque()
        self._active: _Segment | None = None
        self._servo: _Servo | None = None
        self._next_id = 1
        self._current_id = 0

    # -- state -----------------------------------------------------------------------------------

    @property
    def q(self) -> np.ndarray:
        with self._lock:
            return self._q.copy()

    @property
    def qd(self) -> np.ndarray:
        with self._lock:
            return self._qd.copy()

    @property
    def enabled(self) -> bool:
        return self._enabled

    @property
    def estop_pressed(self) -> bool:
        return self._estop

    @property
    def speed_factor(self) -> int:
        return self._speed_factor

    @property
    def current_command_id(self) -> int:
        return self._current_id

    def alarms(self) -> list[int]:
        with self._lock:
            return list(self._alarms)

    def _moving(self) -> bool:
        if self._active is not None or self._queue:
            return True
        if self._servo is not None and self._servo.elapsed < self._servo.t:
            return True
        return bool(np.max(np.abs(self._q_ref - self._q)) > SETTLE_RAD or np.max(np.abs(self._qd)) > 1e-3)

    def robot_mode(self) -> int:
        with self._lock:
            if self._alarms:
                return int(RobotMode.ERROR)
            if not self._enabled:
                return int(RobotMode.DISABLED)
            return int(RobotMode.RUNNING if self._moving() else RobotMode.ENABLE)

    def gate(self, allowed_in_error: bool = False, allowed_in_estop: bool = False) -> int:
        """The refusal code for a command in the current state (0 = may run), per the V4 rules."""
        with self._lock:
            if self._estop and not allowed_in_estop:
                return int(ErrorId.EMERGENCY_STOP)
            if self._alarms and not allowed_in_error:
                return int(ErrorId.IN_ERROR)
            return int(ErrorId.OK)

    # -- dashboard commands ----------------------------------------------------------------------

    def enable(self, load: float | None = None, center: np.ndarray | None = None) -> int:
        with self._lock:
            if (code := self.gate()) != 0:
                return code
            if load is not None:
                self._load = float(load)
            if center is not None:
                self._center = np.asarray(center, dtype=float)
            self._enabled = True
            self._hold()
            return 0

    def disable(self) -> int:
        with self._lock:
            if (code := self.gate()) != 0:
                return code
            self._enabled = False
            self._hold()
            return 0

    def clear_error(self) -> int:
        """Clears every alarm whose cause is gone (the e-stop alarm stays while the button is pressed)."""
        with self._lock:
            self._alarms = [a for a in self._alarms if self._estop and a == Alarm.SOFTWARE_ESTOP]
            return 0

    def emergency_stop(self, pressed: bool) -> int:
        with self._lock:
            if pressed:
                self._estop = True
                self._enabled = False
                self._raise(int(Alarm.SOFTWARE_ESTOP))
            else:
                self._estop = False
            return 0

    def set_speed_factor(self, ratio: int) -> int:
        with self._lock:
            if (code := self.gate()) != 0:
                return code
            self._speed_factor = int(ratio)
            return 0

    def stop(self) -> int:
        """Stop the queue and any servo target (Stop()); always allowed, in error and e-stop too."""
        with self._lock:
            self._hold()
            return 0

    def get_angle_deg(self) -> np.ndarray:
        with self._lock:
            return np.degrees(self._q)

    def get_pose6(self) -> np.ndarray:
        """The flange in the base frame as Dobot's [x, y, z, rx, ry, rz] (mm, deg)."""
        with self._lock:
            return cr5.matrix_to_pose6(cr5.fk(self._q))

    # -- motion commands -------------------------------------------------------------------------

    def _motion_gate(self) -> int:
        if (code := self.gate()) != 0:
            return code
        if not self._enabled:
            return int(ErrorId.FAILED)
        return 0

    def _check_joint_target(self, q: np.ndarray) -> int | None:
        """The alarm a joint target raises, or None if the arm can take it."""
        for j in range(6):
            if q[j] > cr5.JOINT_LIMITS[j, 1]:
                return joint_limit_alarm(j, True)
            if q[j] < cr5.JOINT_LIMITS[j, 0]:
                return joint_limit_alarm(j, False)
        if cr5.self_collision(q, self._tool_offset):
            return int(Alarm.FLANGE_INTERFERENCE)
        return None

    def _solve_pose(self, T: np.ndarray, seed: np.ndarray) -> tuple[np.ndarray | None, int | None]:
        """Joint angles for flange pose T near `seed`, or the alarm: no solution / beyond limits / self-collision."""
        q = cr5.ik(T, seed)
        if q is None:
            no_solution = len(cr5.ik_all(T, q6_free=float(seed[5]))) == 0
            return None, int(Alarm.IK_NO_SOLUTION if no_solution else Alarm.IK_OUT_OF_LIMITS)
        if cr5.self_collision(q, self._tool_offset):
            q2 = cr5.ik(T, seed, avoid_self_collision=True)
            if q2 is None or np.max(np.abs(q2 - seed)) > np.pi / 2:
                return None, int(Alarm.FLANGE_INTERFERENCE)
            q = q2
        return q, None

    def _queue_seed(self) -> np.ndarray:
        if self._queue:
            return self._queue[-1].q_goal
        if self._active is not None:
            return self._active.q_goal
        return self._q_ref

    def _enqueue(self, kind: str, q_goal: np.ndarray, v: float, a: float, T1: np.ndarray | None = None) -> tuple[int, int]:
        seg = _Segment(cmd_id=self._next_id, kind=kind, q_goal=q_goal, speed=v / 100.0, accel=a / 100.0, T1=T1)
        self._next_id += 1
        self._queue.append(seg)
        return 0, seg.cmd_id

    def mov_j(self, joint_deg: np.ndarray | None = None, pose6: np.ndarray | None = None, v: float = 100, a: float = 100) -> tuple[int, int]:
        """Queue a joint-space move to joint angles (deg) or a flange pose; returns (error id, command id)."""
        return self._queue_move("joint", joint_deg, pose6, v, a)

    def mov_l(self, joint_deg: np.ndarray | None = None, pose6: np.ndarray | None = None, v: float = 100, a: float = 100) -> tuple[int, int]:
        """Queue a straight-line flange move; the path is checked as it runs (an unreachable point on it alarms)."""
        return self._queue_move("linear", joint_deg, pose6, v, a)

    def _queue_move(self, kind: str, joint_deg: np.ndarray | None, pose6: np.ndarray | None, v: float, a: float) -> tuple[int, int]:
        """MovJ/MovL: a target in joints or as a flange pose; it ends any servo stream."""
        with self._lock:
            if (code := self._motion_gate()) != 0:
                return code, 0
            self._servo = None
            if joint_deg is not None:
                q = np.radians(np.asarray(joint_deg, dtype=float))
                alarm = self._check_joint_target(q)
                T1 = cr5.fk(q)
            elif pose6 is not None:
                T1 = cr5.pose6_to_matrix(pose6)
                q, alarm = self._solve_pose(T1, self._queue_seed())
            else:
                raise ValueError(f"{kind}: a move needs a joint target or a pose")
            if alarm is not None:
                self._raise(alarm)
                return int(ErrorId.FAILED), 0
            return self._enqueue(kind, q, v, a, T1=T1 if kind == "linear" else None)

    def servo_j(self, joint_deg: np.ndarray, t: float = 0.1, aheadtime: float = 50, gain: float = 500) -> int:
        """ServoJ to joint angles (deg): the error id (`servo` also gives the command id)."""
        return self.servo("joint", joint_deg, t, aheadtime, gain)[0]

    def servo_p(self, pose6: np.ndarray, t: float = 0.1, aheadtime: float = 50, gain: float = 500) -> int:
        """ServoP to a flange pose6 (mm, deg): the error id (`servo` also gives the command id)."""
        return self.servo("pose", pose6, t, aheadtime, gain)[0]

    def servo(self, kind: str, target: np.ndarray, t: float = 0.1, aheadtime: float = 50, gain: float = 500) -> tuple[int, int]:
        """ServoJ (`kind` "joint", degrees) or ServoP ("pose", pose6): (error id, command id).

        An accepted target takes the next id of the motion commands' sequence and is the current
        command from then on, as a controller answers `0,{ResultID},ServoP(..)` like MovJ.
        """
        with self._lock:
            self.servo_commands += 1
            if (code := self._motion_gate()) != 0:
                return code, 0
            if kind == "joint":
                q = np.radians(np.asarray(target, dtype=float))
                alarm = self._check_joint_target(q)
            else:
                seed = self._servo.goal if self._servo is not None else self._q_ref
                q, alarm = self._solve_pose(cr5.pose6_to_matrix(target), seed)
            if alarm is not None:
                self._raise(alarm)
                return int(ErrorId.FAILED), 0
            if (code := self._servo_to(q, t, aheadtime, gain)) != 0:
                return code, 0
            self._current_id = self._next_id
            self._next_id += 1
            return 0, self._current_id

    def _servo_to(self, q_goal: np.ndarray, t: float, aheadtime: float, gain: float) -> int:
        if self._active is not None or self._queue:
            return int(ErrorId.FAILED)  # a queued motion is running: servoing waits for it
        # The stream's speed: from the previous servo target (where the controller was told to be),
        # not from the reference, which lags behind whenever the simulation runs slower than the
        # wall clock the driver streams by.
        prev = self._servo.goal if self._servo is not None else self._q_ref
        speed = np.abs(q_goal - prev) / t
        j = int(np.argmax(speed))
        if speed[j] > cr5.JOINT_SPEED_LIMIT * 1.05:
            self._raise(overspeed_alarm(j), f"servo target J{j + 1} {np.degrees(prev[j]):.1f} -> {np.degrees(q_goal[j]):.1f} deg "
                        f"in t = {t * 1000:.0f} ms ({np.degrees(speed[j]):.0f} deg/s; limit {np.degrees(cr5.JOINT_SPEED_LIMIT):.0f}); "
                        f"reference at {np.degrees(self._q_ref[j]):.1f}, actual {np.degrees(self._q[j]):.1f} deg")
            return int(ErrorId.FAILED)
        omega = SERVO_OMEGA * float(np.sqrt(gain / 500.0))
        self._servo = _Servo(start=self._q_ref.copy(), goal=q_goal.copy(), t=float(t), elapsed=0.0, omega=omega, feedforward=float(aheadtime) / 100.0)
        return 0

    # -- alarms ----------------------------------------------------------------------------------

    def _raise(self, alarm: int, detail: str = "") -> None:
        if alarm not in self._alarms:
            self._alarms.append(alarm)
            self.alarm_log.append((self.time, int(alarm), detail))
        self._hold()

    def raise_alarm(self, alarm: int) -> None:
        """Latch an alarm from outside (the world reports a collision, a test injects a fault)."""
        with self._lock:
            self._raise(int(alarm))

    def _hold(self) -> None:
        """Drop the queue and servo target; the reference stops where the arm is."""
        self._queue.clear()
        if self._active is not None:
            self._current_id = self._active.cmd_id
        self._active = None
        self._servo = None
        self._q_ref = self._q.copy()
        self._qd_ref = np.zeros(6)

    def teleport(self, q: np.ndarray) -> None:
        """Put the arm at rest at `q (6,)` rad at once, its queue and servo target dropped: the
        simulator's reset between runs (an operator re-placing the arms), never a motion command."""
        q = np.asarray(q, dtype=float)
        if q.shape != (6,) or not cr5.within_limits(q):
            raise ValueError(f"{self.name}: angles {np.degrees(q).round(1).tolist()} deg are not within the CR5's limits")
        with self._lock:
            self._q = q.copy()
            self._qd = np.zeros(6)
            self._hold()
            self._q_ref_checked = q.copy()

    # -- simulation ------------------------------------------------------------------------------

    def step(self, dt: float) -> None:
        """Advance the controller and the joints by `dt` seconds of simulated time."""
        if not dt > 0:
            return
        with self._lock:
            n = max(1, int(np.ceil(dt / SUBSTEP_S - 1e-9)))
            h = dt / n
            for _ in range(n):
                self._substep(h)
            self.time += dt
            # the reference the controller plans must stay inside the limits and clear of the arm's body
            if self._enabled and not self._alarms and not np.array_equal(self._q_ref, self._q_ref_checked):
                self._q_ref_checked = self._q_ref.copy()
                alarm = self._check_joint_target(self._q_ref)
                if alarm is not None:
                    self._raise(alarm)

    def _substep(self, h: float) -> None:
        omega, ff = SERVO_OMEGA * 2.0, 1.0  # queued motions: the controller's own stiff tracking
        if self._enabled and not self._alarms:
            if self._active is None and self._queue:
                self._start(self._queue.popleft())
            if self._active is not None:
                self._advance_segment(h)
            elif self._servo is not None:
                s = self._servo
                s.elapsed += h
                f = min(s.elapsed / s.t, 1.0)
                self._q_ref = s.start + f * (s.goal - s.start)
                self._qd_ref = (s.goal - s.start) / s.t if f < 1.0 else np.zeros(6)
                omega, ff = s.omega, s.feedforward
        if not self._enabled:
            # brakes on: the joints stop where they are
            self._qd[:] = 0.0
            return
        # critically damped; `ff` of the reference velocity is fed forward (aheadtime's effect)
        qdd = omega**2 * (self._q_ref - self._q) + 2 * omega * (ff * self._qd_ref - self._qd)
        qdd = np.clip(qdd, -cr5.JOINT_ACCEL_LIMIT, cr5.JOINT_ACCEL_LIMIT)
        self._qd = np.clip(self._qd + h * qdd, -cr5.JOINT_SPEED_LIMIT, cr5.JOINT_SPEED_LIMIT)
        self._q = self._q + h * self._qd

    def _start(self, seg: _Segment) -> None:
        seg.q0 = self._q_ref.copy()
        scale = self._speed_factor / 100.0
        if seg.kind == "joint":
            dq = float(np.max(np.abs(seg.q_goal - seg.q0)))
            vmax = cr5.JOINT_SPEED_LIMIT * scale * seg.speed
            amax = MOVJ_ACCEL * scale * seg.accel
            seg.duration = max(1.875 * dq / vmax, np.sqrt(5.7735 * dq / amax), 0.02)
        else:
            seg.T0 = cr5.fk(seg.q0)
            assert seg.T1 is not None
            dist = float(np.linalg.norm(seg.T1[:3, 3] - seg.T0[:3, 3]))
            rots = Rotation.from_matrix(np.stack([seg.T0[:3, :3], seg.T1[:3, :3]]))
            ang = float((rots[1] * rots[0].inv()).magnitude())
            seg.slerp = Slerp([0.0, 1.0], rots)
            v = MOVL_SPEED * scale * seg.speed
            a = MOVL_ACCEL * scale * seg.accel
            w = MOVL_ANGULAR_SPEED * scale * seg.speed
            seg.duration = max(1.875 * dist / v, np.sqrt(5.7735 * dist / a), 1.875 * ang / w, 0.02)
        self._active = seg
        self._current_id = seg.cmd_id

    def _line_point(self, seg: _Segment, t: float, seed: np.ndarray) -> np.ndarray | None:
        """Joint angles at time t on a MovL segment's line, solved from `seed`."""
        assert seg.T0 is not None and seg.T1 is not None and seg.slerp is not None
        s, _ = _quintic(t / seg.duration)
        if s >= 1.0:
            return seg.q_goal.copy()
        T = np.eye(4)
        T[:3, 3] = seg.T0[:3, 3] + s * (seg.T1[:3, 3] - seg.T0[:3, 3])
        T[:3, :3] = seg.slerp([s]).as_matrix()[0]
        return cr5.ik(T, seed)

    def _advance_segment(self, h: float) -> None:
        seg = self._active
        assert seg is not None and seg.q0 is not None
        seg.elapsed += h
        t = min(seg.elapsed, seg.duration)
        if seg.kind == "joint":
            s, _ = _quintic(t / seg.duration)
            q_new = seg.q0 + s * (seg.q_goal - seg.q0)
        else:
            if seg.knots is None:
                seg.knots = (0.0, seg.q0.copy(), 0.0, seg.q0.copy())
            while seg.knots[2] < t:
                t0, q0 = seg.knots[2], seg.knots[3]
                t1 = min(t0 + MOVL_IK_PERIOD_S, seg.duration)
                q1 = self._line_point(seg, t1, q0)
                if q1 is None or np.max(np.abs(q1 - q0)) > cr5.JOINT_SPEED_LIMIT * (t1 - t0) * 1.5 + 1e-3:
                    # the line leaves the workspace or flips configuration: the real arm alarms the same way
                    j = 0 if q1 is None else int(np.argmax(np.abs(q1 - q0)))
                    self._raise(int(Alarm.IK_NO_SOLUTION) if q1 is None else overspeed_alarm(j))
                    return
                seg.knots = (t0, q0, t1, q1)
            t0, q0, t1, q1 = seg.knots
            f = 1.0 if t1 <= t0 else (t - t0) / (t1 - t0)
            q_new = q0 + f * (q1 - q0)
        self._qd_ref = (q_new - self._q_ref) / h if t < seg.duration else np.zeros(6)
        self._q_ref = q_new
        if seg.elapsed >= seg.duration:
            self._q_ref = seg.q_goal.copy()
            self._qd_ref = np.zeros(6)
            self._active = None

    # -- poses -----------------------------------------------------------------------------------

    def flange_pose_base(self) -> np.ndarray:
        """4x4 base <- flange (actual joints)."""
        with self._lock:
            return cr5.fk(self._q)

    def flange_pose_world(self) -> np.ndarray:
        """4x4 world <- flange."""
        return self._T_world_base @ self.flange_pose_base()

    def mount_pose_world(self) -> np.ndarray:
        """4x4 world <- bag mount (bolted to the flange)."""
        return self.flange_pose_world() @ self._T_flange_mount

    # -- feedback --------------------------------------------------------------------------------

    def fill_feedback(self, rec: np.ndarray | None = None) -> np.ndarray:
        """The 1440-byte feedback record for the current state (units as the controller sends them)."""
        rec = new_feedback() if rec is None else rec
        with self._lock:
            q, qd, q_ref, qd_ref = self._q.copy(), self._qd.copy(), self._q_ref.copy(), self._qd_ref.copy()
            mode = self.robot_mode()
            enabled, alarms, moving = self._enabled, bool(self._alarms), self._moving()
            sf, cmd_id, sim_t = self._speed_factor, self._current_id, self.time
            load, center = self._load, self._center.copy()
        T = cr5.fk(q)
        T_ref = cr5.fk(q_ref)
        eps = 1e-3
        T_next = cr5.fk(q + eps * qd)
        lin = (T_next[:3, 3] - T[:3, 3]) / eps * 1000.0
        ang = so3_log(T_next[:3, :3] @ T[:3, :3].T) / eps
        rec["RobotMode"] = mode
        offset = self.clock_offset
        rec["TimeStamp"] = int(round((sim_t + offset) * 1000)) if offset is not None else int(_time.time() * 1000)
        rec["RunTime"] = int(sim_t * 1000)
        rec["SpeedScaling"] = sf / 100.0
        rec["VRobot"] = 48.0
        rec["IRobot"] = 1.2 if enabled else 0.3
        rec["QTarget"] = np.degrees(q_ref)
        rec["QDTarget"] = np.degrees(qd_ref)
        rec["QActual"] = np.degrees(q)
        rec["QDActual"] = np.degrees(qd)
        rec["ToolVectorActual"] = cr5.matrix_to_pose6(T)
        rec["ToolVectorTarget"] = cr5.matrix_to_pose6(T_ref)
        rec["TCPSpeedActual"] = np.concatenate([lin, np.degrees(ang)])
        rec["MotorTemperatures"] = 32.0
        rec["JointModes"] = 8.0
        rec["VActual"] = 48.0 if enabled else 0.0
        rec["VelocityRatio"] = sf
        rec["AccelerationRatio"] = sf
        rec["XYZVelocityRatio"] = sf
        rec["RVelocityRatio"] = sf
        rec["XYZAccelerationRatio"] = sf
        rec["RAccelerationRatio"] = sf
        rec["BrakeStatus"] = 0x3F if enabled else 0
        rec["EnableStatus"] = int(enabled)
        rec["RunningStatus"] = int(moving and enabled and not alarms)
        rec["ErrorStatus"] = int(alarms)
        rec["RunQueuedCmd"] = int(moving and enabled and not alarms)
        rec["CurrentCommandId"] = cmd_id
        rec["Load"] = load
        rec["CenterX"], rec["CenterY"], rec["CenterZ"] = center
        rec["ActualQuaternion"] = matrix_to_quat_wxyz(T[:3, :3])
        rec["TargetQuaternion"] = matrix_to_quat_wxyz(T_ref[:3, :3])
        return rec
