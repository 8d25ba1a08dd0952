"""Controller: MPC shape servoing along the planned SOI path with an online Broyden Jacobian."""

from bagit.services.controller.broyden import BroydenJacobian
from bagit.services.controller.controller import CONTROLLERS, ControlOutput, ShapeServo
from bagit.services.controller.mpc import MpcSolver
from bagit.services.controller.subgoal import SubgoalTracker, rms_error

__all__ = ["BroydenJacobian", "CONTROLLERS", "ControlOutput", "ShapeServo", "MpcSolver", "SubgoalTracker", "rms_error"]
