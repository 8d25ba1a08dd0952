"""Frames between the controller (bag-mount poses in the world, SI) and a CR5 (flange in its base, mm/deg).

The controller commands each bag mount's pose in the world frame. A CR5 takes the tool flange's
pose in its own base frame, as Dobot's pose6 [x, y, z, rx, ry, rz] (mm, deg, see bagit.common.cr5),
with user frame 0 and tool frame 0 selected (the driver checks this at bring-up):

    T_base_flange = T_world_base^-1 @ T_world_mount @ T_flange_mount^-1

and back for the feedback. `ArmState.tool_pose` is the mount in the world as [x, y, z, roll,
pitch, yaw] (m, rad; fixed-axis x-y-z, the convention of bagit.common.geometry.matrix_to_rpy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bagit.common import cr5
from bagit.common.dobot import RobotMode
from bagit.common.dual_arm import Poses
from bagit.common.geometry import invert_transform, matrix_to_rpy
from bagit.common.messages import ArmState
from bagit.common.rig import ARMS, ArmConfig, ArmName


def poses_to_arrays(poses: Poses) -> tuple[np.ndarray, np.ndarray]:
    """Positions `(2, 3)` and rotations `(2, 3, 3)` in ARMS order."""
    p = np.stack([poses[a][:3, 3] for a in ARMS]).astype(float)
    R = np.stack([poses[a][:3, :3] for a in ARMS]).astype(float)
    return p, R


def arrays_to_poses(p: np.ndarray, R: np.ndarray) -> Poses:
    """'left'/'right' -> (4, 4) from positions `(2, 3)` and rotations `(2, 3, 3)`."""
    out: dict[ArmName, np.ndarray] = {}
    for i, a in enumerate(ARMS):
        T = np.eye(4)
        T[:3, :3] = R[i]
        T[:3, 3] = p[i]
        out[a] = T
    return out


@dataclass(frozen=True)
class ArmFrames:
    """One arm's fixed transforms (4x4): world <- base and flange <- mount, with their inverses."""

    T_world_base: np.ndarray
    T_base_world: np.ndarray
    T_flange_mount: np.ndarray
    T_mount_flange: np.ndarray

    @classmethod
    def from_config(cls, arm: ArmConfig) -> ArmFrames:
        Twb, Tfm = arm.T_world_base(), arm.T_flange_mount()
        return cls(Twb, invert_transform(Twb), Tfm, invert_transform(Tfm))

    def flange_in_base(self, T_world_mount: np.ndarray) -> np.ndarray:
        """4x4 base <- flange for a mount pose in the world."""
        return self.T_base_world @ T_world_mount @ self.T_mount_flange

    def mount_in_world(self, T_base_flange: np.ndarray) -> np.ndarray:
        """4x4 world <- mount for a flange pose in the base frame."""
        return self.T_world_base @ T_base_flange @ self.T_flange_mount

    def mount_from_pose6(self, pose6: np.ndarray) -> np.ndarray:
        """4x4 world <- mount from the controller's flange pose6 (GetPose / ToolVectorActual)."""
        return self.mount_in_world(cr5.pose6_to_matrix(pose6))


def mount_velocity(frames: ArmFrames, T_world_mount: np.ndarray, tcp_speed: np.ndarray) -> np.ndarray:
    """`(6,)` mount [linear m/s, angular rad/s] in the world from the feedback's TCPSpeedActual.

    TCPSpeedActual is the flange's [vx, vy, vz (mm/s), wx, wy, wz (deg/s)] in the base frame; the
    mount sits `offset` from the flange, so it also moves with omega x offset.
    """
    R = frames.T_world_base[:3, :3]
    v_f = R @ (np.asarray(tcp_speed[:3], dtype=float) / 1000.0)
    w = R @ np.radians(np.asarray(tcp_speed[3:6], dtype=float))
    lever = T_world_mount[:3, 3] - (T_world_mount @ frames.T_mount_flange)[:3, 3]  # flange -> mount, world
    return np.concatenate([v_f + np.cross(w, lever), w])


def controller_fault(rec: np.ndarray) -> str | None:
    """Why a feedback record says the arm cannot move (error, collision), or None."""
    mode = int(rec["RobotMode"])
    if bool(rec["CollisionState"]) or mode == int(RobotMode.COLLISION):
        return "collision detected"
    if bool(rec["ErrorStatus"]) or mode == int(RobotMode.ERROR):
        return f"controller in error (robot mode {mode})"
    return None


def feedback_state(arm: str, rec: np.ndarray, frames: ArmFrames, estopped: bool = False, stamp: float | None = None) -> ArmState:
    """An `ArmState` (SI, world frame, the mount as the tool) from one feedback record."""
    mode = int(rec["RobotMode"])
    T = frames.mount_from_pose6(rec["ToolVectorActual"])
    vel = mount_velocity(frames, T, rec["TCPSpeedActual"])
    reason = controller_fault(rec)
    kw = {} if stamp is None else {"stamp": stamp}
    return ArmState(
        arm=arm,
        robot_mode=mode,
        q=np.radians(np.asarray(rec["QActual"], dtype=float)),
        qd=np.radians(np.asarray(rec["QDActual"], dtype=float)),
        tool_pose=np.concatenate([T[:3, 3], matrix_to_rpy(T[:3, :3])]),
        tool_speed=float(np.linalg.norm(vel[:3])),
        enabled=bool(rec["EnableStatus"]),
        error=reason is not None,
        error_reason=reason,
        command_id=int(rec["CurrentCommandId"]),
        estopped=estopped,
        **kw,
    )
