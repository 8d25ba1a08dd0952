"""Messages the services exchange, as pydantic v2 models.

Every message carries `schema_version` and `stamp` (seconds since the epoch, when it was made).
Units are SI throughout (metres, radians, seconds) whatever the device speaks. Array fields hold
numpy arrays; on the wire (`bagit.common.wire`) they travel as raw little-endian bytes beside a
JSON header, never as JSON numbers.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal, TypeAlias

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, PlainSerializer, field_validator, model_validator

from bagit.common.names import ESTOP_RELEASE_SOURCES, ControllerName, PlannerName, ServoMode, Stage

SCHEMA_VERSION = 1


def _array(dtype: str) -> Any:
    def coerce(v: Any) -> np.ndarray:
        a = np.asarray(v)
        if a.dtype == object:
            raise ValueError("array of mixed or non-numeric values")
        return np.ascontiguousarray(a, dtype=np.dtype(dtype))

    return Annotated[
        np.ndarray,
        BeforeValidator(coerce),
        PlainSerializer(lambda a: a.tolist(), when_used="json"),
    ]


if TYPE_CHECKING:  # to a type checker each is an ndarray; pydantic sees the coercion and the serializer
    ArrayF64: TypeAlias = np.ndarray
    ArrayF32: TypeAlias = np.ndarray
    ArrayU8: TypeAlias = np.ndarray
    ArrayU16: TypeAlias = np.ndarray
else:
    ArrayF64 = _array("<f8")
    ArrayF32 = _array("<f4")
    ArrayU8 = _array("u1")
    ArrayU16 = _array("<u2")


def _check_points(a: np.ndarray, what: str) -> np.ndarray:
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{what} must have shape (n, 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} has NaN or infinite values")
    return a


class Message(BaseModel):
    """Base of every message: a kind (for the wire), a schema version and a timestamp."""

    model_config = ConfigDict(arbitrary_types_allowed=True, extra="forbid")
    KIND: ClassVar[str] = ""

    schema_version: int = SCHEMA_VERSION
    stamp: float = Field(default_factory=time.time)

    @field_validator("schema_version")
    @classmethod
    def _version(cls, v: int) -> int:
        if v != SCHEMA_VERSION:
            raise ValueError(f"schema version {v} is not the supported {SCHEMA_VERSION}")
        return v


class CameraInfo(BaseModel):
    """Pinhole intrinsics and extrinsics of an RGB-D camera (the frame header)."""

    model_config = ConfigDict(extra="forbid")

    width: int = Field(640, ge=1, le=8192)
    height: int = Field(480, ge=1, le=8192)
    fx: float = Field(390.7, gt=0)
    fy: float = Field(390.7, gt=0)
    cx: float = 320.0
    cy: float = 240.0
    depth_scale: float = Field(0.001, gt=0, description="metres per depth unit")
    T_world_camera: list[list[float]] = Field(default_factory=lambda: np.eye(4).tolist())

    def K(self) -> np.ndarray:
        """The 3x3 intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def extrinsics(self) -> np.ndarray:
        """4x4 world <- camera."""
        return np.asarray(self.T_world_camera, dtype=float)


class RgbdFrame(Message):
    """One aligned colour + depth frame. color: (H, W, 3) uint8 RGB; depth: (H, W) uint16 in depth units."""

    KIND: ClassVar[str] = "rgbd"
    seq: int = 0
    camera: CameraInfo = CameraInfo()
    color: ArrayU8
    depth: ArrayU16
    run_id: str | None = None  # a lockstep simulator: the run whose world the frame shows (a real camera: None)

    @field_validator("depth")
    @classmethod
    def _shape(cls, v: np.ndarray) -> np.ndarray:
        if v.ndim != 2:
            raise ValueError(f"depth must be (H, W), got {v.shape}")
        return v


class PointCloud(Message):
    """A (down-sampled) cloud for display. points: (n, 3) float32 world; colors: (n, 3) uint8."""

    KIND: ClassVar[str] = "cloud"
    seq: int = 0
    points: ArrayF32
    colors: ArrayU8 | None = None


