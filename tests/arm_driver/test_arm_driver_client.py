"""DobotClient against a scripted fake controller: reply matching, malformed and missing replies,
broken feedback packets, partial reads, lost connections and reconnect back-off."""

import socket
import threading
import time

import numpy as np
import pytest
from suite_support import HANG_S, wait_until

from bagit.common import dobot
from bagit.common.errors import ProtocolError
from bagit.services.arm_driver.client import CommandRejected, ConnectionLost, DobotClient


class FakeController:
    """Two loopback ports: the dashboard answers with `script(command text) -> bytes to send` (or None:
    stay silent); the feedback port sends whatever the test pushes with `push(bytes)`."""

    def __init__(self, script):
        self.script = script
        self.received: list[str] = []
        self._dash = self._listen()
        self._fb = self._listen()
        self.fb_conns: list[socket.socket] = []
        self.dash_conns: list[socket.socket] = []
        self._stop = threading.Event()
        for fn in (self._serve_dash, self._serve_fb):
            threading.Thread(target=fn, daemon=True).start()

    @staticmethod
    def _listen():
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", 0))
        s.listen(4)
        s.settimeout(0.05)
        return s

    @property
    def ports(self):
        return self._dash.getsockname()[1], self._fb.getsockname()[1]

    def _accept(self, lst):
        while not self._stop.is_set():
            try:
                c, _ = lst.accept()
                return c
            except TimeoutError:
                continue
            except OSError:
                return None
        return None

    def _serve_dash(self):
        while (c := self._accept(self._dash)) is not None:
            self.dash_conns.append(c)
            threading.Thread(target=self._client, args=(c,), daemon=True).start()

    def _client(self, c):
        sp = dobot.CommandSplitter()
        try:
            while True:
                data = c.recv(4096)
                if not data:
                    return
                for text in sp.feed(data):
                    self.received.append(text)
                    out = self.script(text)
                    if out:
                        for chunk in out if isinstance(out, list) else [out]:
                            c.sendall(chunk)
                            time.sleep(0.005)
        except OSError:
            return

    def _serve_fb(self):
        while (c := self._accept(self._fb)) is not None:
            self.fb_conns.append(c)

    def push(self, data: bytes, chunk: int | None = None):
        for c in self.fb_conns:
            for i in range(0, len(data), chunk or len(data)):
                c.sendall(data[i : i + (chunk or len(data))])
                if chunk:
                    time.sleep(0.001)

    def hang_up(self):
        for c in self.dash_conns + self.fb_conns:
            try:
                c.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            c.close()
        self.dash_conns.clear()
        self.fb_conns.clear()

    def close(self):
        self._stop.set()
        self.hang_up()
        self._dash.close()
        self._fb.close()


def echo_ok(text):
    return f"0,{{}},{text};".encode()


@pytest.fixture
def fake():
    made = []

    def make(script=echo_ok):
        f = FakeController(script)
        made.append(f)
        return f

    yield make
    for f in made:
        f.close()


def client_for(f, **kw):
    c = DobotClient("left", "127.0.0.1", *f.ports, reply_timeout_s=kw.pop("reply_timeout_s", 0.3), **kw)
    c.connect()
    return c


def packet(mode=5, x=100.0):
    rec = dobot.new_feedback()
    rec["RobotMode"] = mode
    rec["ToolVectorActual"] = [x, 0, 300, 180, 0, 0]
    rec["EnableStatus"] = 1
    return rec.tobytes()


def wait_for(cond, timeout=HANG_S):
    return wait_until(cond, timeout)


def test_replies_are_matched_to_their_commands_and_errors_are_typed(fake):
    def script(text):
        if text.startswith("RobotMode"):
            return f"0,{{5}},{text};".encode()
        if text.startswith("EnableRobot"):
            return f"-2,{{}},{text};".encode()
        return echo_ok(text)

    f = fake(script)
    c = client_for(f)
    assert c.robot_mode() == 5
    c.speed_factor(40)
    with pytest.raises(CommandRejected) as e:
        c.enable(0.3, (0, 0, 60))
    assert e.value.error_id == -2 and "robot in error" in str(e.value)
    assert f.received[-1] == "EnableRobot(0.3,0,0,60)"
    assert c.stats()["rejected"] == 1
    c.close()


