"""The dual-arm input and the gripper poses, typed: what the controller asks of both mounts and where they are.

The controller's input u `(12,)` = [left dx dy dz drx dry drz, right ...] (world frame, metres and
rotation-vector radians, per control tick) travels as a plain array on the wire (`Command.u`) and
through the QP; `DualArmIncrement` names its halves where code takes it apart, and the index
constants below are the one place its layout is written down. `apply_increment` is the one way an
increment moves poses (the controller's prediction, the arm driver's target, the ideal arms), and
`pose_increment` its inverse (what the measured grippers did).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from bagit.common.rig import ARMS, ArmName
from bagit.common.so3 import rotvec_between

# 'left' / 'right' -> (4, 4) world <- mount (the gripper's pose)
Poses = dict[ArmName, np.ndarray]

INCREMENT_SIZE = 12  # u (12,)
ARM_SIZE = 6  # each arm's (6,) = [dp (3,), drotvec (3,)]
ARM_SLICE: dict[ArmName, slice] = {"left": slice(0, 6), "right": slice(6, 12)}
TRANSLATION: dict[ArmName, slice] = {"left": slice(0, 3), "right": slice(6, 9)}
ROTATION: dict[ArmName, slice] = {"left": slice(3, 6), "right": slice(9, 12)}
POSITION_COLUMNS: tuple[int, ...] = (0, 1, 2, 6, 7, 8)  # both grippers' translations inside u (12,)


def check_increment(u: np.ndarray, what: str = "u") -> np.ndarray:
    """`u` as a float `(12,)` array; ValueError naming `what` if it has another shape."""
    a = np.asarray(u, dtype=float)
    if a.shape != (INCREMENT_SIZE,):
        raise ValueError(f"{what} must have shape ({INCREMENT_SIZE},) = [left dp drot, right dp drot], got {a.shape}")
    return a


def check_poses(poses: Mapping[ArmName, np.ndarray], what: str = "poses") -> None:
    """ValueError unless `poses` holds a `(4, 4)` transform for each arm."""
    for a in ARMS:
        shape = np.shape(poses[a]) if a in poses else None
        if shape != (4, 4):
            raise ValueError(f"{what} must be {{'left': (4, 4), 'right': (4, 4)}}; {a!r} is {shape}")


@dataclass(frozen=True)
class DualArmIncrement:
    """One tick's motion of both mounts: `left`, `right` `(6,)` = [dx dy dz (m), drx dry drz (rad)], world frame."""

    left: np.ndarray
    right: np.ndarray

    def __post_init__(self) -> None:
        for name in ARMS:
            v = np.asarray(getattr(self, name), dtype=float)
            if v.shape != (ARM_SIZE,):
                raise ValueError(f"{name} must have shape ({ARM_SIZE},), got {v.shape}")
            object.__setattr__(self, name, v)

    @classmethod
    def from_array(cls, u: np.ndarray) -> DualArmIncrement:
        """From the flat input `u (12,)`."""
        a = check_increment(u)
        return cls(a[ARM_SLICE["left"]].copy(), a[ARM_SLICE["right"]].copy())

    @classmethod
    def zero(cls) -> DualArmIncrement:
        return cls(np.zeros(ARM_SIZE), np.zeros(ARM_SIZE))

    def to_array(self) -> np.ndarray:
        """The flat input `(12,)`."""
        return np.concatenate([self.left, self.right])

    def arm(self, name: ArmName | str) -> np.ndarray:
        """One arm's `(6,)`."""
        return self.left if name == "left" else self.right

    def translation(self, name: ArmName | str) -> np.ndarray:
        """One arm's translation `(3,)` (m)."""
        return self.arm(name)[:3]

    def rotation(self, name: ArmName | str) -> np.ndarray:
        """One arm's rotation-vector increment `(3,)` (rad)."""
        return self.arm(name)[3:]


def apply_increment(poses: Mapping[ArmName, np.ndarray], u: DualArmIncrement | np.ndarray) -> Poses:
    """The poses `{'left', 'right'}: (4, 4)` after the increment: each mount translated by its dp and
    turned by its drotvec, both in the world frame (T' = [exp(drot) R, p + dp])."""
    check_poses(poses)
    inc = u if isinstance(u, DualArmIncrement) else DualArmIncrement.from_array(u)
    out: Poses = {}
    for name in ARMS:
        T = np.array(poses[name], dtype=float)
        T[:3, 3] += inc.translation(name)
        T[:3, :3] = Rotation.from_rotvec(inc.rotation(name)).as_matrix() @ T[:3, :3]
        out[name] = T
    return out


def pose_increment(before: Mapping[ArmName, np.ndarray], after: Mapping[ArmName, np.ndarray]) -> np.ndarray:
    """The increment u `(12,)` that takes `before` to `after` (apply_increment's inverse)."""
    u = np.empty(INCREMENT_SIZE)
    for name in ARMS:
        u[TRANSLATION[name]] = after[name][:3, 3] - before[name][:3, 3]
        u[ROTATION[name]] = rotvec_between(before[name][:3, :3], after[name][:3, :3])
    return u
