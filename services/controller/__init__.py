"""Controller: MPC shape servoing along the planned SOI path with an online Broyden Jacobian
(paper section VI-B), and the IBVS and SSVS baselines."""

from bagit.services.controller.baselines import IbvsController, SsvsController
from bagit.services.controller.broyden import BroydenJacobian, Exploration
from bagit.services.controller.controller import CONTROLLERS, Controller, ShapeServo, make_controller
from bagit.services.controller.guard import SoiGuard
from bagit.services.controller.mpc import MpcController, MpcSolution, MpcSolver
from bagit.services.controller.servo import ControlOutput, c7_limits
from bagit.services.controller.subgoal import SubgoalTracker, rms_error

__all__ = [
    "BroydenJacobian",
    "CONTROLLERS",
    "ControlOutput",
    "Controller",
    "Exploration",
    "IbvsController",
    "MpcController",
    "MpcSolution",
    "MpcSolver",
    "ShapeServo",
    "SoiGuard",
    "SsvsController",
    "SubgoalTracker",
    "c7_limits",
    "make_controller",
    "rms_error",
]
