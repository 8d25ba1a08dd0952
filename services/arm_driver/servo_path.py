"""The one path from a controller command to a ServoP, pure: no sockets, threads or clock of its own.

    path = ServoPath(rig, DriverConfig(), on_event=log)
    path.restart(feedback_records)       # at rest where the controllers command the arms
    path.submit(u, dt, now)              # a controller increment; the violations found
    path.hold(reason, now)               # the controller asks to hold: brake to rest
    path.watchdog(now)                   # no command for watchdog_s: brake to rest
    out = path.cycle(now, active_arms)   # one servo period: each arm's ServoP (or ServoJ), or a fault

Its layers, in the order a command goes through them:
  targets    the increment moves the target (`TargetIntegrator`), kept within a lead of the
             trajectory (`pull_back`) and clamped into the static envelope (`limits.clip_target`)
  smoothing  12-DoF Ruckig towards the target, jerk-limited (`RuckigSmoother`; a stop brakes at the stop's limits)
  limits     every pose that leaves goes through `check_and_clip` (workspace, separation, speed)
  reach      a step the joints cannot follow: its rotation lags (near the wrist singularity), else it is
             shortened to what they can (`reach.solve_within`)
  wire       the flange pose in each arm's base as a ServoP (or the joints as a ServoJ)

Both hosts drive it: the `ArmDriver` (its servo thread and TCP links around it) on a rig, and
`bagit run`'s `Cr5Arms` on the simulator's clock. Every event (clip, slow-down, watchdog stop) is
counted in `counters` and told to `on_event`. Not thread-safe: the host serialises calls.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bagit.common import cr5
from bagit.common.messages import ArmState
from bagit.common.rig import ARMS, ArmName, RigConfig
from bagit.common.so3 import matrix_to_rpy
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.arm_driver.frames import ArmFrames, Poses
from bagit.services.arm_driver.limits import MEASURED_TOL_M, Envelope, Violation, check_and_clip, clip_target, violations
from bagit.services.arm_driver.reach import Joints, Reach, arm_solver, joint_solver, solve_within, wrist_lag
from bagit.services.arm_driver.smoothing import RuckigSmoother, StreamStep
from bagit.services.arm_driver.targets import TargetIntegrator, pull_back
from bagit.services.arm_driver.wire import ServoCommand, servo_commands

# A step whose joints would move faster than this fraction of the CR5's joint speed limit is shortened
# (the controller alarms at the limit, measured from its own lagging reference: keep well clear).
REACH_JOINT_SPEED_FRACTION = 0.5


@dataclass
class Tick:
    """One period through targets, smoothing and limits: the poses to send (None: send nothing), what
    the gate found, the trajectory; `halting`: the poses brake to rest (a stop, not a command tracked)."""

    command: Poses | None
    violations: list[Violation] = field(default_factory=list)
    step: StreamStep | None = None
    mode: str = "idle"
    halting: bool = False


@dataclass
class Cycle:
    """One servo period, through reach and wire: the mount `poses` to send (None: nothing), their
    `joints`, each arm's `servo` command, a `fault` that stops the arms; `halting`: braking to rest."""

    poses: Poses | None = None
    joints: Joints | None = None
    fault: str | None = None
    violations: list[Violation] = field(default_factory=list)
    halting: bool = False
    servo: dict[ArmName, ServoCommand] = field(default_factory=dict)


