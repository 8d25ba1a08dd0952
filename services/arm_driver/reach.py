"""Joint-space reach of each servo command: a step the joints cannot follow lags or is slowed, not refused.

Near a wrist singularity of the CR5 (J5 near 0) a small Cartesian step asks J4 and J6 for a large
turn; sent as is, the controller alarms on its joint speed limit and stops that arm dead. The
driver therefore solves every command with `bagit.common.cr5.ik` nearest the joints of the last
one, and when some joint would move more than `max_joint_step_rad` in a period:

- first the tool's rotation lags (`wrist_lag`): the mounts (which hold the rim) go where they are
  sent, and the tool turns only as far as the wrist can follow: a damped least-squares step from the
  last joints, the position exact, the rotation it cannot make about the singular axis left for
  later; the trajectory catches the target up, jerk-limited, once the wrist is clear of J5 = 0.
  Without it, a wrist passing near J5 = 0 again and again spins J4 and J6 (about half a turn each
  pass, at the joints' speed) until J4 winds into its +-360 deg limit, where the arm is held
  (docs/experiments.md, the core zoo's control failures);
- where that cannot be followed either (the edge of the reach, the tool against the arm), the
  longest part of the step every joint can follow (the same fraction for both arms, so they stay
  in step): the arms stop short of a target out of reach; only a command that cannot be followed at
  all is refused.

Both engage only where the full step cannot be followed, so a run that never slowed is unchanged.

    solve = joint_solver(frames, seeds, mount_offsets, max_joint_step_rad)
    lag = wrist_lag(frames, seeds, mount_offsets, arm_solver(frames, seeds, mount_offsets, max_joint_step_rad))
    reach = solve_within(prev, cmd, solve, lag=lag, accept=ok)   # solve(poses) -> (joints per arm, None) or (None, why)
    reach.poses, reach.joints, reach.fraction, reach.why, reach.lagged
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from bagit.common import cr5
from bagit.common.rig import ARMS, ArmName
from bagit.common.so3 import rotvec_between, so3_exp, so3_log
from bagit.services.arm_driver.frames import ArmFrames, Poses

Joints = dict[ArmName, np.ndarray]  # arm -> (6,) rad
Solver = Callable[[Poses], tuple[Joints | None, str | None]]
ArmSolver = Callable[[ArmName, np.ndarray], tuple[np.ndarray | None, str | None]]
Lag = Callable[[Poses, float], Poses]  # (cmd, share s of the wrist's rotation made) -> poses: cmd's positions, lagging rotations

BISECTIONS = 10  # the fraction sent is within 1/1024 of the longest that can be followed
ELBOW_MARGIN_RAD = cr5.ELBOW_MARGIN_RAD  # the driver keeps the elbow this far from straight
# ... or, where it already is closer (`elbow_floor`), no straighter than its seed less this (the IK's round-off).
ELBOW_SLACK_RAD = 1e-9
# Damping of the wrist's rotation step (rad of joint per rad of tool turn): a rotation the joints make with
# a gain below it (about the singular axis, J5 within ~6 deg of 0) is made only in part, 1 / (2 LAG_DAMPING)
# rad of joint per rad at most.
LAG_DAMPING = 0.1
# A joint the lagging step would take within this of its limit is held where it is (the rotation lags instead).
LIMIT_MARGIN_RAD = float(np.radians(1.0))


@dataclass(frozen=True)
class Reach:
    """What to send: `poses` (None: nothing can be sent), their `joints`, the `fraction` of the step kept."""

    poses: Poses | None
    joints: Joints | None
    fraction: float
    why: str | None  # why the full step could not be sent (None when it could)
    lagged: str | None = None  # the full step's positions were sent, its rotation only in part: why (`wrist_lag`)


def interpolate(prev: Poses, cmd: Poses, s: float) -> Poses:
    """Poses a fraction `s` of the way from `prev` to `cmd`: positions linearly, rotations along the geodesic."""
    out: dict[ArmName, np.ndarray] = {}
    for a in ARMS:
        T = np.eye(4)
        T[:3, 3] = prev[a][:3, 3] + s * (cmd[a][:3, 3] - prev[a][:3, 3])
        T[:3, :3] = so3_exp(s * rotvec_between(prev[a][:3, :3], cmd[a][:3, :3])) @ prev[a][:3, :3]
        out[a] = T
    return out


def elbow_floor(seed: np.ndarray) -> float:
    """How far from straight the elbow of a solution nearest `seed (6,)` must stay: ELBOW_MARGIN_RAD, or
    where the seed already is when closer. Creeping at the edge of the reach puts each pose sent ever
    nearer the margin, and the ServoP's 6 decimals put the controller's target up to ~3e-7 rad inside
    it: a restart from that target holds there and may leave it, never straighten the elbow further."""
    return min(ELBOW_MARGIN_RAD, abs(float(seed[2])) - ELBOW_SLACK_RAD)


def arm_solver(
    frames: dict[ArmName, ArmFrames], seeds: Joints, mount_offsets: dict[ArmName, np.ndarray], max_joint_step_rad: float
) -> ArmSolver:
    """Solve one arm's mount pose nearest its seed: (joints, None) or (None, why): see `joint_solver`."""

    def solve_arm(a: ArmName, pose: np.ndarray) -> tuple[np.ndarray | None, str | None]:
        seed = seeds[a]
        q = cr5.ik(frames[a].flange_in_base(pose), seed)
        if q is None or abs(q[2]) < elbow_floor(seed):
            return None, f"{a}: out of the arm's reach"
        step = np.abs(q - seed)
        if step.max() > max_joint_step_rad:
            j = int(np.argmax(step))
            return None, (f"{a}: a joint would have to move faster than it can "
                          f"(J{j + 1} {np.degrees(seed[j]):.1f} -> {np.degrees(q[j]):.1f} deg in one period)")
        if cr5.self_collision(q, mount_offsets[a]):
            return None, f"{a}: the tool would be against the arm's own body"
        return q, None

    return solve_arm


