"""Dobot TCP/IP protocol V4 (CR series): the pieces both ends share.

The simulated controllers (bagit.services.sim.dobot_server) and the arm driver's client speak
the same text and binary formats through this module, so the two cannot drift apart.

Ports. V4 controllers take every command, settings and motion alike, on the dashboard port
29999, one command and one reply at a time; port 30004 pushes a 1440-byte little-endian
feedback packet every 8 ms (30005 every 200 ms, 30006 configurable; not used here).

Commands. ASCII, `Name(arg, ..., key=value, ...)`; names are case-insensitive; a pose or joint
vector travels as `{a,b,c,d,e,f}`, e.g. `MovL(pose={-500,100,200,150,0,90},v=50)` or
`ServoP(-500,100,200,150,0,90,t=0.1,aheadtime=50,gain=500)`. Angles are degrees, lengths
millimetres, a Cartesian pose is [x, y, z, rx, ry, rz] (see bagit.common.cr5 for the Euler
convention). `format_command` writes one; `parse_command` reads one with a small hand-written
grammar (no eval); `CommandSplitter` cuts a byte stream into commands (a command ends at its
closing parenthesis, whatever TCP segments it came in; blank space, newlines and `;` between
commands are ignored; malformed text comes out as one `Frame` per send).

Replies. `ErrorID,{value,...},Command(...);` with the command echoed as sent: `0,{},EnableRobot();`,
`0,{1},MovL(pose={...});` (queued motions return their command id), `-10000,{},Mov(...);`.
`format_reply` / `parse_reply` / `split_replies`.

Error ids (V4 manual, chapter 5): 0 ok; -1 not executed; -2 refused, robot in error (alarm);
-3 refused, emergency stop pressed; -4 refused, powered off; -10000 no such command; -20000 wrong
number of parameters; -3000k type/format of required parameter k wrong; -4000k range of required
parameter k wrong; -5000k type/name of optional parameter k wrong; -6000k range of optional
parameter k wrong. k counts positional parameters from 1 within their group; an error in a named
(`key=value`) parameter is k = 1 whatever its position (MovJ(joint={..},a=50,v=500) is -60001).
`ErrorId` holds the fixed ones, `param_error(...)` builds the others.
While in error only ClearError, GetErrorID, EmergencyStop, RobotMode and Stop (always allowed) run;
with the emergency stop pressed, the same (EmergencyStop(0) releases it). A motion command to a disabled arm gets -1.
A target the arm cannot take (no inverse solution, beyond a joint limit, the flange against the
arm's body, a servo step faster than a joint can go) is answered -1 and latches the matching alarm:
RobotMode becomes 9 and the feedback's ErrorStatus 1 until ClearError(). Malformed text is answered
-10000 like an unknown command. MovJ/MovL reply `{command id}` and run in order; the feedback's
CurrentCommandId is the one running (or last run), RobotMode 7 while anything moves, 5 when idle.
ServoJ/ServoP reply `{command id}` too (the same sequence; the accepted target becomes the current
command); the target is reached `t` seconds later plus the servo loop's lag.

Alarms (the controller's alarm ids, as GetErrorID lists them; alarmController.json): 17 inverse
kinematics has no solution, 18 solution outside the joint limits, 48+j joint j overspeed,
64+2j / 65+2j joint j beyond its positive / negative limit (j = 0..5), 77 flange interferes with
the robot body, 132 software emergency stop. See `Alarm`.

Robot modes (RobotMode() and the feedback's RobotMode): `RobotMode`, 4 disabled, 5 enabled and
idle, 7 running, 9 error, 11 collision.

Feedback packet: `FEEDBACK_DTYPE`, a numpy structured dtype with the documented byte offsets
(`FEEDBACK_FIELDS`), itemsize 1440; `TestValue` is always 0x0123456789ABCDEF, `MessageSize` 1440.
Units as the controller sends them: QActual/QTarget degrees, QDActual degrees/s,
ToolVectorActual/Target [x, y, z, rx, ry, rz] mm and degrees (the same numbers as GetPose),
TimeStamp milliseconds since the epoch. The two one-byte `User`/`Tool` fields are the selected
frame indices and `UserValue`/`ToolValue` (the manual's "User[6]"/"Tool[6]") their values.
`new_feedback()` makes a blank packet, `parse_feedback(bytes)` checks and reads one,
`FeedbackAssembler` cuts a TCP stream into packets.
"""

