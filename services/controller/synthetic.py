"""A synthetic deformable rim for controller tests and benchmarks: the controller never sees its equations.

Linear-blend skinning of the rim's rest shape by the two grippers' rigid motions (each point
follows the grippers with weights that fall off around the rim, clamped stretches follow one
gripper fully), plus a sag of the free stretches that grows with the slack left when the grippers
come together: smooth, nonlinear and coupled, like a fabric rim held by two mounts.
"""

from __future__ import annotations

import numpy as np

from bagit.common.geometry import make_transform, ramanujan_perimeter
from bagit.common.rig import ArmName


class SyntheticRim:
    def __init__(self, n_x: int = 16, perimeter: float = 0.68, aspect: float = 1.3, center=(0.0, 0.0, 0.4), sag_gain: float = 1.5):
        self.n_x = n_x
        b = perimeter / ramanujan_perimeter(aspect, 1.0)
        a = aspect * b
        t = 2 * np.pi * np.arange(n_x) / n_x
        self.center = np.asarray(center, dtype=float)
        self.rest = np.stack([b * np.cos(t), a * np.sin(t), np.zeros(n_x)], 1) + self.center  # CCW from above
        side = np.sin(t)  # -1 at the left handle (-y), +1 at the right (+y)
        self.w_right = np.clip(0.5 + 0.8 * side, 0.0, 1.0)
        self.w_left = 1.0 - self.w_right
        self.free = (self.w_right > 0) & (self.w_right < 1)
        self.sep0 = 2 * a
        self.sag_gain = sag_gain
        self._home: dict[ArmName, np.ndarray] = {
            "left": make_transform(None, self.center + [0, -a, 0]),
            "right": make_transform(None, self.center + [0, a, 0]),
        }

    def home(self) -> dict[ArmName, np.ndarray]:
        return {k: v.copy() for k, v in self._home.items()}

    def rim(self, grippers: dict[ArmName, np.ndarray]) -> np.ndarray:
        """`(n_x, 3)` rim for gripper poses (4x4, world)."""
        out = np.zeros_like(self.rest)
        weights: tuple[tuple[ArmName, np.ndarray], ...] = (("left", self.w_left), ("right", self.w_right))
        for name, w in weights:
            D = grippers[name] @ np.linalg.inv(self._home[name])  # the gripper's motion from home
            out += w[:, None] * (self.rest @ D[:3, :3].T + D[:3, 3])
        sep = np.linalg.norm(grippers["right"][:3, 3] - grippers["left"][:3, 3])
        slack = max(self.sep0 - sep, 0.0)
        bump = 4 * self.w_right * self.w_left  # 1 mid-way along the free stretches, 0 at the clamps
        out[:, 2] -= self.sag_gain * slack**1.5 * bump / np.sqrt(self.sep0)
        return out
