"""A simulated CR5 controller on TCP: the V4 dashboard port and the 8 ms real-time feedback port.

`DobotControllerServer(robot, dashboard_port=29999, feedback_port=30004)` serves one
`SimulatedCR5` on 127.0.0.1 by default; port 0 asks for free ports (read them back from
`dashboard_port` / `feedback_port` after `start()`), so several controllers and parallel tests can
share a machine. The dashboard port answers one reply per command, `ErrorID,{values},Command;`,
to any number of clients; the feedback port pushes the 1440-byte packet to every connected client
every 8 ms of wall-clock time. `stop()` closes every socket and joins every thread.

Who advances the arm: a rig's simulation loop calls `robot.step(dt)`; a controller on its own can
be run with `step_in_background=True` (wall-clock stepping), which is what the protocol tests use.

Commands (names case-insensitive, formats of the V4 manual; error ids in bagit.common.dobot):
  EnableRobot([load[,cx,cy,cz[,isCheck]]])  DisableRobot()  ClearError()  EmergencyStop(1|0)
  PowerOn()  Stop()  SpeedFactor(1..100)  RobotMode()  GetAngle()  GetPose([user=i,tool=i])
  GetErrorID()  GetCurrentCommandID()  PositiveKin(j1..j6[,user=,tool=])
  InverseKin(x..rz[,user=,tool=,useJointNear=0|1,jointNear={j1..j6}]) (JointNear too)
  MovJ(joint={..}|pose={..}[,user=,tool=,a=,v=,cp=])  MovL(joint={..}|pose={..}[,user=,tool=,a=,v=,speed=,cp=,r=])
  ServoJ(j1..j6[,t=,aheadtime=,gain=])  ServoP(x..rz[,t=,aheadtime=,gain=])
The simulated arm has one user frame and one tool frame: indices 0..50 are accepted and all mean
the base and flange frames. `cp` and `r` (blending) are accepted and ignored: motions stop at each
target. Malformed text is answered -10000 like an unknown command, never by closing the link: once
per malformed send (bagit.common.dobot.CommandSplitter), and a command split over several TCP
segments is put together first; one left unfinished for `command_timeout` (1 s) gets its -10000.
"""

from __future__ import annotations

import math
import socket
import threading
import time
from collections.abc import Callable, Mapping
from typing import Self

import numpy as np

from bagit.common import cr5
from bagit.common.dobot import (
    COMMAND_TIMEOUT_S,
    DASHBOARD_PORT,
    FEEDBACK_PERIOD_S,
    FEEDBACK_PORT,
    Command,
    CommandSplitter,
    ErrorId,
    format_error_ids,
    format_reply,
    param_error,
    parse_command,
)
from bagit.common.errors import ProtocolError
from bagit.services.sim.cr5_sim import SimulatedCR5

Values = list[float] | list[int] | str | None
CR5_MAX_LOAD_KG = 5.0


class _ParamError(Exception):
    def __init__(self, code: int):
        super().__init__(code)
        self.code = code


