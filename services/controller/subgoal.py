"""Choosing the next subgoal g_next on the planned path from the current SOI."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from bagit.common.errors import BadControlInput


def rms_error(x: np.ndarray, g: np.ndarray) -> float:
    """RMS point distance between two SOIs `(n_x, 3)`."""
    return float(np.sqrt(np.mean(np.sum((np.asarray(x) - np.asarray(g)) ** 2, axis=-1))))


class SubgoalTracker:
    """Walks along path `(n_nodes, n_x, 3)`: advance when close enough to the current subgoal or when a
    later node is already nearer, but never past g† (dagger_index) before g† itself was reached, that
    is, `dagger_settle_ticks` updates after the SOI first came within tolerance of it (while the
    controller keeps the grippers still and the bag settles).

    `dagger_check(x)`, when given, must also hold of the SOI at the settle's end (the lift's start): if
    it does not, the settle is void, the controller servoes to g† again, and the next settle starts
    once the SOI is within tolerance and passes the check. Once `dagger_wait_ticks` updates have gone
    by since the first void settle, the next settle's end lifts whatever the check says (a bound on
    the time it may cost). A settle whose end passes the check is the same as without one."""

    def __init__(
        self,
        path: np.ndarray,
        dagger_index: int,
        subgoal_tol: float,
        goal_tol: float,
        stall_ticks: int = 45,
        dagger_settle_ticks: int = 0,
        dagger_check: Callable[[np.ndarray], bool] | None = None,
        dagger_wait_ticks: int = 0,
    ):
        self.path = np.asarray(path, dtype=float)
        if self.path.ndim != 3 or len(self.path) < 1 or self.path.shape[2] != 3:
            raise BadControlInput(f"path must have shape (n_nodes, n_x, 3), got {self.path.shape}")
        if not np.all(np.isfinite(self.path)):
            raise BadControlInput("path has NaN or infinite points")
        if not 0 <= dagger_index < len(self.path):
            raise BadControlInput(f"dagger_index {dagger_index} outside the path of {len(self.path)} nodes")
        self.dagger = dagger_index
        self.subgoal_tol = subgoal_tol
        self.goal_tol = goal_tol
        self.index = min(1, len(self.path) - 1)
        self.dagger_reached = dagger_index == 0
        # A node the bag cannot match exactly (the path's nodes are ideal ellipses) counts as reached
        # once the error to it stops improving for `stall_ticks` ticks while within 2x the tolerance.
        self.stall_ticks = stall_ticks
        self._best = np.inf
        self._since_best = 0
        if dagger_settle_ticks < 0:
            raise BadControlInput(f"dagger_settle_ticks must be >= 0, got {dagger_settle_ticks}")
        self.dagger_settle_ticks = dagger_settle_ticks
        self.settled_ticks = 0  # updates since the SOI first came within tolerance of g†
        if dagger_wait_ticks < 0:
            raise BadControlInput(f"dagger_wait_ticks must be >= 0, got {dagger_wait_ticks}")
        self.dagger_check = dagger_check
        self.dagger_wait_ticks = dagger_wait_ticks
        self.void_settles = 0  # settles at g† whose end failed dagger_check
        self._void_ticks = 0  # updates since the first of them

    def _reached(self, x: np.ndarray, k: int) -> bool:
        e = self.error(x, k)
        if e <= self.subgoal_tol:
            return True
        return self._since_best >= self.stall_ticks and e <= 2 * self.subgoal_tol

    def update(self, x: np.ndarray) -> int:
        """The index of g_next for the SOI `x (n_x, 3)`."""
        last = len(self.path) - 1
        if self.void_settles and not self.dagger_reached:
            self._void_ticks += 1
        e = self.error(x, self.index)
        if e < self._best - 1e-3:
            self._best, self._since_best = e, 0
        else:
            self._since_best += 1
        start = self.index
        settle_due = not self.dagger_reached  # the settle counts one update at g† at most once per call
        while self.index < last:
            if self.index == self.dagger and settle_due:
                self._settle_at_dagger(x)
                settle_due = False
            limit = last if self.dagger_reached else self.dagger
            close = self._reached(x, self.index)
            ahead = self.index + 1 <= limit and self.error(x, self.index + 1) < self.error(x, self.index)
            if (close or ahead) and self.index + 1 <= limit:
                self.index += 1
                self._best, self._since_best = np.inf, 0  # a stall on one node says nothing of the next
            else:
                break
        if self.index == self.dagger and settle_due:
            self._settle_at_dagger(x)
        if self.index != start:
            self._best, self._since_best = np.inf, 0
        return self.index

    def _settle_at_dagger(self, x: np.ndarray) -> None:
        """One update at g†: the settle starts when the SOI first comes within tolerance (after a void
        settle: and passes `dagger_check`) and then counts every update; g† is reached when it is over
        and the SOI passes the check, else the settle is void and the servoing to g† goes on."""
        if self.settled_ticks == 0 and not (self._reached(x, self.dagger) and (self.void_settles == 0 or self._lift_ok(x))):
            return
        self.settled_ticks += 1
        if self.settled_ticks > self.dagger_settle_ticks:
            if self._lift_ok(x):
                self.dagger_reached = True
            else:
                self.settled_ticks = 0
                self.void_settles += 1

    def _lift_ok(self, x: np.ndarray) -> bool:
        """May the lift start from the SOI `x (n_x, 3)`: no check, the check's wait over, or it holds."""
        if self.dagger_check is None or (self.void_settles > 0 and self._void_ticks >= self.dagger_wait_ticks):
            return True
        return bool(self.dagger_check(x))

    @property
    def settling(self) -> bool:
        """At g†, reached once, and the bag still settling before the lift."""
        return not self.dagger_reached and self.settled_ticks > 0

    def error(self, x: np.ndarray, k: int) -> float:
        """RMS error of `x` to node k once the node is slid along itself to match x (see `slide_to`)."""
        return rms_error(x, slide_to(self.path[k], x))

    @property
    def stage(self) -> str:
        return "bagging" if self.dagger_reached else "pre-bagging"

    def progress(self) -> float:
        """Share of the path behind g_next: index / (n_nodes - 1)."""
        return self.index / max(len(self.path) - 1, 1)

    def done(self, x: np.ndarray) -> bool:
        """At g*: within goal_tol, or as close as the bag gets (stalled within 2x the subgoal tolerance;
        the run is then judged on what the rim really does round the object)."""
        if not (self.dagger_reached and self.index == len(self.path) - 1):
            return False
        e = self.error(x, self.index)
        return e <= self.goal_tol or (self._since_best >= self.stall_ticks and e <= 2 * self.subgoal_tol)


def slide_to(target: np.ndarray, x: np.ndarray, steps: int = 16) -> np.ndarray:
    """`target (n_x, 3)` re-sampled along its own closed polyline with the phase (a fraction of a
    spacing either way, plus whole shifts) that best matches `x (n_x, 3)`.

    SOI points have no material identity: between frames they slide along the rim. Comparing x with
    a subgoal after this slide leaves only the rim's shape and pose in the error, not the sliding.
    """
    target = np.asarray(target, dtype=float)
    x = np.asarray(x, dtype=float)
    nxt = np.roll(target, -1, axis=0)
    prv = np.roll(target, 1, axis=0)
    f = np.linspace(-0.5, 0.5, steps + 1)[:, None, None]
    cand = np.where(f >= 0, target + f * (nxt - target), target - f * (prv - target))  # (steps+1, n_x, 3)
    cand = np.stack([np.roll(cand, shift, axis=1) for shift in (-1, 0, 1)], axis=1).reshape(-1, *target.shape)
    cost = np.mean(np.sum((cand - x) ** 2, axis=-1), axis=-1)  # mean square, in (phase, shift) order
    k = int(np.argmin(cost))
    return cand[k] if cost[k] < np.mean(np.sum((target - x) ** 2, axis=-1)) else target
