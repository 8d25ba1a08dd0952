"""Small SO(3) helpers for the loops that run per packet or per period (the arm driver, the simulated
CR5s): scipy's Rotation costs 50-300 us for one rotation, these a few.

Rotation vectors are world-frame: R = exp(r) R0 turns R0 by |r| about r / |r|. Euler angles are
extrinsic x, y, z (roll, pitch, yaw: R = Rz(yaw) Ry(pitch) Rx(roll)), as in URDF and as Dobot's
rx, ry, rz; scipy's `Rotation.from_euler("xyz", ...)` is the same convention.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def left_jacobian(r: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian `(3, 3)` at rotation vector `r (3,)`: omega = J_l(r) r_dot for R = exp(r) R0."""
    th = math.sqrt(float(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]))
    K = _skew(r)
    if th < 1e-6:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    return np.eye(3) + ((1.0 - math.cos(th)) / th**2) * K + ((th - math.sin(th)) / th**3) * (K @ K)


def so3_exp(r: np.ndarray) -> np.ndarray:
    """Rotation matrix `(3, 3)` of rotation vector `r (3,)` (Rodrigues; scipy's is ~50x slower per call)."""
    th = math.sqrt(float(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]))
    K = _skew(r)
    if th < 1e-8:
        return np.eye(3) + K + 0.5 * (K @ K)
    return np.eye(3) + (math.sin(th) / th) * K + ((1.0 - math.cos(th)) / th**2) * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector `(3,)` of rotation matrix `R (3, 3)`, angle in [0, pi]."""
    c = min(max((R[0, 0] + R[1, 1] + R[2, 2] - 1.0) / 2.0, -1.0), 1.0)
    th = math.acos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-6:
        return 0.5 * w * (1.0 + th * th / 6.0)
    if th < math.pi - 1e-4:
        return (th / (2.0 * math.sin(th))) * w
    return Rotation.from_matrix(R).as_rotvec()  # near pi the antisymmetric part vanishes: let scipy resolve the axis


def rotvec_between(R_from: np.ndarray, R_to: np.ndarray) -> np.ndarray:
    """`(3,)` world-frame rotation vector r with R_to = exp(r) R_from."""
    return so3_log(R_to @ R_from.T)


def rpy_to_matrix(rpy: np.ndarray | Sequence[float]) -> np.ndarray:
    """Rotation `(3, 3)` of roll, pitch, yaw `(3,)` (radians, extrinsic x, y, z)."""
    cr, sr = math.cos(rpy[0]), math.sin(rpy[0])
    cp, sp = math.cos(rpy[1]), math.sin(rpy[1])
    cy, sy = math.cos(rpy[2]), math.sin(rpy[2])
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def matrix_to_rpy(R: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw `(3,)` (radians, extrinsic x, y, z) of a rotation `R (3, 3)`; pitch in [-pi/2, pi/2].

    At gimbal lock (pitch = +-pi/2) only roll - yaw (or roll + yaw) is defined: yaw is set to 0, as scipy does."""
    sp = -float(R[2, 0])
    if abs(sp) < 1.0 - 1e-9:
        return np.array([math.atan2(R[2, 1], R[2, 2]), math.asin(sp), math.atan2(R[1, 0], R[0, 0])])
    if sp > 0:
        return np.array([math.atan2(R[0, 1], R[1, 1]), math.pi / 2, 0.0])
    return np.array([math.atan2(-R[0, 1], R[1, 1]), -math.pi / 2, 0.0])


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternion `(4,)` as (w, x, y, z), w >= 0, of a rotation `R (3, 3)` (Shepperd's method: stable for any angle)."""
    t = float(R[0, 0] + R[1, 1] + R[2, 2])
    d = (float(R[0, 0]), float(R[1, 1]), float(R[2, 2]))
    if t >= max(d):
        w = 0.5 * math.sqrt(max(1.0 + t, 0.0))
        q = [w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)]
    elif d[0] >= d[1] and d[0] >= d[2]:
        x = 0.5 * math.sqrt(max(1.0 + d[0] - d[1] - d[2], 0.0))
        q = [(R[2, 1] - R[1, 2]) / (4 * x), x, (R[0, 1] + R[1, 0]) / (4 * x), (R[0, 2] + R[2, 0]) / (4 * x)]
    elif d[1] >= d[2]:
        y = 0.5 * math.sqrt(max(1.0 - d[0] + d[1] - d[2], 0.0))
        q = [(R[0, 2] - R[2, 0]) / (4 * y), (R[0, 1] + R[1, 0]) / (4 * y), y, (R[1, 2] + R[2, 1]) / (4 * y)]
    else:
        z = 0.5 * math.sqrt(max(1.0 - d[0] - d[1] + d[2], 0.0))
        q = [(R[1, 0] - R[0, 1]) / (4 * z), (R[0, 2] + R[2, 0]) / (4 * z), (R[1, 2] + R[2, 1]) / (4 * z), z]
    n = math.sqrt(sum(float(c) * float(c) for c in q))
    return np.array(q, dtype=float) / (-n if q[0] < 0 else n)