def _num(v: object, code: int, integer: bool = False) -> float:
    """A finite number (an integer if `integer`), or _ParamError(code)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _ParamError(code)
    if integer and not isinstance(v, int):
        raise _ParamError(code)
    return float(v)


def _in(x: float, lo: float, hi: float, code: int) -> float:
    if not lo <= x <= hi:
        raise _ParamError(code)
    return x


def _vec6(v: object, code: int) -> np.ndarray:
    """Six finite numbers in braces, or _ParamError(code) (a word such as `nan` inside is a type error)."""
    if not isinstance(v, tuple) or len(v) != 6:
        raise _ParamError(code)
    return np.array([_num(x, code) for x in v])


def _positional6(cmd: Command) -> np.ndarray:
    """The six required numbers of ServoJ/ServoP/PositiveKin/InverseKin."""
    if len(cmd.args) < 6:
        raise _ParamError(int(ErrorId.PARAM_COUNT))
    return np.array([_num(a, param_error(ErrorId.REQUIRED_TYPE, i + 1)) for i, a in enumerate(cmd.args[:6])])


VEC6 = None  # an option whose value is six numbers in braces (InverseKin's jointNear)
Spec = dict[str, tuple[float, float, bool] | None]  # option name (lower case) -> (lo, hi, integer) or VEC6

# the options the commands take, with firmware V4.6's ranges (ServoJ/ServoP's t is [0.004, 3600] s
# since V4.6, [0.02, 3600] before)
_FRAME = (0, 50, True)
_OPTIONS: dict[str, Spec] = {
    "movj": {"user": _FRAME, "tool": _FRAME, "a": (1, 100, True), "v": (1, 100, True), "cp": (0, 100, True)},
    "movl": {
        "user": _FRAME, "tool": _FRAME, "a": (1, 100, True), "v": (1, 100, True), "speed": (1, 1e6, True),
        "cp": (0, 100, True), "r": (0, 100, True),
    },
    "servo": {"t": (0.004, 3600.0, False), "aheadtime": (20.0, 100.0, False), "gain": (200.0, 1000.0, False)},
    "frames": {"user": _FRAME, "tool": _FRAME},
    "inversekin": {"user": _FRAME, "tool": _FRAME, "usejointnear": (0, 1, True), "jointnear": VEC6},
}  # fmt: skip


def _named_options(named: Mapping[str, object], spec: Spec, out: dict | None = None) -> dict[str, float | np.ndarray]:
    """Named optional parameters (`key=value`) checked against `spec`, added to `out`.

    The manual numbers a named parameter's errors -50001 (unknown name, given twice, wrong type) and
    -60001 (out of range) whatever its position; -5000k/-6000k by position are for positional ones.
    """
    out = {} if out is None else out
    type_err, range_err = param_error(ErrorId.OPTIONAL_TYPE, 1), param_error(ErrorId.OPTIONAL_RANGE, 1)
    for name, v in named.items():
        key = name.lower()
        if key not in spec or key in out:
            raise _ParamError(type_err)
        if (rng := spec[key]) is VEC6:
            out[key] = _vec6(v, type_err)
        else:
            out[key] = _in(_num(v, type_err, rng[2]), rng[0], rng[1], range_err)
    return out


def _positional_options(args: list, names: list[str], spec: Spec) -> dict[str, float]:
    """Optional parameters given by position (`names` in order): the k-th one's errors are -5000k / -6000k."""
    out = {}
    for k, (name, v) in enumerate(zip(names, args, strict=False), start=1):
        rng = spec[name]
        if rng is VEC6:
            raise TypeError(f"option {name!r} takes six numbers: it cannot be given by position")
        lo, hi, integer = rng
        out[name] = _in(_num(v, param_error(ErrorId.OPTIONAL_TYPE, k), integer), lo, hi, param_error(ErrorId.OPTIONAL_RANGE, k))
    return out


def _scalar_option(opts: Mapping[str, float | np.ndarray], key: str, default: float) -> float:
    """A number option's value (one whose spec is a range, not VEC6), or `default` when not given."""
    v = opts.get(key, default)
    if isinstance(v, np.ndarray):
        raise TypeError(f"option {key!r} takes a number, not six")
    return v