class SoiState(Message):
    """The bag rim as n_x ordered points. rim: (n_x, 3) world frame."""

    KIND: ClassVar[str] = "soi"
    seq: int = 0
    source_stamp: float = 0.0
    rim: ArrayF64
    n_points: int = 0
    inlier_fraction: float = 1.0
    solve_ms: float = 0.0
    # Lockstep: an SOI is also perception's answer to its frame (`answer`; a frame with none gets a StepAck):
    # the frame gave an ObjectDetection too (its stamp), and what perception went without (StepAck.late).
    object_stamp: float | None = Field(None, allow_inf_nan=False)
    late: str | None = Field(None, max_length=1000)

    @field_validator("rim")
    @classmethod
    def _rim(cls, v: np.ndarray) -> np.ndarray:
        return _check_points(v, "rim")

    def answer(self) -> StepAck:
        """Perception's answer to the frame this SOI was made from, which the SOI stands for in lockstep."""
        return StepAck(service="perception", frame=self.source_stamp, soi_seq=self.seq, object_stamp=self.object_stamp,
                       late=self.late, stamp=self.source_stamp)


class EllipseParams(BaseModel):
    """A 2-D ellipse in the bottom frame F_m: centre, semi-axes (a >= b) and angle of the major axis."""

    model_config = ConfigDict(extra="forbid")
    center: tuple[float, float]
    a: float
    b: float
    alpha: float


class Goal(Message):
    """Bagging SOI g† and goal SOI g* with the ellipse they came from. g_*: (n_x, 3); frame: (4, 4) world <- F_m."""

    KIND: ClassVar[str] = "goal"
    run_id: str | None = None
    g_dagger: ArrayF64
    g_star: ArrayF64
    frame: ArrayF64
    ellipse: EllipseParams
    perimeter: float
    c1: float
    c2: float
    c3: float
    vertices: ArrayF64
    object_height: float = 0.0


class Path(Message):
    """A planned SOI path g0 ... g† ... g*. nodes: (n_nodes, n_x, 3)."""

    KIND: ClassVar[str] = "path"
    run_id: str | None = None
    success: bool = True
    planner: PlannerName = "cbirrt"
    nodes: ArrayF64
    dagger_index: int
    time_s: float = 0.0
    iterations: int = 0


