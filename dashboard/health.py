"""Service health: which services hold a liveliness token, and how fast their streams arrive.

Liveliness says up or down (a crashed service disappears within its link lease); the rates and
last-seen times come from the messages the dashboard itself receives, per stream (the key under
bagit/<rig>/, e.g. "perception/soi"). A service that goes away raises a warning that stays until
it comes back.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

RATE_WINDOW_S = 2.0
_MAX_ARRIVALS = 1024  # bounds memory at any rate: 512 Hz over the window


@dataclass
class ServiceRow:
    service: str
    up: bool
    since_s: float  # seconds since it last changed
    streams: list[str]


@dataclass
class StreamRow:
    stream: str
    rate_hz: float
    last_seen_s: float  # seconds ago
    count: int


class HealthBoard:
    """Thread-safe record of liveliness changes and stream arrivals (clock injectable for tests)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic, window_s: float = RATE_WINDOW_S) -> None:
        self._clock = clock
        self._window = window_s
        self._lock = threading.Lock()
        self._services: dict[str, tuple[bool, float]] = {}
        self._arrivals: dict[str, deque[float]] = {}
        self._counts: dict[str, int] = {}
        self._lost: dict[str, float] = {}  # services that went away: when

    def note(self, stream: str) -> None:
        """One message arrived on `stream`."""
        now = self._clock()
        with self._lock:
            q = self._arrivals.get(stream)
            if q is None:
                q = self._arrivals[stream] = deque(maxlen=_MAX_ARRIVALS)
            q.append(now)
            self._counts[stream] = self._counts.get(stream, 0) + 1

    def service_changed(self, service: str, alive: bool) -> bool:
        """Record a liveliness change; True when it is a loss worth a warning."""
        now = self._clock()
        with self._lock:
            was = self._services.get(service)
            self._services[service] = (alive, now)
            if alive:
                self._lost.pop(service, None)
                return False
            lost = was is not None and was[0]
            if lost:
                self._lost[service] = now
            return lost

    def _rate(self, q: deque[float], now: float) -> float:
        recent = [t for t in q if now - t <= self._window]
        if len(recent) < 2:
            return 0.0
        span = max(now - recent[0], 1e-9)
        return (len(recent) - 1) / span if span > 0 else 0.0

    def streams(self) -> list[StreamRow]:
        now = self._clock()
        with self._lock:
            return [
                StreamRow(s, self._rate(q, now), now - q[-1], self._counts[s])
                for s, q in sorted(self._arrivals.items())
            ]

    def services(self) -> list[ServiceRow]:
        now = self._clock()
        with self._lock:
            streams = sorted(self._arrivals)
            rows = []
            for name, (up, t) in sorted(self._services.items()):
                own = [s for s in streams if _owns(name, s)]
                rows.append(ServiceRow(name, up, now - t, own))
            return rows

    def warnings(self) -> list[str]:
        now = self._clock()
        with self._lock:
            return [f"{s} went away {now - t:.0f} s ago" for s, t in sorted(self._lost.items())]

    def is_up(self, service: str) -> bool | None:
        with self._lock:
            v = self._services.get(service)
            return None if v is None else v[0]


def _owns(service: str, stream: str) -> bool:
    """Whether `service` publishes `stream`, by the key's first chunk: perception -> perception/soi;
    arm_driver or arm-left -> arm/left/state; a run coordinator ("run...") -> run/state."""
    head = stream.split("/", 1)[0]
    s = service.replace("-", "_")
    return s == head or s.startswith(head + "_") or (head == "camera" and s in ("sim", "camera"))


def health_markdown(board: HealthBoard) -> str:
    """The health panel: services with their streams' rates, then the stream table."""
    rates = {r.stream: r for r in board.streams()}
    lines = ["| service | state | for | streams |", "|---|---|---|---|"]
    services = board.services()
    for r in services:
        state = "up" if r.up else "**DOWN**"
        streams = ", ".join(f"{s} {rates[s].rate_hz:.0f} Hz" for s in r.streams if s in rates) or "-"
        lines.append(f"| {r.service} | {state} | {_ago(r.since_s)} | {streams} |")
    if not services:
        lines.append("| (no liveliness tokens seen) | | | |")
    lines += ["", "| stream | rate | last seen | count |", "|---|---|---|---|"]
    for s in rates.values():
        lines.append(f"| {s.stream} | {s.rate_hz:.1f} Hz | {_ago(s.last_seen_s)} ago | {s.count} |")
    if not rates:
        lines.append("| (nothing received yet) | | | |")
    return "\n".join(lines)


def _ago(s: float) -> str:
    if s < 60:
        return f"{s:.1f} s"
    if s < 3600:
        return f"{s / 60:.0f} min"
    return f"{s / 3600:.1f} h"
