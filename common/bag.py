"""The bag's physics and looks (a scenario's `bag.fabric` and `bag.rim`) and the simulated scene's
light and camera noise (a scenario's `sim`), each field optional with the value every run used
before these fields existed, so that older scenario files give the same runs bit for bit.

The defaults are the simulator's constants (services/sim/scene.py builds the MuJoCo flex from
these models); the bounds are what is physically sane for a table-top fabric bag, wide enough for
the bag zoo's envelope (bench/zoo.py), so a negative or absurd value is a one-line `BadScenario`.
The light, the depth noise and the camera's calibration error are the simulator's alone: a lab's rig
has its own lights and camera, and perception never reads these fields.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

RGB = tuple[float, float, float]

# -- defaults: the one bag every run used before (the simulator's constants) --------------------------
FABRIC_STRETCH_N_PER_M = 8000.0  # membrane stiffness E*t: 8 MPa at 1 mm, a woven fabric that stretches little
FABRIC_MASS_KG = 0.08  # a light woven bag
FABRIC_DAMPING_S = 0.002  # Rayleigh damping of the membrane (time units)
FABRIC_FRICTION = 0.5
RIM_TUBE_RADIUS_M = 0.006  # the binding's radius (drawn, and its bending section)
RIM_YOUNG_PA = 1e5  # the binding's Young's modulus before bending was a field: EI = E pi r^4 / 4
RIM_BENDING_NM2 = RIM_YOUNG_PA * math.pi * RIM_TUBE_RADIUS_M**4 / 4  # ~1.02e-4 N m^2, a doubled fabric strip's
RIM_COLOR: RGB = (0.85, 0.05, 0.05)  # the red edge
RIM_PERIMETER_M = 0.68  # the paper's bag: the simulated rim of a scenario that gives neither bag.rim_perimeter nor bag.initial_rim
KEY_LIGHT_DIRECTION = (0.0, 0.0, -1.0)  # straight down onto the table

# -- physically sane bounds (validation) --------------------------------------------------------------
STRETCH_RANGE_N_PER_M = (50.0, 2e6)  # cling film's ~100 N/m to a coated tarp's ~1 MN/m
MASS_RANGE_KG = (0.005, 2.0)
DAMPING_RANGE_S = (0.0, 0.1)
FRICTION_RANGE = (0.0, 2.0)
BENDING_RANGE_NM2 = (1e-8, 0.1)  # a loose hem to a stiff steel-wire hoop
LIGHT_INTENSITY_RANGE = (0.05, 4.0)  # x today's lights
MIN_LIGHT_ELEVATION_RAD = math.radians(5.0)  # the key light shines down onto the table from above its plane
DEPTH_NOISE_RANGE = (0.0, 10.0)  # x the D455 model's depth noise
MAX_CALIBRATION_OFFSET_M = 0.1  # the camera's true position this far from the calibrated one, per axis, at most
MAX_CALIBRATION_TURN_DEG = 10.0  # its true orientation turned this far from the calibrated one, at most


def check_rgb(v: RGB, what: str) -> RGB:
    """`v` when each component is in [0, 1], else ValueError naming `what`."""
    if not all(0.0 <= c <= 1.0 for c in v):
        raise ValueError(f"{what} components must be in [0, 1], got {v}")
    return v


class FabricSpec(BaseModel):
    """The bag's fabric: a membrane that resists stretching (a MuJoCo flex shell, services/sim/scene.py)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    stretch_n_per_m: float = Field(FABRIC_STRETCH_N_PER_M, ge=STRETCH_RANGE_N_PER_M[0], le=STRETCH_RANGE_N_PER_M[1],
                                   description="membrane stretch stiffness E*t (N/m)")
    mass_kg: float = Field(FABRIC_MASS_KG, ge=MASS_RANGE_KG[0], le=MASS_RANGE_KG[1], description="the whole bag's mass (kg)")
    damping_s: float = Field(FABRIC_DAMPING_S, ge=DAMPING_RANGE_S[0], le=DAMPING_RANGE_S[1], description="membrane Rayleigh damping (s)")
    friction: float = Field(FABRIC_FRICTION, ge=FRICTION_RANGE[0], le=FRICTION_RANGE[1], description="sliding friction coefficient")