class Command(Message):
    """A dual-arm increment u: (12,) = [left dx dy dz drx dry drz, right ...] (m, rad) over `dt` seconds."""

    KIND: ClassVar[str] = "cmd"
    run_id: str | None = None
    seq: int = 0
    u: ArrayF64
    dt: float = Field(1 / 30, gt=0, le=1.0)
    mode: Literal["servo", "hold"] = "servo"
    reason: str | None = None
    # the camera stamp of the SOI the command was computed from (0: none, e.g. a hold for a stale SOI),
    # so a consumer can drop commands built from old frames and a benchmark can time frame -> command
    source_stamp: float = 0.0

    @field_validator("u")
    @classmethod
    def _u(cls, v: np.ndarray) -> np.ndarray:
        if v.shape != (12,):
            raise ValueError(f"u must have shape (12,), got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError("u has NaN or infinite values")
        return v


class ArmState(Message):
    """One arm as its controller reports it. q, qd: (6,) rad, rad/s; tool_pose: (6,) world [x y z rx ry rz] m, rad."""

    KIND: ClassVar[str] = "arm_state"
    arm: Literal["left", "right"]
    robot_mode: int = 0
    q: ArrayF64
    qd: ArrayF64
    tool_pose: ArrayF64
    tool_speed: float = 0.0
    enabled: bool = False
    error: bool = False
    error_reason: str | None = None
    command_id: int = 0
    estopped: bool = False
    events: dict[str, int] = Field(default_factory=dict, description="the arm side's counts this run (RunResult.arm_events)")
    target_pose: ArrayF64 | None = Field(
        None, description="(6,) world [x y z rx ry rz] (m, rad): where the arm side is taking the tool, the end of the "
        "increments it has taken (target_pose - tool_pose: the motion still in flight); None: not reported")
    slowed: bool = Field(False, description="the arm side's last servo period sent only part of its step: the joints could not follow")


class ControllerStatus(Message):
    """One control tick as the controller saw it, for live plots: errors (m RMS, None without a valid SOI) and solve time."""

    KIND: ClassVar[str] = "controller_status"
    run_id: str | None = None
    seq: int = 0
    controller: ControllerName = "mpc"
    mode: ServoMode = "servo"
    stage: Stage = "pre-bagging"
    reason: str | None = None
    subgoal_index: int = 0
    progress: float = Field(0.0, ge=0.0, le=1.0)
    error_to_subgoal: float | None = None
    error_to_goal: float | None = None
    solve_ms: float = 0.0
    done: bool = False
    ticks: int = Field(0, ge=0, description="control ticks of this run so far")
    # Lockstep: the last status of a tick is also the controller's answer to its step (`answer`; a tick
    # that sent none answers on sim/ack): the step's time, the command the tick sent, what it went without.
    frame: float | None = Field(None, allow_inf_nan=False)
    cmd_seq: int | None = None
    late: str | None = Field(None, max_length=1000)

    def answer(self) -> StepAck:
        """The controller's answer to the step this status ends (`frame` set), which the status stands for in lockstep."""
        return StepAck(service="controller", run_id=self.run_id, frame=self.frame, cmd_seq=self.cmd_seq, status_seq=self.seq,
                       late=self.late, stamp=self.frame if self.frame is not None else self.stamp)


class RunState(Message):
    """Where the current run is: its id, stage, progress through the path (0..1) and any failure reason."""

    KIND: ClassVar[str] = "run_state"
    run_id: str | None = None
    scenario: str | None = None
    stage: Stage = "idle"
    progress: float = Field(0.0, ge=0.0, le=1.0)
    elapsed_s: float = 0.0
    reason: str | None = None
    result: dict[str, Any] | None = None
    # What the run was started with, so every service configures itself from run/state alone.
    scenario_doc: dict[str, Any] | None = None
    controller: str | None = None
    planner: str | None = None
    seed: int | None = None
    params: dict[str, Any] = {}


class RunControl(Message):
    """A request on run/control: start a scenario (by name or as a document), stop, or reset."""

    KIND: ClassVar[str] = "run_control"
    action: Literal["start", "stop", "reset"]
    scenario: str | None = None
    scenario_doc: dict[str, Any] | None = None
    params: dict[str, Any] = {}
    controller: str | None = None
    planner: str | None = None
    seed: int | None = None


class RunControlReply(Message):
    """The answer to a RunControl: accepted or refused, with the reason."""

    KIND: ClassVar[str] = "run_control_reply"
    accepted: bool
    run_id: str | None = None
    reason: str | None = None


class EStop(Message):
    """Engage (latching) or reset the emergency stop."""

    KIND: ClassVar[str] = "estop"
    engage: bool = True
    source: str = "unknown"
    reason: str | None = None

    def may_act(self) -> bool:
        """Any engage; a release only from ESTOP_RELEASE_SOURCES (the dashboard, the CLI): the one rule
        every service applies, so no service's view of the latch is released by a stray process."""
        return self.engage or self.source in ESTOP_RELEASE_SOURCES


class ClockTick(Message):
    """The simulated rig's time, from `bagit sim` on sim/clock (`BusConfig.clock == "sim"`).

    t: seconds on the rig's clock (the simulated controllers' time: it never goes back, resets
    included). `servo_tick` n: the arm driver runs servo cycle n now, at `t`, and answers it.
    `keepalive`: camera frames come further apart than the controller's keep-alive pace, and the
    controller ticks now on its last SOI (a keep-alive, or a hold) and answers it, as at a frame.
    `frame`: a camera frame falls at `t` too (after the servo tick, if both do): the coordinator's
    tick at `t` waits until that frame (and its control tick) is handled, as `bagit run` orders them."""

    KIND: ClassVar[str] = "clock"
    t: float = Field(ge=0.0, allow_inf_nan=False)
    servo_tick: int | None = Field(None, ge=0)
    run_id: str | None = None
    keepalive: bool = False
    frame: bool = False

    @property
    def control_step(self) -> bool:
        """Whether the controller ticks at `t` (a frame's or a keep-alive's step; a step that is no servo
        tick counts as one): the arm driver publishes the arms' states only at such steps."""
        return self.frame or self.keepalive or self.servo_tick is None


class StepAck(Message):
    """A service's answer to one step of a lockstep simulator (sim/ack): it is done with it.

    The simulator steps on once every answer it needs is in (see bagit.services.sim.lockstep):
    perception for a frame (`frame` = its stamp, `soi_seq` the SOI it made, None if none; a frame with
    an SOI is answered by the SOI itself, `SoiState.answer`), the
    coordinator for that frame (`stage` after it, planning included), the controller for it
    (`cmd_seq` the command it sent, `status_seq` its status, None if none; a tick that sent a status is
    answered by its last status, `ControllerStatus.answer`, which only the coordinator hears), the
    coordinator again once it has handled that status (`status_seq`, `stage` after it: the run may be
    over; `cmd_seq`, the tick's command, which the simulator waits for the driver to have), the arm driver for
    a command it received (`cmd_seq`) and for a servo tick (`tick`, `servo_sent`: the ServoP/ServoJ it
    sent each arm)."""

    KIND: ClassVar[str] = "ack"
    service: str = Field(min_length=1, max_length=64)
    run_id: str | None = None
    frame: float | None = Field(None, allow_inf_nan=False)
    soi_seq: int | None = None
    object_stamp: float | None = Field(None, allow_inf_nan=False)  # perception: the frame also gave an ObjectDetection
    stage: Stage | None = None
    cmd_seq: int | None = None
    status_seq: int | None = None  # controller: the status it sent for the frame; planner: that status handled
    tick: int | None = Field(None, ge=0)
    servo_sent: dict[str, int] | None = None
    late: str | None = Field(None, max_length=1000, description="what this answer went without after waiting the lockstep time-out: "
                             "the step may differ from `bagit run`'s")


class SimTruth(Message):
    """The simulator's ground truth, for tests and benchmarks only (no service may read it).
    rim: (n, 3) the true rim vertices in order, world frame."""

    KIND: ClassVar[str] = "sim_truth"
    run_id: str | None = None
    scenario: str | None = None
    sim_time: float = 0.0
    realtime_factor: float = 0.0
    frames: int = 0
    rim: ArrayF64
    passed_through: bool = False
    max_penetration_m: float = 0.0
    clearance_m: float = 0.0
    final: bool = False  # the world as run `run_id` ended (published once, at that step), not a periodic sample
    exact: bool | None = None  # lockstep: every step of the run was answered in full (None: not lockstep)
    inexact: list[str] = Field(default_factory=list, max_length=100)  # lockstep: why it was not (drops, late answers)

    @field_validator("rim")
    @classmethod
    def _rim(cls, v: np.ndarray) -> np.ndarray:
        return _check_points(v, "rim")


class ObjectDetection(Message):
    """Which object perception sees, and where, from the ArUco marker on it (as in the paper).

    ok: the marker was found and its id is in the object library; then vertices `(n_v, 3)` is the
    object's bottom outline V in the world, T_world_object `(4, 4)` world <- the object's bottom
    frame, T_world_marker `(4, 4)` world <- marker, height its height (m). Otherwise `error` says
    why (no marker in view, an id not in the library) and the arrays are None. source_stamp is the
    frame's stamp; run_id the run perception was following when it looked."""

    KIND: ClassVar[str] = "object"
    seq: int = 0
    source_stamp: float = 0.0
    run_id: str | None = None
    ok: bool = True
    error: str | None = None
    marker_id: int | None = None
    name: str | None = None
    vertices: ArrayF64 | None = None
    T_world_object: ArrayF64 | None = None
    T_world_marker: ArrayF64 | None = None
    height: float | None = None
    reprojection_px: float | None = None
    depth_pixels: int = 0
    others: list[int] = []
    detect_ms: float = 0.0

    @field_validator("vertices")
    @classmethod
    def _v(cls, v: np.ndarray | None) -> np.ndarray | None:
        if v is not None:
            _check_points(v, "vertices")
            if len(v) < 3:
                raise ValueError(f"vertices needs at least 3 points, got {len(v)}")
        return v

    @field_validator("T_world_object", "T_world_marker")
    @classmethod
    def _T(cls, v: np.ndarray | None) -> np.ndarray | None:
        if v is not None and (v.shape != (4, 4) or not np.all(np.isfinite(v))):
            raise ValueError(f"a transform must be a finite (4, 4), got {v.shape}")
        return v

    @model_validator(mode="after")
    def _complete(self) -> ObjectDetection:
        if self.ok and (self.marker_id is None or self.vertices is None or self.T_world_object is None
                        or self.height is None or not np.isfinite(self.height) or self.height <= 0):
            raise ValueError("a detection with ok=True needs marker_id, vertices, T_world_object and a positive height")
        if not self.ok and not self.error:
            raise ValueError("a failed detection (ok=False) needs its error")
        return self


class RecorderStatus(Message):
    """The recorder's counters since it started (`started`: when, its clock), about once a second and at
    each write error: a run's result tells from two of them whether its recording failed and what was lost."""

    KIND: ClassVar[str] = "recorder_status"
    started: float = 0.0
    messages: int = 0  # on disk
    lost: int = 0  # received and not on disk: write errors, a dead writer
    overflow: int = 0  # dropped with the writer behind
    errors: int = 0  # write errors so far
    error: str | None = Field(None, max_length=1000, description="the write error in progress; None while it records")
    last_error: str | None = Field(None, max_length=1000)
    file: str | None = Field(None, max_length=1000)


MESSAGE_TYPES: dict[str, type[Message]] = {
    m.KIND: m
    for m in (RgbdFrame, PointCloud, SoiState, Goal, Path, Command, ControllerStatus, ArmState, RunState, RunControl, RunControlReply, EStop, SimTruth,
              ObjectDetection, ClockTick, StepAck, RecorderStatus)
}
