"""The key space of a rig (bagit/<rig>/...) and the QoS of each key, in one table."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Literal

import zenoh

from bagit.common.errors import BusError
from bagit.common.messages import (
    ArmState,
    ClockTick,
    Command,
    ControllerStatus,
    EStop,
    Goal,
    Message,
    ObjectDetection,
    PointCloud,
    RecorderStatus,
    RgbdFrame,
    RunControl,
    RunState,
    SimTruth,
    SoiState,
    StepAck,
)
from bagit.common.messages import Path as PathMsg

_NAME_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def check_name(v: str, what: str) -> str:
    """`v` if it can be one chunk of a key expression (a rig or service name); ValueError otherwise."""
    if not _NAME_RE.match(v):
        raise ValueError(f"{what} {v!r} must be 1-64 letters, digits, '_' or '-' (it is a key-expression chunk)")
    return v


Reliability = Literal["best_effort", "reliable"]
Congestion = Literal["drop", "block"]
PriorityName = Literal["real_time", "interactive_high", "interactive_low", "data_high", "data", "data_low", "background"]


@dataclass(frozen=True)
class QoS:
    """How a key's samples travel: reliability, what a full queue does, priority and batching."""

    reliability: Reliability
    congestion: Congestion
    priority: PriorityName
    express: bool = False

    def reliable(self) -> QoS:
        """The same priority, but every sample delivered: reliable, and a full queue blocks the publisher."""
        return QoS("reliable", "block", self.priority, self.express)

    def publisher_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for zenoh.Session.declare_publisher."""
        return {
            "reliability": zenoh.Reliability.RELIABLE if self.reliability == "reliable" else zenoh.Reliability.BEST_EFFORT,
            **self.query_kwargs(),
        }

    def query_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for zenoh.Session.get (queries have no reliability knob)."""
        return {
            "congestion_control": zenoh.CongestionControl.BLOCK if self.congestion == "block" else zenoh.CongestionControl.DROP,
            "priority": getattr(zenoh.Priority, self.priority.upper()),
            "express": self.express,
        }


# Latest-wins state: a late sample is worth less than the next one, so never stall the publisher.
STATE = QoS("best_effort", "drop", "data")
STATE_HIGH = QoS("best_effort", "drop", "data_high")
DISPLAY = QoS("best_effort", "drop", "data_low")
# Results and commands: every one matters; block the publisher rather than lose one.
RESULT = QoS("reliable", "block", "data_high")
COMMAND = QoS("reliable", "block", "interactive_high", express=True)
CONTROL = QoS("reliable", "block", "interactive_low")
# The emergency stop overtakes everything, unbatched.
ESTOP = QoS("reliable", "block", "real_time", express=True)


@dataclass(frozen=True)
class KeySpec:
    """One row of the key space: key under bagit/<rig>/, what it carries, how, and why."""

    key: str
    message: type[Message] | None
    qos: QoS | None
    kind: Literal["pub", "query", "liveliness"]
    why: str
    # A lockstep simulator's step waits for samples on this key (a frame, an SOI, an arm state...): under
    # lockstep it is published reliable and blocking (`QoS.reliable`), since one dropped sample would
    # leave a service waiting, or answering without it, and the run different from `bagit run`'s.
    lockstep: bool = False


# The key space and QoS, in one place (docs/architecture.md's "Zenoh key space and QoS" is generated from this).
KEY_TABLE: tuple[KeySpec, ...] = (
    KeySpec("camera/rgbd", RgbdFrame, STATE, "pub", "640x480 colour + depth, ~1.5 MB; a stale frame is useless", lockstep=True),
    KeySpec("perception/cloud", PointCloud, DISPLAY, "pub",
            "down-sampled cloud, for display only; made only while subscribed (the dashboard subscribes while a browser watches)"),
    KeySpec("perception/soi", SoiState, STATE_HIGH, "pub", "rim estimate; the controller wants the newest", lockstep=True),
    KeySpec("perception/object", ObjectDetection, STATE, "pub",
            "marker id, object and its outline V in the world, ~1 Hz while a run perceives; the newest replaces the last", lockstep=True),
    KeySpec("planner/goal", Goal, RESULT, "pub", "g† and g* of a run: once per run, must arrive"),
    KeySpec("planner/path", PathMsg, RESULT, "pub", "SOI path of a run: once per run, must arrive"),
    KeySpec("controller/cmd", Command, COMMAND, "pub",
            "arm increments: none may be lost or reordered; `source_stamp` = the camera stamp of the SOI it came from "
            "(0 for a hold without one); `run_id` must be the servoing run's"),
    KeySpec("controller/status", ControllerStatus, DISPLAY, "pub", "per-tick errors and solve time, for live plots", lockstep=True),
    KeySpec("arm/*/state", ArmState, STATE_HIGH, "pub", "joint and tool state of the left or right arm; newest wins", lockstep=True),
    KeySpec("run/state", RunState, STATE, "pub", "run id, stage, progress, reason; republished periodically", lockstep=True),
    KeySpec("run/control", RunControl, CONTROL, "query", "queryable: start, stop or reset; answered by a RunControlReply"),
    KeySpec("recorder/status", RecorderStatus, STATE, "pub",
            "the recorder's counters (on disk, lost, write errors) ~1 Hz and at each error: a run's result says what its recording lost"),
    KeySpec("estop", EStop, ESTOP, "pub", "emergency stop: highest priority, express, reliable; released only by `source` dashboard or cli"),
    KeySpec("alive/*", None, None, "liveliness", "liveliness token per service; gone within ~1 s of its death"),
    KeySpec("sim/clock", ClockTick, CONTROL, "pub",
            "the simulated rig's time and servo ticks: every service's clock when the bus config says `clock: sim`"),
    KeySpec("sim/clock/keepalive", ClockTick, CONTROL, "pub",
            "lockstep: sim/clock's keep-alive ticks again, for the controller, which ticks on them and on nothing else of it"),
    KeySpec("sim/ack/**", StepAck, CONTROL, "pub",
            "lockstep: each service's answer to a frame or servo tick, on its own key (sim/ack/<service>; the coordinator's "
            "answers to the controller's statuses on sim/ack/planner/status): a service hears only the answers it waits for; "
            "the simulator steps on when all it follows are in (perception's it knows from the coordinator's)"),
    KeySpec("sim/truth", SimTruth, DISPLAY, "pub",
            "simulator ground truth (true rim, pass-through, real-time factor) for tests and benchmarks only: no service may subscribe"),
)