from __future__ import annotations

import codecs
import math
import re
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from types import MappingProxyType
from typing import Any

import numpy as np

from bagit.common.errors import ProtocolError

DASHBOARD_PORT = 29999
FEEDBACK_PORT = 30004
FEEDBACK_PERIOD_S = 0.008
FEEDBACK_SIZE = 1440
TEST_VALUE = 0x0123456789ABCDEF
ROBOT_TYPE_CR5 = 5
MAX_COMMAND_CHARS = 4096
COMMAND_TIMEOUT_S = 1.0  # an unfinished command this long after the client's last byte is answered -10000


class RobotMode(IntEnum):
    INIT = 1
    BRAKE_OPEN = 2
    POWEROFF = 3
    DISABLED = 4
    ENABLE = 5
    BACKDRIVE = 6
    RUNNING = 7
    SINGLE_MOVE = 8
    ERROR = 9
    PAUSE = 10
    COLLISION = 11


class ErrorId(IntEnum):
    OK = 0
    FAILED = -1
    IN_ERROR = -2
    EMERGENCY_STOP = -3
    POWER_OFF = -4
    UNKNOWN_COMMAND = -10000
    PARAM_COUNT = -20000
    REQUIRED_TYPE = -30000
    REQUIRED_RANGE = -40000
    OPTIONAL_TYPE = -50000
    OPTIONAL_RANGE = -60000


def param_error(kind: ErrorId, k: int) -> int:
    """The error id for parameter `k` (1-based in its group), e.g. param_error(REQUIRED_RANGE, 1) = -40001."""
    if kind not in (ErrorId.REQUIRED_TYPE, ErrorId.REQUIRED_RANGE, ErrorId.OPTIONAL_TYPE, ErrorId.OPTIONAL_RANGE):
        raise ValueError(f"{kind!r} is not a per-parameter error")
    return int(kind) - int(k)


class Alarm(IntEnum):
    IK_NO_SOLUTION = 17
    IK_OUT_OF_LIMITS = 18
    JOINT1_OVERSPEED = 48  # + j for joint j (0-based)
    JOINT1_POSITIVE_LIMIT = 64  # + 2j positive, + 2j + 1 negative
    FLANGE_INTERFERENCE = 77
    SOFTWARE_ESTOP = 132


def overspeed_alarm(j: int) -> int:
    return int(Alarm.JOINT1_OVERSPEED) + j


def joint_limit_alarm(j: int, positive: bool) -> int:
    return int(Alarm.JOINT1_POSITIVE_LIMIT) + 2 * j + (0 if positive else 1)


def describe_alarm(alarm: int) -> str:
    """A short name for a controller alarm id (the ones `Alarm` documents; others by number)."""
    a = int(alarm)
    if a == Alarm.IK_NO_SOLUTION:
        return "no inverse kinematics solution"
    if a == Alarm.IK_OUT_OF_LIMITS:
        return "inverse solution beyond the joint limits"
    if Alarm.JOINT1_OVERSPEED <= a < Alarm.JOINT1_OVERSPEED + 6:
        return f"joint {a - Alarm.JOINT1_OVERSPEED + 1} overspeed"
    if Alarm.JOINT1_POSITIVE_LIMIT <= a < Alarm.JOINT1_POSITIVE_LIMIT + 12:
        k = a - Alarm.JOINT1_POSITIVE_LIMIT
        return f"joint {k // 2 + 1} beyond its {'negative' if k % 2 else 'positive'} limit"
    if a == Alarm.FLANGE_INTERFERENCE:
        return "flange interferes with the robot body"
    if a == Alarm.SOFTWARE_ESTOP:
        return "software emergency stop"
    return f"alarm {a}"


# -- the real-time feedback packet ---------------------------------------------------------------

