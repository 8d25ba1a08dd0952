"""Bounded time series behind the live plots.

Samples are appended on the receive thread (O(1)); the render thread reads a copy as arrays a few
times a second. Time is seconds since the first sample of the current run (message stamps, so the
plot shows when things happened, not when they arrived); a new run id starts the plot afresh.
"""

from __future__ import annotations

import threading
from collections import deque

import numpy as np

DEFAULT_CAPACITY = 1800  # one minute at 30 Hz


class Series:
    """Columns sharing one time axis; None values are stored as NaN (gaps in the plot)."""

    def __init__(self, columns: tuple[str, ...], capacity: int = DEFAULT_CAPACITY) -> None:
        self.columns = columns
        self._rows: deque[tuple[float, ...]] = deque(maxlen=capacity)
        self._lock = threading.Lock()
        self._t0: float | None = None
        self._run: str | None = None
        self.version = 0  # bumps on every change, so the renderer skips unchanged plots

    def add(self, stamp: float, values: tuple[float | None, ...], run_id: str | None = None) -> None:
        with self._lock:
            if run_id is not None and run_id != self._run:
                self._rows.clear()
                self._t0 = None
                self._run = run_id
            if self._t0 is None:
                self._t0 = stamp
            row = (stamp - self._t0,) + tuple(np.nan if v is None else float(v) for v in values)
            if self._rows and row[0] < self._rows[-1][0]:
                return  # out-of-order sample: the plot's time axis must increase
            self._rows.append(row)
            self.version += 1

    def clear(self) -> None:
        with self._lock:
            self._rows.clear()
            self._t0 = None
            self.version += 1

    def arrays(self) -> tuple[np.ndarray, ...]:
        """(t, column_1, ...) as float64 arrays of equal length."""
        with self._lock:
            if not self._rows:
                return tuple(np.zeros(0) for _ in range(len(self.columns) + 1))
            a = np.asarray(self._rows, dtype=float)
        return tuple(a[:, i] for i in range(a.shape[1]))

    def __len__(self) -> int:
        with self._lock:
            return len(self._rows)

    def last(self) -> tuple[float, ...] | None:
        with self._lock:
            return self._rows[-1] if self._rows else None
