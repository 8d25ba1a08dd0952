"""The ground floor: messages, scenario and parameter models, shared geometry, errors.

Nothing here imports a service.
"""

from bagit.common.errors import (
    BadCloud,
    BadMessage,
    BadScenario,
    BadVertices,
    BagItError,
    InfeasibleGoal,
    PlanningFailed,
    ProtocolError,
    SafetyViolation,
)

__all__ = [
    "BagItError",
    "BadCloud",
    "BadMessage",
    "BadScenario",
    "BadVertices",
    "InfeasibleGoal",
    "PlanningFailed",
    "ProtocolError",
    "SafetyViolation",
]
