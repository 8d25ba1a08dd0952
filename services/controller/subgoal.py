"""Choosing the next subgoal g_next on the planned path from the current SOI."""

from __future__ import annotations

import numpy as np


def rms_error(x: np.ndarray, g: np.ndarray) -> float:
    """RMS point distance between two SOIs `(n_x, 3)`."""
    return float(np.sqrt(np.mean(np.sum((np.asarray(x) - np.asarray(g)) ** 2, axis=-1))))


class SubgoalTracker:
    """Walks along path `(n_nodes, n_x, 3)`: advance when close enough to the current subgoal or when a
    later node is already nearer, but never past g† (dagger_index) before g† itself was reached."""

    def __init__(self, path: np.ndarray, dagger_index: int, subgoal_tol: float, goal_tol: float):
        self.path = np.asarray(path, dtype=float)
        if self.path.ndim != 3 or len(self.path) < 1:
            raise ValueError("path must have shape (n_nodes, n_x, 3)")
        if not 0 <= dagger_index < len(self.path):
            raise ValueError(f"dagger_index {dagger_index} outside the path")
        self.dagger = dagger_index
        self.subgoal_tol = subgoal_tol
        self.goal_tol = goal_tol
        self.index = min(1, len(self.path) - 1)
        self.dagger_reached = dagger_index == 0

    def update(self, x: np.ndarray) -> int:
        """The index of g_next for the SOI `x (n_x, 3)`."""
        last = len(self.path) - 1
        while self.index < last:
            limit = last if self.dagger_reached else self.dagger
            if self.index == self.dagger and rms_error(x, self.path[self.index]) <= self.subgoal_tol:
                self.dagger_reached = True
                limit = last
            close = rms_error(x, self.path[self.index]) <= self.subgoal_tol
            ahead = self.index + 1 <= limit and rms_error(x, self.path[self.index + 1]) < rms_error(x, self.path[self.index])
            if (close or ahead) and self.index + 1 <= limit:
                self.index += 1
            else:
                break
        if self.index == self.dagger and rms_error(x, self.path[self.dagger]) <= self.subgoal_tol:
            self.dagger_reached = True
        return self.index

    @property
    def stage(self) -> str:
        return "bagging" if self.dagger_reached else "pre-bagging"

    def progress(self) -> float:
        return self.index / max(len(self.path) - 1, 1)

    def done(self, x: np.ndarray) -> bool:
        return self.dagger_reached and self.index == len(self.path) - 1 and rms_error(x, self.path[-1]) <= self.goal_tol
