"""The Zenoh transport every service shares: session set-up, the key space, QoS per key, typed
publishers and subscribers, run-control queries and liveliness.

Zenoh is imported here and in the service nodes only; the pure algorithm modules never see it.
Payloads are `bagit.common.wire` bytes (a JSON header plus raw little-endian arrays, no pickle).
A payload that does not decode to the expected message of this schema version is logged,
counted per key and dropped: it never reaches a callback and never raises in a Zenoh thread.

    cfg = BusConfig(rig="lab", connect=["tcp/127.0.0.1:7447"])
    with open_session(cfg) as s:
        keys = Keys(cfg.rig)
        pub = Publisher(s, keys.perception_soi, SoiState)
        cache = LatestCache(s, keys.perception_soi, SoiState)
        token = declare_alive(s, keys, "perception")

Loopback by default: with no config file a session listens on tcp/127.0.0.1 only and multicast
scouting is off, so nothing is reachable from, or discovered on, the lab network unless a config
says so. Multicast scouting finds peers on the LAN without configuration; it is off by default so
that tests and two rigs on one network never join each other by accident. The link lease is 1 s
(keep-alives every 250 ms), so the death of a process is noticed within about a second.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Generic, Literal, TypeVar

import zenoh
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from bagit.common import wire
from bagit.common.errors import BadMessage, BagItError, BusError
from bagit.common.clock import CLOCK_KINDS, ClockKind, SimClock, WallClock, make_clock
from bagit.common.messages import (
    ArmState,
    ClockTick,
    Command,
    ControllerStatus,
    EStop,
    Goal,
    Message,
    ObjectDetection,
    Path as PathMsg,
    PointCloud,
    RgbdFrame,
    RunControl,
    RunControlReply,
    RunState,
    SimTruth,
    SoiState,
    StepAck,
)

log = logging.getLogger("bagit.bus")

M = TypeVar("M", bound=Message)
R = TypeVar("R", bound=Message)

_NAME_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
_ENDPOINT_RE = re.compile(r"^[a-z][a-z0-9-]*/\S+$")
DEFAULT_ROUTER_PORT = 7447

# ---------------------------------------------------------------------------------------------
# Session configuration
# ---------------------------------------------------------------------------------------------


def _check_name(v: str, what: str) -> str:
    if not _NAME_RE.match(v):
        raise ValueError(f"{what} {v!r} must be 1-64 letters, digits, '_' or '-' (it is a key-expression chunk)")
    return v


class BusConfig(BaseModel):
    """Where a service's Zenoh session listens and connects, and on which rig.

    With `config_file` (a Zenoh json5 config) the file is the base and only the fields set
    explicitly here override it; without one, every field applies and the session stays on
    loopback. A file without listen endpoints also gets the loopback default.
    """

    model_config = ConfigDict(extra="forbid")

    rig: str = Field("default", description="rig name: the second chunk of every key, so rigs can share a network")
    mode: Literal["peer", "client", "router"] = "peer"
    connect: list[str] = Field(default_factory=list, description="endpoints to connect to, e.g. tcp/10.0.0.2:7447")
    listen: list[str] | None = Field(
        None, description="endpoints to listen on; None = tcp/127.0.0.1:0 (peer), tcp/127.0.0.1:7447 (router), none (client)"
    )
    multicast_scouting: bool = Field(False, description="discover peers by UDP multicast on the LAN (off: loopback tests, rig isolation)")
    config_file: Path | None = Field(None, description="a Zenoh json5 config used as the base")
    lease_ms: int = Field(1000, ge=100, le=60_000, description="link lease: a silent peer is declared dead after this")
    adminspace: bool = Field(False, description="answer queries on the @/ admin space (needed by `locators`)")
    tls_ca: Path | None = Field(None, description="CA certificate (PEM) that signs every identity on the rig")
    tls_cert: Path | None = Field(None, description="this service's certificate (PEM); its common name is its identity")
    tls_key: Path | None = Field(None, description="this service's private key (PEM), with tls_cert: mutual TLS")
    scouting_delay_ms: int | None = Field(
        None, ge=0, le=10_000, description="how long a peer's open waits for scouting; None = 0 without multicast, 500 with"
    )
    clock: ClockKind = Field("wall", description="wall: this host's clock (a real rig); sim: the simulator's, from sim/clock (lockstep)")

    @field_validator("rig")
    @classmethod
    def _rig(cls, v: str) -> str:
        return _check_name(v, "rig name")

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints(cls, v: list[str] | None) -> list[str] | None:
        for e in v or []:
            if not _ENDPOINT_RE.match(e):
                raise ValueError(f"endpoint {e!r} is not '<proto>/<address>' (e.g. tcp/127.0.0.1:7447)")
        return v

    @model_validator(mode="after")
    def _tls_pair(self) -> "BusConfig":
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("tls_cert and tls_key go together")
        return self

    def listen_endpoints(self, mode: str | None = None) -> list[str]:
        """The listen endpoints this config asks for (loopback unless set) in `mode` (default: self.mode)."""
        if self.listen is not None:
            return list(self.listen)
        mode = mode or self.mode
        if mode == "router":
            return [f"tcp/127.0.0.1:{DEFAULT_ROUTER_PORT}"]
        if mode == "peer":
            return ["tcp/127.0.0.1:0"]
        return []

    def to_zenoh(self) -> zenoh.Config:
        """Build the zenoh.Config. Raises BusError for an unreadable or invalid config file."""
        explicit = self.model_fields_set
        if self.config_file is not None:
            try:
                zc = zenoh.Config.from_file(str(self.config_file))
            except (zenoh.ZError, OSError, ValueError) as e:
                raise BusError(f"zenoh config {self.config_file}: {_one_line(e)}") from None
            file_listen = config_value(zc, "listen/endpoints")
            # zenoh's default listen (a dict per mode on [::]) means the file did not say: stay on loopback
            listen_unset = isinstance(file_listen, dict) or file_listen is None
            mode = self.mode if "mode" in explicit else (config_value(zc, "mode") or "peer")
        else:
            zc = zenoh.Config()
            explicit = set(type(self).model_fields)
            listen_unset = True
            mode = self.mode
        try:
            if "mode" in explicit:
                zc.insert_json5("mode", json.dumps(self.mode))
            if "connect" in explicit:
                zc.insert_json5("connect/endpoints", json.dumps(self.connect))
            if "listen" in explicit or listen_unset:
                zc.insert_json5("listen/endpoints", json.dumps(self.listen_endpoints(mode)))
            if "multicast_scouting" in explicit:
                zc.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
            if "lease_ms" in explicit:
                zc.insert_json5("transport/link/tx/lease", json.dumps(self.lease_ms))
            if "scouting_delay_ms" in explicit or "multicast_scouting" in explicit:
                delay = self.scouting_delay_ms if self.scouting_delay_ms is not None else (500 if self.multicast_scouting else 0)
                zc.insert_json5("scouting/delay", json.dumps(delay))
            if "tls_ca" in explicit and self.tls_ca is not None:
                zc.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(self.tls_ca)))
            if "tls_cert" in explicit and self.tls_cert is not None and self.tls_key is not None:
                # the same identity whether this end dials or listens; mutual: both ends show a certificate
                for side in ("connect", "listen"):
                    zc.insert_json5(f"transport/link/tls/{side}_certificate", json.dumps(str(self.tls_cert)))
                    zc.insert_json5(f"transport/link/tls/{side}_private_key", json.dumps(str(self.tls_key)))
                zc.insert_json5("transport/link/tls/enable_mtls", "true")
            if "adminspace" in explicit:
                zc.insert_json5("adminspace/enabled", json.dumps(self.adminspace))
        except (zenoh.ZError, ValueError) as e:
            raise BusError(f"zenoh config: {_one_line(e)}") from None
        return zc


def config_value(zc: zenoh.Config, key: str) -> Any:
    """A value of a zenoh.Config, parsed (zenoh's get_json returns JSON text); None if absent."""
    try:
        return json.loads(zc.get_json(key))
    except (zenoh.ZError, ValueError, TypeError):
        return None


def _one_line(e: BaseException) -> str:
    s = str(e).strip()
    return s.splitlines()[0] if s else type(e).__name__


def open_session(cfg: BusConfig) -> zenoh.Session:
    """Open a Zenoh session for `cfg`. Raises BusError when Zenoh refuses (port taken, router absent...).

    A client whose config says `connect.timeout_ms: -1` (the deploy/ host configs) waits here
    until the router answers, which is what a service started at boot wants.
    """
    zenoh.try_init_log_from_env()
    zc = cfg.to_zenoh()
    try:
        return zenoh.open(zc)
    except zenoh.ZError as e:
        raise BusError(
            f"cannot open a zenoh {cfg.mode} session (listen {cfg.listen_endpoints()}, connect {cfg.connect}): {_one_line(e)}"
        ) from None


def locators(session: zenoh.Session, timeout: float = 2.0) -> list[str]:
    """The endpoints `session` really listens on (port 0 resolved). Needs BusConfig(adminspace=True)."""
    zid = str(session.zid())
    for reply in session.get(f"@/{zid}/*", timeout=timeout):
        if reply.ok is None:
            continue
        try:
            info = json.loads(reply.ok.payload.to_bytes())
        except (ValueError, UnicodeDecodeError):
            continue
        if isinstance(info, dict) and isinstance(info.get("locators"), list):
            return [str(x) for x in info["locators"]]
    raise BusError(f"session {zid} did not report its locators (open it with BusConfig(adminspace=True))")


def add_bus_arguments(p: argparse.ArgumentParser) -> None:
    """The Zenoh flags every service takes, named as in zenoh-python's examples."""
    g = p.add_argument_group("zenoh")
    g.add_argument("--rig", help="rig name (key prefix bagit/<rig>/...)")
    g.add_argument("-m", "--mode", choices=["peer", "client", "router"], help="zenoh session mode")
    g.add_argument("-e", "--connect", action="append", metavar="ENDPOINT", help="endpoint to connect to (repeatable)")
    g.add_argument("-l", "--listen", action="append", metavar="ENDPOINT", help="endpoint to listen on (repeatable)")
    g.add_argument("--zenoh-config", metavar="FILE", help="zenoh json5 config file (base; the flags override it)")
    g.add_argument("--multicast-scouting", action="store_true", default=None, help="discover peers by UDP multicast")
    g.add_argument("--tls-ca", metavar="PEM", help="CA certificate of the rig (TLS endpoints)")
    g.add_argument("--tls-cert", metavar="PEM", help="this service's certificate (mutual TLS identity)")
    g.add_argument("--tls-key", metavar="PEM", help="this service's private key")
    g.add_argument("--clock", choices=list(CLOCK_KINDS), help="the rig's clock: wall (real rig) or sim (the simulator's sim/clock, lockstep)")


def bus_config_from_args(args: argparse.Namespace, base: BusConfig | None = None) -> BusConfig:
    """Overlay the flags of `add_bus_arguments` on `base` (e.g. the `bus:` section of a service config)."""
    data = base.model_dump(exclude_unset=True) if base is not None else {}
    for flag, field in (("rig", "rig"), ("mode", "mode"), ("connect", "connect"), ("listen", "listen"),
                        ("zenoh_config", "config_file"), ("multicast_scouting", "multicast_scouting"),
                        ("tls_ca", "tls_ca"), ("tls_cert", "tls_cert"), ("tls_key", "tls_key"), ("clock", "clock")):
        v = getattr(args, flag, None)
        if v is not None:
            data[field] = v
    return parse_bus_config(data)


def parse_bus_config(data: dict[str, Any]) -> BusConfig:
    """Validate a bus config mapping; BusError naming the first bad field otherwise."""
    try:
        return BusConfig.model_validate(data)
    except ValidationError as e:
        first = e.errors()[0]
        where = ".".join(map(str, first["loc"])) or "bus"
        raise BusError(f"bus config: {where}: {first['msg'].removeprefix('Value error, ')}") from None


# ---------------------------------------------------------------------------------------------
# QoS and the key space
# ---------------------------------------------------------------------------------------------

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


# The key space and QoS, in one place (README "Zenoh key space and QoS" is generated from this).
KEY_TABLE: tuple[KeySpec, ...] = (
    KeySpec("camera/rgbd", RgbdFrame, STATE, "pub", "640x480 colour + depth, ~1.5 MB; a stale frame is useless"),
    KeySpec("perception/cloud", PointCloud, DISPLAY, "pub", "down-sampled cloud, for display only"),
    KeySpec("perception/soi", SoiState, STATE_HIGH, "pub", "rim estimate; the controller wants the newest"),
    KeySpec("perception/object", ObjectDetection, STATE, "pub",
            "marker id, object and its outline V in the world, ~1 Hz while a run perceives; the newest replaces the last"),
    KeySpec("planner/goal", Goal, RESULT, "pub", "g† and g* of a run: once per run, must arrive"),
    KeySpec("planner/path", PathMsg, RESULT, "pub", "SOI path of a run: once per run, must arrive"),
    KeySpec("controller/cmd", Command, COMMAND, "pub", "arm increments: none may be lost or reordered; `source_stamp` = the camera stamp of the SOI it came from (0 for a hold without one); `run_id` must be the servoing run's"),
    KeySpec("controller/status", ControllerStatus, DISPLAY, "pub", "per-tick errors and solve time, for live plots"),
    KeySpec("arm/*/state", ArmState, STATE_HIGH, "pub", "joint and tool state of the left or right arm; newest wins"),
    KeySpec("run/state", RunState, STATE, "pub", "run id, stage, progress, reason; republished periodically"),
    KeySpec("run/control", RunControl, CONTROL, "query", "queryable: start, stop or reset; answered by a RunControlReply"),
    KeySpec("estop", EStop, ESTOP, "pub", "emergency stop: highest priority, express, reliable; released only by `source` dashboard or cli"),
    KeySpec("alive/*", None, None, "liveliness", "liveliness token per service; gone within ~1 s of its death"),
    KeySpec("sim/clock", ClockTick, CONTROL, "pub",
            "the simulated rig's time and servo ticks: every service's clock when the bus config says `clock: sim`"),
    KeySpec("sim/ack", StepAck, CONTROL, "pub",
            "lockstep: each service's answer to a frame or servo tick; the simulator steps on when all are in"),
    KeySpec("sim/truth", SimTruth, DISPLAY, "pub",
            "simulator ground truth (true rim, pass-through, real-time factor) for tests and benchmarks only: no service may subscribe"),
)


class Keys:
    """The key expressions of one rig: bagit/<rig>/..."""

    def __init__(self, rig: str = "default") -> None:
        try:
            self.rig = _check_name(rig, "rig name")
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
        self.alive_any = f"{p}/alive/*"
        self.sim_clock = f"{p}/sim/clock"
        self.sim_ack = f"{p}/sim/ack"
        self.sim_truth = f"{p}/sim/truth"  # tests and benchmarks only
        self.all = f"{p}/**"

    def arm_state(self, arm: Literal["left", "right"]) -> str:
        if arm not in ("left", "right"):
            raise BusError(f"arm must be 'left' or 'right', got {arm!r}")
        return f"{self.prefix}/arm/{arm}/state"

    def alive(self, service: str) -> str:
        try:
            return f"{self.prefix}/alive/{_check_name(service, 'service name')}"
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
    """The key space and QoS as a Markdown table (README-ready)."""
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
        lines.append(f"| `{r.key}` | {msg} | {r.kind} | " + " | ".join(q) + f" | {r.why} |")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Drop accounting
# ---------------------------------------------------------------------------------------------


class DropCounters:
    """Thread-safe count of payloads dropped per key, with the last reason. Logs the first few
    and then every 100th per key, so a flood of garbage cannot flood the log."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: dict[str, int] = {}
        self._last: dict[str, str] = {}

    def add(self, key: str, reason: str) -> int:
        with self._lock:
            n = self._counts.get(key, 0) + 1
            self._counts[key] = n
            self._last[key] = reason
        if n <= 5 or n % 100 == 0:
            log.warning("dropped payload #%d on %s: %s", n, key, reason)
        return n

    def count(self, key: str | None = None) -> int:
        """Drops on `key`, or on every key if None."""
        with self._lock:
            return sum(self._counts.values()) if key is None else self._counts.get(key, 0)

    def last_reason(self, key: str) -> str | None:
        with self._lock:
            return self._last.get(key)

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)


DROPS = DropCounters()  # process-wide; every subscriber also counts its own


def _payload_bytes(sample_or_query: Any) -> bytes | None:
    p = sample_or_query.payload
    return None if p is None else p.to_bytes()


# ---------------------------------------------------------------------------------------------
# Publishing and subscribing
# ---------------------------------------------------------------------------------------------


def _default_qos(key: str, msg_type: type[Message]) -> QoS:
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != "bagit":
        raise BusError(f"key {key!r} is outside bagit/<rig>/...; pass qos= explicitly")
    spec = Keys(parts[1]).spec(key)
    if spec is None or spec.qos is None:
        raise BusError(f"key {key!r} is not in the key table; pass qos= explicitly")
    if spec.message is not msg_type:
        raise BusError(f"key {key!r} carries {spec.message.__name__ if spec.message else 'no message'}, not {msg_type.__name__}")
    return spec.qos


def encoding_for(msg_type: type[Message]) -> zenoh.Encoding:
    """application/octet-stream tagged with the message kind and schema version (visible to zenoh tools)."""
    from bagit.common.messages import SCHEMA_VERSION

    return zenoh.Encoding("application/octet-stream").with_schema(f"bagit.{msg_type.KIND}.v{SCHEMA_VERSION}")


class Publisher(Generic[M]):
    """Puts messages of one type on one key with that key's QoS (from KEY_TABLE unless given)."""

    def __init__(self, session: zenoh.Session, key: str, msg_type: type[M], qos: QoS | None = None) -> None:
        self.key = key
        self.msg_type = msg_type
        self.qos = qos or _default_qos(key, msg_type)
        self.sent = 0
        self._pub = session.declare_publisher(key, encoding=encoding_for(msg_type), **self.qos.publisher_kwargs())

    @property
    def matched(self) -> bool:
        """True once some subscriber matches this key (puts before that reach no one)."""
        return _matching(self._pub)

    def put(self, msg: M) -> int:
        """Send one message; returns the payload size in bytes."""
        if not isinstance(msg, self.msg_type):
            raise BadMessage(f"{self.key} carries {self.msg_type.__name__}, not {type(msg).__name__}")
        payload = wire.encode(msg)
        self._pub.put(payload)
        self.sent += 1
        return len(payload)

    def close(self) -> None:
        try:
            self._pub.undeclare()
        except zenoh.ZError:
            pass  # the session is already closed

    def __enter__(self) -> "Publisher[M]":
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()


class Subscriber(Generic[M]):
    """Calls `callback(msg)` for each sample on `key` that decodes as `msg_type`.

    Everything else is logged, counted (`dropped`, and per key in `counters`) and dropped. The
    callback runs in a Zenoh-owned Python thread; an exception in it is logged and counted in
    `callback_errors`, never propagated.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        msg_type: type[M],
        callback: Callable[[M], None],
        counters: DropCounters = DROPS,
    ) -> None:
        self.key = key
        self.msg_type = msg_type
        self.callback = callback
        self.counters = counters
        self.received = 0
        self.dropped = 0
        self.callback_errors = 0
        self.last_error: str | None = None
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(key, self._on_sample)

    def _decode(self, sample: zenoh.Sample) -> M | None:
        if sample.kind != zenoh.SampleKind.PUT:
            return None
        key = str(sample.key_expr)
        try:
            raw = _payload_bytes(sample) or b""
            msg = wire.decode(raw, self.msg_type)
        except BadMessage as e:
            reason = str(e)
        except Exception as e:  # noqa: BLE001 - a hostile payload must never kill the Zenoh thread
            reason = f"undecodable payload: {type(e).__name__}: {_one_line(e)}"
        else:
            with self._lock:
                self.received += 1
            return msg
        with self._lock:
            self.dropped += 1
            self.last_error = reason
        self.counters.add(key, reason)
        return None

    def _on_sample(self, sample: zenoh.Sample) -> None:
        msg = self._decode(sample)
        if msg is None:
            return
        self._deliver(msg, str(sample.key_expr))

    def _deliver(self, msg: M, key: str) -> None:
        try:
            self.callback(msg)
        except Exception:  # noqa: BLE001
            with self._lock:
                self.callback_errors += 1
                n = self.callback_errors
            if n <= 5 or n % 100 == 0:
                log.exception("callback on %s failed (#%d)", key, n)

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass

    def __enter__(self) -> "Subscriber[M]":
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()


class LatestCache(Subscriber[M]):
    """Latest-wins state on a key: the newest good message per concrete key, with its receive time
    (time.monotonic). For a wildcard key such as arm/*/state each arm has its own entry."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        msg_type: type[M],
        on_update: Callable[[M], None] | None = None,
        counters: DropCounters = DROPS,
    ) -> None:
        self._cond = threading.Condition()
        self._latest: dict[str, tuple[M, float]] = {}
        self._newest_key: str | None = None
        super().__init__(session, key, msg_type, on_update or (lambda _m: None), counters)

    def _deliver(self, msg: M, key: str) -> None:
        with self._cond:
            self._latest[key] = (msg, time.monotonic())
            self._newest_key = key
            self._cond.notify_all()
        super()._deliver(msg, key)

    def get(self, key: str | None = None) -> M | None:
        """The newest message (on `key`, or on any key of the subscription)."""
        item = self.get_with_time(key)
        return None if item is None else item[0]

    def get_with_time(self, key: str | None = None) -> tuple[M, float] | None:
        with self._cond:
            k = key if key is not None else self._newest_key
            return None if k is None else self._latest.get(k)

    def items(self) -> dict[str, tuple[M, float]]:
        with self._cond:
            return dict(self._latest)

    def age(self, key: str | None = None, now: float | None = None) -> float:
        """Seconds since the newest message arrived; inf if none has."""
        item = self.get_with_time(key)
        if item is None:
            return math.inf
        return (time.monotonic() if now is None else now) - item[1]

    def wait(self, timeout: float, key: str | None = None, newer_than: float | None = None) -> M | None:
        """Block until a message (received after monotonic time `newer_than`, if given) is cached."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                k = key if key is not None else self._newest_key
                item = None if k is None else self._latest.get(k)
                if item is not None and (newer_than is None or item[1] > newer_than):
                    return item[0]
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)


# ---------------------------------------------------------------------------------------------
# Queries: run control
# ---------------------------------------------------------------------------------------------


class Server(Generic[M, R]):
    """A queryable on `key`: decodes each query as `req_type`, answers `handler(req)` (a `rep_type`).

    A malformed query is counted and answered with `on_bad(reason)` if given, else with a Zenoh
    error reply; a BagItError from the handler becomes `on_error(reason)` the same way. Nothing
    raised in here reaches the Zenoh thread.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        req_type: type[M],
        rep_type: type[R],
        handler: Callable[[M], R],
        on_bad: Callable[[str], R] | None = None,
        counters: DropCounters = DROPS,
    ) -> None:
        self.key = key
        self.req_type = req_type
        self.rep_type = rep_type
        self.handler = handler
        self.on_bad = on_bad
        self.counters = counters
        self.served = 0
        self.dropped = 0
        self._lock = threading.Lock()
        self._q = session.declare_queryable(key, self._on_query)

    def _answer(self, query: zenoh.Query) -> R | str:
        try:
            req = wire.decode(_payload_bytes(query) or b"", self.req_type)
        except BadMessage as e:
            with self._lock:
                self.dropped += 1
            self.counters.add(self.key, str(e))
            return f"bad request: {e}"
        except Exception as e:  # noqa: BLE001
            with self._lock:
                self.dropped += 1
            self.counters.add(self.key, f"undecodable request: {type(e).__name__}")
            return f"bad request: {type(e).__name__}"
        try:
            rep = self.handler(req)
        except BagItError as e:
            return _one_line(e)
        except Exception as e:  # noqa: BLE001
            log.exception("handler on %s failed", self.key)
            return f"internal error: {type(e).__name__}: {_one_line(e)}"
        if not isinstance(rep, self.rep_type):
            return f"internal error: handler returned {type(rep).__name__}, not {self.rep_type.__name__}"
        with self._lock:
            self.served += 1
        return rep

    def _on_query(self, query: zenoh.Query) -> None:
        with query:
            out = self._answer(query)
            try:
                if isinstance(out, str):
                    if self.on_bad is not None:
                        query.reply(query.key_expr, wire.encode(self.on_bad(out)), encoding=encoding_for(self.rep_type))
                    else:
                        query.reply_err(out.encode())
                else:
                    query.reply(query.key_expr, wire.encode(out), encoding=encoding_for(self.rep_type))
            except Exception:  # noqa: BLE001 - the querier may be gone
                log.exception("could not reply on %s", self.key)

    def close(self) -> None:
        try:
            self._q.undeclare()
        except zenoh.ZError:
            pass

    def __enter__(self) -> "Server[M, R]":
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()


def request(
    session: zenoh.Session, key: str, req: Message, rep_type: type[R], timeout: float = 5.0, qos: QoS = CONTROL
) -> R:
    """Send `req` as a query on `key` and return the first reply that decodes as `rep_type`.

    Raises BusError if nobody answers in `timeout` seconds or every answer is an error, BadMessage
    if the only answers are malformed.
    """
    errors: list[str] = []
    bad: list[str] = []
    deadline = time.monotonic() + timeout
    querier = session.declare_querier(key, timeout=timeout, **qos.query_kwargs())
    try:
        # a queryable declared a moment ago may not have reached us yet: wait for one, within the budget
        while not _matching(querier) and time.monotonic() < deadline:
            time.sleep(0.005)
        if not _matching(querier):
            raise BusError(f"no answer on {key} within {timeout:g} s: nobody serves it (is the run coordinator up?)")
        replies = list(querier.get(payload=wire.encode(req), encoding=encoding_for(type(req))))
    finally:
        querier.undeclare()
    for reply in replies:
        if reply.ok is not None:
            try:
                return wire.decode(_payload_bytes(reply.ok) or b"", rep_type)
            except BadMessage as e:
                bad.append(str(e))
        elif reply.err is not None:
            try:
                errors.append(reply.err.payload.to_string())
            except ValueError:
                errors.append("non-text error")
    if errors:
        raise BusError(f"{key}: {errors[0]}")
    if bad:
        raise BadMessage(f"{key}: reply {bad[0]}")
    raise BusError(f"no answer on {key} within {timeout:g} s (is the run coordinator up?)")


def _matching(entity: Any) -> bool:
    try:
        status = entity.matching_status  # a MatchingStatus in 1.10 (typed as bool in the stubs)
    except zenoh.ZError:
        return False
    return bool(getattr(status, "matching", status))


def serve_run_control(session: zenoh.Session, keys: Keys, handler: Callable[[RunControl], RunControlReply]) -> Server:
    """The run coordinator's queryable: every request gets a RunControlReply, refused with the
    reason if the request is malformed or the handler raises a BagItError."""
    return Server(
        session,
        keys.run_control,
        RunControl,
        RunControlReply,
        handler,
        on_bad=lambda reason: RunControlReply(accepted=False, reason=reason),
    )


def request_run_control(session: zenoh.Session, keys: Keys, req: RunControl, timeout: float = 5.0) -> RunControlReply:
    """Ask the rig's run coordinator to start, stop or reset."""
    return request(session, keys.run_control, req, RunControlReply, timeout=timeout, qos=CONTROL)


# ---------------------------------------------------------------------------------------------
# Liveliness
# ---------------------------------------------------------------------------------------------


def rig_clock(session: zenoh.Session, keys: Keys, kind: ClockKind) -> tuple[WallClock | SimClock, Subscriber | None]:
    """The clock a service on this bus reads: the wall clock, or a SimClock following sim/clock
    (close the returned subscriber with the service)."""
    clock = make_clock(kind)
    if not isinstance(clock, SimClock):
        return clock, None
    sim = clock
    return clock, Subscriber(session, keys.sim_clock, ClockTick, lambda m: sim.advance(m.t, m.servo_tick))


def declare_alive(session: zenoh.Session, keys: Keys, service: str) -> zenoh.LivelinessToken:
    """Announce `service` as alive until the token is undeclared or the session dies.

    Keep the returned token referenced: Zenoh undeclares a token as soon as it is garbage-collected.
    """
    return session.liveliness().declare_token(keys.alive(service))


class LivelinessWatcher:
    """Which services of a rig are alive. `on_change(service, alive)` is called when one appears or
    disappears (a crashed process disappears when its link lease, 1 s by default, expires)."""

    def __init__(self, session: zenoh.Session, keys: Keys, on_change: Callable[[str, bool], None] | None = None) -> None:
        self.keys = keys
        self.on_change = on_change
        self._alive: set[str] = set()
        self._cond = threading.Condition()
        self._sub = session.liveliness().declare_subscriber(keys.alive_any, self._on_sample, history=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        service = str(sample.key_expr).rsplit("/", 1)[-1]
        up = sample.kind == zenoh.SampleKind.PUT
        with self._cond:
            changed = (service in self._alive) != up
            (self._alive.add if up else self._alive.discard)(service)
            self._cond.notify_all()
        if changed and self.on_change is not None:
            try:
                self.on_change(service, up)
            except Exception:  # noqa: BLE001
                log.exception("liveliness callback failed for %s", service)

    def alive(self) -> set[str]:
        with self._cond:
            return set(self._alive)

    def wait_for(self, service: str, alive: bool = True, timeout: float = 2.0) -> bool:
        """Block until `service` is (or, with alive=False, is no longer) alive; False on timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while (service in self._alive) != alive:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass

    def __enter__(self) -> "LivelinessWatcher":
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()
