"""Arm driver: both Dobot CR5s over TCP/IP V4, a command's one path to a ServoP, the supervision.

A command's path, each layer one module (all pure: no Zenoh, no sockets):
  targets     TargetIntegrator, pull_back: the increment moves the target, kept within a lead
  smoothing   RuckigSmoother: 12-DoF jerk-limited trajectory towards the target; a stop at the stop's limits
  limits      Envelope, check_and_clip: the one gate every outgoing pose goes through
  reach       solve_within: a step the joints cannot follow (near a singularity) is shortened, not refused
  wire        ServoCommand: the flange pose in each arm's base as a ServoP (or the joints as a ServoJ)
  servo_path  ServoPath: the layers above in order, plus the watchdog; what `bagit run`'s arms drive too

Around it:
  frames      mount pose in the world <-> flange pose6 in each arm's base; feedback -> ArmState
  machine     the supervision as a pure state machine: latches, links, restart, replies' tally
  gate        which commands may move the arms (the servoing run's, fresh) and who may release the e-stop
  client      DobotClient: dashboard requests matched to replies, 1440-byte feedback, reconnect
  links       Cr5Links: both clients; bring-up, shutdown, EmergencyStop, ServoPs and their replies
  driver      ArmDriver: the thin shell (threads, the lock, the clock) around the path, machine and links
  node        ArmDriverNode: the driver on Zenoh (the only module that imports it)
  config      DriverConfig: ServoP aheadtime/gain, time-outs, back-off, target lead (limits: rig.SafetyLimits)
"""

from bagit.services.arm_driver.client import CommandRejected, ConnectionLost, DobotClient
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.arm_driver.driver import ArmDriver
from bagit.services.arm_driver.limits import Envelope, Violation, check_and_clip, violations
from bagit.services.arm_driver.servo_path import ServoPath, Tick

__all__ = [
    "ArmDriver",
    "CommandRejected",
    "ConnectionLost",
    "DobotClient",
    "DriverConfig",
    "Envelope",
    "ServoPath",
    "Tick",
    "Violation",
    "check_and_clip",
    "violations",
]
