"""MPC shape servoing (paper section VI-B) as a condensed QP solved with PIQP.

Prediction over the horizon T: x̄ = A x_t + B ū with A = 1_{T x 1} ⊗ I_{3 n_x} and B = L_h ⊗ J
(L_h the lower-triangular matrix of ones). With Q = q I and R = r I the condensed Hessian and
gradient only need the small factors:

    H = q (L_hᵀ L_h) ⊗ (Jᵀ J) + r I,      g = q (L_hᵀ 1) ⊗ (Jᵀ (x_t - k)),

so a tick costs a 12T x 12T dense solve whatever n_x is. Constraints: C7 boxes on every input
(speed limits x dt), C6 the grippers' separation along their current axis within [d_min, d_max]
at every step of the horizon (the rim cannot stretch further, the mounts must not collide),
C8 the model (eliminated by condensing). Only the first input is applied.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import piqp


ROTATION_COST_FACTOR = 10.0


@dataclass
class MpcSolution:
    u: np.ndarray  # (12,) first input
    u_bar: np.ndarray  # (12 T,)
    solve_ms: float
    status: str


class MpcSolver:
    """Holds the PIQP solver between ticks and re-uses its set-up through `update`."""

    def __init__(self, horizon: int, q: float, r: float):
        self.T = horizon
        self.q = q
        self.r = r
        L = np.tril(np.ones((horizon, horizon)))
        self._LtL = L.T @ L
        self._Lt1 = L.T @ np.ones(horizon)
        self._L = L
        # Rotations cost ROTATION_COST_FACTOR more per unit: a mount's turn moves the rim little, and an
        # input that barely shows in the SOI must not be spent on the camera's noise.
        per_tick = np.array([1.0] * 3 + [ROTATION_COST_FACTOR] * 3 + [1.0] * 3 + [ROTATION_COST_FACTOR] * 3)
        self._r_diag = r * np.tile(per_tick, horizon)
        self._solver: piqp.DenseSolver | None = None
        self._shape: tuple[int, int] | None = None

    def solve(
        self,
        J: np.ndarray,
        x: np.ndarray,
        target: np.ndarray,
        u_max: np.ndarray,
        sep_axis: np.ndarray | None = None,
        sep_now: float = 0.0,
        sep_limits: tuple[float, float] = (0.0, np.inf),
    ) -> MpcSolution:
        """Inputs for the SOI `x (3 n_x,)` to reach `target (3 n_x,)` under the model J `(3 n_x, 12)`.

        `u_max (12,)`: C7 bound per input per tick. `sep_axis (3,)`: unit vector from the left to the
        right gripper; the separation along it stays within `sep_limits` over the horizon (C6).
        """
        T = self.T
        t0 = time.perf_counter()
        JtJ = J.T @ J
        H = self.q * np.kron(self._LtL, JtJ) + np.diag(self._r_diag)
        g = self.q * np.kron(self._Lt1, J.T @ (x - target))
        ub = np.tile(u_max, T)
        lb = -ub
        G = hl = hu = None
        if sep_axis is not None:
            a = np.concatenate([-sep_axis, np.zeros(3), sep_axis, np.zeros(3)])  # d(separation)/du
            G = np.kron(self._L, a[None, :])  # row k: separation change after k+1 steps
            hl = np.full(T, sep_limits[0] - sep_now)
            hu = np.full(T, sep_limits[1] - sep_now)
            # If the grippers are already outside the band, only ask for no worse.
            hl = np.minimum(hl, 0.0)
            hu = np.maximum(hu, 0.0)
        H = np.asfortranarray(H)
        G = np.asfortranarray(G) if G is not None else None
        shape = (12 * T, 0 if G is None else G.shape[0])
        if self._solver is None or shape != self._shape:
            self._solver = piqp.DenseSolver()
            self._solver.settings.verbose = False
            self._solver.settings.eps_abs = 1e-7
            self._solver.settings.eps_rel = 1e-7
            self._solver.setup(H, g, None, None, G, hl, hu, lb, ub)
            self._shape = shape
        else:
            self._solver.update(P=H, c=g, G=G, h_l=hl, h_u=hu, x_l=lb, x_u=ub)
        status = self._solver.solve()
        u_bar = np.asarray(self._solver.result.x, dtype=float)
        ok = str(status).endswith("PIQP_SOLVED") or "SOLVED" in str(status)
        if not ok or not np.all(np.isfinite(u_bar)):
            u_bar = np.zeros(12 * T)
        u_bar = np.clip(u_bar, lb, ub)  # solver tolerance must never leak past C7
        return MpcSolution(u_bar[:12].copy(), u_bar, (time.perf_counter() - t0) * 1e3, str(status))