def joint_solver(
    frames: dict[ArmName, ArmFrames], seeds: Joints, mount_offsets: dict[ArmName, np.ndarray], max_joint_step_rad: float
) -> Solver:
    """Solve each arm in `frames` nearest its `seeds`; refuse a step no joint could follow in a period.

    Refused: a pose out of reach (or with the elbow closer to straight than `elbow_floor`), one where
    some joint moves more than `max_joint_step_rad` from its seed, or one that puts the tool
    (`mount_offsets`, in the flange frame) against the arm's body.
    """
    solve_arm = arm_solver(frames, seeds, mount_offsets, max_joint_step_rad)

    def solve(poses: Poses) -> tuple[Joints | None, str | None]:
        out = {}
        for a in frames:
            q, why = solve_arm(a, poses[a])
            if q is None:
                return None, why
            out[a] = q
        return out, None

    return solve


def _dls_step(q0: np.ndarray, p_goal: np.ndarray, R_goal: np.ndarray, tool: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joint steps `(6,)` from `q0` towards the tool point at `p_goal (3,)` with rotation `R_goal (3, 3)`
    (base frame): the position's minimum-norm step, and the rotation's damped least-squares step in the
    position's null space (the second never moves the tool point, to first order); and the `(6,)` mask of
    the joints free to move: one the sum would take within LIMIT_MARGIN_RAD of its limit is held."""
    F = cr5.fk(q0)
    e_p = p_goal - (F[:3, 3] + F[:3, :3] @ tool)
    e_o = so3_log(R_goal @ F[:3, :3].T)
    J = cr5.jacobian(q0, tool)
    free = np.ones(6, dtype=bool)
    dq_p = dq_o = np.zeros(6)
    for _ in range(2):
        Jf = J * free  # (6, 6) held joints' columns zero
        Jp_pinv = np.linalg.pinv(Jf[:3])
        dq_p = Jp_pinv @ e_p
        A = Jf[3:] @ (np.eye(6) - Jp_pinv @ Jf[:3])  # (3, 6) the rotation the position's null space makes
        U, S, Vt = np.linalg.svd(A, full_matrices=False)
        dq_o = Vt.T @ ((S / (S**2 + LAG_DAMPING**2)) * (U.T @ (e_o - Jf[3:] @ dq_p)))
        q1 = q0 + dq_p + dq_o
        out = (q1 < cr5.JOINT_LIMITS[:, 0] + LIMIT_MARGIN_RAD) | (q1 > cr5.JOINT_LIMITS[:, 1] - LIMIT_MARGIN_RAD)
        if not (out & free).any():
            break
        free &= ~out
    return dq_p, dq_o, free


def _onto_position(q: np.ndarray, p_goal: np.ndarray, tool: np.ndarray, free: np.ndarray, iterations: int = 3) -> np.ndarray:
    """`q (6,)` moved (the `free` joints, minimum-norm Newton steps) until the tool point is at `p_goal (3,)`:
    the linear step leaves a second-order error, which the exact inverse kinematics would turn into a
    large wrist turn this close to J5 = 0."""
    for _ in range(iterations):
        F = cr5.fk(q)
        e = p_goal - (F[:3, 3] + F[:3, :3] @ tool)
        if float(np.abs(e).max()) < 1e-12:
            break
        q = q + np.linalg.pinv(cr5.jacobian(q, tool)[:3] * free) @ e
    return q


def wrist_lag(
    frames: dict[ArmName, ArmFrames], seeds: Joints, mount_offsets: dict[ArmName, np.ndarray], solve_arm: ArmSolver
) -> Lag:
    """For each arm in `frames` that cannot follow its step (`solve_arm`): `cmd`'s mount position with the
    rotation of the damped least-squares step from its `seeds` (`_dls_step`), `s` of the way (0: only the
    turn the position's step makes). The other arms keep `cmd`'s pose."""

    def lag(cmd: Poses, s: float) -> Poses:
        out = dict(cmd)
        for a, fr in frames.items():
            if solve_arm(a, cmd[a])[0] is not None:
                continue
            Tb = fr.flange_in_base(cmd[a])
            tool = np.asarray(mount_offsets[a], dtype=float)
            p_goal = Tb[:3, 3] + Tb[:3, :3] @ tool
            dq_p, dq_o, free = _dls_step(seeds[a], p_goal, Tb[:3, :3], tool)
            R_base = cr5.fk(_onto_position(seeds[a] + dq_p + s * dq_o, p_goal, tool, free))[:3, :3]
            T = cmd[a].copy()
            T[:3, :3] = fr.T_world_base[:3, :3] @ R_base  # the mount's rotation is the flange's
            out[a] = T
        return out

    return lag


def _lagged(cmd: Poses, solve: Solver, lag: Lag, accept: Callable[[Poses], bool], bisections: int) -> Reach | None:
    """The largest share of the wrist's rotation step (`lag`) that `solve` and `accept` take, with
    `cmd`'s positions; None if not even the position alone can be sent so."""
    best: tuple[float, Poses, Joints] | None = None
    for s in (1.0, 0.0):
        poses = lag(cmd, s)
        q, _ = solve(poses)
        if q is not None and accept(poses):
            best = (s, poses, q)
            break
    if best is None:
        return None
    if best[0] == 0.0:
        lo, hi = 0.0, 1.0
        for _ in range(bisections):
            mid = 0.5 * (lo + hi)
            poses = lag(cmd, mid)
            q, _ = solve(poses)
            if q is not None and accept(poses):
                lo, best = mid, (mid, poses, q)
            else:
                hi = mid
    s, poses, joints = best
    turn = max(float(np.linalg.norm(rotvec_between(poses[a][:3, :3], cmd[a][:3, :3]))) for a in poses)
    return Reach(poses, joints, 1.0, None, lagged=f"the rotation lags {np.degrees(turn):.2f} deg ({s:.0%} of the wrist's step)")


def solve_within(
    prev: Poses, cmd: Poses, solve: Solver, bisections: int = BISECTIONS, lag: Lag | None = None,
    accept: Callable[[Poses], bool] = lambda poses: True,
) -> Reach:
    """The longest part of the step `prev -> cmd` that `solve` accepts (see the module doc).

    If the full step is refused and `lag` is given, first `cmd`'s positions with the rotations lagging
    (`wrist_lag`; `accept` must also take them: the envelope). Otherwise `solve` is monotone in
    practice: a joint step grows with the Cartesian step, so bisection on the fraction finds the
    longest acceptable one. `prev` itself was accepted last period; if it is no longer (the joints it
    was solved from changed), nothing can be sent.
    """
    joints, why = solve(cmd)
    if joints is not None:
        return Reach(cmd, joints, 1.0, None)
    if lag is not None and (lagged := _lagged(cmd, solve, lag, accept, bisections)) is not None:
        return lagged
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