# (name, numpy format, byte offset) as in the V4 manual's table; reserved bytes are named Reserved*.
FEEDBACK_FIELDS: list[tuple[str, str | tuple[str, int], int]] = [
    ("MessageSize", "<u2", 0),
    ("Reserved0", ("<u2", 3), 2),
    ("DigitalInputs", "<u8", 8),
    ("DigitalOutputs", "<u8", 16),
    ("RobotMode", "<u8", 24),
    ("TimeStamp", "<u8", 32),
    ("RunTime", "<u8", 40),
    ("TestValue", "<u8", 48),
    ("Reserved1", "<f8", 56),
    ("SpeedScaling", "<f8", 64),
    ("LinearMomentumNorm", "<f8", 72),
    ("VMain", "<f8", 80),
    ("VRobot", "<f8", 88),
    ("IRobot", "<f8", 96),
    ("ProgramState", "<f8", 104),
    ("SafetyStatus", "<f8", 112),
    ("ToolAccelerometer", ("<f8", 3), 120),
    ("ElbowPosition", ("<f8", 3), 144),
    ("ElbowVelocity", ("<f8", 3), 168),
    ("QTarget", ("<f8", 6), 192),
    ("QDTarget", ("<f8", 6), 240),
    ("QDDTarget", ("<f8", 6), 288),
    ("ITarget", ("<f8", 6), 336),
    ("MTarget", ("<f8", 6), 384),
    ("QActual", ("<f8", 6), 432),
    ("QDActual", ("<f8", 6), 480),
    ("IActual", ("<f8", 6), 528),
    ("ActualTCPForce", ("<f8", 6), 576),
    ("ToolVectorActual", ("<f8", 6), 624),
    ("TCPSpeedActual", ("<f8", 6), 672),
    ("TCPForce", ("<f8", 6), 720),
    ("ToolVectorTarget", ("<f8", 6), 768),
    ("TCPSpeedTarget", ("<f8", 6), 816),
    ("MotorTemperatures", ("<f8", 6), 864),
    ("JointModes", ("<f8", 6), 912),
    ("VActual", ("<f8", 6), 960),
    ("HandType", ("u1", 4), 1008),
    ("User", "u1", 1012),
    ("Tool", "u1", 1013),
    ("RunQueuedCmd", "u1", 1014),
    ("PauseCmdFlag", "u1", 1015),
    ("VelocityRatio", "u1", 1016),
    ("AccelerationRatio", "u1", 1017),
    ("JerkRatio", "u1", 1018),
    ("XYZVelocityRatio", "u1", 1019),
    ("RVelocityRatio", "u1", 1020),
    ("XYZAccelerationRatio", "u1", 1021),
    ("RAccelerationRatio", "u1", 1022),
    ("XYZJerkRatio", "u1", 1023),
    ("RJerkRatio", "u1", 1024),
    ("BrakeStatus", "u1", 1025),
    ("EnableStatus", "u1", 1026),
    ("DragStatus", "u1", 1027),
    ("RunningStatus", "u1", 1028),
    ("ErrorStatus", "u1", 1029),
    ("JogStatus", "u1", 1030),
    ("RobotType", "u1", 1031),
    ("DragButtonSignal", "u1", 1032),
    ("EnableButtonSignal", "u1", 1033),
    ("RecordButtonSignal", "u1", 1034),
    ("ReappearButtonSignal", "u1", 1035),
    ("JawButtonSignal", "u1", 1036),
    ("SixForceOnline", "u1", 1037),
    ("CollisionState", "u1", 1038),
    ("ArmApproachState", "u1", 1039),
    ("J4ApproachState", "u1", 1040),
    ("J5ApproachState", "u1", 1041),
    ("J6ApproachState", "u1", 1042),
    ("Reserved2", ("u1", 61), 1043),
    ("VibrationDisZ", "<f8", 1104),
    ("CurrentCommandId", "<u8", 1112),
    ("MActual", ("<f8", 6), 1120),
    ("Load", "<f8", 1168),
    ("CenterX", "<f8", 1176),
    ("CenterY", "<f8", 1184),
    ("CenterZ", "<f8", 1192),
    ("UserValue", ("<f8", 6), 1200),
    ("ToolValue", ("<f8", 6), 1248),
    ("TraceIndex", "<f8", 1296),
    ("SixForceValue", ("<f8", 6), 1304),
    ("TargetQuaternion", ("<f8", 4), 1352),
    ("ActualQuaternion", ("<f8", 4), 1384),
    ("AutoManualMode", "<u2", 1416),
    ("Reserved3", ("u1", 22), 1418),
]

FEEDBACK_DTYPE = np.dtype(
    {
        "names": [f[0] for f in FEEDBACK_FIELDS],
        "formats": [f[1] for f in FEEDBACK_FIELDS],
        "offsets": [f[2] for f in FEEDBACK_FIELDS],
        "itemsize": FEEDBACK_SIZE,
    }
)