def test_replies_split_across_reads_and_answered_out_of_order(fake):
    held = {}

    def script(text):
        if text.startswith("GetAngle"):
            held["angle"] = text  # answered only after the next command
            return None
        if text.startswith("RobotMode"):
            body = f"0,{{1,2,3,4,5,6}},{held['angle']};0,{{5}},{text};".encode()
            return [body[:7], body[7:30], body[30:]]  # and in pieces
        return echo_ok(text)

    c = client_for(fake(script))
    p1 = c.send("GetAngle()")
    p2 = c.send("RobotMode()")
    assert c.wait(p2).values == [5.0]
    assert c.wait(p1).values == [1, 2, 3, 4, 5, 6]
    c.close()


def test_a_later_reply_fails_an_earlier_unanswered_request(fake):
    def script(text):
        return None if text.startswith("GetPose") else echo_ok(text)

    c = client_for(fake(script))
    p1 = c.send("GetPose()")
    p2 = c.send("ClearError()")
    assert c.wait(p2).ok
    with pytest.raises(ProtocolError, match="no reply to GetPose"):
        c.wait(p1)
    c.close()


def test_malformed_replies_are_reported_and_the_link_survives(fake):
    answers = iter([b"garbage;", b"0,{},NotWhatWasSent();", b"-1,{oops;"])

    def script(text):
        if text.startswith("Stop"):
            return next(answers)
        return f"0,{{5}},{text};".encode()

    c = client_for(fake(script))
    with pytest.raises(ProtocolError, match="malformed reply"):
        c.request("Stop()")
    with pytest.raises(ProtocolError, match="no reply"):  # echo of another command: this one timed out
        c.request("Stop()", timeout=0.2)
    with pytest.raises(ProtocolError, match="malformed reply"):
        c.request("Stop()")
    assert c.robot_mode() == 5  # still talking
    s = c.stats()
    assert s["malformed_replies"] == 2 and s["unexpected_replies"] == 1 and s["timeouts"] == 1 and s["connected"]
    c.close()


def test_values_of_the_wrong_shape_are_protocol_errors(fake):
    def script(text):
        if text.startswith("GetPose"):
            return f"0,{{1,2,three}},{text};".encode()
        if text.startswith("RobotMode"):
            return f"0,{{}},{text};".encode()
        return echo_ok(text)

    c = client_for(fake(script))
    with pytest.raises(ProtocolError, match="expected 6 numbers"):
        c.get_pose()
    with pytest.raises(ProtocolError, match="RobotMode returned"):
        c.robot_mode()
    c.close()


def test_a_silent_controller_times_out_and_a_late_reply_is_not_misdelivered(fake):
    late = []

    def script(text):
        if text.startswith("GetAngle"):
            late.append(text)
            return None
        if text.startswith("RobotMode") and late:
            return [f"0,{{1,1,1,1,1,1}},{late.pop()};".encode(), f"0,{{5}},{text};".encode()]
        return echo_ok(text)

    c = client_for(fake(script))
    t0 = time.monotonic()
    with pytest.raises(ProtocolError, match=r"within 1[5-9]\d ms"):  # how long it went unanswered: 150 ms or a little more
        c.request("GetAngle()", timeout=0.15)
    assert time.monotonic() - t0 > 0.14  # it waited out its time-out first (how much longer is the machine's load)
    assert c.robot_mode() == 5  # the stale GetAngle reply arrives first and is dropped, not handed to RobotMode
    assert c.stats()["unexpected_replies"] == 1
    c.close()


