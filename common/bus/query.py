"""Queries: a typed queryable (Server), a typed request, and the rig's run control on top."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any, Generic, TypeVar

import zenoh

from bagit.common import wire
from bagit.common.bus.drops import DROPS, DropCounters
from bagit.common.bus.keys import CONTROL, Keys, QoS
from bagit.common.bus.pubsub import encoding_for, matching, payload_bytes
from bagit.common.errors import BadMessage, BagItError, BusError, first_line
from bagit.common.messages import Message, RunControl, RunControlReply

log = logging.getLogger("bagit.bus")

M = TypeVar("M", bound=Message)
R = TypeVar("R", bound=Message)


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
            req = wire.decode(payload_bytes(query) or b"", self.req_type)
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
            return first_line(e)
        except Exception as e:  # noqa: BLE001
            log.exception("handler on %s failed", self.key)
            return f"internal error: {type(e).__name__}: {first_line(e)}"
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

    def __enter__(self) -> Server[M, R]:
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
        while not matching(querier) and time.monotonic() < deadline:
            time.sleep(0.005)
        if not matching(querier):
            raise BusError(f"no answer on {key} within {timeout:g} s: nobody serves it (is the run coordinator up?)")
        replies = list(querier.get(payload=wire.encode(req), encoding=encoding_for(type(req))))
    finally:
        querier.undeclare()
    for reply in replies:
        if reply.ok is not None:
            try:
                return wire.decode(payload_bytes(reply.ok) or b"", rep_type)
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