class RimSpec(BaseModel):
    """The binding along the bag's opening: a hem with a little bending stiffness, and its colour."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    bending_nm2: float = Field(RIM_BENDING_NM2, ge=BENDING_RANGE_NM2[0], le=BENDING_RANGE_NM2[1], description="bending stiffness EI (N m^2)")
    color: RGB = Field(RIM_COLOR, description="RGB of a red-edged bag's binding, each in [0, 1] (perception is told it by its config)")

    @field_validator("color")
    @classmethod
    def _color(cls, v: RGB) -> RGB:
        return check_rgb(v, "bag.rim.color")


class LightSpec(BaseModel):
    """The simulated scene's lights: today's two lamps and the camera's headlight, scaled, with the key
    lamp shining along `direction` onto the table's origin."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    intensity: float = Field(1.0, ge=LIGHT_INTENSITY_RANGE[0], le=LIGHT_INTENSITY_RANGE[1], description="x today's light")
    direction: tuple[float, float, float] = Field(KEY_LIGHT_DIRECTION, description="the key light's direction (world), pointing down")

    @field_validator("direction")
    @classmethod
    def _direction(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        n = float(np.linalg.norm(v))
        if not n > 1e-9:
            raise ValueError("sim.light.direction must be a non-zero vector")
        if -v[2] / n < math.sin(MIN_LIGHT_ELEVATION_RAD):
            raise ValueError(f"sim.light.direction {v} must point down onto the table (at least "
                             f"{math.degrees(MIN_LIGHT_ELEVATION_RAD):g} degrees below the horizontal)")
        return v

    def unit_direction(self) -> np.ndarray:
        """(3,) the key light's direction, of unit length."""
        d = np.asarray(self.direction, dtype=float)
        return d / np.linalg.norm(d)


class CalibrationError(BaseModel):
    """How far the camera's true pose is from the calibrated one the rig believes (its `camera:` config):
    the simulator renders from the true pose, perception back-projects with the believed one, as on a
    rig whose hand-eye calibration is off. The true pose is the believed one moved by `offset_m` (world
    axes) and turned by the rotation vector `turn_deg` (world axes, degrees) about the camera's centre."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    offset_m: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="the true position minus the believed (m, world)")
    turn_deg: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="the true orientation's rotation vector from the believed (deg, world)")

    @field_validator("offset_m")
    @classmethod
    def _offset(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if max(abs(c) for c in v) > MAX_CALIBRATION_OFFSET_M:
            raise ValueError(f"sim.camera.calibration_error.offset_m {v} is beyond {MAX_CALIBRATION_OFFSET_M:g} m on an axis")
        return v

    @field_validator("turn_deg")
    @classmethod
    def _turn(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if float(np.linalg.norm(v)) > MAX_CALIBRATION_TURN_DEG:
            raise ValueError(f"sim.camera.calibration_error.turn_deg {v} turns more than {MAX_CALIBRATION_TURN_DEG:g} degrees")
        return v

    def true_pose(self, T_believed: np.ndarray) -> np.ndarray:
        """(4, 4) world <- camera as it really is, from the believed `T_believed (4, 4)`; T_believed itself
        (the same array) when there is no error, so that runs without one are unchanged bit for bit."""
        if not any(self.offset_m) and not any(self.turn_deg):
            return T_believed
        from scipy.spatial.transform import Rotation

        T = np.array(T_believed, dtype=float)
        T[:3, :3] = Rotation.from_rotvec(np.radians(self.turn_deg)).as_matrix() @ T[:3, :3]
        T[:3, 3] += np.asarray(self.offset_m, dtype=float)
        return T

    def size(self) -> tuple[float, float]:
        """(offset in m, turn in degrees): the error's two magnitudes."""
        return float(np.linalg.norm(self.offset_m)), float(np.linalg.norm(self.turn_deg))


class SimCameraSpec(BaseModel):
    """The simulated D455's degradation (services/sim/camera.py `DepthNoise`) and its pose's error."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    depth_noise: float = Field(1.0, ge=DEPTH_NOISE_RANGE[0], le=DEPTH_NOISE_RANGE[1],
                               description="x the depth noise's standard deviation (dropouts and flying pixels unchanged)")
    calibration_error: CalibrationError = CalibrationError()


class SimSpec(BaseModel):
    """What only the simulator uses: its light, its camera's noise and the error of its calibrated pose."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    light: LightSpec = LightSpec()
    camera: SimCameraSpec = SimCameraSpec()
