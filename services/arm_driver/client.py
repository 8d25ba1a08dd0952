"""A client for one Dobot CR controller over TCP/IP protocol V4: dashboard commands and feedback.

Dashboard (port 29999): commands go out as text; a reader thread cuts the replies
(`ErrorID,{values},Command(...);`, bagit.common.dobot) and hands each to the request that sent the
command it echoes, so several requests may be in flight (the servo loop's ServoP and an e-stop
from another thread) without a reply ever going to the wrong caller. V4 answers in order, so a
reply to a later command means the earlier ones got none; a reply that does not parse is taken as
the oldest request's (and reported as malformed). `request()` waits with a time-out; `call()` also
turns a non-zero ErrorID into `CommandRejected`.

Feedback (port 30004): a reader thread cuts the stream into 1440-byte packets with the shared
dtype (bagit.common.dobot.parse_feedback, which checks MessageSize and the test value). A packet that
fails is counted and reported, and the reader re-synchronises on the next header it can verify
(MessageSize 1440 at offset 0, the test value at 48), so a corrupted packet costs only itself.

Connections: `connect()` opens both sockets; any socket error, EOF or `drop()` closes both and fails
the requests in flight with `ConnectionLost`. `reconnect_if_due()` tries again with exponential
back-off, which only resets once a feedback packet has arrived (a controller that accepts the
connection but stays silent is retried ever less often, not four times a second). `epoch` counts successful connects, so the
driver can tell that the controller it
talks to may have changed state in between (it then takes a fresh target from the current pose).
"""

from __future__ import annotations

import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import cast

import numpy as np

from bagit.common import dobot
from bagit.common.dobot import ErrorId, Reply
from bagit.common.errors import ProtocolError

MAX_REPLY_BUFFER = 65536  # a reply longer than this without its ';' is garbage
_HEADER_SIZE = dobot.FEEDBACK_SIZE.to_bytes(2, "little")
_TEST_BYTES = dobot.TEST_VALUE.to_bytes(8, "little")
_TEST_OFFSET = dobot.FEEDBACK_DTYPE_FIELDS["TestValue"][1]

_ERROR_NAMES = {
    int(ErrorId.FAILED): "not executed",
    int(ErrorId.IN_ERROR): "robot in error",
    int(ErrorId.EMERGENCY_STOP): "emergency stop pressed",
    int(ErrorId.POWER_OFF): "robot powered off",
    int(ErrorId.UNKNOWN_COMMAND): "unknown or malformed command",
    int(ErrorId.PARAM_COUNT): "wrong number of parameters",
}


def describe_error(error_id: int) -> str:
    """A short reason for a V4 ErrorID."""
    if error_id in _ERROR_NAMES:
        return _ERROR_NAMES[error_id]
    for base, what in ((-30000, "type of required parameter"), (-40000, "range of required parameter"),
                       (-50000, "type of optional parameter"), (-60000, "range of optional parameter")):
        if base - 100 < error_id < base:
            return f"wrong {what} {base - error_id}"
    return f"error {error_id}"


class ConnectionLost(ProtocolError):
    """The link to a controller is down (refused, reset, closed or silent)."""


class CommandRejected(ProtocolError):
    """The controller answered a command with a non-zero ErrorID."""

    def __init__(self, arm: str, reply: Reply):
        self.arm = arm
        self.reply = reply
        self.error_id = reply.error_id
        super().__init__(f"{arm}: {reply.command} refused: {reply.error_id} ({describe_error(reply.error_id)})")


def _key(text: str) -> str:
    """A command's identity for matching its reply: no whitespace, case kept, at most 256 characters
    (the controller echoes a malformed command collapsed and cut to 256)."""
    return "".join(text.split())[:256]