def test_feedback_in_pieces_and_corrupted_packets_are_survived(fake):
    f = fake()
    c = client_for(f)
    assert wait_for(lambda: f.fb_conns)
    f.push(packet(x=1.0) + packet(x=2.0), chunk=333)  # partial reads
    assert wait_for(lambda: c.stats()["packets"] == 2)
    assert c.latest()[0]["ToolVectorActual"][0] == 2.0
    bad = bytearray(packet(x=3.0))
    bad[48:56] = (0xDEADBEEF).to_bytes(8, "little")  # wrong test value
    f.push(bytes(bad) + b"\x00junk" * 7 + packet(x=4.0) + packet(x=5.0)[:700])
    assert wait_for(lambda: c.stats()["packets"] == 3)
    assert c.latest()[0]["ToolVectorActual"][0] == 4.0
    s = c.stats()
    assert s["bad_packets"] >= 1 and s["bytes_skipped"] >= 1440 and s["connected"]
    assert "test value" in s["last_error"]
    f.push(packet(x=5.0)[700:])  # the rest of the split packet completes it
    assert wait_for(lambda: c.latest()[0]["ToolVectorActual"][0] == 5.0)
    c.close()


def test_a_wrong_message_size_is_refused_and_resynchronised(fake):
    f = fake()
    c = client_for(f)
    assert wait_for(lambda: f.fb_conns)
    bad = bytearray(packet(x=7.0))
    bad[0:2] = (1000).to_bytes(2, "little")
    f.push(bytes(bad) + packet(x=8.0))
    assert wait_for(lambda: c.stats()["packets"] == 1)
    assert c.latest()[0]["ToolVectorActual"][0] == 8.0 and c.stats()["bad_packets"] == 1
    c.close()


def test_a_dropped_link_fails_requests_in_flight_and_reconnects_with_back_off(fake):
    f = fake(lambda text: None)  # never answers
    c = client_for(f, reconnect_initial_s=0.05, reconnect_max_s=0.2)
    first = c.epoch
    p = c.send("RobotMode()")
    time.sleep(0.05)
    f.hang_up()
    with pytest.raises(ConnectionLost):
        c.wait(p, timeout=1.0)
    assert wait_for(lambda: not c.connected)
    with pytest.raises(ConnectionLost):
        c.send("RobotMode()")
    assert not c.reconnect_if_due(now=0.0)  # an instant before the back-off ends: no attempt
    assert wait_for(lambda: c.reconnect_if_due(), timeout=2.0)
    assert c.connected and c.epoch == first + 1
    assert c.latest()[0] is None  # nothing from before the drop is taken as current
    c.close()


def test_refused_connections_back_off_exponentially():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    c = DobotClient("right", "127.0.0.1", port, port, reconnect_initial_s=0.01, reconnect_max_s=0.04)
    with pytest.raises(ConnectionLost, match="cannot connect"):
        c.connect()
    waits = []
    for _ in range(5):
        before = time.monotonic()
        assert not c.reconnect_if_due(now=time.monotonic() + 10)
        waits.append(c._next_attempt - before)
    assert waits[0] == pytest.approx(0.01, abs=0.005)
    assert waits[1] == pytest.approx(0.02, abs=0.005)
    assert max(waits) == pytest.approx(0.04, abs=0.005)  # capped
    assert c.stats()["connect_failures"] == 6
    c.close()


def test_servo_text_is_the_v4_format():
    text = DobotClient.servo_text("ServoP", np.array([-500.0, 100.0, 200.25, 150.0, 0.0, 90.0]), 0.03, 50.0, 500.0)
    assert text == "ServoP(-500,100,200.25,150,0,90,t=0.03,aheadtime=50,gain=500)"
    cmd = dobot.parse_command(text)
    assert cmd.key == "servop" and len(cmd.args) == 6 and cmd.named["t"] == 0.03
    with pytest.raises(ProtocolError):
        DobotClient.servo_text("ServoP", np.array([np.nan, 0, 0, 0, 0, 0]), 0.03, 50.0, 500.0)
