"""Refusing to servo on a SOI that is missing, stale or implausible: command zero and say why.

The controller never extrapolates a SOI it does not have: a held tick commands zero and the
Broyden estimate does not learn across the gap.
"""

from __future__ import annotations

import numpy as np

MAX_POINT_SPEED_MPS = 1.0  # no rim point moves faster than this; a faster jump is a perception glitch
JUMP_SLACK_M = 0.01  # plus this much, for the camera's noise and the points sliding along the rim


class SoiGuard:
    """Vets each SOI `(n_x, 3)` before it is servoed on.

    timeout_s: no SOI for longer than this -> hold ('stopped arriving'); max_age_s: a SOI whose
    source stamp (the camera frame's time) is older than this -> hold ('stale'); max_speed_mps: a
    point moving faster than this between consecutive SOIs -> hold ('jumped').
    """

    def __init__(
        self,
        timeout_s: float = 0.25,
        max_age_s: float = 0.3,
        max_speed_mps: float = MAX_POINT_SPEED_MPS,
        n_x: int | None = None,
    ):
        self.timeout_s = timeout_s
        self.max_age_s = max_age_s
        self.max_speed = max_speed_mps
        self.n_x = n_x
        self._last: np.ndarray | None = None
        self._last_t: float | None = None

    def check(self, x: np.ndarray | None, now: float, source_stamp: float | None = None) -> str | None:
        """None if `x (n_x, 3)` may be servoed on at time `now` (s), else the reason to hold."""
        if x is None:
            if self._last_t is None:
                return "no SOI received"
            if now - self._last_t > self.timeout_s:
                return f"SOI stopped arriving {now - self._last_t:.2f} s ago"
            return "no new SOI this tick"
        x = np.asarray(x, dtype=float)
        if x.ndim != 2 or x.shape[1] != 3 or (self.n_x is not None and x.shape[0] != self.n_x):
            return f"SOI has shape {x.shape}, expected ({self.n_x if self.n_x else 'n_x'}, 3)"
        if not np.all(np.isfinite(x)):
            return "SOI has NaN or infinite points"
        if source_stamp is not None:
            age = now - source_stamp
            if not np.isfinite(age) or age > self.max_age_s:
                return f"SOI is stale ({age:.2f} s old)"
        if self._last is not None and self._last.shape == x.shape and self._last_t is not None:
            dt = max(now - self._last_t, 1e-3)
            jump = float(np.linalg.norm(x - self._last, axis=1).max())
            if jump > self.max_speed * dt + JUMP_SLACK_M:
                # Take it as the new reference: one held tick per jump, so a real (if fast) change of
                # the SOI passes on the next tick instead of locking the controller out for good.
                self._last, self._last_t = x.copy(), now
                return f"SOI jumped {jump * 100:.1f} cm in {dt * 1e3:.0f} ms: implausible"
        self._last, self._last_t = x.copy(), now
        return None