def _struct_fields(dt: np.dtype) -> MappingProxyType[str, tuple[Any, ...]]:
    """A structured dtype's fields: name -> (dtype, offset); TypeError for a plain dtype."""
    if dt.fields is None:
        raise TypeError(f"{dt} is not a structured dtype")
    return dt.fields


FEEDBACK_DTYPE_FIELDS = _struct_fields(FEEDBACK_DTYPE)  # name -> (dtype, offset in the packet)


def _check_layout() -> None:
    """The table leaves no gap and no overlap: each field starts where the previous one ends."""
    end = 0
    for name, _, off in FEEDBACK_FIELDS:
        if off != end:
            raise AssertionError(f"feedback field {name} at {off}, expected {end}")
        end = off + FEEDBACK_DTYPE_FIELDS[name][0].itemsize
    if end != FEEDBACK_SIZE:
        raise AssertionError(f"feedback fields end at {end}, not {FEEDBACK_SIZE}")


_check_layout()


def new_feedback() -> np.ndarray:
    """A zeroed feedback record (shape `()`) with MessageSize, TestValue and RobotType filled in."""
    rec = np.zeros((), dtype=FEEDBACK_DTYPE)
    rec["MessageSize"] = FEEDBACK_SIZE
    rec["TestValue"] = TEST_VALUE
    rec["RobotType"] = ROBOT_TYPE_CR5
    return rec


def parse_feedback(data: bytes | bytearray | memoryview) -> np.ndarray:
    """One 1440-byte packet as a record (shape `()`), or ProtocolError if it is not a valid packet."""
    buf = bytes(data)
    if len(buf) != FEEDBACK_SIZE:
        raise ProtocolError(f"feedback packet has {len(buf)} bytes, expected {FEEDBACK_SIZE}")
    rec = np.frombuffer(buf, dtype=FEEDBACK_DTYPE)[0]
    if int(rec["TestValue"]) != TEST_VALUE:
        raise ProtocolError(f"feedback test value is {int(rec['TestValue']):#x}, expected {TEST_VALUE:#x} (byte order or framing)")
    if int(rec["MessageSize"]) != FEEDBACK_SIZE:
        raise ProtocolError(f"feedback MessageSize is {int(rec['MessageSize'])}, expected {FEEDBACK_SIZE}")
    return np.array(rec, dtype=FEEDBACK_DTYPE)