class Keys:
    """The key expressions of one rig: bagit/<rig>/..."""

    def __init__(self, rig: str = "default") -> None:
        try:
            self.rig = check_name(rig, "rig name")
        except ValueError as e:
            raise BusError(str(e)) from None
        self.prefix = f"bagit/{rig}"
        p = self.prefix
        self.camera_rgbd = f"{p}/camera/rgbd"
        self.perception_cloud = f"{p}/perception/cloud"
        self.perception_soi = f"{p}/perception/soi"
        self.perception_object = f"{p}/perception/object"
        self.planner_goal = f"{p}/planner/goal"
        self.planner_path = f"{p}/planner/path"
        self.controller_cmd = f"{p}/controller/cmd"
        self.controller_status = f"{p}/controller/status"
        self.arm_state_any = f"{p}/arm/*/state"
        self.run_state = f"{p}/run/state"
        self.run_control = f"{p}/run/control"
        self.estop = f"{p}/estop"
        self.recorder_status = f"{p}/recorder/status"
        self.alive_any = f"{p}/alive/*"
        self.sim_clock = f"{p}/sim/clock"
        self.sim_keepalive = f"{p}/sim/clock/keepalive"  # the keep-alive ticks of sim/clock, again (the controller's)
        self.sim_ack = f"{p}/sim/ack/**"  # every answer (tools; the simulator follows only those it waits on)
        self.sim_truth = f"{p}/sim/truth"  # tests and benchmarks only
        self.all = f"{p}/**"

    def arm_state(self, arm: Literal["left", "right"]) -> str:
        if arm not in ("left", "right"):
            raise BusError(f"arm must be 'left' or 'right', got {arm!r}")
        return f"{self.prefix}/arm/{arm}/state"

    def step_ack(self, service: str) -> str:
        """The key `service` answers lockstep steps on (sim/ack/<service>)."""
        try:
            return f"{self.prefix}/sim/ack/{check_name(service, 'service name')}"
        except ValueError as e:
            raise BusError(str(e)) from None

    def status_ack(self, service: str) -> str:
        """The key `service` answers the controller's statuses on (sim/ack/<service>/status): apart from its
        answers to frames, which the controller follows, so that the controller hears only those."""
        return f"{self.step_ack(service)}/status"

    def alive(self, service: str) -> str:
        try:
            return f"{self.prefix}/alive/{check_name(service, 'service name')}"
        except ValueError as e:
            raise BusError(str(e)) from None

    def spec(self, key: str) -> KeySpec | None:
        """The KEY_TABLE row a concrete key (or key expression) of this rig belongs to, if any."""
        try:
            k = zenoh.KeyExpr(key)
        except zenoh.ZError:
            return None
        for row in KEY_TABLE:
            pattern = zenoh.KeyExpr(f"{self.prefix}/{row.key}")
            if pattern.includes(k):
                return row
        return None


def _priority_label(q: QoS) -> str:
    return q.priority.replace("_", " ")


def key_table_markdown(rig: str = "<rig>") -> str:
    """The key space and QoS as a Markdown table (as docs/architecture.md shows it)."""
    lines = [
        "| key (under `bagit/<rig>/`) | message | kind | reliability | congestion | priority | express | why |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in KEY_TABLE:
        msg = f"`{r.message.__name__}`" if r.message else "-"
        if r.qos is None:
            q = ["-", "-", "-", "-"]
        else:
            q = [r.qos.reliability.replace("_", "-"), r.qos.congestion, _priority_label(r.qos), "yes" if r.qos.express else "no"]
            if r.lockstep and r.qos.reliability != "reliable":
                q[0], q[1] = q[0] + " (lockstep: reliable)", q[1] + " (lockstep: block)"
        lines.append(f"| `{r.key}` | {msg} | {r.kind} | " + " | ".join(q) + f" | {r.why} |")
    return "\n".join(lines)

