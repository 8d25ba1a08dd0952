"""Where to draw the two CR5s: link segments from the measured joint angles, gripper poses.

The links are drawn as cylinders between consecutive joint frames of the CR5's DH chain
(bagit.common.cr5.link_frames): each segment is rigid, so its length never changes and only its
pose is updated per sample. Gripper poses arrive as [x y z rx ry rz] (m, rad; fixed-axis X-Y-Z
as Dobot's, R = Rz Ry Rx), and a controller Command moves them by a world-frame increment.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from bagit.common import cr5
from bagit.common.errors import SafetyViolation
from bagit.common.geometry import make_transform, pose_to_matrix

N_LINKS = 6


def link_segments(T_world_base: np.ndarray, q: np.ndarray) -> np.ndarray:
    """`(6, 2, 3)`: start and end of each link, world frame, for joint angles `q (6,)` rad."""
    q = np.asarray(q, dtype=float)
    if q.shape != (6,) or not np.all(np.isfinite(q)):
        raise SafetyViolation(f"joint angles must be 6 finite values, got shape {q.shape}")
    frames = np.asarray(T_world_base, dtype=float)[None] @ cr5.link_frames(q)  # (7, 4, 4)
    origins = frames[:, :3, 3]
    return np.stack([origins[:-1], origins[1:]], axis=1)


def link_lengths() -> np.ndarray:
    """`(6,)` lengths of the segments `link_segments` returns (constant: sqrt(a_i^2 + d_i^2))."""
    return np.hypot(cr5.DH_A, cr5.DH_D)


def segment_pose(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position `(3,)` (the midpoint) and quaternion wxyz `(4,)` turning local +z onto b - a."""
    d = np.asarray(b, dtype=float) - np.asarray(a, dtype=float)
    n = np.linalg.norm(d)
    mid = (np.asarray(a, dtype=float) + np.asarray(b, dtype=float)) / 2
    if n < 1e-12:
        return mid, np.array([1.0, 0.0, 0.0, 0.0])
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, d / n)
    s = np.linalg.norm(axis)
    c = float(np.dot(z, d / n))
    if s < 1e-12:  # parallel or anti-parallel to z
        rot = Rotation.identity() if c > 0 else Rotation.from_rotvec([np.pi, 0.0, 0.0])
    else:
        rot = Rotation.from_rotvec(axis / s * np.arctan2(s, c))
    return mid, wxyz(rot.as_matrix())


def wxyz(R: np.ndarray) -> np.ndarray:
    """Quaternion `(4,)` scalar first (viser's convention) of a rotation `(3, 3)`."""
    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()
    return np.array([w, x, y, z])


def tool_matrix(tool_pose: np.ndarray) -> np.ndarray:
    """4x4 world <- gripper from ArmState.tool_pose `(6,)` = [x y z rx ry rz] (m, rad)."""
    p = np.asarray(tool_pose, dtype=float)
    if p.shape != (6,) or not np.all(np.isfinite(p)):
        raise SafetyViolation(f"tool pose must be 6 finite values, got shape {p.shape}")
    return pose_to_matrix(p[:3], p[3:])


def commanded_matrix(T_world_tool: np.ndarray, u_arm: np.ndarray) -> np.ndarray:
    """Where one increment `u_arm (6,)` = [dx dy dz drx dry drz] (world frame, rotation vector)
    sends the gripper at `T_world_tool`: the target of that control tick."""
    u = np.asarray(u_arm, dtype=float)
    T = np.asarray(T_world_tool, dtype=float)
    R = Rotation.from_rotvec(u[3:6]).as_matrix() @ T[:3, :3]
    return make_transform(R, T[:3, 3] + u[:3])


def command_speeds(u: np.ndarray, dt: float) -> tuple[float, float, float, float]:
    """Linear (m/s) and angular (rad/s) speeds of the left and right gripper a Command asks for:
    (left_linear, right_linear, left_angular, right_angular)."""
    u = np.asarray(u, dtype=float).reshape(2, 6)
    lin = np.linalg.norm(u[:, :3], axis=1) / dt
    ang = np.linalg.norm(u[:, 3:], axis=1) / dt
    return float(lin[0]), float(lin[1]), float(ang[0]), float(ang[1])