class FeedbackAssembler:
    """Cuts the feedback port's byte stream into 1440-byte packets, checking each one's test value.

    `feed(chunk)` returns the packets completed by the chunk (oldest first); a packet that fails the
    check raises ProtocolError (the stream has lost its framing; reconnect).
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[np.ndarray]:
        self._buf.extend(chunk)
        out = []
        while len(self._buf) >= FEEDBACK_SIZE:
            packet = bytes(self._buf[:FEEDBACK_SIZE])
            del self._buf[:FEEDBACK_SIZE]
            out.append(parse_feedback(packet))
        return out

    @property
    def pending(self) -> int:
        """Bytes received towards the next packet."""
        return len(self._buf)


# -- commands ------------------------------------------------------------------------------------

Value = int | float | str | tuple[float | str, ...]


@dataclass
class Command:
    """A parsed command: `name` as sent, `key` its lower-case form, positional `args`, `named` args in order.

    `text` is the command as received (whitespace-trimmed), which replies echo.
    """

    name: str
    args: list[Value] = field(default_factory=list)
    named: dict[str, Value] = field(default_factory=dict)
    text: str = ""

    @property
    def key(self) -> str:
        return self.name.lower()


def _fmt_number(v: float | int) -> str:
    if isinstance(v, (bool, np.bool_)):
        return str(int(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    x = float(v)
    if not math.isfinite(x):
        raise ProtocolError(f"cannot send a non-finite number ({x})")
    s = f"{x:.6f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _fmt_value(v: object) -> str:
    if isinstance(v, str):
        if not _BARE_RE.fullmatch(v):
            raise ProtocolError(f"cannot send {v!r}: only letters, digits and _ . - are allowed in a bare word")
        return v
    if isinstance(v, (list, tuple, np.ndarray)):
        return "{" + ",".join(_fmt_number(x) for x in np.asarray(v, dtype=float).ravel()) + "}"
    return _fmt_number(v)  # type: ignore[arg-type]


def format_command(name: str, *args: object, **named: object) -> str:
    """`Name(a,b,...,key=value,...)`; sequences become `{...}`; floats get up to 6 decimals."""
    if not _NAME_RE.fullmatch(name):
        raise ProtocolError(f"bad command name {name!r}")
    parts = [_fmt_value(a) for a in args]
    for k, v in named.items():
        if not _NAME_RE.fullmatch(k):
            raise ProtocolError(f"bad parameter name {k!r}")
        parts.append(f"{k}={_fmt_value(v)}")
    return f"{name}({','.join(parts)})"


_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_BARE_RE = re.compile(r"[A-Za-z0-9_.\-]+")
_NUMBER_RE = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_INT_RE = re.compile(r"[+-]?\d+")


def _parse_scalar(tok: str) -> int | float | str:
    tok = tok.strip()
    if _INT_RE.fullmatch(tok):
        return int(tok)
    if _NUMBER_RE.fullmatch(tok):
        return float(tok)
    if len(tok) >= 2 and tok[0] == tok[-1] == '"' and '"' not in tok[1:-1]:
        return tok[1:-1]
    if _BARE_RE.fullmatch(tok):
        return tok
    raise ProtocolError(f"bad value {tok!r}")


def _parse_value(tok: str) -> Value:
    """A scalar or a `{...}` vector. A vector item that is a word (`nan`, `a`) stays text: it is a
    well-formed command with a parameter of the wrong type, which the controller numbers -3000k/-5000k."""
    tok = tok.strip()
    if tok.startswith("{"):
        if not tok.endswith("}") or "{" in tok[1:-1] or "}" in tok[1:-1]:
            raise ProtocolError(f"bad vector {tok!r}")
        inner = tok[1:-1].strip()
        if not inner:
            return ()
        items = [_parse_scalar(s) for s in inner.split(",")]
        return tuple(float(x) if isinstance(x, int) else x for x in items)
    if not tok:
        raise ProtocolError("empty parameter")
    return _parse_scalar(tok)


def _split_top(s: str) -> list[str]:
    """`s` split at commas outside braces."""
    parts: list[str] = []
    cur: list[str] = []
    depth = 0
    for ch in s:
        if ch == "{":
            depth += 1
        elif ch == "}":
            depth -= 1
            if depth < 0:
                raise ProtocolError("unbalanced '}'")
        if ch == "," and depth == 0:
            parts.append("".join(cur))
            cur = []
        else:
            cur.append(ch)
    if depth != 0:
        raise ProtocolError("unbalanced '{'")
    parts.append("".join(cur))
    return parts


def parse_command(text: str) -> Command:
    """One command `Name(args)` (case kept; compare `Command.key`), or ProtocolError saying what is wrong.

    Positional parameters must come before named ones; a name may appear once.
    """
    t = text.strip()
    if len(t) > MAX_COMMAND_CHARS:
        raise ProtocolError(f"command longer than {MAX_COMMAND_CHARS} characters")
    m = re.fullmatch(r"([A-Za-z_][A-Za-z0-9_]*)\s*\((.*)\)", t, flags=re.S)
    if not m:
        raise ProtocolError(f"not a command: {t[:60]!r}")
    name, body = m.group(1), m.group(2)
    cmd = Command(name=name, text=t)
    if not body.strip():
        return cmd
    for part in _split_top(body):
        km = re.fullmatch(r"\s*([A-Za-z_][A-Za-z0-9_]*)\s*=(.*)", part, flags=re.S)
        if km:
            key = km.group(1)
            if key in cmd.named:
                raise ProtocolError(f"parameter {key} given twice")
            cmd.named[key] = _parse_value(km.group(2))
        else:
            if cmd.named:
                raise ProtocolError("positional parameter after a named one")
            cmd.args.append(_parse_value(part))
    return cmd


class Frame(str):
    """One piece of the dashboard stream: a command's text, or, when `malformed`, text that cannot be
    one (answered -10000 as a whole). A str, so code that only wants the text can ignore the flag."""

    malformed: bool = False

    @classmethod
    def bad(cls, text: str) -> Frame:
        f = cls(text)
        f.malformed = True
        return f


_SEPARATORS = " \t\r\n;"
_NAME_START_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*[ \t]*")
_COMPLETE, _PARTIAL, _BAD = "complete", "partial", "bad"


def _scan(s: str, limit: int) -> tuple[str, int]:
    """Where the command at the start of `s` stands: (_COMPLETE, index after its ')'), (_PARTIAL, 0)
    while more text may complete it (or its first `limit` characters do not), or (_BAD, 0) once it
    cannot be a command (junk before the '(', a newline before the closing ')', junk right after it)."""
    m = _NAME_START_RE.match(s, 0, limit)
    if m is None:
        return _BAD, 0
    j = m.end()
    if j == min(len(s), limit):
        return _PARTIAL, 0
    if s[j] != "(":
        return _BAD, 0
    depth = 0
    for i in range(j, min(len(s), limit)):
        ch = s[i]
        if ch == "(":
            depth += 1
        elif ch == "\n":
            return _BAD, 0
        elif ch == ")":
            depth -= 1
            if depth == 0:
                rest = s[i + 1 :].lstrip(" \t")
                if not rest or rest[0] in _SEPARATORS or rest[0].isalpha() or rest[0] == "_":
                    return _COMPLETE, i + 1
                return _BAD, 0
    return _PARTIAL, 0


class CommandSplitter:
    """Cuts the dashboard port's byte stream into commands, one `Frame` per command or malformed send.

    A command may arrive in several TCP segments: it ends at the ')' that closes its '(';
    whitespace, newlines and ';' between commands are dropped. Text that cannot be a command, a
    command longer than `max_chars`, or one the client left unfinished for `timeout_s`, becomes ONE
    malformed frame (as the manual answers each send once, never once per stray character or per
    segment): a malformed piece runs to the end of its line, to the ')' closing an over-long command,
    or to the client's next pause of `timeout_s`. The server calls `expire()` while the client is quiet.
    """

    def __init__(self, max_chars: int = MAX_COMMAND_CHARS, timeout_s: float = COMMAND_TIMEOUT_S) -> None:
        self.max_chars = max_chars
        self.timeout_s = timeout_s
        self._decoder = codecs.getincrementaldecoder("utf-8")(errors="replace")
        self._buf = ""
        self._bad: str | None = None  # the malformed piece's text so far (its first max_chars + 1)
        self._depth: int | None = None  # an over-long command's parenthesis depth: its ')' ends it
        self._last = 0.0

    def feed(self, chunk: bytes | str, now: float | None = None) -> list[Frame]:
        """The frames that `chunk` completes, oldest first."""
        self._buf += self._decoder.decode(chunk) if isinstance(chunk, (bytes, bytearray)) else chunk
        self._last = time.monotonic() if now is None else now
        out: list[Frame] = []
        while True:
            if self._bad is not None:
                if not self._skip_bad(out):
                    break
                continue
            self._buf = self._buf.lstrip(_SEPARATORS)
            if not self._buf:
                break
            kind, end = _scan(self._buf, self.max_chars)
            if kind == _COMPLETE:
                out.append(Frame(self._buf[:end]))
                self._buf = self._buf[end:]
            elif kind == _BAD:
                self._bad, self._depth = "", None
            elif len(self._buf) > self.max_chars:  # too long: malformed up to its closing ')'
                self._bad, self._depth = "", 0
            else:
                break
        return out

    def _skip_bad(self, out: list[Frame]) -> bool:
        """Take the malformed piece's text from the buffer; True (and its frame in `out`) once it ended."""
        end = self._bad_end(self._buf)
        piece = self._buf if end is None else self._buf[:end]
        self._bad = ((self._bad or "") + piece)[: self.max_chars + 1]
        if end is None:
            self._buf = ""
            return False
        self._buf = self._buf[end:]
        out.append(Frame.bad(self._bad.rstrip()))
        self._bad = self._depth = None
        return True

    def _bad_end(self, s: str) -> int | None:
        """Index where the malformed piece ends in `s` (after the closing ')' of an over-long command,
        or at a newline), or None if it goes on."""
        if self._depth is None:
            i = s.find("\n")
            return None if i < 0 else i
        for i, ch in enumerate(s):
            if ch == "\n":
                return i
            if ch == "(":
                self._depth += 1
            elif ch == ")" and self._depth > 0:
                self._depth -= 1
                if self._depth == 0:
                    return i + 1
        return None

    def expire(self, now: float | None = None) -> Frame | None:
        """The unfinished piece as one malformed frame once the client has been quiet for `timeout_s`."""
        now = time.monotonic() if now is None else now
        if now - self._last < self.timeout_s:
            return None
        return self.flush()

    def flush(self) -> Frame | None:
        """Whatever unfinished text is buffered, as one malformed frame; None if nothing is."""
        rest = ((self._bad or "") + self._buf).strip(_SEPARATORS)[: self.max_chars + 1]
        had_bad = self._bad is not None
        self._buf, self._bad, self._depth = "", None, None
        return Frame.bad(rest) if rest or had_bad else None

    @property
    def pending(self) -> bool:
        """Text of an unfinished command or malformed piece is buffered."""
        return self._bad is not None or bool(self._buf.strip(_SEPARATORS))

    def quiet_left_s(self, now: float | None = None) -> float | None:
        """Seconds of quiet left before `expire` answers the unfinished piece; None when nothing is
        unfinished (a reader may then block until the client sends)."""
        if not self.pending:
            return None
        now = time.monotonic() if now is None else now
        return max(self.timeout_s - (now - self._last), 0.0)


