"""Typed publishers and subscribers: one message type per key, with that key's QoS.

A payload that does not decode to the expected message of this schema version is logged,
counted per key and dropped: it never reaches a callback and never raises in a Zenoh thread.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any, Generic, TypeVar

import zenoh

from bagit.common import wire
from bagit.common.bus.drops import DROPS, DropCounters
from bagit.common.bus.keys import Keys, QoS
from bagit.common.errors import BadMessage, BusError, first_line
from bagit.common.messages import SCHEMA_VERSION, Message

log = logging.getLogger("bagit.bus")

M = TypeVar("M", bound=Message)


def _default_qos(key: str, msg_type: type[Message], lockstep: bool = False) -> QoS:
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != "bagit":
        raise BusError(f"key {key!r} is outside bagit/<rig>/...; pass qos= explicitly")
    spec = Keys(parts[1]).spec(key)
    if spec is None or spec.qos is None:
        raise BusError(f"key {key!r} is not in the key table; pass qos= explicitly")
    if spec.message is not msg_type:
        raise BusError(f"key {key!r} carries {spec.message.__name__ if spec.message else 'no message'}, not {msg_type.__name__}")
    return spec.qos.reliable() if lockstep and spec.lockstep else spec.qos


def encoding_for(msg_type: type[Message]) -> zenoh.Encoding:
    """application/octet-stream tagged with the message kind and schema version (visible to zenoh tools)."""
    return zenoh.Encoding("application/octet-stream").with_schema(f"bagit.{msg_type.KIND}.v{SCHEMA_VERSION}")


class Publisher(Generic[M]):
    """Puts messages of one type on one key with that key's QoS (from KEY_TABLE unless given; with
    `lockstep`, a key a lockstep step waits on goes reliable and blocking: `KeySpec.lockstep`)."""

    def __init__(self, session: zenoh.Session, key: str, msg_type: type[M], qos: QoS | None = None, lockstep: bool = False) -> None:
        self.key = key
        self.msg_type = msg_type
        self.qos = qos or _default_qos(key, msg_type, lockstep)
        self.sent = 0
        self._pub = session.declare_publisher(key, encoding=encoding_for(msg_type), **self.qos.publisher_kwargs())

    @property
    def matched(self) -> bool:
        """True once some subscriber matches this key (puts before that reach no one)."""
        return matching(self._pub)

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

    def __enter__(self) -> Publisher[M]:
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()


class _Typed(Generic[M]):
    """Decodes samples on one key as `msg_type`; anything else is logged, counted (`dropped`, and per key
    in `counters`) and dropped."""

    def __init__(self, key: str, msg_type: type[M], counters: DropCounters) -> None:
        self.key = key
        self.msg_type = msg_type
        self.counters = counters
        self.received = 0
        self.dropped = 0
        self.last_error: str | None = None
        self._lock = threading.Lock()

    def _decode(self, sample: zenoh.Sample) -> M | None:
        if sample.kind != zenoh.SampleKind.PUT:
            return None
        key = str(sample.key_expr)
        try:
            raw = payload_bytes(sample) or b""
            msg = wire.decode(raw, self.msg_type)
        except BadMessage as e:
            reason = str(e)
        except Exception as e:  # noqa: BLE001 - a hostile payload must never kill the Zenoh thread
            reason = f"undecodable payload: {type(e).__name__}: {first_line(e)}"
        else:
            with self._lock:
                self.received += 1
            return msg
        with self._lock:
            self.dropped += 1
            self.last_error = reason
        self.counters.add(key, reason)
        return None


class Subscriber(_Typed[M]):
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
        super().__init__(key, msg_type, counters)
        self.callback = callback
        self.callback_errors = 0
        self._sub = session.declare_subscriber(key, self._on_sample)

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

    def __enter__(self) -> Subscriber[M]:
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


class Polled(_Typed[M]):
    """Samples on `key` that Zenoh keeps in a ring of the last `capacity` (older ones dropped) until the
    owner takes them (`take`, `latest`): no Python thread is woken per sample, where a `Subscriber`
    wakes one for each (about a fifth of a millisecond of CPU here). For what a loop reads at its own
    pace (a display's plots, a value read once a run has ended), never for what a step waits on."""

    def __init__(self, session: zenoh.Session, key: str, msg_type: type[M], capacity: int, counters: DropCounters = DROPS) -> None:
        super().__init__(key, msg_type, counters)
        self._last: M | None = None
        self._sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(capacity))

    def take(self) -> list[M]:
        """The good messages that came since the last take, oldest first (at most `capacity`)."""
        out: list[M] = []
        while True:
            try:
                sample = self._sub.try_recv()
            except zenoh.ZError:  # undeclared: nothing more comes
                break
            if sample is None:
                break
            msg = self._decode(sample)
            if msg is not None:
                out.append(msg)
        if out:
            self._last = out[-1]
        return out

    def latest(self) -> M | None:
        """The newest good message so far (None: none yet)."""
        self.take()
        return self._last

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass


def payload_bytes(sample_or_query: Any) -> bytes | None:
    p = sample_or_query.payload
    return None if p is None else p.to_bytes()


def matching(entity: Any) -> bool:
    try:
        status = entity.matching_status  # a MatchingStatus in 1.10 (typed as bool in the stubs)
    except zenoh.ZError:
        return False
    return bool(getattr(status, "matching", status))
