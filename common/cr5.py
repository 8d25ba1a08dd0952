"""Kinematics of the Dobot CR5, shared by the simulator, the arm driver and the dashboard.

The CR5 is a UR-like 6R arm. Dobot's published URDF (`cr5_robot.urdf`) puts the link offsets at
d1 0.147, a2 0.427, a3 0.357, d4 0.141, d5 0.116, d6 0.105 m; reach about 900 mm; J3 within
±160°, the other joints ±360°. Its chain equals the standard UR Denavit-Hartenberg chain with the
joint angles shifted: theta_DH = q + JOINT_OFFSET (J2 and J4 by -90°). So q = 0 is Dobot's zero
(the arm straight up), and `fk(np.radians([0, 0, -90, 0, 90, 0]))` gives the flange at
(473, -141, 469) mm, rx, ry, rz = (-180, 0, -90)°, as in Dobot's own PositiveKin example.

Angles `q` are radians here; the wire protocol speaks degrees (see bagit.common.dobot). Dobot's
pose convention is [x, y, z, rx, ry, rz] in millimetres and degrees, rx, ry, rz being fixed-axis
X-Y-Z angles (R = Rz(rz) Ry(ry) Rx(rx)).

Public API: `fk(q) -> (4, 4)` base <- flange; `link_frames(q) -> (7, 4, 4)`; `ik_all(T) -> (k, 6)`
(the analytic solutions); `ik(T, q_seed) -> (6,) | None` (the valid solution nearest the seed);
`within_limits(q)`; `self_collision(q)`; `jacobian(q, tool_offset) -> (6, 6)`; `pose6_to_matrix(pose)`,
`matrix_to_pose6(T)`.
"""

from __future__ import annotations

import math

import numpy as np

from bagit.common.so3 import matrix_to_rpy, rpy_to_matrix

D1, A2, A3, D4, D5, D6 = 0.147, -0.427, -0.357, 0.141, 0.116, 0.105
DH_D = np.array([D1, 0.0, 0.0, D4, D5, D6])
DH_A = np.array([0.0, A2, A3, 0.0, 0.0, 0.0])
DH_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])
JOINT_OFFSET = np.array([0.0, -np.pi / 2, 0.0, -np.pi / 2, 0.0, 0.0])  # theta_DH = q + JOINT_OFFSET
JOINT_LIMITS = np.radians([[-360, 360], [-360, 360], [-160, 160], [-360, 360], [-360, 360], [-360, 360]])
JOINT_SPEED_LIMIT = np.radians(180.0)  # rad/s per joint
# rad/s^2 per joint: Dobot publishes no joint acceleration for the CR5; this is the project's model of it (the
# simulated controller's servo loop never accelerates a joint faster), in line with what arms of its class
# (5 kg, ~0.9 m, 180 deg/s joints) reach braking from full speed: the UR5's hardware manual (CB3, stop
# category 0 at full speed, reach and payload) stops joint 0 from 183 deg/s in 244 ms, about 13 rad/s^2.
JOINT_ACCEL_LIMIT = 12.0
REACH_M = 0.9
# An elbow stretched straight (J3 = 0) is the edge of the reach and a singularity: a target there,
# rounded to the wire's 6 decimals or solved from the controller's own seed, may have no solution,
# and the controller alarms. The arm driver keeps the elbow this far from straight, and the planner's
# reach check asks the same of the goal.
ELBOW_MARGIN_RAD = float(np.radians(2.0))
_TWO_PI = 2 * np.pi

# Self-collision model: the flange and wrist as spheres against the base column and the upper arm.
BASE_COLUMN_RADIUS = 0.075
UPPER_ARM_RADIUS = 0.06
WRIST_RADIUS = 0.05


def _dh(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1.0]])


def link_frames(q: np.ndarray) -> np.ndarray:
    """`(7, 4, 4)`: the base, then each joint's frame after it (the last is the tool flange), base frame."""
    theta = np.asarray(q, dtype=float) + JOINT_OFFSET
    out = np.empty((7, 4, 4))
    out[0] = np.eye(4)
    for i in range(6):
        np.matmul(out[i], _dh(float(theta[i]), DH_D[i], DH_A[i], DH_ALPHA[i]), out=out[i + 1])
    return out


def fk(q: np.ndarray) -> np.ndarray:
    """4x4 base <- flange for joint angles `q (6,)` in radians."""
    theta = np.asarray(q, dtype=float) + JOINT_OFFSET
    T = _dh(float(theta[0]), D1, 0.0, DH_ALPHA[0])
    for i in range(1, 6):
        T = T @ _dh(float(theta[i]), DH_D[i], DH_A[i], DH_ALPHA[i])
    return T