# -- replies -------------------------------------------------------------------------------------


@dataclass
class Reply:
    """A parsed reply: `error_id`, the values between the braces (numbers as float, others as text),
    `raw_values` (the text between the braces) and the echoed `command`."""

    error_id: int
    values: list[float | str]
    raw_values: str
    command: str

    @property
    def ok(self) -> bool:
        return self.error_id == 0


def format_reply(error_id: int, values: Sequence[float | int] | str | None, command_text: str) -> str:
    """`ErrorID,{v1,...},Command(...);`; `values` a sequence of numbers or preformatted text."""
    if values is None:
        body = ""
    elif isinstance(values, str):
        body = values
    else:
        body = ",".join(_fmt_number(v) if isinstance(v, (int, np.integer)) else f"{float(v):.6f}" for v in values)
    return f"{int(error_id)},{{{body}}},{command_text.strip()};"


_REPLY_RE = re.compile(r"\s*(-?\d+)\s*,\s*\{(.*?)\}\s*,(.*);\s*", flags=re.S)


def parse_reply(text: str) -> Reply:
    """One reply, or ProtocolError if it is not `ErrorID,{...},Command;`."""
    m = _REPLY_RE.fullmatch(text)
    if not m:
        # values with nested brackets (GetErrorID) contain no '}' before the last: retry greedily
        m = re.fullmatch(r"\s*(-?\d+)\s*,\s*\{(.*)\}\s*,([^{}]*);\s*", text, flags=re.S)
    if not m:
        raise ProtocolError(f"not a Dobot reply: {text.strip()[:80]!r}")
    raw = m.group(2).strip()
    values: list[float | str] = []
    if raw and not raw.startswith("["):
        for s in raw.split(","):
            s = s.strip()
            values.append(float(s) if _NUMBER_RE.fullmatch(s) else s)
    elif raw:
        values.append(raw)
    return Reply(error_id=int(m.group(1)), values=values, raw_values=raw, command=m.group(3).strip())


