"""Refusing to servo on a SOI that is missing, stale or implausible: command zero and say why."""

from __future__ import annotations

import numpy as np

MAX_POINT_SPEED_MPS = 1.0  # no rim point moves faster than this; a faster jump is a perception glitch


class SoiGuard:
    def __init__(self, timeout_s: float = 0.25, max_age_s: float = 0.3, max_speed_mps: float = MAX_POINT_SPEED_MPS):
        self.timeout_s = timeout_s
        self.max_age_s = max_age_s
        self.max_speed = max_speed_mps
        self._last: np.ndarray | None = None
        self._last_t: float | None = None

    def check(self, x: np.ndarray | None, now: float, source_stamp: float | None = None) -> str | None:
        """None if `x (n_x, 3)` may be servoed on at time `now`, else the reason to hold."""
        if x is None:
            if self._last_t is None or now - self._last_t > self.timeout_s:
                return "no SOI received" if self._last_t is None else f"SOI stopped arriving {now - self._last_t:.2f} s ago"
            return "no new SOI this tick"
        x = np.asarray(x, dtype=float)
        if not np.all(np.isfinite(x)):
            return "SOI has NaN or infinite points"
        if source_stamp is not None and now - source_stamp > self.max_age_s:
            return f"SOI is stale ({now - source_stamp:.2f} s old)"
        if self._last is not None and self._last.shape == x.shape and self._last_t is not None:
            dt = max(now - self._last_t, 1e-3)
            jump = float(np.linalg.norm(x - self._last, axis=1).max())
            if jump > self.max_speed * dt + 0.01:
                self._last, self._last_t = x.copy(), now  # one held tick per jump; a real move then passes
                return f"SOI jumped {jump * 100:.1f} cm in {dt * 1e3:.0f} ms: implausible"
        self._last, self._last_t = x.copy(), now
        return None
