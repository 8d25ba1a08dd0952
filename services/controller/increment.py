"""The controller's input u `(12,)` = [left dp, drotvec, right dp, drotvec] (world frame) as gripper motion.

`apply_increment` moves gripper poses by u (what the arms are asked to do); `pose_increment` is the
u between two measured poses (what they did).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from bagit.common.so3 import rotvec_between


def apply_increment(grippers: dict[str, np.ndarray], u: np.ndarray) -> dict[str, np.ndarray]:
    """Gripper poses after the 12-D increment u = [left dp, drotvec, right dp, drotvec] (world frame)."""
    out = {}
    for name, off in (("left", 0), ("right", 6)):
        T = grippers[name].copy()
        T[:3, 3] += u[off : off + 3]
        T[:3, :3] = Rotation.from_rotvec(u[off + 3 : off + 6]).as_matrix() @ T[:3, :3]
        out[name] = T
    return out


def pose_increment(before: dict[str, np.ndarray], after: dict[str, np.ndarray]) -> np.ndarray:
    """The 12-D increment u `(12,)` that takes gripper poses `before` to `after` (apply_increment's inverse)."""
    u = np.empty(12)
    for name, off in (("left", 0), ("right", 6)):
        u[off : off + 3] = after[name][:3, 3] - before[name][:3, 3]
        u[off + 3 : off + 6] = rotvec_between(before[name][:3, :3], after[name][:3, :3])
    return u
