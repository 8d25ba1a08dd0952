"""Joint-space reach of each servo command: a step the joints cannot follow is slowed, not refused.

Near a wrist singularity of the CR5 (J5 near 0) a small Cartesian step asks J4 and J6 for a large
turn; sent as is, the controller alarms on its joint speed limit and stops that arm dead. The
driver therefore solves every command with `bagit.common.cr5.ik` nearest the joints of the last
one, and when some joint would move more than `max_joint_step_rad` in a period it sends, instead,
the longest part of the step (the same fraction for both arms, so they stay in step) that every
joint can follow. The arms then pass through a singularity slowly, at the joints' speed, or stop
short of a target out of reach; only a command that cannot be followed at all is refused.

    solve = joint_solver(frames, seeds, mount_offsets, max_joint_step_rad)
    reach = solve_within(prev, cmd, solve)   # solve(poses) -> (joints per arm, None) or (None, why)
    reach.poses, reach.joints, reach.fraction, reach.why
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from bagit.common import cr5
from bagit.common.rig import ARMS, ArmName
from bagit.common.so3 import rotvec_between, so3_exp
from bagit.services.arm_driver.frames import ArmFrames, Poses

Joints = dict[ArmName, np.ndarray]  # arm -> (6,) rad
Solver = Callable[[Poses], tuple[Joints | None, str | None]]

BISECTIONS = 10  # the fraction sent is within 1/1024 of the longest that can be followed
ELBOW_MARGIN_RAD = cr5.ELBOW_MARGIN_RAD  # the driver keeps the elbow this far from straight


@dataclass(frozen=True)
class Reach:
    """What to send: `poses` (None: nothing can be sent), their `joints`, the `fraction` of the step kept."""

    poses: Poses | None
    joints: Joints | None
    fraction: float
    why: str | None  # why the full step could not be sent (None when it could)


def interpolate(prev: Poses, cmd: Poses, s: float) -> Poses:
    """Poses a fraction `s` of the way from `prev` to `cmd`: positions linearly, rotations along the geodesic."""
    out: dict[ArmName, np.ndarray] = {}
    for a in ARMS:
        T = np.eye(4)
        T[:3, 3] = prev[a][:3, 3] + s * (cmd[a][:3, 3] - prev[a][:3, 3])
        T[:3, :3] = so3_exp(s * rotvec_between(prev[a][:3, :3], cmd[a][:3, :3])) @ prev[a][:3, :3]
        out[a] = T
    return out


def joint_solver(
    frames: dict[ArmName, ArmFrames], seeds: Joints, mount_offsets: dict[ArmName, np.ndarray], max_joint_step_rad: float
) -> Solver:
    """Solve each arm in `frames` nearest its `seeds`; refuse a step no joint could follow in a period.

    Refused: a pose out of reach (or with the elbow within `ELBOW_MARGIN_RAD` of straight), one where
    some joint moves more than `max_joint_step_rad` from its seed, or one that puts the tool
    (`mount_offsets`, in the flange frame) against the arm's body.
    """

    def solve(poses: Poses) -> tuple[Joints | None, str | None]:
        out = {}
        for a, fr in frames.items():
            seed = seeds[a]
            q = cr5.ik(fr.flange_in_base(poses[a]), seed)
            if q is None or abs(q[2]) < ELBOW_MARGIN_RAD:
                return None, f"{a}: out of the arm's reach"
            step = np.abs(q - seed)
            if step.max() > max_joint_step_rad:
                j = int(np.argmax(step))
                return None, (f"{a}: a joint would have to move faster than it can "
                              f"(J{j + 1} {np.degrees(seed[j]):.1f} -> {np.degrees(q[j]):.1f} deg in one period)")
            if cr5.self_collision(q, mount_offsets[a]):
                return None, f"{a}: the tool would be against the arm's own body"
            out[a] = q
        return out, None

    return solve


def solve_within(prev: Poses, cmd: Poses, solve: Solver, bisections: int = BISECTIONS) -> Reach:
    """The longest part of the step `prev -> cmd` that `solve` accepts (see the module doc).

    `solve` is monotone in practice: a joint step grows with the Cartesian step, so bisection on the
    fraction finds the longest acceptable one. `prev` itself was accepted last period; if it is no
    longer (the joints it was solved from changed), nothing can be sent.
    """
    joints, why = solve(cmd)
    if joints is not None:
        return Reach(cmd, joints, 1.0, None)
    lo, lo_joints, lo_poses = 0.0, None, None
    hi = 1.0
    for _ in range(bisections):
        mid = 0.5 * (lo + hi)
        poses = interpolate(prev, cmd, mid)
        q, _ = solve(poses)
        if q is None:
            hi = mid
        else:
            lo, lo_joints, lo_poses = mid, q, poses
    if lo_joints is None:
        q, _ = solve(prev)
        if q is None:
            return Reach(None, None, 0.0, why)
        return Reach(prev, q, 0.0, why)
    return Reach(lo_poses, lo_joints, lo, why)
