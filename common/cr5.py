"""Kinematics of the Dobot CR5, shared by the simulator, the arm driver and the dashboard.

A UR-like 6R arm with Dobot's published link offsets (d1 0.147, a2 0.427, a3 0.357, d4 0.141,
d5 0.116, d6 0.105 m) in standard Denavit-Hartenberg form; reach about 900 mm; J3 within ±160°,
the other joints ±360°. Dobot's pose convention is [x, y, z, rx, ry, rz] in millimetres and degrees,
rx, ry, rz being fixed-axis X-Y-Z angles (R = Rz(rz) Ry(ry) Rx(rx)).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

D1, A2, A3, D4, D5, D6 = 0.147, -0.427, -0.357, 0.141, 0.116, 0.105
DH_D = np.array([D1, 0.0, 0.0, D4, D5, D6])
DH_A = np.array([0.0, A2, A3, 0.0, 0.0, 0.0])
DH_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])
JOINT_LIMITS = np.radians([[-360, 360], [-360, 360], [-160, 160], [-360, 360], [-360, 360], [-360, 360]])
JOINT_SPEED_LIMIT = np.radians(180.0)  # rad/s per joint
REACH_M = 0.9


def _dh(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1.0]])


def link_frames(q: np.ndarray) -> np.ndarray:
    """`(7, 4, 4)`: base, then each joint's frame after it (the last is the tool flange), base frame."""
    out = [np.eye(4)]
    for i in range(6):
        out.append(out[-1] @ _dh(q[i], DH_D[i], DH_A[i], DH_ALPHA[i]))
    return np.stack(out)


def fk(q: np.ndarray) -> np.ndarray:
    """4x4 base <- flange for joint angles `q (6,)` in radians."""
    return link_frames(np.asarray(q, dtype=float))[-1]


def within_limits(q: np.ndarray) -> bool:
    q = np.asarray(q, dtype=float)
    return bool(np.all(q >= JOINT_LIMITS[:, 0]) and np.all(q <= JOINT_LIMITS[:, 1]))


def ik(T: np.ndarray, q_seed: np.ndarray, tol: float = 1e-4) -> np.ndarray | None:
    """Joint angles `(6,)` reaching the flange pose T (base frame) nearest `q_seed`, or None if out of reach.

    Damped least squares on the position and rotation-vector error, bounded by the joint limits,
    started from the seed (a streaming arm's current angles), so consecutive targets give
    consecutive solutions.
    """
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return None
    if np.linalg.norm(T[:3, 3] - [0, 0, D1]) > REACH_M + D6:
        return None
    R_goal = T[:3, :3]

    def residual(q: np.ndarray) -> np.ndarray:
        F = fk(q)
        rot = Rotation.from_matrix(R_goal @ F[:3, :3].T).as_rotvec()
        return np.concatenate([F[:3, 3] - T[:3, 3], 0.1 * rot])

    seed = np.clip(np.asarray(q_seed, dtype=float), JOINT_LIMITS[:, 0], JOINT_LIMITS[:, 1])
    res = least_squares(residual, seed, bounds=(JOINT_LIMITS[:, 0], JOINT_LIMITS[:, 1]), xtol=1e-10, ftol=1e-10)
    if np.linalg.norm(res.fun[:3]) > tol or np.linalg.norm(res.fun[3:]) > 10 * tol:
        return None
    return res.x


def pose6_to_matrix(pose: np.ndarray) -> np.ndarray:
    """Dobot [x, y, z, rx, ry, rz] (mm, deg) -> 4x4 (metres)."""
    p = np.asarray(pose, dtype=float)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", np.radians(p[3:6])).as_matrix()
    T[:3, 3] = p[:3] / 1000.0
    return T


def matrix_to_pose6(T: np.ndarray) -> np.ndarray:
    """4x4 (metres) -> Dobot [x, y, z, rx, ry, rz] (mm, deg)."""
    return np.concatenate([T[:3, 3] * 1000.0, np.degrees(Rotation.from_matrix(T[:3, :3]).as_euler("xyz"))])
