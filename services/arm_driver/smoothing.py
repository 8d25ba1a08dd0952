"""Jerk-limited smoothing of both arms' mount poses with one 12-DoF Ruckig instance (`RuckigSmoother`).

Why one instance of 12 DoF: with Ruckig's time synchronisation both arms reach each target at
the same instant, so the rim is never stretched by one arm running ahead of the other, and both
arms stop together.

The DoFs per arm are the mount position (x, y, z, world, m) and its orientation as a rotation
vector r with R = exp(r) R_now (world frame, rad). The orientation coordinates are re-based on the
current orientation every cycle: at r = 0 the rotation vector's rate is exactly the angular
velocity and its second derivative exactly the angular acceleration, so Ruckig's limits are the
true angular limits and no Euler-angle wrap can occur. After a step the new state is mapped back
with the SO(3) left Jacobian (omega = J_l(r) r_dot).

Limits come from `SafetyLimits` and are applied per axis divided by sqrt(3), so that the norm of
the velocity, acceleration and jerk vectors never exceeds the configured Cartesian limit whatever
the direction of motion. (The controller's own increments stay far below: 5 cm/s per axis.)

Halting (a hold, the watchdog, a fault, a lost link, the run's end) is a controlled stop: Ruckig's
velocity interface, target velocity and acceleration zero from the trajectory's current state, with
the stop's Cartesian limits (`SafetyLimits.stop_limits`: the path's speed, the arm's stopping
acceleration and jerk, 4 m/s^2 and 100 m/s^3 at the mount by default) split along the motion
(`braking_shares`): per axis the limits are d_i times the Cartesian one with sum(d_i^2) = 1, so the
norms stay within the limits whatever the profile (|x_i| <= d_i L for every axis gives
|x|^2 <= L^2 sum(d_i^2) = L^2), and a straight motion brakes with the whole budget along its
direction. A motion that just started is still accelerating when it is stopped: with the path's
jerk (10 m/s^3) turning 1 m/s^2 round took 100 ms, in which the arms sped up further (by 5 cm/s);
with the stop's, 10 ms (0.5 cm/s), and 4 cm/s brakes in 2 sqrt(v/j) = 40 ms instead of 126 ms.
It is a Ruckig instance of its own, used only in mode 'stopping': tracking (commands arriving) is
the same computation as without it, bit for bit.

"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ruckig import ControlInterface, InputParameter, OutputParameter, Result, Ruckig, RuckigError, Synchronization

from bagit.common.rig import SafetyLimits
from bagit.common.so3 import left_jacobian, rotvec_between, so3_exp
from bagit.services.arm_driver.frames import Poses, arrays_to_poses, poses_to_arrays

N_DOF = 12
SQRT3 = float(np.sqrt(3.0))
# The share of the braking budget every axis keeps whatever the motion's direction: an axis at rest
# stays at rest, and Ruckig gets no zero limit.
BRAKING_FLOOR = 1e-3


def braking_shares(v: np.ndarray, a: np.ndarray, v_max: float, a_max: float) -> np.ndarray:
    """`(3,)` shares d (sum of squares 1) of one arm's Cartesian limits for braking its linear (or
    angular) motion, velocity `v (3,)` and acceleration `a (3,)`, to rest.

    Every axis gets at least the share its current velocity and acceleration already use, so the
    state starts inside its per-axis limits (a tracking state, within the limits / sqrt(3) per axis,
    uses at most 1/3 per axis); the rest goes along the velocity (along the acceleration when at rest).
    """
    need = np.maximum(np.abs(v) / v_max, np.abs(a) / a_max) ** 2
    spare = 1.0 - float(need.sum())
    if spare <= 0.0:  # a state at the per-axis limits on every axis: nothing left to move
        return np.sqrt(need / need.sum())
    along = v if np.linalg.norm(v) > 0 else a
    n = float(np.linalg.norm(along))
    w = (along / n) ** 2 if n > 0 else np.full(3, 1 / 3)
    w = (1.0 - BRAKING_FLOOR) * w + BRAKING_FLOOR / 3
    return np.sqrt(need + spare * w)


@dataclass
class StreamStep:
    """One cycle's output: the mount poses to command and the trajectory state behind them.

    `velocity`, `acceleration (2, 6)`: per arm [linear (m/s, m/s^2), angular (rad/s, rad/s^2)], world.
    """

    poses: Poses
    velocity: np.ndarray
    acceleration: np.ndarray
    at_rest: bool
    error: str | None = None


class RuckigSmoother:
    """Ruckig over both arms' mount poses; one `step` per servo period.

    Modes: 'idle' (at rest, nothing to stream), 'position' (tracking a target pose),
    'stopping' (velocity target zero, Ruckig's velocity interface, until at rest).
    """

    def __init__(self, limits: SafetyLimits, period: float):
        if not period > 0:
            raise ValueError(f"period must be > 0, got {period}")
        self.period = float(period)
        self._otg = Ruckig(N_DOF, self.period)
        self._inp = InputParameter(N_DOF)
        self._out = OutputParameter(N_DOF)
        lin = [limits.max_tcp_speed_mps / SQRT3, limits.max_tcp_accel_mps2 / SQRT3, limits.max_tcp_jerk_mps3 / SQRT3]
        ang = [limits.max_angular_speed_rps / SQRT3, limits.max_angular_accel_rps2 / SQRT3, limits.max_angular_jerk_rps3 / SQRT3]
        per_arm = [lin] * 3 + [ang] * 3
        lim = np.array(per_arm * 2)  # (12, 3)
        self.max_velocity, self.max_acceleration, self.max_jerk = lim[:, 0], lim[:, 1], lim[:, 2]
        self._inp.max_velocity = self.max_velocity.tolist()
        self._inp.max_acceleration = self.max_acceleration.tolist()
        self._inp.max_jerk = self.max_jerk.tolist()
        self._inp.synchronization = Synchronization.Time
        # braking to rest ('stopping'): its own instance, the stop's limits split along the motion each cycle
        self.stopping = limits.stop_limits()  # (2, 3) [[v, a, j] linear, [v, a, j] angular]
        self._halt_otg = Ruckig(N_DOF, self.period)
        self._halt_inp = InputParameter(N_DOF)
        self._halt_out = OutputParameter(N_DOF)
        self._halt_inp.synchronization = Synchronization.Time
        self._halt_inp.control_interface = ControlInterface.Velocity
        self._halt_inp.target_velocity = [0.0] * N_DOF
        self._halt_inp.target_acceleration = [0.0] * N_DOF
        self._halt_failed = False  # this stop fell back to the per-axis limits
        self.mode = "idle"
        self.p = np.zeros((2, 3))
        self.R = np.tile(np.eye(3), (2, 1, 1))
        self.vel = np.zeros((2, 6))  # [v, omega] per arm
        self.acc = np.zeros((2, 6))
        self.errors = 0

    # -- state -----------------------------------------------------------------------------------

    def reset(self, poses: Poses) -> None:
        """At rest at `poses`, nothing to do until a target or a stop."""
        self.p, self.R = poses_to_arrays(poses)
        self.rest()

    def rest(self) -> None:
        """At rest where the trajectory is now: no velocity, no acceleration, idle."""
        self.vel[:] = 0.0
        self.acc[:] = 0.0
        self.mode = "idle"

    def poses(self) -> Poses:
        return arrays_to_poses(self.p, self.R)

    @property
    def at_rest(self) -> bool:
        return bool(np.all(self.vel == 0.0) and np.all(self.acc == 0.0))

    def track(self) -> None:
        """Follow targets from now on (a new command stream)."""
        self.mode = "position"

    def begin_stop(self) -> None:
        """Brake to rest with Ruckig (velocity and acceleration targets zero), then go idle."""
        if self.mode != "idle":
            self.mode = "idle" if self.at_rest else "stopping"
            self._halt_failed = False

    def halting_limits(self) -> np.ndarray:
        """`(12, 3)` per-axis [velocity, acceleration, jerk] limits for braking from the current state:
        each arm's linear and angular stop limits split along its motion (`braking_shares`)."""
        out = np.empty((N_DOF, 3))
        for i in range(2):
            for k, sl in enumerate((slice(0, 3), slice(3, 6))):
                cart = self.stopping[k]
                d = braking_shares(self.vel[i, sl], self.acc[i, sl], cart[0], cart[1])
                out[6 * i + 3 * k : 6 * i + 3 * k + 3] = d[:, None] * cart[None, :]
        return out

    def sync(self, sent: Poses, previous: Poses, dt: float, rotation_only: bool = False) -> None:
        """Take the pose actually sent (after the safety gate changed it) as the trajectory's state.

        The velocity becomes the step's average, clipped to the limits, the acceleration zero: a kink
        the gate caused and reported, after which the trajectory carries on smoothly from the truth.
        `rotation_only`: the positions sent were the trajectory's own (a rotation that lagged near the
        wrist singularity), so their state carries on untouched.
        """
        p, R = poses_to_arrays(sent)
        pp, Rp = poses_to_arrays(previous)
        lim = self.max_velocity.reshape(2, 6)
        for i in range(2):
            self.R[i] = R[i]
            self.vel[i, 3:] = np.clip(rotvec_between(Rp[i], R[i]) / dt, -lim[i, 3:], lim[i, 3:])
            self.acc[i, 3:] = 0.0
            if not rotation_only:
                self.p[i] = p[i]
                self.vel[i, :3] = np.clip((p[i] - pp[i]) / dt, -lim[i, :3], lim[i, :3])
                self.acc[i, :3] = 0.0

    # -- one cycle -------------------------------------------------------------------------------

    def _set_current(self, inp: InputParameter) -> None:
        """The trajectory's state as Ruckig's current state (orientations re-based: r = 0)."""
        zeros = np.zeros(3)
        inp.current_position = np.concatenate([self.p[0], zeros, self.p[1], zeros]).tolist()
        inp.current_velocity = self.vel.ravel().tolist()
        inp.current_acceleration = self.acc.ravel().tolist()

    def step(self, target: Poses | None = None) -> StreamStep:
        """Advance one period towards `target` (mode 'position') or towards rest (mode 'stopping')."""
        if self.mode == "idle":
            return StreamStep(self.poses(), self.vel.copy(), self.acc.copy(), True)
        if self.mode == "stopping" and not self._halt_failed:
            halted = self._halt_step()
            if halted is not None:
                return halted
        inp = self._inp
        self._set_current(inp)
        if self.mode == "position":
            if target is None:
                raise ValueError("a tracking step needs a target")
            tp, tR = poses_to_arrays(target)
            r = [rotvec_between(self.R[i], tR[i]) for i in range(2)]
            inp.control_interface = ControlInterface.Position
            inp.target_position = np.concatenate([tp[0], r[0], tp[1], r[1]]).tolist()
        else:
            inp.control_interface = ControlInterface.Velocity
        inp.target_velocity = [0.0] * N_DOF
        inp.target_acceleration = [0.0] * N_DOF
        error = None
        try:
            result = self._otg.update(inp, self._out)
        except (RuckigError, RuntimeError) as e:  # ruckig raises on input it refuses (RuckigError is no RuntimeError)
            result, error = Result.Error, str(e)
        if result not in (Result.Working, Result.Finished):
            return self._fail(error or f"ruckig returned {result.name}")
        self._apply(np.asarray(self._out.new_position), np.asarray(self._out.new_velocity), np.asarray(self._out.new_acceleration))
        finished = result == Result.Finished
        if finished and self.mode == "stopping":
            self.rest()
        return StreamStep(self.poses(), self.vel.copy(), self.acc.copy(), self.at_rest)

    def _halt_step(self) -> StreamStep | None:
        """One period of braking with the limits split along the motion; None if Ruckig refused (the
        stop then goes on with the per-axis limits)."""
        lim = self.halting_limits()
        inp = self._halt_inp
        inp.max_velocity, inp.max_acceleration, inp.max_jerk = lim[:, 0].tolist(), lim[:, 1].tolist(), lim[:, 2].tolist()
        self._set_current(inp)
        try:
            result = self._halt_otg.update(inp, self._halt_out)
        except (RuckigError, RuntimeError):
            result = Result.Error
        if result not in (Result.Working, Result.Finished):
            self.errors += 1
            self._halt_failed = True
            return None
        out = self._halt_out
        self._apply(np.asarray(out.new_position), np.asarray(out.new_velocity), np.asarray(out.new_acceleration))
        if result == Result.Finished:
            self.rest()
        return StreamStep(self.poses(), self.vel.copy(), self.acc.copy(), self.at_rest)

    def _apply(self, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray) -> None:
        pos, vel, acc = pos.reshape(2, 6), vel.reshape(2, 6), acc.reshape(2, 6)
        for i in range(2):
            r = pos[i, 3:]
            J = left_jacobian(r)
            self.p[i] = pos[i, :3]
            self.R[i] = so3_exp(r) @ self.R[i]
            self.vel[i, :3], self.vel[i, 3:] = vel[i, :3], J @ vel[i, 3:]
            self.acc[i, :3], self.acc[i, 3:] = acc[i, :3], J @ acc[i, 3:]

    def _fail(self, why: str) -> StreamStep:
        """Ruckig refused: brake if we were tracking; if even braking fails, hold where we are."""
        self.errors += 1
        if self.mode == "position":
            self.mode = "stopping"
            out = self.step()
            out.error = why
            return out
        self.rest()
        return StreamStep(self.poses(), self.vel.copy(), self.acc.copy(), True, error=why)