class PendingReply:
    """A request in flight: `wait()` returns its Reply or raises ProtocolError."""

    def __init__(self, text: str):
        self.text = text
        self.key = _key(text)
        self.sent_at = time.monotonic()
        self._done = threading.Event()
        self._reply: Reply | None = None
        self._error: ProtocolError | None = None

    def _resolve(self, reply: Reply | None = None, error: ProtocolError | None = None) -> None:
        if not self._done.is_set():
            self._reply, self._error = reply, error
            self._done.set()

    @property
    def done(self) -> bool:
        return self._done.is_set()

    def wait(self, timeout: float) -> Reply:
        if not self._done.wait(timeout):  # how long it has been unanswered, not just this wait
            waited = max(timeout, time.monotonic() - self.sent_at)
            raise ProtocolError(f"no reply to {self.text[:60]} within {waited * 1000:.0f} ms")
        if self._error is not None:
            raise self._error
        assert self._reply is not None
        return self._reply


class DobotClient:
    """One controller: dashboard requests, the latest feedback packet, reconnection with back-off."""

    def __init__(
        self,
        name: str,
        host: str = "127.0.0.1",
        dashboard_port: int = dobot.DASHBOARD_PORT,
        feedback_port: int = dobot.FEEDBACK_PORT,
        reply_timeout_s: float = 0.5,
        connect_timeout_s: float = 1.0,
        reconnect_initial_s: float = 0.05,
        reconnect_max_s: float = 2.0,
        on_feedback: Callable[[np.ndarray, float], None] | None = None,
    ):
        self.name = name
        self.host = host
        self.dashboard_port = int(dashboard_port)
        self.feedback_port = int(feedback_port)
        self.reply_timeout_s = float(reply_timeout_s)
        self.connect_timeout_s = float(connect_timeout_s)
        self.on_feedback = on_feedback
        self._backoff0 = float(reconnect_initial_s)
        self._backoff_max = float(reconnect_max_s)
        self._backoff = self._backoff0
        self._next_attempt = 0.0
        self._lock = threading.Lock()
        self._send_lock = threading.RLock()  # one command on the wire at a time (`send_unless` holds it across its check)
        self._dash: socket.socket | None = None
        self._fb: socket.socket | None = None
        self._pending: deque[PendingReply] = deque()
        self._latest: np.ndarray | None = None
        self._latest_t = -np.inf
        self._fb_event = threading.Event()
        self._threads: list[threading.Thread] = []
        self.epoch = 0
        self.connected = False
        self.connected_at = -np.inf
        self.closed = False
        self.counters = {
            "requests": 0, "rejected": 0, "timeouts": 0, "malformed_replies": 0, "unexpected_replies": 0,
            "packets": 0, "bad_packets": 0, "bytes_skipped": 0, "drops": 0, "connect_failures": 0,
        }  # fmt: skip
        self.last_error: str | None = None

    # -- connection ------------------------------------------------------------------------------

    def connect(self) -> None:
        """Open the dashboard and feedback sockets and start their readers; ConnectionLost if refused."""
        if self.closed:
            raise ConnectionLost(f"{self.name}: client is closed")
        socks: list[socket.socket] = []
        try:
            for port in (self.dashboard_port, self.feedback_port):
                s = socket.create_connection((self.host, port), timeout=self.connect_timeout_s)
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                s.settimeout(None)
                socks.append(s)
        except OSError as e:
            for s in socks:
                s.close()
            with self._lock:
                self.counters["connect_failures"] += 1
                self.last_error = f"cannot connect to {self.host}:{port}: {e.strerror or e}"
            raise ConnectionLost(f"{self.name}: {self.last_error}") from None
        with self._lock:
            self._dash, self._fb = socks
            self.epoch += 1
            epoch = self.epoch
            self._latest, self._latest_t = None, -np.inf
            self._fb_event.clear()
            self.connected = True
            self.connected_at = time.monotonic()
        for target, sock, what in ((self._dashboard_reader, socks[0], "dashboard"), (self._feedback_reader, socks[1], "feedback")):
            t = threading.Thread(target=target, args=(sock, epoch), name=f"dobot-{self.name}-{what}", daemon=True)
            t.start()
            self._threads.append(t)
        self._threads = [t for t in self._threads if t.is_alive()]

    def drop(self, reason: str, epoch: int | None = None) -> None:
        """Close both sockets (if `epoch` is still current) and fail every request in flight."""
        with self._lock:
            if epoch is not None and epoch != self.epoch:
                return
            if not self.connected:
                return
            self.connected = False
            self.counters["drops"] += 1
            self.last_error = reason
            socks, self._dash, self._fb = (self._dash, self._fb), None, None
            pending, self._pending = list(self._pending), deque()
            self._next_attempt = time.monotonic() + self._backoff
            self._backoff = min(self._backoff * 2, self._backoff_max)  # reset by the first good packet
        for s in socks:
            if s is not None:
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()
        for p in pending:
            p._resolve(error=ConnectionLost(f"{self.name}: connection lost ({reason})"))

    def reconnect_if_due(self, now: float | None = None) -> bool:
        """Try to reconnect if disconnected and the back-off has passed; True if now connected."""
        if self.connected:
            return True
        if self.closed:
            return False
        now = time.monotonic() if now is None else now
        if now < self._next_attempt:
            return False
        try:
            self.connect()
            return True
        except ConnectionLost:
            self._next_attempt = time.monotonic() + self._backoff
            self._backoff = min(self._backoff * 2, self._backoff_max)
            return False

    def close(self) -> None:
        self.drop("closed")
        self.closed = True
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=1.0)
        self._threads.clear()

    # -- dashboard -------------------------------------------------------------------------------

    def send(self, text: str) -> PendingReply:
        """Send one command without waiting; the returned handle's `wait()` gives its reply. Queued for its
        reply and put on the wire in one turn of the send lock, so the replies' order is the wire's."""
        return cast(PendingReply, self._put(text, None))  # nothing says no

    def send_unless(self, text: str, stop: Callable[[], bool]) -> PendingReply | None:
        """`send`, unless `stop()` says no when it is this command's turn on the wire (None: not sent). What
        latches `stop` before sending on this connection (the e-stop) then finds this command ahead of it, or
        never sent. Asked last before the write: a pause of this process between an answer and the wire
        (SIGSTOP, a starved thread) is then a few instructions wide, not a whole cycle's bookkeeping."""
        return self._put(text, stop)

    def _put(self, text: str, unless: Callable[[], bool] | None) -> PendingReply | None:
        try:
            data = text.encode("ascii")
        except UnicodeEncodeError:
            raise ProtocolError(f"{self.name}: command is not ASCII: {text[:60]!r}") from None
        pending = PendingReply(text)
        with self._send_lock:
            with self._lock:
                if unless is not None and unless():
                    return None
                sock = self._dash
                if sock is None or not self.connected:
                    raise ConnectionLost(f"{self.name}: not connected ({self.last_error or 'never connected'})")
                self._pending.append(pending)
                self.counters["requests"] += 1
                epoch = self.epoch
            try:
                sock.sendall(data)
            except OSError as e:
                self.drop(f"send failed: {e.strerror or e}", epoch)
                pending._resolve(error=ConnectionLost(f"{self.name}: send failed: {e.strerror or e}"))
        return pending

    def wait(self, pending: PendingReply, timeout: float | None = None) -> Reply:
        """The reply to a sent command (ProtocolError on time-out, malformed reply or lost link)."""
        try:
            return pending.wait(self.reply_timeout_s if timeout is None else timeout)
        except ProtocolError as e:
            if pending.done:  # resolved with an error: malformed reply or lost link
                raise
            with self._lock:  # timed out: forget it (a late reply is then counted as unexpected)
                self.counters["timeouts"] += 1
                self.last_error = str(e)
                if pending in self._pending:
                    self._pending.remove(pending)
            raise ProtocolError(f"{self.name}: {e}") from None

    def request(self, text: str, timeout: float | None = None) -> Reply:
        """Send `text` and wait for its reply (any ErrorID)."""
        return self.wait(self.send(text), timeout)

    def check(self, reply: Reply) -> Reply:
        """`reply`, or CommandRejected if its ErrorID is not 0."""
        if reply.error_id != 0:
            with self._lock:
                self.counters["rejected"] += 1
                self.last_error = f"{reply.command}: {reply.error_id} ({describe_error(reply.error_id)})"
            raise CommandRejected(self.name, reply)
        return reply

    def call(self, name: str, *args: object, timeout: float | None = None, **named: object) -> Reply:
        """Format, send and check one command: `call("SpeedFactor", 50)`."""
        return self.check(self.request(dobot.format_command(name, *args, **named), timeout))

    def _dashboard_reader(self, sock: socket.socket, epoch: int) -> None:
        buf = ""
        try:
            while True:
                data = sock.recv(4096)
                if not data:
                    self.drop("controller closed the dashboard connection", epoch)
                    return
                buf += data.decode("utf-8", errors="replace")
                replies, buf = dobot.split_replies(buf)
                for text in replies:
                    self._on_reply(text)
                if len(buf) > MAX_REPLY_BUFFER:
                    self._on_reply(buf[:200])  # reported as malformed
                    buf = ""
        except OSError as e:
            self.drop(f"dashboard: {e.strerror or e}", epoch)

    def _on_reply(self, text: str) -> None:
        try:
            reply = dobot.parse_reply(text)
        except ProtocolError as e:
            with self._lock:
                self.counters["malformed_replies"] += 1
                self.last_error = f"malformed reply {text.strip()[:80]!r}"
                victim = self._pending.popleft() if self._pending else None
            if victim is not None:
                victim._resolve(error=ProtocolError(f"{self.name}: malformed reply to {victim.text[:60]}: {e}"))
            return
        key = _key(reply.command)
        with self._lock:
            idx = next((i for i, p in enumerate(self._pending) if p.key == key), None)
            if idx is None:
                self.counters["unexpected_replies"] += 1
                self.last_error = f"reply to no pending command: {text.strip()[:80]!r}"
                return
            skipped = [self._pending.popleft() for _ in range(idx)]
            match = self._pending.popleft()
            if skipped:
                self.counters["malformed_replies"] += len(skipped)
                self.last_error = f"no reply to {skipped[0].text[:60]}"
        for p in skipped:
            p._resolve(error=ProtocolError(f"{self.name}: no reply to {p.text[:60]} (a later command was answered)"))
        match._resolve(reply=reply)

    # -- typed commands --------------------------------------------------------------------------

    def clear_error(self) -> None:
        self.call("ClearError")

    def enable(self, load_kg: float | None = None, center_mm: tuple[float, float, float] | None = None) -> None:
        """EnableRobot with the payload (kg) and its centre of mass in the flange frame (mm)."""
        if load_kg is None:
            self.call("EnableRobot")
        elif center_mm is None:
            self.call("EnableRobot", float(load_kg))
        else:
            self.call("EnableRobot", float(load_kg), *(float(c) for c in center_mm))

    def disable(self) -> None:
        self.call("DisableRobot")

    def speed_factor(self, ratio: int) -> None:
        self.call("SpeedFactor", int(ratio))

    def emergency_stop_text(self, pressed: bool) -> str:
        return dobot.format_command("EmergencyStop", int(bool(pressed)))

    def robot_mode(self) -> int:
        r = self.call("RobotMode")
        if len(r.values) != 1 or not isinstance(r.values[0], float):
            raise ProtocolError(f"{self.name}: RobotMode returned {r.raw_values!r}")
        return int(r.values[0])

    def get_pose(self) -> np.ndarray:
        """The flange in the base frame, Dobot pose6 (mm, deg)."""
        return self._vector(self.call("GetPose"), 6)

    def error_ids(self) -> list[list[int]]:
        """GetErrorID: the controller's alarm ids, then each servo's."""
        return dobot.parse_error_ids(self.call("GetErrorID").raw_values)

    def _vector(self, reply: Reply, n: int) -> np.ndarray:
        v = reply.values
        if len(v) != n or not all(isinstance(x, float) for x in v):
            raise ProtocolError(f"{self.name}: {reply.command} returned {reply.raw_values[:80]!r}, expected {n} numbers")
        a = np.array(v, dtype=float)
        if not np.all(np.isfinite(a)):
            raise ProtocolError(f"{self.name}: {reply.command} returned non-finite values")
        return a

    @staticmethod
    def servo_text(command: str, target6: np.ndarray, t: float, aheadtime: float, gain: float) -> str:
        """`ServoP(x,y,z,rx,ry,rz,t=..,aheadtime=..,gain=..)` (or ServoJ with joint angles in degrees)."""
        return dobot.format_command(command, *np.asarray(target6, dtype=float).tolist(), t=float(t), aheadtime=float(aheadtime), gain=float(gain))

    # -- feedback --------------------------------------------------------------------------------

    def _feedback_reader(self, sock: socket.socket, epoch: int) -> None:
        buf = bytearray()
        size = dobot.FEEDBACK_SIZE
        try:
            while True:
                data = sock.recv(65536)
                if not data:
                    self.drop("controller closed the feedback connection", epoch)
                    return
                buf.extend(data)
                while len(buf) >= size:
                    try:
                        rec = dobot.parse_feedback(bytes(buf[:size]))
                    except ProtocolError as e:
                        with self._lock:
                            self.counters["bad_packets"] += 1
                            self.last_error = f"bad feedback packet: {e}"
                        skip = self._resync(buf)
                        with self._lock:
                            self.counters["bytes_skipped"] += skip
                        del buf[:skip]
                        continue
                    del buf[:size]
                    self._on_packet(rec, epoch)
        except OSError as e:
            self.drop(f"feedback: {e.strerror or e}", epoch)

    @staticmethod
    def _resync(buf: bytearray) -> int:
        """How many bytes to drop so `buf` starts at the next plausible packet header (all if none)."""
        k = buf.find(_HEADER_SIZE, 1)
        while k != -1:
            if len(buf) - k < _TEST_OFFSET + 8:
                return k  # not enough bytes yet to verify: wait for more
            if buf[k + _TEST_OFFSET : k + _TEST_OFFSET + 8] == _TEST_BYTES:
                return k
            k = buf.find(_HEADER_SIZE, k + 1)
        return len(buf)

    def _on_packet(self, rec: np.ndarray, epoch: int) -> None:
        now = time.monotonic()
        with self._lock:
            if epoch != self.epoch:
                return
            self._latest, self._latest_t = rec, now
            self.counters["packets"] += 1
            self._backoff = self._backoff0  # the link works: a later drop retries quickly again
        self._fb_event.set()
        cb = self.on_feedback
        if cb is not None:
            try:
                cb(rec, now)
            except Exception as e:  # a subscriber's bug must not kill the feedback reader
                self.last_error = f"feedback callback failed: {e!r}"

    def latest(self) -> tuple[np.ndarray | None, float]:
        """The newest feedback record since the last connect and when it arrived (monotonic seconds)."""
        with self._lock:
            return self._latest, self._latest_t

    def feedback_age(self, now: float | None = None) -> float:
        """Seconds since the last good packet (inf if none since connecting)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            return now - self._latest_t

    def silent_for(self, now: float | None = None) -> float:
        """Seconds the feedback port has been quiet: since the last packet, or since connecting if none came."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if not self.connected:
                return np.inf
            return now - max(self._latest_t, self.connected_at)

    def wait_feedback(self, timeout: float) -> bool:
        """Wait for a packet after (re)connecting."""
        return self._fb_event.wait(timeout)

    def stats(self) -> dict:
        with self._lock:
            return {"connected": self.connected, "epoch": self.epoch, "last_error": self.last_error, **self.counters}