def jacobian(q: np.ndarray, tool_offset: np.ndarray | None = None) -> np.ndarray:
    """`(6, 6)` geometric Jacobian at the tool point (`tool_offset (3,)` in the flange frame; None: the
    flange), base frame: rows linear (m/rad) then angular velocity, one column per joint."""
    F = link_frames(q)
    tip = F[6][:3, 3] if tool_offset is None else F[6][:3, :3] @ np.asarray(tool_offset, dtype=float) + F[6][:3, 3]
    axes = F[:6, :3, 2]  # joint i turns about z of frame i-1
    out = np.empty((6, 6))
    out[:3] = np.cross(axes, tip - F[:6, :3, 3]).T
    out[3:] = axes.T
    return out


def within_limits(q: np.ndarray) -> bool:
    q = np.asarray(q, dtype=float)
    return bool(q.shape == (6,) and np.all(np.isfinite(q)) and np.all(q >= JOINT_LIMITS[:, 0]) and np.all(q <= JOINT_LIMITS[:, 1]))


def _segment_distances(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances `(k,)` of `points (k, 3)` to the segment from `a (3,)` to `b (3,)`."""
    ab = b - a
    t = np.clip((points - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    d = points - (a + t[:, None] * ab)
    return np.sqrt(np.einsum("ij,ij->i", d, d))


def self_collision(q: np.ndarray, tool_offset: np.ndarray | None = None) -> bool:
    """Whether the wrist, flange or tool (`tool_offset (3,)` in the flange frame) hits the base column or upper arm.

    A coarse sphere/capsule model, enough to refuse the folded poses a real CR5 alarms on
    ("end flange interferes with the robot body"); adjacent links are not tested against each other.
    """
    F = link_frames(q)
    wrist = [F[5][:3, 3], F[6][:3, 3]]
    if tool_offset is not None:
        wrist.append(F[6][:3, :3] @ np.asarray(tool_offset, dtype=float) + F[6][:3, 3])
    near = WRIST_RADIUS + np.array([BASE_COLUMN_RADIUS, UPPER_ARM_RADIUS])
    base_a, shoulder, elbow = np.zeros(3), F[1][:3, 3], F[2][:3, 3]
    # the wrist and tool against the base column and the upper arm; the wrist-1 joint at the forearm's
    # end against the base column
    if (_segment_distances(np.array(wrist + [F[4][:3, 3]]), base_a, shoulder) < near[0]).any():
        return True
    return bool((_segment_distances(np.array(wrist), shoulder, elbow) < near[1]).any())


def _rotation_gap(A: np.ndarray, B: np.ndarray) -> float:
    """Largest element-wise difference of the rotation parts of two 4x4s (np.allclose's test, without its overhead)."""
    return float(np.abs(A[:3, :3] - B[:3, :3]).max())


def _wrap(a: np.ndarray) -> np.ndarray:
    return (np.asarray(a) + np.pi) % _TWO_PI - np.pi


def _rigid_inv(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _ik_candidates(T: np.ndarray, q6_free: float) -> list[np.ndarray]:
    """The closed-form candidates (Dobot angles, unwrapped), not yet checked against T."""
    p05 = T[:3, 3] - D6 * T[:3, 2]
    r = math.hypot(p05[0], p05[1])
    if r < abs(D4) + 1e-9:
        return []
    Ti = _rigid_inv(T)
    sols = []
    phi = math.atan2(p05[1], p05[0])
    psi = math.acos(min(max(D4 / r, -1.0), 1.0))
    for t1 in (phi + psi + math.pi / 2, phi - psi + math.pi / 2):
        s1, c1 = math.sin(t1), math.cos(t1)
        c5 = (T[0, 3] * s1 - T[1, 3] * c1 - D4) / D6
        if abs(c5) > 1.0 + 1e-9:
            continue
        T01i = _rigid_inv(_dh(t1, D1, 0.0, DH_ALPHA[0]))
        for sign5 in (1.0, -1.0):
            t5 = sign5 * math.acos(min(max(c5, -1.0), 1.0))
            s5 = math.sin(t5)
            if abs(s5) < 1e-9:  # wrist singularity: J6 is free
                t6 = q6_free - JOINT_OFFSET[5]
            else:  # J6 from the base x and y axes seen in the flange frame
                t6 = math.atan2((-Ti[1, 0] * s1 + Ti[1, 1] * c1) / s5, (Ti[0, 0] * s1 - Ti[0, 1] * c1) / s5)
            T46 = _dh(t5, D5, 0.0, DH_ALPHA[4]) @ _dh(t6, D6, 0.0, DH_ALPHA[5])
            T14 = T01i @ T @ _rigid_inv(T46)
            p13 = T14 @ np.array([0.0, -D4, 0.0, 1.0])
            d2 = float(p13[0] ** 2 + p13[1] ** 2)
            c3 = (d2 - A2**2 - A3**2) / (2 * A2 * A3)
            if abs(c3) > 1.0 + 1e-9:
                continue
            # J2, J3 and J4 turn about parallel axes: T14's rotation is Rz(t2 + t3 + t4) Rx(pi/2)
            t234 = math.atan2(T14[1, 0], T14[0, 0])
            for sign3 in (1.0, -1.0):
                t3 = sign3 * math.acos(min(max(c3, -1.0), 1.0))
                t2 = -math.atan2(p13[1], -p13[0]) + math.asin(min(max(A3 * math.sin(t3) / math.sqrt(d2), -1.0), 1.0))
                sols.append(np.array([t1, t2, t3, t234 - t2 - t3, t5, t6]) - JOINT_OFFSET)
    return sols


def ik_all(T: np.ndarray, q6_free: float = 0.0) -> np.ndarray:
    """All analytic solutions `(k, 6)`, k <= 8, in Dobot angles wrapped to [-pi, pi); empty if out of reach.

    The UR closed form: the shoulder angle from the wrist centre, the wrist angle from the
    flange's lateral offset, then a planar two-link problem for J2, J3 and J4. At a wrist
    singularity (J5 = 0) J6 is free and set to `q6_free`. Only exact solutions are kept (the
    clipped arccos near the workspace edge may give inexact ones).
    """
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return np.zeros((0, 6))
    good = [q for q in _wrap(np.array(_ik_candidates(T, q6_free)).reshape(-1, 6)) if np.abs(fk(q) - T).max() <= 1e-6]
    return np.array(good) if good else np.zeros((0, 6))


def _nearest_within_limits(qs: np.ndarray, seed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`qs (k, 6)` with each joint shifted by whole turns to lie nearest `seed` inside the joint limits,
    and a `(k,)` mask of the rows for which every joint has such an angle."""
    base = qs + _TWO_PI * np.round((seed - qs) / _TWO_PI)
    cands = base[None] + _TWO_PI * np.array([-1.0, 0.0, 1.0])[:, None, None]  # (3, k, 6)
    inside = (cands >= JOINT_LIMITS[:, 0]) & (cands <= JOINT_LIMITS[:, 1])
    dist = np.where(inside, np.abs(cands - seed), np.inf)
    pick = np.argmin(dist, axis=0)  # (k, 6)
    out = np.take_along_axis(cands, pick[None], axis=0)[0]
    ok = np.all(np.isfinite(np.take_along_axis(dist, pick[None], axis=0)[0]), axis=1)
    return out, ok


def ik(T: np.ndarray, q_seed: np.ndarray, tol: float = 1e-4, avoid_self_collision: bool = False) -> np.ndarray | None:
    """Joint angles `(6,)` reaching the flange pose T (base frame) nearest `q_seed`, or None if out of reach.

    Of the analytic solutions, each joint is moved by whole turns to the nearest angle within
    limits, and the one closest to the seed (a streaming arm's current angles) wins, so
    consecutive targets give consecutive solutions. `tol` bounds the position error (m).
    """
    T = np.asarray(T, dtype=float)
    seed = np.asarray(q_seed, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or seed.shape != (6,) or not np.all(np.isfinite(seed)):
        return None
    qs, ok = _nearest_within_limits(_wrap(np.array(_ik_candidates(T, float(seed[5]))).reshape(-1, 6)), seed)
    qs = qs[ok]
    for qn in qs[np.argsort(np.sum((qs - seed) ** 2, axis=1), kind="stable")]:
        F = fk(qn)
        if _rotation_gap(F, T) > 1e-6 or np.linalg.norm(F[:3, 3] - T[:3, 3]) > tol:
            continue
        if avoid_self_collision and self_collision(qn):
            continue
        return qn
    return None


def pose6_to_matrix(pose: np.ndarray) -> np.ndarray:
    """Dobot [x, y, z, rx, ry, rz] (mm, deg) -> 4x4 (metres)."""
    p = np.asarray(pose, dtype=float)
    T = np.eye(4)
    T[:3, :3] = rpy_to_matrix(np.radians(p[3:6]))
    T[:3, 3] = p[:3] / 1000.0
    return T


def matrix_to_pose6(T: np.ndarray) -> np.ndarray:
    """4x4 (metres) -> Dobot [x, y, z, rx, ry, rz] (mm, deg)."""
    T = np.asarray(T, dtype=float)
    return np.concatenate([T[:3, 3] * 1000.0, np.degrees(matrix_to_rpy(T[:3, :3]))])
