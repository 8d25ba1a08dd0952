"""The arm driver's motion rules, with no sockets, threads or clock of their own.

`ArmMotion` is what both CR5s' commands go through, whoever hosts it: the `ArmDriver` (its servo
thread, TCP clients and latches around it) on a rig, and `bagit run`'s in-process loop on the
simulator's clock. It holds the motion pipeline (static envelope and lead limit on each increment,
12-axis Ruckig, the safety gate on each pose sent), the watchdog and the joint-speed-aware reach:

    m = ArmMotion(rig, DriverConfig(), on_event=log)
    m.restart(feedback_records)          # at rest where the controllers command the arms
    m.submit(u, dt, now)                 # a controller increment; violations found
    m.hold(reason)                       # the controller asks to hold: brake to rest
    m.watchdog(now)                      # no command for watchdog_s: brake to rest
    out = m.cycle(now, active_arms)      # one servo period: poses (and joints) to send, or a fault

Every event (clip, slow-down, watchdog stop) is counted in `counters` and told to `on_event`.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from bagit.common import cr5
from bagit.common.rig import ARMS, ArmName, RigConfig
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.arm_driver.frames import ArmFrames, Poses
from bagit.services.arm_driver.pipeline import MotionPipeline
from bagit.services.arm_driver.reach import Joints, Reach, joint_solver, solve_within
from bagit.services.arm_driver.safety import Envelope, Violation, violations

# A step whose joints would move faster than this fraction of the CR5's joint speed limit is shortened
# (the controller alarms at the limit, measured from its own lagging reference: keep well clear).
REACH_JOINT_SPEED_FRACTION = 0.5


@dataclass
class Cycle:
    """One servo period: the mount `poses` to send (None: nothing), their `joints`, a `fault` that stops
    the arms; `halting`: the poses brake to rest (sent with the halting servo parameters)."""

    poses: Poses | None = None
    joints: Joints | None = None
    fault: str | None = None
    violations: list[Violation] = field(default_factory=list)
    halting: bool = False


class ArmMotion:
    """Increments in, safe jerk-limited mount poses out (see the module docstring). Not thread-safe:
    the host serialises calls."""

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
        self.env = Envelope.from_rig(rig)
        self.frames = {a: ArmFrames.from_config(rig.arms[a]) for a in ARMS}
        self.pipe = MotionPipeline(self.env, self.period, self.cfg.max_target_lead_m, self.cfg.max_target_lead_rad)
        self.on_event = on_event
        self.counters: Counter[str] = counters if counters is not None else Counter()
        self.violation_counts: Counter[str] = Counter()
        self.last_violations: list[str] = []
        self.q_seed: Joints = {}
        self.last_cmd_t = -np.inf
        self.slowing = False  # the last period's step was shortened to the joints' speed

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
    def moving(self) -> bool:
        return self.pipe.moving

    def aim(self) -> Poses | None:
        """Where the arm side is taking the mounts: the end of the increments taken while it streams,
        the trajectory's own pose while it brakes or rests (None before the first `restart`). Less the
        measured poses, it is the motion still in flight, which a controller's prediction needs: the
        arms follow a command over several servo periods (target, Ruckig, the controllers' servo loop)."""
        if self.pipe.last_sent is None:
            return None
        return self.pipe.targets.end() if self.pipe.mode == "position" else self.pipe.streamer.poses()

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
        found = self.pipe.reset(poses)
        self.q_seed = q
        self.last_cmd_t = -np.inf
        self.record(found)
        return found

    # -- input -----------------------------------------------------------------------------------

    def submit(self, u: np.ndarray, dt: float, now: float) -> list[Violation]:
        """Increment `u (12,)` (world, m and rad; left then right) over `dt` s at `now`. A non-finite
        one is refused whole (a `non_finite` violation); a clipped one counts as `clipped`."""
        found = self.pipe.submit(u, dt, now)
        self.record(found)
        if any(v.kind == "non_finite" for v in found):
            self.counters["rejected"] += 1
            return found
        if found:
            self.counters["clipped"] += 1
        self.last_cmd_t = now
        self.counters["accepted"] += 1
        return found

    def hold(self, reason: str, now: float) -> None:
        """The controller asks to hold: brake to rest; a later increment starts a new stream."""
        self.last_cmd_t = now
        self.pipe.stop()
        self._event("hold", reason)

    def watchdog(self, now: float) -> bool:
        """Brake to rest if no command came for the watchdog's time (stopped at the last period before
        the deadline); True if it stopped the arms now."""
        if self.pipe.mode == "position" and now + self.period - self.last_cmd_t > self.limits.watchdog_s:
            self.pipe.stop()
            self.counters["watchdog_stops"] += 1
            self._event("watchdog", f"no command for {(now - self.last_cmd_t) * 1000:.0f} ms: stopping")
            return True
        return False

    # -- output ----------------------------------------------------------------------------------

    def cycle(self, now: float, active: Sequence[ArmName] = ARMS, check_reach: bool = True) -> Cycle:
        """The poses (and joints) to send to the `active` arms for the period starting at `now`."""
        prev = self.pipe.last_sent
        tick = self.pipe.tick(now)  # a stop in progress carries on whatever else is wrong
        self.record(tick.violations)
        if tick.command is None or prev is None:
            return Cycle(violations=tick.violations)
        if not active or not check_reach:
            return Cycle(tick.command, None, None, tick.violations, tick.halting)
        poses, joints, fault = self.within_reach(prev, tick.command, list(active))
        return Cycle(poses, joints, fault, tick.violations, tick.halting)

    def within_reach(self, prev: Poses, cmd: Poses, active: list[ArmName]) -> tuple[Poses | None, Joints | None, str | None]:
        """`cmd`, or the longest part of the step from `prev` the joints of the `active` arms can follow,
        with their joints; or a fault when not even the last command can be held.

        Each target is solved nearest the joints of the last one (see `reach`): near a singularity the
        arms slow down to the joints' speed instead of making a controller alarm; a target out of
        reach or with the tool against the arm's body stops them short of it.
        """
        limit = cr5.JOINT_SPEED_LIMIT * self.period * REACH_JOINT_SPEED_FRACTION
        solve = joint_solver(
            {a: self.frames[a] for a in active},
            {a: self.q_seed[a] for a in active},
            {a: np.asarray(self.rig.arms[a].mount_offset, dtype=float) for a in active},
            limit,
        )
        r = solve_within(prev, cmd, solve)
        if r.poses is None or r.joints is None:  # (solve_within finds both or neither)
            self.pipe.stop()
            return None, None, f"cannot hold the last command either: {r.why}"
        poses, joints = r.poses, r.joints
        if r.why is not None:
            if r.fraction > 0 and violations(poses, prev, self.period, self.env):
                held = solve_within(prev, prev, solve)  # the shortened step left the envelope (it never should): hold
                if held.poses is None or held.joints is None:
                    self.pipe.stop()
                    return None, None, "cannot hold the last command either: its joints are unreachable now"
                r = Reach(prev, held.joints, 0.0, "the shortened step left the safety envelope")
                poses, joints = prev, held.joints
            self.pipe.replace_last(poses, prev)
            self.counters["slowed"] += 1
            if not self.slowing:
                self._event("slowed", f"{r.why}: {r.fraction:.0%} of the step sent")
        elif self.slowing:
            self._event("slowed", f"full speed again after {self.counters['slowed']} slowed periods in all")
        self.slowing = r.why is not None
        for a in active:
            self.q_seed[a] = joints[a]
        return poses, joints, None
