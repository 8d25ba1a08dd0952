"""Online estimate of the deformation Jacobian J (s_t = J u_t) by Broyden's rank-one update, guarded.

The paper's update: J <- J + eps (s - J u) u^T / (u^T u). On real data a tiny u divides noise by
almost zero and a glitch in the SOI can throw J far off, so the update is skipped for tiny or
non-finite steps and J's norm is bounded.
"""

from __future__ import annotations

import numpy as np

MIN_STEP_NORM = 1e-4  # skip updates for ||u|| below this (m / rad per tick)
MAX_JACOBIAN_NORM = 50.0  # Frobenius bound on J (SOI metres per input unit)


class BroydenJacobian:
    """J: (3 n_x, 12), updated from (u, s) pairs."""

    def __init__(self, J0: np.ndarray, epsilon: float = 0.3, max_norm: float = MAX_JACOBIAN_NORM):
        if not 0.0 < epsilon <= 1.0:
            raise ValueError(f"Broyden rate epsilon must be in (0, 1], got {epsilon}")
        self.J = np.array(J0, dtype=float)
        self.epsilon = epsilon
        self.max_norm = max_norm
        self.updates = 0
        self.skipped = 0

    def update(self, u: np.ndarray, s: np.ndarray) -> bool:
        """One Broyden step from input `u (12,)` and the SOI change `s (3 n_x,)` it caused. True if applied."""
        u = np.asarray(u, dtype=float).ravel()
        s = np.asarray(s, dtype=float).ravel()
        uu = float(u @ u)
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(s))) or uu < MIN_STEP_NORM**2:
            self.skipped += 1
            return False
        J = self.J + self.epsilon * np.outer(s - self.J @ u, u) / uu
        n = np.linalg.norm(J)
        if n > self.max_norm:
            J *= self.max_norm / n
        self.J = J
        self.updates += 1
        return True


def exploration_inputs(step_m: float = 0.004, step_rad: float = 0.04) -> np.ndarray:
    """The exploratory motions `(24, 12)`: each input direction forward then back, bounded in size."""
    scale = np.array([step_m] * 3 + [step_rad] * 3 + [step_m] * 3 + [step_rad] * 3)
    out = []
    for i in range(12):
        e = np.zeros(12)
        e[i] = scale[i]
        out += [e, -e]
    return np.asarray(out)


def jacobian_from_exploration(inputs: np.ndarray, changes: np.ndarray) -> np.ndarray:
    """Finite-difference J `(3 n_x, 12)` from exploratory inputs `(k, 12)` and the SOI changes `(k, 3 n_x)`
    they caused: the least-squares J with changes ~ inputs @ J^T."""
    Jt, *_ = np.linalg.lstsq(inputs, changes, rcond=None)
    return Jt.T
