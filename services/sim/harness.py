"""Two simulated CR5 controllers on loopback, and what watches them from outside: for tests, benchmarks
(`bagit.bench.stop_time`) and the probes (`bagit bench probes`).

The simulated controllers are the arm driver's peer: real TCP, the V4 text protocol and the 1440-byte
feedback, each arm started holding its bag mount at the rig's home pose. `RecordingServer` logs every
command a controller answers, `FeedbackRecorder` keeps every feedback packet on a connection of its
own (both on this process's monotonic clock), `TcpProxy` cuts or silences the links.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from bagit.common import dobot
from bagit.common.geometry import invert_transform
from bagit.common.rig import ARMS, ArmConfig, ArmName, RigConfig
from bagit.services.sim.cr5_sim import SimulatedCR5
from bagit.services.sim.dobot_server import DobotControllerServer
from bagit.services.sim.rig_sim import natural_ik

# Where the simulated rig holds the mounts at the start (exp01-04): 0.21 m apart at 0.47 m height.
HOME_CENTRE = np.array([0.15, 0.0, 0.475])
HOME_HALF_SEPARATION = 0.106


def home_poses(centre: np.ndarray = HOME_CENTRE, half_sep: float = HOME_HALF_SEPARATION) -> dict[ArmName, np.ndarray]:
    """'left'/'right' -> 4x4 world <- mount, as the simulated bag's layout places them on a level rim:
    each mount's z (the tool axis) points along world y into the bag, its y points down."""
    out: dict[ArmName, np.ndarray] = {}
    sides: tuple[tuple[ArmName, float], ...] = (("left", -1.0), ("right", 1.0))
    for name, s in sides:
        z = np.array([0.0, -s, 0.0])
        x = np.array([-s, 0.0, 0.0])
        T = np.eye(4)
        T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
        T[:3, 3] = centre + [0.0, s * half_sep, 0.0]
        out[name] = T
    return out


class RecordingServer(DobotControllerServer):
    """A simulated controller's server that logs every command it answers: (monotonic time, text, reply)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.log: list[tuple[float, str, str]] = []
        self._log_lock = threading.Lock()

    def handle(self, text: str) -> str:
        t = time.monotonic()
        reply = super().handle(text)
        with self._log_lock:
            self.log.append((t, text.strip(), reply))
        return reply

    def commands(self, name: str | None = None) -> list[tuple[float, str, str]]:
        with self._log_lock:
            return [e for e in self.log if name is None or e[1].lower().startswith(name.lower() + "(")]


class TcpProxy:
    """Forwards loopback ports to others so a test can cut every connection at once (`drop()`)."""

    def __init__(self, routes: dict[int, int]):
        """`routes`: target port -> listen port (0: any free one)."""
        self._listeners: dict[int, socket.socket] = {}
        self._conns: list[socket.socket] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.refuse = False
        self._paused: set[int] = set()
        self._mangle: dict[int, Callable[[bytes], bytes]] = {}
        for target, listen in routes.items():
            s = socket.socket()
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(("127.0.0.1", listen))
            s.listen(4)
            s.settimeout(0.05)
            self._listeners[target] = s
            self._spawn(self._accept, s, target)

    def port_for(self, target: int) -> int:
        return self._listeners[target].getsockname()[1]

    def _spawn(self, fn, *args) -> None:
        t = threading.Thread(target=fn, args=args, daemon=True)
        t.start()
        self._threads.append(t)

    def _accept(self, listener: socket.socket, target: int) -> None:
        while not self._stop.is_set():
            try:
                client, _ = listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            if self.refuse:
                client.close()
                continue
            try:
                upstream = socket.create_connection(("127.0.0.1", target), timeout=1.0)
            except OSError:
                client.close()
                continue
            for s in (client, upstream):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._conns += [client, upstream]
            self._spawn(self._pipe, client, upstream, None)
            self._spawn(self._pipe, upstream, client, target)

    def _pipe(self, src: socket.socket, dst: socket.socket, target: int | None) -> None:
        try:
            while True:
                data = src.recv(65536)
                if not data:
                    break
                if target in self._paused:
                    continue  # swallowed: the client hears nothing from `target`
                fn = self._mangle.get(target) if target is not None else None
                dst.sendall(fn(data) if fn is not None else data)
        except OSError:
            pass
        for s in (src, dst):
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def pause(self, target: int) -> None:
        """Stop forwarding what `target` sends (its connections stay open, silent)."""
        self._paused.add(target)

    def resume(self, target: int) -> None:
        self._paused.discard(target)
        self._mangle.pop(target, None)

    def mangle(self, target: int, fn: Callable[[bytes], bytes]) -> None:
        """Pass what `target` sends through `fn` (corrupt it) until `resume(target)`."""
        self._mangle[target] = fn

    def drop(self) -> None:
        """Reset every connection through the proxy (new ones are still accepted unless `refuse`)."""
        with self._lock:
            conns, self._conns = self._conns, []
        for s in conns:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()

    def close(self) -> None:
        self._stop.set()
        self.drop()
        for s in self._listeners.values():
            s.close()
        for t in self._threads:
            t.join(timeout=1.0)


@dataclass
class SimPair:
    """Two simulated CR5s serving on ephemeral loopback ports, and the rig config that points at them."""

    rig: RigConfig
    robots: dict[ArmName, SimulatedCR5]
    servers: dict[ArmName, RecordingServer]
    proxies: dict[ArmName, TcpProxy] = field(default_factory=dict)

    def close(self) -> None:
        for p in self.proxies.values():
            p.close()
        for s in self.servers.values():
            s.stop()


def home_robot(rig: RigConfig, arm: ArmName, pose: np.ndarray) -> SimulatedCR5:
    """`arm`'s simulated CR5 at rest holding its mount at `pose (4, 4)` (world), solved as the simulator places it."""
    conf = rig.arms[arm]
    T_bf = invert_transform(conf.T_world_base()) @ pose @ invert_transform(conf.T_flange_mount())
    q = natural_ik(T_bf)
    assert q is not None, f"{arm}: start pose out of reach"
    return SimulatedCR5(conf, q0=q, name=arm)


