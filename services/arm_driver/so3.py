"""Small SO(3) helpers for the driver's 30 ms loop: scipy's Rotation costs ~50 us a call, these ~5.

Rotation vectors are world-frame: R = exp(r) R0 turns R0 by |r| about r / |r|.
"""

from __future__ import annotations

import math

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
