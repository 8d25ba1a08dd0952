"""Liveliness: a token per running service, and a watcher of which services of a rig are alive."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from bagit.common.bus.keys import Keys

log = logging.getLogger("bagit.bus")


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

    def __enter__(self) -> LivelinessWatcher:
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()
