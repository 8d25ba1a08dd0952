"""The project's error types.

Bad input raises one of these with a one-line reason; the CLI prints it and exits non-zero.
Input errors are also `ValueError` so callers that only know the standard library still catch them.
"""


class BagItError(Exception):
    """Base of every error BagIt raises on purpose."""


class BadCloud(BagItError, ValueError):
    """A point cloud that cannot give an SOI: empty, non-finite, too small or degenerate."""


class BadVertices(BagItError, ValueError):
    """An object's bottom outline V that is not a usable polygon."""


class InfeasibleGoal(BagItError, ValueError):
    """No bagging ellipse with the bag's rim perimeter can hold the object under C1-C3."""


class BadScenario(BagItError, ValueError):
    """A scenario file that is missing, unreadable or invalid."""


class BadMessage(BagItError, ValueError):
    """A payload that does not decode to a known message of the expected schema version."""


class PlanningFailed(BagItError, RuntimeError):
    """The SOI planner found no path within its budget."""


class ProtocolError(BagItError, RuntimeError):
    """A Dobot controller reply or feedback packet that does not parse, or an error it reported."""


class SafetyViolation(BagItError, ValueError):
    """A command that would leave the arms' safe envelope (non-finite, out of limits)."""


class BadControlInput(BagItError, ValueError):
    """A controller set-up that cannot be servoed on: unknown controller, path or poses of the wrong shape."""


class BusError(BagItError, RuntimeError):
    """The Zenoh bus refused: a session that cannot open, a bad bus config, or no answer to a query."""


class BadRecording(BagItError, ValueError):
    """An MCAP recording that is missing, unreadable, not BagIt's, or holds a malformed message."""


class CameraError(BagItError, RuntimeError):
    """A camera or recording that cannot be opened or read: no device, another serial, an unreadable file."""


class MarkerNotFound(BagItError, LookupError):
    """No ArUco marker of a known object (or no calibration board) in the image."""


class NumericalFailure(BagItError, ArithmeticError):
    """A numerical routine (SVD, least squares, a linear solve) got non-finite or degenerate data.

    numpy's LinAlgError ('SVD did not converge') is turned into this where it can happen, so every
    stage can end or hold with a reason instead of crashing.
    """


class SimulationFailed(BagItError, RuntimeError):
    """The physics simulation went unstable: non-finite state, or MuJoCo warned of bad accelerations,
    positions or velocities (it would otherwise reset the world silently and carry on)."""


class WallLimitReached(BagItError, RuntimeError):
    """A run's wall-clock limit passed while the simulator stepped (its physics crawled): the run stops there."""


def first_line(e: BaseException) -> str:
    """The first line of an exception's text (its type's name if it has none): a one-line reason."""
    s = str(e).strip()
    return s.splitlines()[0] if s else type(e).__name__


def refuse_moved(data: object, moved: dict[str, str], owner: str) -> object:
    """`data` (a config mapping before validation) as it is, or ValueError naming the first key that
    is no longer an `owner` setting and where that setting is now (`moved`: key -> its place)."""
    for key in data if isinstance(data, dict) else ():
        if key in moved:
            raise ValueError(f"{key} is no longer a {owner} setting: it is {moved[key]}")
    return data
