"""The rig: where the two arms, the camera and the world are, and how to reach the arm controllers.

Loaded from YAML (`RigConfig.from_file`); the defaults are the paper's set-up in simulation: two
CR5s facing each other across the object, an eye-to-hand D455 above, both controllers on loopback.
World frame: z up, origin on the table under the object, arms along world y (left at -y).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from bagit.common import cr5
from bagit.common.bag import RIM_PERIMETER_M
from bagit.common.board import BoardSpec
from bagit.common.errors import BadScenario
from bagit.common.geometry import make_transform, pose_to_matrix
from bagit.common.messages import CameraInfo

ArmName = Literal["left", "right"]
ARMS: tuple[ArmName, ArmName] = ("left", "right")


class ArmConfig(BaseModel):
    """One CR5: its base in the world, its controller's address, its workspace box (world frame)."""

    model_config = ConfigDict(extra="forbid")

    base_position: tuple[float, float, float]
    base_rpy: tuple[float, float, float]
    host: str = "127.0.0.1"
    dashboard_port: int = Field(29999, ge=1, le=65535)
    feedback_port: int = Field(30004, ge=1, le=65535)
    workspace_min: tuple[float, float, float] = (-0.45, -0.45, 0.15)
    workspace_max: tuple[float, float, float] = (0.45, 0.45, 0.95)
    payload_kg: float = Field(0.3, ge=0.0, le=5.0, description="mount + bag handle, for EnableRobot")
    speed_factor: int = Field(50, ge=1, le=100)
    mount_offset: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.06), description="the bag mount's centre in the tool-flange frame (m)"
    )

    def T_world_base(self) -> np.ndarray:
        """4x4 world <- arm base."""
        return pose_to_matrix(self.base_position, self.base_rpy)

    def T_flange_mount(self) -> np.ndarray:
        """4x4 tool flange <- bag mount (a rigid offset; the mount is bolted to the flange)."""
        return make_transform(None, np.asarray(self.mount_offset, dtype=float))


