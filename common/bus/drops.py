"""The count of payloads dropped because they did not decode, per key."""

from __future__ import annotations

import logging
import threading

log = logging.getLogger("bagit.bus")


class DropCounters:
    """Thread-safe count of payloads dropped per key, with the last reason. Logs the first few
    and then every 100th per key, so a flood of garbage cannot flood the log."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: dict[str, int] = {}
        self._last: dict[str, str] = {}

    def add(self, key: str, reason: str) -> int:
        with self._lock:
            n = self._counts.get(key, 0) + 1
            self._counts[key] = n
            self._last[key] = reason
        if n <= 5 or n % 100 == 0:
            log.warning("dropped payload #%d on %s: %s", n, key, reason)
        return n

    def count(self, key: str | None = None) -> int:
        """Drops on `key`, or on every key if None."""
        with self._lock:
            return sum(self._counts.values()) if key is None else self._counts.get(key, 0)

    def last_reason(self, key: str) -> str | None:
        with self._lock:
            return self._last.get(key)

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)


DROPS = DropCounters()  # process-wide; every subscriber also counts its own