def split_replies(buffer: str) -> tuple[list[str], str]:
    """Complete replies in `buffer` (each ends with ';') and the incomplete rest."""
    parts = buffer.split(";")
    return [p + ";" for p in parts[:-1] if p.strip()], parts[-1]


def format_error_ids(controller: Iterable[int], servos: Sequence[Iterable[int]] | None = None) -> str:
    """GetErrorID's value text: `[[controller ids],[servo 1 ids],...,[servo 6 ids]]`."""
    servos = servos or [[] for _ in range(6)]
    groups = [list(controller)] + [list(s) for s in servos]
    return "[" + ",".join("[" + ",".join(str(int(i)) for i in g) + "]" for g in groups) + "]"


def parse_error_ids(raw_values: str) -> list[list[int]]:
    """GetErrorID's value text back to 7 lists of ids (controller first, then the six servos)."""
    s = raw_values.strip()
    if not (s.startswith("[") and s.endswith("]")):
        raise ProtocolError(f"bad GetErrorID value {s[:80]!r}")
    groups = re.findall(r"\[([^\[\]]*)\]", s[1:-1])
    try:
        return [[int(x) for x in g.split(",") if x.strip()] for g in groups]
    except ValueError:
        raise ProtocolError(f"bad GetErrorID value {s[:80]!r}") from None
