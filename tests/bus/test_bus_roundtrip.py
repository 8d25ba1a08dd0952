"""Bus round trips between two in-process Zenoh peers on loopback: every message model on its own
key with its own QoS, latest-value caches, run-control queries and the e-stop."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zenoh
from bus_support import assert_same_message, example_message, wait_until

from bagit.common.bus import (
    KEY_TABLE,
    DropCounters,
    Keys,
    LatestCache,
    Polled,
    Publisher,
    Server,
    Subscriber,
    request,
    request_run_control,
    serve_run_control,
)
from bagit.common.errors import BagItError, BusError
from bagit.common.messages import MESSAGE_TYPES, ArmState, ControllerStatus, EStop, RunControl, RunControlReply, SoiState


def _key_for(keys: Keys, msg_type) -> str:
    row = next(r for r in KEY_TABLE if r.message is msg_type)
    return f"{keys.prefix}/{row.key.replace('*', 'right')}"


def _pub_kinds() -> list[str]:
    return sorted(k for k, t in MESSAGE_TYPES.items() if any(r.message is t and r.kind == "pub" for r in KEY_TABLE))


def test_every_message_type_has_a_key_in_the_table():
    carried = {r.message for r in KEY_TABLE if r.message is not None}
    assert set(MESSAGE_TYPES.values()) - {RunControlReply} <= carried, "a message model without a key"


@pytest.mark.parametrize("kind", _pub_kinds())
def test_round_trip_on_its_key(pair, kind):
    a, b = pair
    keys = Keys("roundtrip")
    msg = example_message(kind)
    key = _key_for(keys, type(msg))
    got: list = []
    sub = Subscriber(b, key, type(msg), got.append)
    pub = Publisher(a, key, type(msg))
    assert wait_until(lambda: pub.matched)
    for _ in range(3):
        pub.put(msg)
    assert wait_until(lambda: len(got) == 3)
    for m in got:
        assert_same_message(msg, m)
    assert sub.dropped == 0 and sub.received == 3 and pub.sent == 3


def test_run_control_request_and_reply_round_trip(pair):
    a, b = pair
    keys = Keys("rc")
    seen: list[RunControl] = []

    def handler(req: RunControl) -> RunControlReply:
        seen.append(req)
        if req.action == "start" and len(seen) > 1:
            raise BusError("a run is in progress")
        return RunControlReply(accepted=True, run_id="run-1")

    srv = serve_run_control(b, keys, handler)
    req = example_message("run_control")
    rep = request_run_control(a, keys, req, timeout=3.0)
    assert rep.accepted and rep.run_id == "run-1"
    assert_same_message(req, seen[0])
    # a BagItError in the handler becomes a refusal with its reason, not a dead queryable
    rep2 = request_run_control(a, keys, req, timeout=3.0)
    assert not rep2.accepted and rep2.reason == "a run is in progress"
    rep3 = request_run_control(a, keys, RunControl(action="reset"), timeout=3.0)
    assert rep3.accepted
    assert srv.served == 2


def test_run_control_reply_model_round_trips_through_a_query(pair):
    a, b = pair
    keys = Keys("rc2")
    reply = example_message("run_control_reply")
    serve_run_control(b, keys, lambda req: reply)
    back = request_run_control(a, keys, RunControl(action="stop"), timeout=3.0)
    assert_same_message(reply, back)


def test_handler_crash_is_a_refusal_not_a_crash(pair):
    a, b = pair
    keys = Keys("rc3")

    def handler(req):
        raise ZeroDivisionError("boom")

    serve_run_control(b, keys, handler)
    rep = request_run_control(a, keys, RunControl(action="start"), timeout=3.0)
    assert not rep.accepted and "internal error" in rep.reason


def test_request_without_a_coordinator_raises_bus_error(pair):
    a, _ = pair
    with pytest.raises(BusError, match="no answer"):
        request_run_control(a, Keys("nobody"), RunControl(action="start"), timeout=0.3)


def test_generic_server_without_on_bad_replies_with_zenoh_error(pair):
    a, b = pair
    key = "bagit/gen/run/control"
    srv = Server(b, key, RunControl, RunControlReply, lambda r: RunControlReply(accepted=True))
    assert request(a, key, RunControl(action="stop"), RunControlReply, timeout=3.0).accepted
    # the wrong request type gets a Zenoh error reply, which `request` turns into a BusError with the reason
    with pytest.raises(BusError, match="bad request: expected a 'run_control' message"):
        request(a, key, EStop(), RunControlReply, timeout=3.0)
    replies = list(a.get(key, payload=b"not a message", timeout=3.0))
    assert len(replies) == 1 and replies[0].err is not None
    assert "bad magic" in replies[0].err.payload.to_string()
    assert srv.dropped == 2 and srv.served == 1


def test_estop_is_delivered_reliable_real_time_express(pair):
    a, b = pair
    keys = Keys("es")
    samples: list[zenoh.Sample] = []
    raw = b.declare_subscriber(keys.estop, samples.append)
    got: list[EStop] = []
    Subscriber(b, keys.estop, EStop, got.append)
    pub = Publisher(a, keys.estop, EStop)
    assert pub.qos.priority == "real_time" and pub.qos.express and pub.qos.reliability == "reliable"
    assert wait_until(lambda: pub.matched)
    pub.put(EStop(source="test", reason="hand in the workspace"))
    assert wait_until(lambda: len(got) == 1 and len(samples) == 1)
    assert got[0].engage and got[0].reason == "hand in the workspace"
    s = samples[0]
    assert s.priority == zenoh.Priority.REAL_TIME
    assert s.express is True
    assert s.congestion_control == zenoh.CongestionControl.BLOCK
    raw.undeclare()


def test_estop_overtakes_a_frame_flood(pair):
    """With the camera pushing large frames, an e-stop still arrives promptly."""
    a, b = pair
    keys = Keys("flood")
    frames: list = []
    stops: list[float] = []
    Subscriber(b, keys.camera_rgbd, type(example_message("rgbd")), frames.append)
    Subscriber(b, keys.estop, EStop, lambda m: stops.append(time.monotonic()))
    cam = Publisher(a, keys.camera_rgbd, type(example_message("rgbd")))
    es = Publisher(a, keys.estop, EStop)
    assert wait_until(lambda: cam.matched and es.matched)
    big = type(example_message("rgbd"))(color=np.zeros((480, 640, 3), np.uint8), depth=np.zeros((480, 640), np.uint16))
    stop_flood = threading.Event()

    def flood():
        while not stop_flood.is_set():
            cam.put(big)

    t = threading.Thread(target=flood, daemon=True)
    t.start()
    try:
        assert wait_until(lambda: len(frames) >= 2)
        t0 = time.monotonic()
        es.put(EStop(source="test"))
        assert wait_until(lambda: len(stops) == 1)  # through while the frames still flood: not queued behind them
        assert stops[0] >= t0 and t.is_alive() and not stop_flood.is_set()  # its latency under a flood: bench/zenoh.py
    finally:
        stop_flood.set()
        t.join(5)


def test_latest_cache_keeps_newest_per_arm_with_age(pair):
    a, b = pair
    keys = Keys("cache")
    cache = LatestCache(b, keys.arm_state_any, ArmState)
    assert cache.get() is None and cache.age() == float("inf")
    left = Publisher(a, keys.arm_state("left"), ArmState)
    right = Publisher(a, keys.arm_state("right"), ArmState)
    assert wait_until(lambda: left.matched and right.matched)
    t_before = time.monotonic()
    for i in range(5):
        left.put(ArmState(arm="left", command_id=i, q=np.full(6, i), qd=np.zeros(6), tool_pose=np.zeros(6)))
    right.put(ArmState(arm="right", command_id=99, q=np.zeros(6), qd=np.zeros(6), tool_pose=np.zeros(6)))
    assert wait_until(lambda: len(cache.items()) == 2 and cache.get(keys.arm_state("left")).command_id == 4)
    assert cache.get(keys.arm_state("right")).command_id == 99
    msg, t_recv = cache.get_with_time(keys.arm_state("left"))
    assert t_recv >= t_before and 0 <= cache.age(keys.arm_state("left")) <= time.monotonic() - t_before
    # wait(newer_than=...) blocks until something fresher arrives
    assert cache.wait(0.05, key=keys.arm_state("left"), newer_than=time.monotonic()) is None
    left.put(ArmState(arm="left", command_id=5, q=np.zeros(6), qd=np.zeros(6), tool_pose=np.zeros(6)))
    assert cache.wait(2.0, key=keys.arm_state("left"), newer_than=t_recv).command_id == 5


def test_polled_keeps_the_last_messages_for_its_owner_in_order_and_drops_garbage(pair):
    a, b = pair
    keys = Keys("polled")
    counters = DropCounters()
    polled = Polled(b, keys.controller_status, ControllerStatus, 3, counters=counters)
    assert polled.take() == [] and polled.latest() is None
    pub = Publisher(a, keys.controller_status, ControllerStatus)
    assert wait_until(lambda: pub.matched)
    pub.put(ControllerStatus(seq=1))
    a.put(keys.controller_status, b"not a message")  # garbage: counted and dropped, never taken
    pub.put(ControllerStatus(seq=2))
    taken: list[int] = []
    assert wait_until(lambda: taken.extend(m.seq for m in polled.take()) or taken == [1, 2])
    assert polled.dropped == 1 and counters.count(keys.controller_status) == 1
    for i in range(3, 9):  # more than it keeps, with no one taking: the oldest go (no producer waits)
        pub.put(ControllerStatus(seq=i))
    assert wait_until(lambda: polled.latest() is not None and polled.latest().seq == 8)
    pub.put(ControllerStatus(seq=9))
    pub.put(ControllerStatus(seq=10))
    assert wait_until(lambda: taken.extend(m.seq for m in polled.take()) or taken[-1:] == [10])
    assert taken[2:] == [9, 10] and polled.latest().seq == 10  # in order, and the newest kept once taken
    polled.close()
    assert polled.take() == []  # undeclared: nothing more, no error


def test_callback_exception_does_not_stop_the_subscriber(pair):
    a, b = pair
    keys = Keys("cb")
    got: list[SoiState] = []

    def cb(m: SoiState) -> None:
        got.append(m)
        if m.seq == 0:
            raise RuntimeError("consumer bug")

    sub = Subscriber(b, keys.perception_soi, SoiState, cb)
    pub = Publisher(a, keys.perception_soi, SoiState)
    assert wait_until(lambda: pub.matched)
    pub.put(SoiState(seq=0, rim=np.zeros((4, 3))))
    pub.put(SoiState(seq=1, rim=np.zeros((4, 3))))
    assert wait_until(lambda: len(got) == 2)
    assert sub.callback_errors == 1 and sub.dropped == 0


def test_publisher_refuses_the_wrong_type_and_the_wrong_key(pair):
    a, _ = pair
    keys = Keys("types")
    with pytest.raises(BusError, match="carries SoiState"):
        Publisher(a, keys.perception_soi, ArmState)
    with pytest.raises(BusError, match="not in the key table"):
        Publisher(a, f"{keys.prefix}/somewhere/else", SoiState)
    pub = Publisher(a, keys.perception_soi, SoiState)
    with pytest.raises(BagItError):
        pub.put(ArmState(arm="left", q=np.zeros(6), qd=np.zeros(6), tool_pose=np.zeros(6)))  # type: ignore[arg-type]


def test_full_size_rgbd_frame_arrives_bit_exact(pair):
    a, b = pair
    keys = Keys("frame")
    rng = np.random.default_rng(3)
    frame = type(example_message("rgbd"))(
        seq=7, color=rng.integers(0, 255, (480, 640, 3), dtype=np.uint8), depth=rng.integers(0, 65535, (480, 640), dtype=np.uint16)
    )
    got: list = []
    Subscriber(b, keys.camera_rgbd, type(frame), got.append)
    pub = Publisher(a, keys.camera_rgbd, type(frame))
    assert wait_until(lambda: pub.matched)
    size = pub.put(frame)
    assert size < 480 * 640 * 5 + 4096  # raw bytes plus a small header, never JSON numbers
    assert wait_until(lambda: len(got) == 1)
    assert_same_message(frame, got[0])
