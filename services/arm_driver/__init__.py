"""Arm driver: Dobot CR5 TCP/IP V4 client, Ruckig jerk-limited streaming and safety limits.

Modules, each doing one thing (none imports Zenoh; a node wraps `ArmDriver`):
  config    DriverConfig: ServoP aheadtime/gain, time-outs, back-off, target lead (limits: rig.SafetyLimits)
  safety    the envelope and `check_and_clip`, the one gate every outgoing pose goes through
  so3       rotation-vector helpers for the 30 ms loop
  frames    mount pose in the world <-> flange pose6 in each arm's base; feedback -> ArmState
  streaming 12-DoF Ruckig over both mounts' poses; increments -> targets
  pipeline  MotionPipeline: increments in, safe jerk-limited poses out, one period at a time
  reach     a step the joints cannot follow (near a singularity) is shortened, not refused
  client    DobotClient: dashboard requests matched to replies, 1440-byte feedback, reconnect
  driver    ArmDriver: both arms, bring-up/shutdown, servo loop, watchdog, e-stop, faults
  gate      which commands may move the arms (the servoing run's, fresh) and who may release the e-stop
"""

from bagit.services.arm_driver.client import CommandRejected, ConnectionLost, DobotClient
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.arm_driver.driver import ArmDriver
from bagit.services.arm_driver.pipeline import MotionPipeline, Tick
from bagit.services.arm_driver.safety import Envelope, Violation, check_and_clip, violations

__all__ = [
    "ArmDriver",
    "CommandRejected",
    "ConnectionLost",
    "DobotClient",
    "DriverConfig",
    "Envelope",
    "MotionPipeline",
    "Tick",
    "Violation",
    "check_and_clip",
    "violations",
]
