"""Latest-wins hand-over from the receive threads to the render thread.

A Zenoh callback must return at once (a slow subscriber on a reliable key would stall its
publisher), so it only drops the message in a slot. The render thread takes what is due: each
slot at most once per its minimum period, and a newer message simply replaces an older one that
was never drawn (counted as coalesced). Memory is one message per slot, whatever the rates.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any


@dataclass
class Item:
    """One message waiting in a slot, with the monotonic time it arrived."""

    value: Any
    received: float


@dataclass
class SlotStats:
    received: int = 0
    coalesced: int = 0  # replaced before being drawn
    taken: int = 0
    last_taken: float = field(default=-float("inf"))


class LatestSlots:
    """Per-key mailboxes of size one with a per-key minimum period between takes."""

    def __init__(self, min_period_s: dict[str, float] | None = None, default_period_s: float = 1 / 30,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._periods = dict(min_period_s or {})
        self._default = default_period_s
        self._clock = clock
        self._lock = threading.Lock()
        self._pending: dict[str, Item] = {}
        self._stats: dict[str, SlotStats] = {}
        self.wake = threading.Event()

    def period(self, key: str) -> float:
        prefix = key.split(":", 1)[0]  # "arm:left" shares the "arm" period
        return self._periods.get(key, self._periods.get(prefix, self._default))

    def put(self, key: str, value: Any) -> None:
        """Leave `value` for the render thread; O(1), never blocks on drawing."""
        now = self._clock()
        with self._lock:
            st = self._stats.setdefault(key, SlotStats())
            st.received += 1
            if key in self._pending:
                st.coalesced += 1
            self._pending[key] = Item(value, now)
        self.wake.set()

    def take_due(self, force: bool = False, hold: tuple[str, ...] = ()) -> dict[str, Item]:
        """The pending items whose slot's period has passed since its last take (all with force); slots
        whose key (or its prefix before ':') is in `hold` keep their item for a later take."""
        now = self._clock()
        out: dict[str, Item] = {}
        with self._lock:
            for key in list(self._pending):
                st = self._stats[key]
                if not force and key.split(":", 1)[0] in hold:
                    continue
                if force or now - st.last_taken >= self.period(key):
                    out[key] = self._pending.pop(key)
                    st.taken += 1
                    st.last_taken = now
            if not self._pending:
                self.wake.clear()
        return out

    def next_due_in(self, hold: tuple[str, ...] = ()) -> float | None:
        """Seconds until the earliest pending slot (not held, see `take_due`) is due (0 if one is), None if nothing waits."""
        now = self._clock()
        with self._lock:
            keys = [k for k in self._pending if k.split(":", 1)[0] not in hold]
            if not keys:
                return None
            return max(0.0, min(self._stats[k].last_taken + self.period(k) - now for k in keys))

    def stats(self) -> dict[str, dict[str, int]]:
        with self._lock:
            return {k: {"received": s.received, "coalesced": s.coalesced, "taken": s.taken} for k, s in self._stats.items()}