def start_sims(rig: RigConfig | None = None, poses: dict[ArmName, np.ndarray] | None = None, proxy: bool = False) -> SimPair:
    """Start both controllers holding `poses` (default `home_poses()`); with `proxy`, the rig goes through TcpProxy."""
    rig = rig or RigConfig()
    poses = poses or home_poses()
    robots: dict[ArmName, SimulatedCR5] = {}
    servers: dict[ArmName, RecordingServer] = {}
    proxies: dict[ArmName, TcpProxy] = {}
    arms: dict[ArmName, ArmConfig] = {}
    try:
        for a in ARMS:
            conf = rig.arms[a]
            robots[a] = home_robot(rig, a, poses[a])
            servers[a] = RecordingServer(robots[a], dashboard_port=0, feedback_port=0, step_in_background=True).start()
            ports = (servers[a].dashboard_port, servers[a].feedback_port)
            if proxy:
                proxies[a] = TcpProxy({ports[0]: 0, ports[1]: 0})
                ports = (proxies[a].port_for(ports[0]), proxies[a].port_for(ports[1]))
            arms[a] = conf.model_copy(update={"dashboard_port": ports[0], "feedback_port": ports[1]})
    except BaseException:
        for p in proxies.values():
            p.close()
        for s in servers.values():
            s.stop()
        raise
    return SimPair(rig.model_copy(update={"arms": arms}), robots, servers, proxies)


def servo_positions(server: RecordingServer, t0: float = -np.inf, t1: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """(times, flange positions (n, 3) m in the base frame) of the ServoP commands a controller accepted."""
    rows = [(t, text) for t, text, reply in server.commands("ServoP") if t0 <= t <= t1 and reply.startswith("0,")]
    if not rows:
        return np.zeros(0), np.zeros((0, 3))
    xyz = np.array([[float(v) for v in text[len("ServoP(") :].split(",")[:3]] for _, text in rows]) / 1000.0
    return np.array([r[0] for r in rows]), xyz


class DashboardText:
    """A minimal V4 dashboard client, as a vendor's or a user's script talks: raw text out, replies in."""

    def __init__(self, port: int, host: str = "127.0.0.1"):
        self.sock = socket.create_connection((host, port), timeout=3.0)
        self.buf = ""

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def raw(self, text: str) -> str:
        """Send one command; its one reply (an error if several come)."""
        self.sock.sendall(text.encode())
        while ";" not in self.buf:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError("the controller closed the connection")
            self.buf += chunk.decode(errors="replace")
        replies, self.buf = dobot.split_replies(self.buf)
        if len(replies) != 1:
            raise ValueError(f"{len(replies)} replies to one command: {replies}")
        return replies[0]

    def ask(self, text: str) -> dobot.Reply:
        return dobot.parse_reply(self.raw(text))

    def collect(self, seconds: float, until: int | None = None) -> list[dobot.Reply]:
        """The replies that arrive within `seconds` (or as soon as `until` have)."""
        self.sock.settimeout(0.05)
        end = time.monotonic() + seconds
        try:
            while time.monotonic() < end and (until is None or self.buf.count(";") < until):
                try:
                    chunk = self.sock.recv(65536)
                except TimeoutError:
                    continue
                if not chunk:
                    raise ConnectionError("the controller closed the connection")
                self.buf += chunk.decode(errors="replace")
        finally:
            self.sock.settimeout(3.0)
        replies, self.buf = dobot.split_replies(self.buf)
        return [dobot.parse_reply(r) for r in replies]

    def close(self) -> None:
        self.sock.close()


def servo_parameter(text: str, name: str) -> float | None:
    """A named parameter of a logged ServoP/ServoJ (`aheadtime`, `gain`, `t`), None if not given."""
    for part in text.rstrip(")").split(","):
        key, _, value = part.partition("=")
        if key.strip() == name:
            return float(value)
    return None


class FeedbackRecorder:
    """Listens to a controller's feedback port on its own connection and keeps every packet: (monotonic t, record)."""

    def __init__(self, port: int, host: str = "127.0.0.1"):
        self.sock = socket.create_connection((host, port), timeout=2.0)
        self.sock.settimeout(0.2)
        self.packets: list[tuple[float, np.ndarray]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        asm = dobot.FeedbackAssembler()
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            if not data:
                return
            t = time.monotonic()
            for rec in asm.feed(data):
                with self._lock:
                    self.packets.append((t, rec))

    def series(self, field_name: str, t0: float = -np.inf, t1: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """Times `(n,)` and values `(n, ...)` of one feedback field between t0 and t1."""
        with self._lock:
            sel = [(t, np.array(r[field_name], dtype=float)) for t, r in self.packets if t0 <= t <= t1]
        if not sel:
            return np.zeros(0), np.zeros((0,))
        return np.array([s[0] for s in sel]), np.stack([s[1] for s in sel])

    def close(self) -> None:
        self._stop.set()
        self.sock.close()
        self._thread.join(timeout=1.0)
