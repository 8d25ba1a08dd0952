"""Where the controller's increments put the target both arms stream to (the path's first layer).

`TargetIntegrator` turns the increments into targets: a `Command` moves the target by u over its
`dt`, linearly, starting when it arrives; a new command first completes the previous one, so every
increment is applied exactly once. Positions add, rotations compose (R <- exp(drv) R, about world
axes, as the controller's own model does). `pull_back` keeps a target within a lead of the
trajectory's pose, so a runaway controller cannot pull the arms far ahead of where they are.
"""

from __future__ import annotations

import numpy as np

from bagit.common.dual_arm import apply_increment
from bagit.common.rig import ARMS
from bagit.common.so3 import rotvec_between, so3_exp
from bagit.services.arm_driver.frames import Poses, arrays_to_poses, poses_to_arrays
from bagit.services.arm_driver.limits import Violation


def pull_back(end: Poses, p: np.ndarray, R: np.ndarray, max_lead_m: float, max_lead_rad: float) -> list[Violation]:
    """Limit how far `end` is from the trajectory's positions `p (2, 3)` and rotations `R (2, 3, 3)`
    (in place); the leads it cut."""
    found = []
    for i, a in enumerate(ARMS):
        T = end[a]
        d = T[:3, 3] - p[i]
        n = float(np.linalg.norm(d))
        if n > max_lead_m:
            T[:3, 3] = p[i] + d * (max_lead_m / n)
            found.append(Violation(a, "lead", f"target {n * 1000:.0f} mm ahead, pulled back to {max_lead_m * 1000:.0f} mm"))
        rv = rotvec_between(R[i], T[:3, :3])
        ang = float(np.linalg.norm(rv))
        if ang > max_lead_rad:
            T[:3, :3] = so3_exp(rv * (max_lead_rad / ang)) @ R[i]
            found.append(Violation(a, "lead", f"target turned {ang:.2f} rad ahead, pulled back to {max_lead_rad:.2f} rad"))
    return found


class TargetIntegrator:
    """The target pose both arms stream to, built from the controller's increments.

    The committed target holds every increment already completed; the active segment moves the
    target from `start` to `end` linearly over its `dt`, from the time its command arrived.
    """

    def __init__(self) -> None:
        self.start_p = np.zeros((2, 3))
        self.start_R = np.tile(np.eye(3), (2, 1, 1))
        self.end_p = self.start_p.copy()
        self.end_R = self.start_R.copy()
        self.t0 = 0.0
        self.dt = 1.0
        self._rv = np.zeros((2, 3))  # end = exp(rv) start

    def reset(self, poses: Poses) -> None:
        p, R = poses_to_arrays(poses)
        self.start_p, self.start_R = p, R
        self.end_p, self.end_R = p.copy(), R.copy()
        self._rv = np.zeros((2, 3))
        self.t0, self.dt = 0.0, 1.0

    def end(self) -> Poses:
        """Where the target will be once the active segment completes."""
        return arrays_to_poses(self.end_p, self.end_R)

    def proposed_end(self, u: np.ndarray) -> Poses:
        """The end pose after increment `u (12,)` on top of the current end (not applied)."""
        return apply_increment(self.end(), u)

    def add(self, end: Poses, dt: float, now: float) -> None:
        """Complete the active segment, then move towards `end` over `dt` seconds from `now`."""
        self.start_p, self.start_R = self.end_p.copy(), self.end_R.copy()
        self.end_p, self.end_R = poses_to_arrays(end)
        self._rv = np.stack([rotvec_between(self.start_R[i], self.end_R[i]) for i in range(2)])
        self.t0, self.dt = float(now), float(dt)

    def target(self, t: float) -> Poses:
        """The target pose at time `t`."""
        f = min(max((t - self.t0) / self.dt, 0.0), 1.0)
        if f >= 1.0:
            return self.end()
        p = self.start_p + f * (self.end_p - self.start_p)
        R = np.stack([so3_exp(f * self._rv[i]) @ self.start_R[i] for i in range(2)])
        return arrays_to_poses(p, R)
