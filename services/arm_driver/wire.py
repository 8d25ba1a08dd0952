"""The path's last layer: the ServoP (or ServoJ) each arm is sent, as the controller takes it.

A mount pose in the world becomes the flange's pose6 in that arm's base (mm, deg; `frames`), or,
with `servo_command: servoj`, the joints the reach check solved (deg). The driver writes it on the
dashboard port (`DobotClient.servo_text`); `bagit run` hands it to the simulated controller
directly, rounded to the 6 decimals the text carries (`on_wire`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from bagit.common import cr5
from bagit.common.rig import ArmName
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.arm_driver.frames import ArmFrames, Poses
from bagit.services.arm_driver.reach import Joints


@dataclass(frozen=True)
class ServoCommand:
    """One arm's motion request: `name` ServoP or ServoJ, `values (6,)` pose6 (mm, deg) or joints (deg)."""

    name: str
    values: np.ndarray
    t: float
    aheadtime: float
    gain: float

    def on_wire(self) -> np.ndarray:
        """`values (6,)` as the text on the wire carries them (6 decimals)."""
        return np.round(self.values, 6)


def servo_commands(
    poses: Poses, joints: Joints | None, halting: bool, arms: Sequence[ArmName],
    frames: dict[ArmName, ArmFrames], cfg: DriverConfig, servo_t: float,
) -> dict[ArmName, ServoCommand]:
    """The command for each of `arms`; `halting`: the poses brake to rest (the halting servo parameters)."""
    aheadtime, gain = cfg.servo_params(halting)
    out = {}
    for a in arms:
        if cfg.servo_command == "servoj" and joints is not None:
            out[a] = ServoCommand("ServoJ", np.degrees(joints[a]), servo_t, aheadtime, gain)
        else:
            out[a] = ServoCommand("ServoP", cr5.matrix_to_pose6(frames[a].flange_in_base(poses[a])), servo_t, aheadtime, gain)
    return out
