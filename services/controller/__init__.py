"""Controller: MPC shape servoing along the planned SOI path with an online Broyden Jacobian
(paper section VI-B), the IBVS and SSVS baselines, and the action-primitive methods AutoBag and
ShakingBot, and BimaManip's MPC through a learned SOI model (Table I)."""

from bagit.services.controller.baselines import IbvsController, SsvsController
from bagit.services.controller.bimamanip import BimaManipController
from bagit.services.controller.broyden import BroydenJacobian, Exploration
from bagit.services.controller.controller import CONTROLLERS, Controller, ShapeServo, make_controller
from bagit.services.controller.guard import SoiGuard
from bagit.services.controller.mpc import MpcController, MpcSolution, MpcSolver
from bagit.services.controller.primitives import AutoBagController, PrimitiveController, ShakingBotController
from bagit.services.controller.servo import ControlOutput, c7_limits
from bagit.services.controller.subgoal import SubgoalTracker, rms_error

__all__ = [
    "AutoBagController",
    "BimaManipController",
    "BroydenJacobian",
    "CONTROLLERS",
    "ControlOutput",
    "Controller",
    "Exploration",
    "IbvsController",
    "MpcController",
    "MpcSolution",
    "MpcSolver",
    "PrimitiveController",
    "ShakingBotController",
    "ShapeServo",
    "SoiGuard",
    "SsvsController",
    "SubgoalTracker",
    "c7_limits",
    "make_controller",
    "rms_error",
]
