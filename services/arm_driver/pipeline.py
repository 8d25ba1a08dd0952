"""From controller increments to the poses sent each servo period: targets, Ruckig, safety gate.

`MotionPipeline` is the driver's motion logic without sockets or threads, so it can be tested
and benchmarked on its own (and driven by property tests with arbitrary input):

    pipe = MotionPipeline(Envelope.from_rig(rig), period=0.03)
    pipe.reset(measured_mount_poses)          # at rest, nothing streams
    pipe.submit(u, dt, now)                   # a command: starts a stream if none runs
    out = pipe.tick(now)                      # every period: out.command is None or the poses to send
    pipe.stop()                               # watchdog / fault: Ruckig brakes to rest, then idle

Every increment goes through the static envelope (workspace boxes, mount separation) and a lead
limit (how far the target may run ahead of the commanded pose) when it arrives; every pose that
leaves goes through `check_and_clip`, so the limits hold whatever comes in.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bagit.common.rig import ARMS
from bagit.common.so3 import rotvec_between, so3_exp
from bagit.services.arm_driver.frames import Poses
from bagit.services.arm_driver.safety import MEASURED_TOL_M, Envelope, Violation, check_and_clip, clip_target, violations
from bagit.services.arm_driver.streaming import Streamer, StreamStep, TargetIntegrator


@dataclass
class Tick:
    """One period's result: the poses to send (None: send nothing), what the gate found, the trajectory;
    `halting`: the poses brake to rest (a stop, not a command being tracked)."""

    command: Poses | None
    violations: list[Violation] = field(default_factory=list)
    step: StreamStep | None = None
    mode: str = "idle"
    halting: bool = False


class MotionPipeline:
    """Increments in, safe jerk-limited mount poses out, one servo period at a time."""

    def __init__(self, env: Envelope, period: float, max_lead_m: float = 0.05, max_lead_rad: float = 0.35):
        self.env = env
        self.period = float(period)
        self.max_lead_m = float(max_lead_m)
        self.max_lead_rad = float(max_lead_rad)
        self.streamer = Streamer(env.limits, self.period)
        self.targets = TargetIntegrator()
        self.last_sent: Poses | None = None

    # -- state -----------------------------------------------------------------------------------

    def reset(self, poses: Poses) -> list[Violation]:
        """Start over at rest at `poses` (the measured mount poses); returns the limits they already break
        by more than an arm's following error (MEASURED_TOL_M)."""
        self.streamer.reset(poses)
        self.targets.reset(poses)
        self.last_sent = {a: np.array(poses[a], dtype=float) for a in ARMS}
        return violations(self.last_sent, None, self.period, self.env, tol=MEASURED_TOL_M)

    @property
    def mode(self) -> str:
        """'idle', 'position' (streaming) or 'stopping'."""
        return self.streamer.mode

    @property
    def moving(self) -> bool:
        return self.streamer.mode != "idle"

    def stop(self) -> None:
        """Brake smoothly to rest and forget the target; a later `submit` starts a new stream from there."""
        self.streamer.begin_stop()

    def halt(self) -> None:
        """Drop the trajectory at once (the controllers stopped the arms themselves: e-stop); idle."""
        self.streamer.mode = "idle"
        self.streamer.vel[:] = 0.0
        self.streamer.acc[:] = 0.0

    # -- input -----------------------------------------------------------------------------------

    def submit(self, u: np.ndarray, dt: float, now: float) -> list[Violation]:
        """Apply increment `u (12,)` (left dx dy dz drx dry drz, right ..., world, m and rad) over `dt` s.

        A non-finite increment or dt is rejected whole. A stream starts from the commanded pose if
        none runs. Returns the violations found (the target was clipped, or the command rejected).
        """
        u = np.asarray(u, dtype=float)
        if u.shape != (12,) or not np.all(np.isfinite(u)) or not (np.isfinite(dt) and 0 < dt <= 10.0):
            return [Violation("both", "non_finite", "increment rejected: it must be 12 finite numbers over 0 < dt <= 10 s")]
        if self.streamer.mode != "position":
            # a new stream: the target starts where the trajectory is now, never at an old target
            self.targets.reset(self.streamer.poses())
            self.streamer.track()
        end = self.targets.proposed_end(u)
        found = self._pull_back(end)
        end, clipped = clip_target(end, self.env, self.streamer.poses())
        self.targets.add(end, dt, now)
        return found + clipped

    def _pull_back(self, end: Poses) -> list[Violation]:
        """Limit how far `end` is from the trajectory's current pose (in place)."""
        found = []
        for i, a in enumerate(ARMS):
            T = end[a]
            d = T[:3, 3] - self.streamer.p[i]
            n = float(np.linalg.norm(d))
            if n > self.max_lead_m:
                T[:3, 3] = self.streamer.p[i] + d * (self.max_lead_m / n)
                found.append(Violation(a, "lead", f"target {n * 1000:.0f} mm ahead, pulled back to {self.max_lead_m * 1000:.0f} mm"))
            rv = rotvec_between(self.streamer.R[i], T[:3, :3])
            ang = float(np.linalg.norm(rv))
            if ang > self.max_lead_rad:
                T[:3, :3] = so3_exp(rv * (self.max_lead_rad / ang)) @ self.streamer.R[i]
                found.append(Violation(a, "lead", f"target turned {ang:.2f} rad ahead, pulled back to {self.max_lead_rad:.2f} rad"))
        return found

    # -- output ----------------------------------------------------------------------------------

    def tick(self, now: float) -> Tick:
        """The poses to command for the period starting at `now` (they are reached at now + period)."""
        if self.last_sent is None:
            raise RuntimeError("MotionPipeline.reset() must come before tick()")
        mode = self.streamer.mode
        if mode == "idle":
            return Tick(None, mode="idle")
        target = self.targets.target(now + self.period) if mode == "position" else None
        step = self.streamer.step(target)
        found: list[Violation] = []
        if step.error:
            found.append(Violation("both", "trajectory", step.error))
        cmd, gate = check_and_clip(step.poses, self.last_sent, self.period, self.env)
        found += gate
        if cmd is not step.poses:  # the gate changed it: continue the trajectory from what was sent
            self.streamer.sync(cmd if cmd is not None else self.last_sent, self.last_sent, self.period)
        if cmd is None:
            self.streamer.begin_stop()
            self.streamer.sync(self.last_sent, self.last_sent, self.period)  # at rest where the arm was sent
            self.streamer.mode = "idle"
        else:
            self.last_sent = cmd
        return Tick(cmd, found, step, self.streamer.mode, halting=mode == "stopping")

    def replace_last(self, sent: Poses, previous: Poses) -> None:
        """The driver sent `sent` instead of the last tick's command (the joints could not follow it,
        see `reach`): carry the trajectory on from what was sent, `previous` being the command before."""
        self.streamer.sync(sent, previous, self.period)
        self.last_sent = {a: np.array(sent[a], dtype=float) for a in ARMS}

    def commanded(self) -> Poses:
        """The last poses sent (or the reset poses)."""
        if self.last_sent is None:
            raise RuntimeError("MotionPipeline.reset() must come before commanded()")
        return {a: self.last_sent[a].copy() for a in ARMS}