class DobotControllerServer:
    """Serves one simulated CR5 over Dobot's TCP/IP protocol V4 (see the module docstring)."""

    # commands that still run while the arm is in error / with the e-stop pressed (V4 manual 4.0.5);
    # Stop is always allowed
    _IN_ERROR = {"clearerror", "geterrorid", "emergencystop", "robotmode", "stop"}

    def __init__(
        self,
        robot: SimulatedCR5,
        host: str = "127.0.0.1",
        dashboard_port: int = DASHBOARD_PORT,
        feedback_port: int = FEEDBACK_PORT,
        feedback_period: float = FEEDBACK_PERIOD_S,
        step_in_background: bool = False,
        command_timeout: float = COMMAND_TIMEOUT_S,
    ):
        self.robot = robot
        self.command_timeout = float(command_timeout)
        self.host = host
        self._ports = (dashboard_port, feedback_port)
        self.feedback_period = float(feedback_period)
        self._step_in_background = step_in_background
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._clients: list[socket.socket] = []
        self._feedback_clients: list[socket.socket] = []
        self._clients_lock = threading.Lock()
        self._push_lock = threading.Lock()
        self._dash_sock: socket.socket | None = None
        self._fb_sock: socket.socket | None = None
        self.packets_sent = 0
        # Lockstep: the feedback goes out when the world has stepped (the simulator pushes it), not every
        # 8 ms of wall time: a world that waits for its rig has nothing new to say.
        self._periodic = threading.Event()
        self._periodic.set()
        self.on_servo: Callable[[], None] | None = None  # after each ServoP/ServoJ taken (a lockstep simulator waits for them)
        self._handlers: dict[str, Callable[[Command], tuple[int, Values]]] = {
            "enablerobot": self._enable,
            "disablerobot": self._no_args(lambda: (self.robot.disable(), None)),
            "clearerror": self._no_args(lambda: (self.robot.clear_error(), None)),
            "poweron": self._no_args(lambda: (0, None)),
            "stop": self._no_args(lambda: (self.robot.stop(), None)),
            "emergencystop": self._estop,
            "speedfactor": self._speed_factor,
            "robotmode": self._no_args(lambda: (0, [self.robot.robot_mode()])),
            "getangle": self._no_args(lambda: (0, self.robot.get_angle_deg().tolist())),
            "getpose": self._get_pose,
            "geterrorid": self._no_args(lambda: (0, format_error_ids(self.robot.alarms()))),
            "getcurrentcommandid": self._no_args(lambda: (0, [self.robot.current_command_id])),
            "positivekin": self._positive_kin,
            "inversekin": self._inverse_kin,
            "movj": self._mov,
            "movl": self._mov,
            "servoj": self._servo,
            "servop": self._servo,
        }

    # -- lifecycle -------------------------------------------------------------------------------

    @property
    def dashboard_port(self) -> int:
        return self._dash_sock.getsockname()[1] if self._dash_sock else self._ports[0]

    @property
    def feedback_port(self) -> int:
        return self._fb_sock.getsockname()[1] if self._fb_sock else self._ports[1]

    def _listen(self, port: int) -> socket.socket:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((self.host, port))
        except OSError as e:
            s.close()
            raise OSError(f"{self.robot.name}: cannot listen on {self.host}:{port}: {e.strerror}") from None
        s.listen(8)
        return s

    def start(self) -> Self:
        self._dash_sock = self._listen(self._ports[0])
        try:
            self._fb_sock = self._listen(self._ports[1])
        except OSError:
            self._dash_sock.close()
            self._dash_sock = None
            raise
        self._spawn(self._accept_loop, self._dash_sock, self._serve_dashboard, name="dashboard-accept")
        self._spawn(self._accept_loop, self._fb_sock, self._add_feedback_client, name="feedback-accept")
        self._spawn(self._push_loop, name="feedback-push")
        if self._step_in_background:
            self._spawn(self._step_loop, name="step")
        return self

    def _spawn(self, target: Callable, *args: object, name: str = "") -> None:
        t = threading.Thread(target=target, args=args, name=f"{self.robot.name}-{name}", daemon=True)
        t.start()
        with self._clients_lock:
            self._threads.append(t)

    @property
    def periodic_push(self) -> bool:
        """Whether feedback goes out every `feedback_period` of wall time (else only when pushed)."""
        return self._periodic.is_set()

    @periodic_push.setter
    def periodic_push(self, on: bool) -> None:
        if on:
            self._periodic.set()
        else:
            self._periodic.clear()

    def stop(self) -> None:
        """Close every socket and join every thread (idempotent)."""
        self._stop.set()
        self._periodic.set()  # the push loop wakes to see the stop
        for s in (self._dash_sock, self._fb_sock):
            if s is not None:
                try:
                    s.shutdown(socket.SHUT_RDWR)  # wakes a blocked accept (Linux); close alone does not
                except OSError:
                    pass
                s.close()
        with self._clients_lock:
            for c in self._clients + self._feedback_clients:
                try:
                    c.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                c.close()
            self._clients.clear()
            self._feedback_clients.clear()
        with self._clients_lock:
            threads = list(self._threads)
            self._threads.clear()
        for t in threads:
            if t is not threading.current_thread():
                t.join(timeout=2.0)

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- sockets ---------------------------------------------------------------------------------

    def _accept_loop(self, listener: socket.socket, on_client: Callable[[socket.socket], None]) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = listener.accept()  # blocks; stop() shuts the listener down to end it
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            on_client(conn)

    def _serve_dashboard(self, conn: socket.socket) -> None:
        with self._clients_lock:
            self._clients.append(conn)
        self._spawn(self._client_loop, conn, name="client")

    def _client_loop(self, conn: socket.socket) -> None:
        """One reply per command or malformed send (see CommandSplitter); a command may span segments.
        The read blocks until the client sends, or until an unfinished command's time-out: nothing polls."""
        splitter = CommandSplitter(timeout_s=self.command_timeout)
        try:
            while not self._stop.is_set():
                left = splitter.quiet_left_s()
                conn.settimeout(None if left is None else max(left, 1e-3))  # 0 would make the socket non-blocking
                try:
                    data = conn.recv(65536)
                except TimeoutError:
                    data = None
                if data == b"":
                    return
                frames = splitter.feed(data) if data else []
                if (late := splitter.expire()) is not None:  # unfinished and the client quiet: answer it once
                    frames.append(late)
                for frame in frames:
                    conn.sendall(self.handle(frame).encode("utf-8"))
        except OSError:
            return
        finally:
            with self._clients_lock:
                if conn in self._clients:
                    self._clients.remove(conn)
            conn.close()

    def _add_feedback_client(self, conn: socket.socket) -> None:
        conn.settimeout(0.05)
        with self._clients_lock:
            self._feedback_clients.append(conn)

    def _push_loop(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            if not self._periodic.is_set():  # lockstep: asleep until periodic again or stopped
                self._periodic.wait()
                next_t = time.monotonic()
                continue
            next_t += self.feedback_period
            delay = next_t - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            elif delay < -self.feedback_period:
                next_t = time.monotonic()  # fell behind (a loaded machine): do not burst to catch up
            if self.periodic_push:
                self.push_feedback()

    def push_feedback(self) -> None:
        """One feedback packet of the current state to every feedback client now. The 8 ms loop
        calls it; so does a lockstep simulator after each step, so its driver sees that step at once."""
        with self._push_lock:  # one packet at a time on each socket, whoever pushes
            with self._clients_lock:
                clients = list(self._feedback_clients)
            if not clients:
                return
            packet = self.robot.fill_feedback().tobytes()
            for c in clients:
                try:
                    c.sendall(packet)
                except OSError:  # gone, or too slow to keep up: drop it as the controller would
                    with self._clients_lock:
                        if c in self._feedback_clients:
                            self._feedback_clients.remove(c)
                    c.close()
            self.packets_sent += 1

    def _step_loop(self) -> None:
        last = time.monotonic()
        while not self._stop.wait(0.004):
            now = time.monotonic()
            self.robot.step(min(now - last, 0.05))
            last = now

    # -- commands --------------------------------------------------------------------------------

    def handle(self, text: str) -> str:
        """The reply to one command (also usable without sockets); a malformed `Frame` gets -10000."""
        echo = " ".join(text.split())[:256]
        if getattr(text, "malformed", False):
            return format_reply(int(ErrorId.UNKNOWN_COMMAND), None, echo)
        try:
            cmd = parse_command(text)
        except ProtocolError:
            return format_reply(int(ErrorId.UNKNOWN_COMMAND), None, echo)
        handler = self._handlers.get(cmd.key)
        if handler is None:
            return format_reply(int(ErrorId.UNKNOWN_COMMAND), None, cmd.text)
        allowed = cmd.key in self._IN_ERROR
        gate = self.robot.gate(allowed_in_error=allowed, allowed_in_estop=allowed)
        if gate != 0:
            return format_reply(gate, None, cmd.text)
        try:
            code, values = handler(cmd)
        except _ParamError as e:
            code, values = e.code, None
        return format_reply(code, values if code == 0 else None, cmd.text)

    @staticmethod
    def _no_args(fn: Callable[[], tuple[int, Values]]) -> Callable[[Command], tuple[int, Values]]:
        def run(cmd: Command) -> tuple[int, Values]:
            if cmd.args or cmd.named:
                raise _ParamError(int(ErrorId.PARAM_COUNT))
            return fn()

        return run

    def _enable(self, cmd: Command) -> tuple[int, Values]:
        if cmd.named or len(cmd.args) not in (0, 1, 4, 5):
            raise _ParamError(int(ErrorId.PARAM_COUNT))
        vals = [_num(a, param_error(ErrorId.OPTIONAL_TYPE, i + 1), integer=(i == 4)) for i, a in enumerate(cmd.args)]
        if vals:
            _in(vals[0], 0.0, CR5_MAX_LOAD_KG, param_error(ErrorId.OPTIONAL_RANGE, 1))
        for i in range(1, min(len(vals), 4)):
            _in(vals[i], -999.0, 999.0, param_error(ErrorId.OPTIONAL_RANGE, i + 1))
        if len(vals) == 5:
            _in(vals[4], 0, 1, param_error(ErrorId.OPTIONAL_RANGE, 5))
        load = vals[0] if vals else None
        center = np.array(vals[1:4]) if len(vals) >= 4 else None
        return self.robot.enable(load, center), None

    def _estop(self, cmd: Command) -> tuple[int, Values]:
        if cmd.named or len(cmd.args) != 1:
            raise _ParamError(int(ErrorId.PARAM_COUNT))
        mode = _in(_num(cmd.args[0], param_error(ErrorId.REQUIRED_TYPE, 1), integer=True), 0, 1, param_error(ErrorId.REQUIRED_RANGE, 1))
        return self.robot.emergency_stop(bool(mode)), None

    def _speed_factor(self, cmd: Command) -> tuple[int, Values]:
        if cmd.named or len(cmd.args) != 1:
            raise _ParamError(int(ErrorId.PARAM_COUNT))
        r = _in(_num(cmd.args[0], param_error(ErrorId.REQUIRED_TYPE, 1), integer=True), 1, 100, param_error(ErrorId.REQUIRED_RANGE, 1))
        return self.robot.set_speed_factor(int(r)), None

    def _get_pose(self, cmd: Command) -> tuple[int, Values]:
        if cmd.args or len(cmd.named) not in (0, 2):
            raise _ParamError(int(ErrorId.PARAM_COUNT))
        _named_options(cmd.named, _OPTIONS["frames"])
        return 0, self.robot.get_pose6().tolist()

    def _positive_kin(self, cmd: Command) -> tuple[int, Values]:
        if len(cmd.args) != 6:
            raise _ParamError(int(ErrorId.PARAM_COUNT))
        q = _positional6(cmd)
        _named_options(cmd.named, _OPTIONS["frames"])
        return 0, cr5.matrix_to_pose6(cr5.fk(np.radians(q))).tolist()

    def _inverse_kin(self, cmd: Command) -> tuple[int, Values]:
        """The solution nearest the current angles, or nearest jointNear when useJointNear=1 (names
        case-insensitive: the manual writes jointNear and JointNear, Dobot's Python client sends JointNear)."""
        if len(cmd.args) != 6:
            raise _ParamError(int(ErrorId.PARAM_COUNT))
        pose = _positional6(cmd)
        opts = _named_options(cmd.named, _OPTIONS["inversekin"])
        seed = np.radians(self.robot.get_angle_deg())
        if opts.get("usejointnear") == 1 and "jointnear" in opts:
            seed = np.radians(opts["jointnear"])
        q = cr5.ik(cr5.pose6_to_matrix(pose), seed)
        if q is None:
            return int(ErrorId.FAILED), None
        return 0, np.degrees(q).tolist()

    def _mov(self, cmd: Command) -> tuple[int, Values]:
        if cmd.args:
            raise _ParamError(param_error(ErrorId.REQUIRED_TYPE, 1))  # V4 wants joint={..} or pose={..}
        named = list(cmd.named.items())
        if not named or named[0][0].lower() not in ("joint", "pose"):
            raise _ParamError(param_error(ErrorId.REQUIRED_TYPE, 1))
        kind, target = named[0][0].lower(), _vec6(named[0][1], param_error(ErrorId.REQUIRED_TYPE, 1))
        opts = _named_options(dict(named[1:]), _OPTIONS[cmd.key])
        v, a = _scalar_option(opts, "v", 100.0), _scalar_option(opts, "a", 100.0)
        move = self.robot.mov_j if cmd.key == "movj" else self.robot.mov_l
        code, cmd_id = move(joint_deg=target, v=v, a=a) if kind == "joint" else move(pose6=target, v=v, a=a)
        return code, [cmd_id]

    def _servo(self, cmd: Command) -> tuple[int, Values]:
        if not 6 <= len(cmd.args) <= 9:
            raise _ParamError(int(ErrorId.PARAM_COUNT))
        target = _positional6(cmd)
        spec = _OPTIONS["servo"]
        opts = _named_options(cmd.named, spec, _positional_options(cmd.args[6:], ["t", "aheadtime", "gain"], spec))
        t, ahead, gain = _scalar_option(opts, "t", 0.1), _scalar_option(opts, "aheadtime", 50.0), _scalar_option(opts, "gain", 500.0)
        code, cmd_id = self.robot.servo("joint" if cmd.key == "servoj" else "pose", target, t, ahead, gain)
        if self.on_servo is not None:
            self.on_servo()
        return code, [cmd_id]
