"""Malformed payloads on the bus are logged, counted per key and dropped; they never reach a
callback, never kill the subscriber, and good messages keep flowing after them."""

from __future__ import annotations

import json
import logging
import struct

import numpy as np
import pytest
from bus_support import wait_until

from bagit.common import wire
from bagit.common.bus import DropCounters, Keys, LatestCache, Publisher, Subscriber, request_run_control, serve_run_control
from bagit.common.messages import ArmState, RunControl, RunControlReply, SoiState


def _rewrite_header(payload: bytes, edit) -> bytes:
    """Decode the JSON header of a wire payload, let `edit` change it, and re-frame it."""
    (hlen,) = struct.unpack("<I", payload[4:8])
    header = json.loads(payload[8 : 8 + hlen])
    edit(header)
    h = json.dumps(header).encode()
    return payload[:4] + struct.pack("<I", len(h)) + h + payload[8 + hlen :]


def _malformed(good_soi: bytes, good_arm: bytes) -> dict[str, bytes]:
    def wrong_version(h):
        h["v"] = 99

    def huge_shape(h):
        h["arrays"]["rim"]["shape"] = [2**30, 3]

    def lying_length(h):
        h["arrays"]["rim"]["nbytes"] = 10**9

    def bad_dtype(h):
        h["arrays"]["rim"]["dtype"] = "|O"

    def nan_field(h):
        h["fields"]["inlier_fraction"] = "lots"

    return {
        "empty": b"",
        "garbage": b"\x00\xffnot a bagit message at all",
        "magic only": b"BGT1",
        "header length beyond payload": b"BGT1" + struct.pack("<I", 10**6) + b"{}",
        "header not json": b"BGT1" + struct.pack("<I", 5) + b"{{{{{",
        "wrong kind": good_arm,
        "wrong schema version": _rewrite_header(good_soi, wrong_version),
        "truncated arrays": good_soi[:-40],
        "huge declared shape": _rewrite_header(good_soi, huge_shape),
        "array length beyond payload": _rewrite_header(good_soi, lying_length),
        "object dtype": _rewrite_header(good_soi, bad_dtype),
        "invalid field": _rewrite_header(good_soi, nan_field),
    }


def test_malformed_payloads_are_dropped_and_counted(pair, caplog):
    a, b = pair
    keys = Keys("bad")
    good = SoiState(seq=1, rim=np.arange(24, dtype=float).reshape(8, 3))
    good_arm = ArmState(arm="left", q=np.zeros(6), qd=np.zeros(6), tool_pose=np.zeros(6))
    bad = _malformed(wire.encode(good), wire.encode(good_arm))

    counters = DropCounters()
    got: list[SoiState] = []
    sub = Subscriber(b, keys.perception_soi, SoiState, got.append, counters=counters)
    cache = LatestCache(b, keys.perception_soi, SoiState, counters=counters)
    pub = Publisher(a, keys.perception_soi, SoiState)
    assert wait_until(lambda: pub.matched)

    with caplog.at_level(logging.WARNING, logger="bagit.bus"):
        for payload in bad.values():
            a.put(keys.perception_soi, payload)
        pub.put(good)  # a good one after the garbage still arrives
        # both subscribers hear every sample, each in its own time: wait for the two
        assert wait_until(lambda: len(got) == 1 and sub.dropped == len(bad) and cache.get() is not None and cache.dropped == len(bad)), \
            (len(got), sub.dropped, cache.received, cache.dropped)

    assert got[0].seq == 1 and np.array_equal(got[0].rim, good.rim)
    assert sub.received == 1 and cache.received == 1
    assert cache.get().seq == 1  # the cache never held a malformed value
    # both subscribers counted every bad payload under the key it came on
    assert counters.count(keys.perception_soi) == 2 * len(bad)
    assert counters.snapshot() == {keys.perception_soi: 2 * len(bad)}
    assert counters.last_reason(keys.perception_soi)
    assert any("dropped payload" in r.getMessage() for r in caplog.records)
    # rate-limited logging: 5 first drops per key, then every 100th
    assert sum("dropped payload" in r.getMessage() for r in caplog.records) <= 2 * len(bad)


@pytest.mark.parametrize(
    "payload, reason",
    [
        (b"junk", "bad magic"),
        ("wrong_version", "schema version 99"),
        ("truncated", "do not match shape"),
        ("huge", "do not match shape"),
    ],
)
def test_drop_reason_is_recorded(pair, payload, reason):
    a, b = pair
    keys = Keys("why")
    good = wire.encode(SoiState(rim=np.zeros((8, 3))))
    payload = {
        "wrong_version": _rewrite_header(good, lambda h: h.update(v=99)),
        "truncated": good[:-16],
        "huge": _rewrite_header(good, lambda h: h["arrays"]["rim"].update(shape=[2**30, 3])),
    }.get(payload, payload)
    got: list = []
    sub = Subscriber(b, keys.perception_soi, SoiState, got.append, counters=DropCounters())
    pub = Publisher(a, keys.perception_soi, SoiState)
    assert wait_until(lambda: pub.matched)
    a.put(keys.perception_soi, payload)
    assert wait_until(lambda: sub.dropped == 1)
    assert reason in sub.last_error and got == []


def test_delete_samples_are_ignored(pair):
    a, b = pair
    keys = Keys("del")
    got: list = []
    pub = Publisher(a, keys.perception_soi, SoiState)
    sub = Subscriber(b, keys.perception_soi, SoiState, got.append, counters=DropCounters())
    assert wait_until(lambda: pub.matched)
    a.delete(keys.perception_soi)
    pub.put(SoiState(rim=np.zeros((4, 3))))
    assert wait_until(lambda: len(got) == 1)
    assert sub.dropped == 0 and sub.received == 1


def test_malformed_run_control_gets_a_refusal(pair):
    a, b = pair
    keys = Keys("badq")
    calls: list = []
    srv = serve_run_control(b, keys, lambda r: calls.append(r) or RunControlReply(accepted=True))
    assert request_run_control(a, keys, RunControl(action="reset"), timeout=3.0).accepted
    replies = list(a.get(keys.run_control, payload=b"BGT1garbage", timeout=3.0))
    assert len(replies) == 1 and replies[0].ok is not None
    rep = wire.decode(replies[0].ok.payload.to_bytes(), RunControlReply)
    assert not rep.accepted and rep.reason.startswith("bad request")
    assert len(calls) == 1 and srv.dropped == 1