class ServoPath:
    """Increments in, safe jerk-limited ServoPs out (see the module docstring)."""

    def __init__(
        self,
        rig: RigConfig,
        cfg: DriverConfig | None = None,
        on_event: Callable[[str, str], None] | None = None,
        counters: Counter[str] | None = None,
    ):
        self.rig = rig
        self.cfg = cfg or DriverConfig()
        self.limits = rig.safety
        self.period = float(self.limits.servo_period_s)
        self.servo_t = self.period * self.cfg.servo_t_factor
        # A cycle this long after the last one finds the arms stopped at its target (its ServoP's t ran out)
        # for a whole period: resuming the trajectory would start them again at its old velocity, a jump.
        self.stall_s = self.servo_t + self.period
        self.env = Envelope.from_rig(rig)
        self.frames = {a: ArmFrames.from_config(rig.arms[a]) for a in ARMS}
        self.smoother = RuckigSmoother(self.limits, self.period)
        self.targets = TargetIntegrator()
        self.last_sent: Poses | None = None
        self.on_event = on_event
        self.counters: Counter[str] = counters if counters is not None else Counter()
        self.violation_counts: Counter[str] = Counter()
        self.last_violations: list[str] = []
        self.q_seed: Joints = {}
        self.last_cmd_t = -np.inf
        self.slowing = False  # the last period's step was shortened to the joints' speed
        self.lagging = False  # the last period's rotation lagged the step's (near the wrist singularity)
        self._before: tuple[Poses, Joints] | None = None  # the poses sent and joint seeds before the last cycle (`unsend`)

    def _event(self, kind: str, detail: str) -> None:
        if self.on_event is not None:
            self.on_event(kind, detail)

    def record(self, found: list[Violation]) -> None:
        """Count the violations found (by kind) and keep the last ones for the status."""
        if found:
            for v in found:
                self.violation_counts[v.kind] += 1
            self.last_violations = [str(v) for v in found]

    # -- state -----------------------------------------------------------------------------------

    @property
    def mode(self) -> str:
        """'idle', 'position' (streaming) or 'stopping'."""
        return self.smoother.mode

    @property
    def moving(self) -> bool:
        return self.smoother.mode != "idle"

    def aim(self) -> Poses | None:
        """Where the path is taking the mounts: the end of the increments taken while it streams, the
        trajectory's own pose while it brakes or rests (None before the first `reset`). Less the
        measured poses, it is the motion still in flight, which a controller's prediction needs: the
        arms follow a command over several servo periods (target, Ruckig, the controllers' servo loop)."""
        if self.last_sent is None:
            return None
        return self.targets.end() if self.mode == "position" else self.smoother.poses()

    def lay_over(self, state: ArmState, **update: Any) -> ArmState:
        """`state` with where the path takes that mount (`aim`, as `target_pose`) and whether its last
        period was slowed, plus `update`: what the controller predicts from and stops asking for."""
        out: dict[str, Any] = {"slowed": self.slowing}
        aim = self.aim()
        if aim is not None:
            T = aim[state.arm]
            out["target_pose"] = np.concatenate([T[:3, 3], matrix_to_rpy(T[:3, :3])])
        return state.model_copy(update={**out, **update})

    def commanded(self) -> Poses:
        """The last poses sent (or the reset poses)."""
        if self.last_sent is None:
            raise RuntimeError("ServoPath.reset() must come before commanded()")
        return {a: self.last_sent[a].copy() for a in ARMS}

    def reset(self, poses: Poses) -> list[Violation]:
        """Start over at rest at mount `poses`; the limits they already break by more than an arm's
        following error (MEASURED_TOL_M)."""
        self.smoother.reset(poses)
        self.targets.reset(poses)
        self.last_sent = {a: np.array(poses[a], dtype=float) for a in ARMS}
        return violations(self.last_sent, None, self.period, self.env, tol=MEASURED_TOL_M)

    def restart(self, records: dict[ArmName, np.ndarray]) -> list[Violation] | None:
        """At rest at the poses the controllers command (feedback `ToolVectorTarget`, `QTarget`: the
        measured ones once the arms settle). None if a record reports a non-finite pose; else the
        limits those poses already break (the host faults on any).

        Not the actual poses: an arm still following its last target would get a first target back
        behind it, a jump the controller alarms on (joint overspeed) or a jerk the other way."""
        poses = {a: self.frames[a].mount_from_pose6(records[a]["ToolVectorTarget"]) for a in ARMS}
        q = {a: np.radians(np.asarray(records[a]["QTarget"], dtype=float)) for a in ARMS}
        if not all(np.all(np.isfinite(poses[a])) and np.all(np.isfinite(q[a])) for a in ARMS):
            return None
        found = self.reset(poses)
        self.q_seed = q
        self.last_cmd_t = -np.inf
        self.record(found)
        return found

    def stop(self) -> None:
        """Brake smoothly to rest and forget the target; a later `submit` starts a new stream from there."""
        self.smoother.begin_stop()

    def halt(self) -> None:
        """Drop the trajectory at once (the controllers stopped the arms themselves: e-stop, a pause); idle."""
        self.smoother.rest()

    def unsend(self) -> None:
        """The last cycle's ServoPs never went out (too old to send): at rest where the arms were last sent,
        so that a new stream starts there (from the unsent poses, its first ServoP would jump by every
        step the arms never got)."""
        if self._before is None:
            self.halt()
            return
        poses, q = self._before
        self._before = None
        self.reset(poses)
        self.q_seed = q

    # -- in: targets -----------------------------------------------------------------------------

    def submit(self, u: np.ndarray, dt: float, now: float) -> list[Violation]:
        """Increment `u (12,)` (left dx dy dz drx dry drz, right ..., world, m and rad) over `dt` s at `now`.

        A non-finite increment or dt is refused whole (a `non_finite` violation, counted `rejected`);
        one whose target was pulled back or clamped counts as `clipped`. A stream starts from the
        trajectory's pose if none runs."""
        u = np.asarray(u, dtype=float)
        if u.shape != (12,) or not np.all(np.isfinite(u)) or not (np.isfinite(dt) and 0 < dt <= 10.0):
            found = [Violation("both", "non_finite", "increment rejected: it must be 12 finite numbers over 0 < dt <= 10 s")]
            self.record(found)
            self.counters["rejected"] += 1
            return found
        if self.smoother.mode != "position":
            # a new stream: the target starts where the trajectory is now, never at an old target
            self.targets.reset(self.smoother.poses())
            self.smoother.track()
        end = self.targets.proposed_end(u)
        found = pull_back(end, self.smoother.p, self.smoother.R, self.cfg.max_target_lead_m, self.cfg.max_target_lead_rad)
        end, clipped = clip_target(end, self.env, self.smoother.poses())
        self.targets.add(end, dt, now)
        found += clipped
        self.record(found)
        if found:
            self.counters["clipped"] += 1
        self.last_cmd_t = now
        self.counters["accepted"] += 1
        return found

    def hold(self, reason: str, now: float) -> None:
        """The controller asks to hold: brake to rest; a later increment starts a new stream."""
        self.last_cmd_t = now
        self.stop()
        self._event("hold", reason)

    def watchdog(self, now: float) -> bool:
        """Brake to rest if no command came for the watchdog's time (stopped at the last period before
        the deadline); True if it stopped the arms now."""
        if self.mode == "position" and now + self.period - self.last_cmd_t > self.limits.watchdog_s:
            self.stop()
            self.counters["watchdog_stops"] += 1
            self._event("watchdog", f"no command for {(now - self.last_cmd_t) * 1000:.0f} ms: stopping")
            return True
        return False

    # -- out: smoothing, limits ------------------------------------------------------------------

    def tick(self, now: float) -> Tick:
        """The poses to command for the period starting at `now` (reached at now + period), through
        smoothing and the limits' gate."""
        if self.last_sent is None:
            raise RuntimeError("ServoPath.reset() must come before tick()")
        sm, mode = self.smoother, self.smoother.mode
        if mode == "idle":
            return Tick(None, mode="idle")
        target = self.targets.target(now + self.period) if mode == "position" else None
        step = sm.step(target)
        found: list[Violation] = []
        if step.error:
            found.append(Violation("both", "trajectory", step.error))
        cmd, gate = check_and_clip(step.poses, self.last_sent, self.period, self.env)
        found += gate
        if cmd is not step.poses:  # the gate changed it: continue the trajectory from what was sent
            sm.sync(cmd if cmd is not None else self.last_sent, self.last_sent, self.period)
        if cmd is None:
            sm.begin_stop()
            sm.sync(self.last_sent, self.last_sent, self.period)  # at rest where the arm was sent
            sm.mode = "idle"
        else:
            self.last_sent = cmd
        return Tick(cmd, found, step, sm.mode, halting=mode == "stopping")

    # -- out: reach, wire ------------------------------------------------------------------------

    def cycle(self, now: float, active: Sequence[ArmName] = ARMS) -> Cycle:
        """The ServoPs (or ServoJs) for the `active` arms for the period starting at `now`. The reach
        check runs for ServoJ (it solves the joints) and when `check_reach` is set."""
        prev = self.last_sent
        self._before = None if prev is None else (prev, {a: q.copy() for a, q in self.q_seed.items()})
        tick = self.tick(now)  # a stop in progress carries on whatever else is wrong
        self.record(tick.violations)
        if tick.command is None or prev is None:
            return Cycle(violations=tick.violations)
        poses: Poses | None = tick.command
        joints: Joints | None = None
        fault: str | None = None
        if active and (self.cfg.servo_command == "servoj" or self.cfg.check_reach):
            poses, joints, fault = self.within_reach(prev, tick.command, list(active))
        if poses is None:
            return Cycle(None, None, fault, tick.violations, tick.halting)
        servo = servo_commands(poses, joints, tick.halting, active, self.frames, self.cfg, self.servo_t)
        return Cycle(poses, joints, fault, tick.violations, tick.halting, servo)

    def _episode(self, kind: str, was: bool, now: bool, start: str, end: str) -> bool:
        """Count a period of `kind` (`now`) and tell when a run of them starts (`start`) or ends (`end`); `now`."""
        if now:
            self.counters[kind] += 1
            if not was:
                self._event(kind, start)
        elif was:
            self._event(kind, f"{end} after {self.counters[kind]} {kind} periods in all")
        return now

    def within_reach(self, prev: Poses, cmd: Poses, active: list[ArmName]) -> tuple[Poses | None, Joints | None, str | None]:
        """`cmd`, or the longest part of the step from `prev` the joints of the `active` arms can follow,
        with their joints; or a fault when not even the last command can be held.

        Each target is solved nearest the joints of the last one (see `reach`): near the wrist singularity
        the tools' rotation lags while the mounts go where they are sent; else the arms slow down to the
        joints' speed instead of making a controller alarm; a target out of reach or with the tool against
        the arm's body stops them short of it.
        """
        limit = cr5.JOINT_SPEED_LIMIT * self.period * REACH_JOINT_SPEED_FRACTION
        frames = {a: self.frames[a] for a in active}
        seeds = {a: self.q_seed[a] for a in active}
        tools = {a: np.asarray(self.rig.arms[a].mount_offset, dtype=float) for a in active}
        solve = joint_solver(frames, seeds, tools, limit)
        lag = wrist_lag(frames, seeds, tools, arm_solver(frames, seeds, tools, limit))
        r = solve_within(prev, cmd, solve, lag=lag, accept=lambda poses: not violations(poses, prev, self.period, self.env))
        if r.lagged is not None and r.poses is not None and r.joints is not None:
            # the positions go as planned; the rotation carries on from what is sent
            self.smoother.sync(r.poses, prev, self.period, rotation_only=True)
            self.last_sent = {a: np.array(r.poses[a], dtype=float) for a in ARMS}
        self.lagging = self._episode("lagged", self.lagging, r.lagged is not None, f"near the wrist singularity: {r.lagged}",
                                     "the rotation follows again")
        if r.poses is None or r.joints is None:  # (solve_within finds both or neither)
            self.stop()
            return None, None, f"cannot hold the last command either: {r.why}"
        poses, joints = r.poses, r.joints
        if r.why is not None:
            if r.fraction > 0 and violations(poses, prev, self.period, self.env):
                held = solve_within(prev, prev, solve)  # the shortened step left the envelope (it never should): hold
                if held.poses is None or held.joints is None:
                    self.stop()
                    return None, None, "cannot hold the last command either: its joints are unreachable now"
                r = Reach(prev, held.joints, 0.0, "the shortened step left the safety envelope")
                poses, joints = prev, held.joints
            # the trajectory carries on from what is sent, `prev` being the command before
            self.smoother.sync(poses, prev, self.period)
            self.last_sent = {a: np.array(poses[a], dtype=float) for a in ARMS}
        self.slowing = self._episode("slowed", self.slowing, r.why is not None, f"{r.why}: {r.fraction:.0%} of the step sent",
                                     "full speed again")
        for a in active:
            self.q_seed[a] = joints[a]
        return poses, joints, None