class CameraConfig(BaseModel):
    """An eye-to-hand RGB-D camera, placed by position and look-at point; D455 intrinsics at 640x480."""

    model_config = ConfigDict(extra="forbid")

    position: tuple[float, float, float] = (0.55, 0.0, 1.25)
    look_at: tuple[float, float, float] = (0.0, 0.0, 0.45)
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    width: int = Field(640, ge=16, le=4096)
    height: int = Field(480, ge=16, le=4096)
    fx: float = Field(390.7, gt=0)
    fy: float = Field(390.7, gt=0)
    cx: float | None = None
    cy: float | None = None
    fps: float = Field(30.0, gt=0, le=120)
    depth_scale: float = Field(0.001, gt=0)
    serial: str | None = None

    def T_world_camera(self) -> np.ndarray:
        """4x4 world <- camera, camera axes as in OpenCV/RealSense: x right, y down, z forward."""
        p = np.asarray(self.position, dtype=float)
        z = np.asarray(self.look_at, dtype=float) - p
        z /= np.linalg.norm(z)
        x = np.cross(z, np.asarray(self.up, dtype=float))
        if np.linalg.norm(x) < 1e-9:  # looking straight along `up`
            x = np.cross(z, [0.0, 1.0, 0.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        return make_transform(np.column_stack([x, y, z]), p)

    def with_pose(self, T_world_camera: np.ndarray) -> CameraConfig:
        """A copy placed at `T_world_camera (4, 4)` (e.g. calibrated): position, a look-at point 1 m along
        the optical axis and `up` = the camera's -y, which `T_world_camera()` turns back into exactly T."""
        T = np.asarray(T_world_camera, dtype=float)
        p, z, y = T[:3, 3], T[:3, 2], T[:3, 1]
        return self.model_copy(update={"position": tuple(map(float, p)), "look_at": tuple(map(float, p + z)), "up": tuple(map(float, -y))})

    def info(self) -> CameraInfo:
        """The frame header for this camera."""
        return CameraInfo(
            width=self.width,
            height=self.height,
            fx=self.fx,
            fy=self.fy,
            cx=self.cx if self.cx is not None else (self.width - 1) / 2,
            cy=self.cy if self.cy is not None else (self.height - 1) / 2,
            depth_scale=self.depth_scale,
            T_world_camera=self.T_world_camera().tolist(),
        )


def _default_arms() -> dict[ArmName, ArmConfig]:
    return {
        # Bases 0.6 m either side of the object, facing each other (the right arm turned by pi).
        "left": ArmConfig(base_position=(0.0, -0.6, 0.0), base_rpy=(0.0, 0.0, np.pi / 2)),
        "right": ArmConfig(
            base_position=(0.0, 0.6, 0.0), base_rpy=(0.0, 0.0, -np.pi / 2), dashboard_port=29989, feedback_port=30014
        ),
    }


# How far short of half its rim's perimeter the mounts stay (`rim_separation_limit_m`): what the rig's one fixed
# limit, 0.32 m, always left under the paper's 0.68 m bag (0.34 - 0.32), now kept for every bag, so that a run
# of a 0.68 m bag keeps the limit it had to the last bit.
RIM_SEPARATION_MARGIN_M = 0.02


def rim_separation_limit_m(rim_perimeter_m: float) -> float:
    """The farthest apart the two mounts may hold a rim of perimeter P (m): P/2 - RIM_SEPARATION_MARGIN_M.

    Why P/2: two points of a closed curve of length P are at most P/2 apart (the two arcs between them are
    each at least as long as the chord and together P long), and a mount's centre is the mean of the rim
    points it clamps, inside the rim's convex hull, whose diameter is the rim's. So no intact rim can hold
    the mounts further apart than P/2, whatever the mounts' shape: that is the rim folded flat and pulled
    taut between them. Beyond it the arms pull against each other through the fabric (a real bag tears; the
    simulated membrane stretches). The shapes the method asks for lie well inside: a round rim holds the
    mounts P/pi (0.32 P) apart, the simulator's start rim 0.31 P (an ellipse of aspect 1.3) and, pulled
    taut, 0.33 P (each of its mounts clamps a quarter of the rim); the goal's rim has the bag's perimeter.
    """
    return rim_perimeter_m / 2 - RIM_SEPARATION_MARGIN_M


class SafetyLimits(BaseModel):
    """Limits the arm driver enforces on every outgoing command.

    Two sets of acceleration and jerk limits, each a norm per arm (linear at the mount, angular):
    - the path's (`max_*`): what every command keeps while the arms follow the controller;
    - the stop's (`stop_*`): what a stop keeps, braking from wherever the path left the arms to rest
      (the watchdog, a hold, a fault, a lost link, the run's end). A controlled stop with the drives
      powered, as IEC 60204-1 stop category 2: at the arm's stopping limits, not the gentle ones that
      keep a bag's rim smooth, so that the arms are still within the watchdog's budget of the last
      command that reached them (`bagit.bench.stop_timeline`). Speed stays the path's: a stop only slows.

    The stop's limits are within the CR5's, with margin: 4 m/s^2 at the mount asks a joint at most
    `cr5.JOINT_ACCEL_LIMIT` (12 rad/s^2) while the mount is 0.33 m or more from that joint's axis (at
    home the rig's mounts are 0.4-0.6 m from the axes of the base, shoulder and elbow joints);
    8 rad/s^2 for turning the tool, which the wrist joints do nearly one to one; the jerks such that
    each reaches its full value in 40 ms. Braking from a motion that just started is bound by the jerk, from the path's full speed by
    both (0.25 m/s: 100 ms). Validated: a stop never brakes more gently than the path follows, and never
    asks for more than the CR5's joints can give (angular at most the joint bound, linear at most the
    joint bound at full reach).
    """

    model_config = ConfigDict(extra="forbid")

    max_tcp_speed_mps: float = Field(0.25, gt=0, le=1.0)
    max_tcp_accel_mps2: float = Field(1.0, gt=0, le=10.0)
    max_tcp_jerk_mps3: float = Field(10.0, gt=0, le=500.0)
    max_angular_speed_rps: float = Field(1.0, gt=0, le=5.0)
    max_angular_accel_rps2: float = Field(4.0, gt=0, le=50.0)
    max_angular_jerk_rps3: float = Field(40.0, gt=0, le=1000.0)
    stop_tcp_accel_mps2: float = Field(4.0, gt=0, description="a stop's deceleration at the mount (norm)")
    stop_tcp_jerk_mps3: float = Field(100.0, gt=0, le=1000.0, description="a stop's jerk at the mount (norm)")
    stop_angular_accel_rps2: float = Field(8.0, gt=0, description="a stop's angular deceleration of the tool (norm)")
    stop_angular_jerk_rps3: float = Field(200.0, gt=0, le=2000.0, description="a stop's angular jerk of the tool (norm)")
    min_flange_distance_m: float = Field(0.08, ge=0.0, description="the mounts at least this far apart: the tools must not meet")
    max_flange_distance_m: float | None = Field(
        None, gt=0.0, description="the rig's own ceiling on the mounts' separation (m), if it has one (its cell, its cables); "
        "the arms keep the lower of it and the bag's rim's (`max_separation_m`); the workspace boxes bound them besides",
    )
    rim_perimeter_m: float = Field(
        RIM_PERIMETER_M, gt=0.05, lt=10.0, description="the perimeter of the rim of the bag the arms hold (m): the separation "
        "follows it (`rim_separation_limit_m`); `bagit run` and `bagit up` set the scenario's, a lab its own bag's (`RigConfig.for_bag`)",
    )
    watchdog_s: float = Field(
        0.12, gt=0, le=5.0,
        description="no command for this long: the arms brake to rest (issued a servo period ahead, so a gap of "
        "watchdog_s - servo_period_s halts them). The controller sends one every control tick while servoing, a "
        "keep-alive between camera frames, so at 30 Hz a whole late tick passes; commands older than this are refused",
    )
    servo_period_s: float = Field(0.03, ge=0.03, le=0.2, description="ServoP no faster than every 30 ms")

    @model_validator(mode="after")
    def _watchdog_lets_a_late_command_pass(self) -> SafetyLimits:
        """The watchdog acts a servo period ahead of its deadline, so it halts after a gap of watchdog_s -
        servo_period_s; with watchdog_s >= 4 servo periods that gap is at least 3/4 of the watchdog, more
        than two of the controller's keep-alive periods (`bagit.services.controller.session.KEEPALIVE_SHARE`)."""
        if self.watchdog_s < 4 * self.servo_period_s:
            raise ValueError(f"watchdog_s ({self.watchdog_s:g} s) must be at least 4 servo periods ({4 * self.servo_period_s:g} s)")
        return self

    @model_validator(mode="after")
    def _a_stop_brakes_at_least_as_hard_as_the_path_and_within_the_cr5(self) -> SafetyLimits:
        """A stop gentler than the path would take longer than following the path to rest; one harder than
        the CR5's joints can brake would only make the controller lag (or alarm) instead."""
        pairs = (("stop_tcp_accel_mps2", "max_tcp_accel_mps2"), ("stop_tcp_jerk_mps3", "max_tcp_jerk_mps3"),
                 ("stop_angular_accel_rps2", "max_angular_accel_rps2"), ("stop_angular_jerk_rps3", "max_angular_jerk_rps3"))
        for stop, path in pairs:
            if getattr(self, stop) < getattr(self, path):
                raise ValueError(f"{stop} ({getattr(self, stop):g}) must be at least {path} ({getattr(self, path):g}): "
                                 "a stop brakes at least as hard as the path follows")
        ceilings = (("stop_tcp_accel_mps2", cr5.JOINT_ACCEL_LIMIT * cr5.REACH_M), ("stop_angular_accel_rps2", cr5.JOINT_ACCEL_LIMIT))
        for stop, most in ceilings:
            if getattr(self, stop) > most:
                raise ValueError(f"{stop} ({getattr(self, stop):g}) is more than the CR5's joints can brake ({most:g}, cr5.JOINT_ACCEL_LIMIT)")
        return self

    @model_validator(mode="after")
    def _the_bag_fits_between_the_tools(self) -> SafetyLimits:
        """The tools cannot come closer than `min_flange_distance_m`: a rim that cannot hold them that far apart
        is too small for this rig (or its ceiling below its floor)."""
        if self.max_separation_m <= self.min_flange_distance_m:
            raise ValueError(f"the mounts may be at most {self.max_separation_m * 1000:.0f} mm apart (a rim of {self.rim_perimeter_m:g} m"
                             + (f", the rig's ceiling {self.max_flange_distance_m:g} m" if self.max_flange_distance_m is not None else "")
                             + f"), not more than min_flange_distance_m ({self.min_flange_distance_m * 1000:.0f} mm): the bag is too small for the tools")
        return self

    @property
    def max_separation_m(self) -> float:
        """The farthest apart the arm driver lets the mounts be: the bag's rim's limit, under the rig's own ceiling if any."""
        bag = rim_separation_limit_m(self.rim_perimeter_m)
        return bag if self.max_flange_distance_m is None else min(bag, self.max_flange_distance_m)

    def path_limits(self) -> np.ndarray:
        """`(2, 3)` [[speed, acceleration, jerk] linear (m), [...] angular (rad)]: what following keeps."""
        return np.array([[self.max_tcp_speed_mps, self.max_tcp_accel_mps2, self.max_tcp_jerk_mps3],
                         [self.max_angular_speed_rps, self.max_angular_accel_rps2, self.max_angular_jerk_rps3]])

    def stop_limits(self) -> np.ndarray:
        """`(2, 3)` as `path_limits`, what a stop keeps: the path's speed, the stop's acceleration and jerk."""
        return np.array([[self.max_tcp_speed_mps, self.stop_tcp_accel_mps2, self.stop_tcp_jerk_mps3],
                         [self.max_angular_speed_rps, self.stop_angular_accel_rps2, self.stop_angular_jerk_rps3]])

    @property
    def halt_gap_s(self) -> float:
        """The longest gap between two commands that does not halt the arms."""
        return self.watchdog_s - self.servo_period_s


class RigConfig(BaseModel):
    """The whole rig."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field("sim", pattern=r"^[A-Za-z0-9_-]{1,64}$", description="rig name, the Zenoh key prefix")
    arms: dict[ArmName, ArmConfig] = Field(default_factory=_default_arms)
    camera: CameraConfig = CameraConfig()
    safety: SafetyLimits = SafetyLimits()
    table_height: float = 0.0
    board: BoardSpec = Field(default_factory=BoardSpec, description="the calibration board and where it lies (bagit calibrate)")

    @classmethod
    def from_file(cls, path: str | Path) -> RigConfig:
        p = Path(path)
        try:
            data = yaml.safe_load(p.read_text(encoding="utf-8")) or {}
            return cls.model_validate(data)
        except (OSError, yaml.YAMLError) as e:
            raise BadScenario(f"cannot read rig config {p}: {e}") from None
        except ValidationError as e:
            first = e.errors()[0]
            raise BadScenario(f"{p}: {'.'.join(map(str, first['loc']))}: {first['msg']}") from None

    def for_bag(self, rim_perimeter_m: float) -> RigConfig:
        """This rig holding a bag whose rim is `rim_perimeter_m` (m) long: its separation limit follows that rim.
        BadScenario when the rig cannot hold it (too small for the tools)."""
        try:
            safety = SafetyLimits.model_validate({**self.safety.model_dump(), "rim_perimeter_m": rim_perimeter_m})
        except ValidationError as e:
            raise BadScenario(f"a bag of perimeter {rim_perimeter_m:g} m: {e.errors()[0]['msg']}") from None
        return self.model_copy(update={"safety": safety})

    def to_yaml(self) -> str:
        import json

        return yaml.safe_dump(json.loads(self.model_dump_json(exclude_none=True)), sort_keys=False)
