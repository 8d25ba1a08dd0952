"""MPC shape servoing (paper section VI-B) as a condensed QP solved with PIQP.

Prediction over the horizon T: x̄ = A x_t + B ū with A = 1_{T x 1} ⊗ I_{3 n_x} and B = L_h ⊗ J
(L_h the lower-triangular matrix of ones). With Q = q I and R block-diagonal over the ticks
(`input_weight`: a diagonal plus the twist term below), eliminating x̄ (C8)
leaves a QP in ū alone whose Hessian and gradient only need the small factors:

    H = Bᵀ Q B + R = q (L_hᵀ L_h) ⊗ (Jᵀ J) + R,      c = Bᵀ Q (A x_t - k̄) = q (L_hᵀ 1) ⊗ (Jᵀ (x_t - g)),

so a tick costs a 12T x 12T dense solve whatever n_x is (`prediction_matrices` builds the
paper's A and B explicitly, for reference and tests). Constraints: C7 boxes on every input (speed
limits x dt, translation and rotation separately); C6 the grippers' separation along their
current axis within [d_min, d_max] at every step of the horizon, as linear rows on the cumulative
inputs: the fabric rim cannot be pulled further apart than about half its perimeter, and held
closer than the subgoal's shape needs it goes slack and folds in (see ServoBase.separation_band).
Only the first input is applied.

R's twist term (`ControllerParams.experimental.twist_weight`; the paper leaves R open): per tick, twist |ω_L - ω_R|²
on the difference of the two grippers' rotation increments, so they turn together and the rim
moves as a body instead of being creased between its clamps (see `input_weight`). The paper's QP
form is unchanged: it is a choice of R, and `uncondensed_qp` takes the same R.

PIQP is an interior-point solver and takes no primal start in its Python API (v0.7), so the
"warm start" it can use is its set-up: the KKT structure and workspace are kept between ticks and
only the data change through `update()`. (Shifting the origin to last tick's shifted plan was
measured to leave the iteration count unchanged, ~8 per tick.)
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import piqp
import scipy.sparse as sp

from bagit.common.dual_arm import INCREMENT_SIZE, POSITION_COLUMNS, ROTATION, TRANSLATION
from bagit.common.params import MethodParams
from bagit.common.rig import ARMS
from bagit.services.controller import servo as servo_mod
from bagit.services.controller.servo import ServoBase

ROTATION_COST_FACTOR = 10.0  # a mount's turn moves the rim little: spend it only where it pays


@dataclass
class MpcSolution:
    u: np.ndarray  # (12,) the first input, the one applied
    u_bar: np.ndarray  # (12 T,) the whole plan
    solve_ms: float  # QP build + solve, wall time
    status: str
    iterations: int
    ok: bool


def prediction_matrices(J: np.ndarray, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """The paper's A `(3 n_x T, 3 n_x)` = 1_{T x 1} ⊗ I and B `(3 n_x T, 12 T)` = L_h ⊗ J, built explicitly.

    Only for reference and tests: the controller never forms these (B alone is 960 x 120 at n_x = 32)."""
    n = J.shape[0]
    A = np.kron(np.ones((horizon, 1)), np.eye(n))
    B = np.kron(np.tril(np.ones((horizon, horizon))), J)
    return A, B


def rotation_weighted_r(r: float, horizon: int) -> np.ndarray:
    """Diagonal of R `(12 T,)`: r per unit of translation, ROTATION_COST_FACTOR r per radian."""
    per_tick = np.ones(INCREMENT_SIZE)
    for arm in ARMS:
        per_tick[ROTATION[arm]] = ROTATION_COST_FACTOR
    return r * np.tile(per_tick, horizon)


def input_weight(r: float, horizon: int, twist: float = 0.0) -> np.ndarray:
    """R `(12T, 12T)`: `rotation_weighted_r` on the diagonal plus, per tick, twist |ω_L - ω_R|², the
    cost of the two grippers turning differently (ω: each gripper's rotation increment, `dual_arm.ROTATION`).

    Why: each mount clamps a rigid quarter of the rim, so turning both alike moves the rim as a body,
    while turning them differently bends the free fabric between the clamps, which buckles into a fold
    (inwards, under the object's bottom, as often as outwards) that a linear J cannot predict: traced
    in the simulator, the MPC yawed the mounts apart to widen the rim's near side and creased it instead."""
    R = np.diag(rotation_weighted_r(r, horizon))
    if twist > 0:
        D = np.zeros((3, INCREMENT_SIZE))
        D[:, ROTATION["left"]] = np.eye(3)
        D[:, ROTATION["right"]] = -np.eye(3)
        R += twist * np.kron(np.eye(horizon), D.T @ D)
    return R


def separation_gradient(axis: np.ndarray) -> np.ndarray:
    """d(separation)/du `(12,)`: the change of the grippers' distance along the unit `axis (3,)` (left -> right)."""
    a = np.zeros(INCREMENT_SIZE)
    a[TRANSLATION["left"]] = -axis
    a[TRANSLATION["right"]] = axis
    return a


def separation_bounds(sep_now: float, limits: tuple[float, float], recover: float, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """Bounds `(T,)`, `(T,)` on the separation change after k+1 steps: inside the band `limits` it may
    move anywhere in it; outside, it must come back by at least `recover` per step (0: no worse)."""
    k = np.arange(1, horizon + 1)
    lo = np.minimum(limits[0] - sep_now, k * recover)
    hi = np.maximum(limits[1] - sep_now, -k * recover)
    return lo, np.maximum(hi, lo)


class MpcSolver:
    """The condensed MPC QP, solved with PIQP; the solver and its set-up live between ticks.

    backend: 'dense' (piqp.DenseSolver, the default: the condensed QP is small and dense) or
    'sparse' (piqp.SparseSolver on the same QP, for comparison).
    """

    def __init__(
        self, horizon: int, q: float, r: float, backend: str = "dense", eps: float = 1e-7, twist: float = 0.0
    ):
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        if backend not in ("dense", "sparse"):
            raise ValueError(f"backend must be 'dense' or 'sparse', got {backend!r}")
        self.T = horizon
        self.q = q
        self.r = r
        self.backend = backend
        self.eps = eps
        L = np.tril(np.ones((horizon, horizon)))
        self._L = L
        self._LtL = L.T @ L
        self._Lt1 = L.T @ np.ones(horizon)
        if not (np.isfinite(twist) and twist >= 0):
            raise ValueError(f"twist must be a finite weight >= 0, got {twist}")
        self.R = input_weight(r, horizon, twist)
        # Fixed sparsity patterns (the sparse solver's update needs the same pattern every tick).
        n = 12 * horizon
        self._triu = np.triu_indices(n)
        order = np.lexsort((self._triu[0], self._triu[1]))  # column-major, as CSC stores them
        self._triu = (self._triu[0][order], self._triu[1][order])
        rows, cols = [], []
        for k in range(horizon):
            for j in range(k + 1):
                for c in POSITION_COLUMNS:
                    rows.append(k)
                    cols.append(12 * j + c)
        self._g_rows, self._g_cols = np.asarray(rows), np.asarray(cols)
        self._g_pos = np.asarray(cols) % 12
        self._solver: piqp.DenseSolver | piqp.SparseSolver | None = None
        self._has_g: bool | None = None
        self.last: MpcSolution | None = None

    def condensed(self, J: np.ndarray, x: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """H `(12T, 12T)` and c `(12T,)` of the condensed cost for `J (3 n_x, 12)`, `x`, `target (3 n_x,)`."""
        H = self.q * np.kron(self._LtL, J.T @ J) + self.R
        c = self.q * np.outer(self._Lt1, J.T @ (x - target)).ravel()
        return H, c

    def solve(
        self,
        J: np.ndarray,
        x: np.ndarray,
        target: np.ndarray,
        u_max: np.ndarray,
        sep_axis: np.ndarray | None = None,
        sep_now: float = 0.0,
        sep_limits: tuple[float, float] = (0.0, np.inf),
        sep_recover: float = 0.0,
    ) -> MpcSolution:
        """Inputs for the SOI `x (3 n_x,)` to reach `target (3 n_x,)` under the model `J (3 n_x, 12)`.

        `u_max (12,)`: C7 bound per input per tick. `sep_axis (3,)`: unit vector from the left to the
        right gripper; the separation along it stays within `sep_limits` over the horizon (C6). If the
        grippers are already outside that band they must head back by `sep_recover` (m) per step
        (0: only no worse), never faster than the band asks.
        """
        T = self.T
        t0 = time.perf_counter()
        J = np.asarray(J, dtype=float)
        x = np.asarray(x, dtype=float).ravel()
        target = np.asarray(target, dtype=float).ravel()
        zeros = np.zeros(12 * T)
        if not (np.all(np.isfinite(J)) and np.all(np.isfinite(x)) and np.all(np.isfinite(target))):
            return self._fail(zeros, t0, "non-finite model or SOI")
        try:
            return self._solve(J, x, target, u_max, sep_axis, sep_now, sep_limits, sep_recover, t0)
        except (ValueError, RuntimeError, ArithmeticError, np.linalg.LinAlgError) as e:
            # PIQP's set-up or factorisation refusing the data: a failed tick (the arms hold), not a crash
            self._solver = None  # set up afresh next tick
            return self._fail(zeros, t0, f"solver error: {e}")

    def _solve(self, J, x, target, u_max, sep_axis, sep_now, sep_limits, sep_recover, t0) -> MpcSolution:
        T = self.T
        zeros = np.zeros(12 * T)
        with np.errstate(over="ignore", invalid="ignore"):  # an overflowing model is caught just below
            H, c = self.condensed(J, x, target)
        if not (np.all(np.isfinite(H)) and np.all(np.isfinite(c))):
            return self._fail(zeros, t0, "non-finite QP data")
        ub = np.tile(np.asarray(u_max, dtype=float), T)
        lb = -ub
        has_g = sep_axis is not None
        G = hl = hu = None
        if has_g:
            a = separation_gradient(np.asarray(sep_axis, dtype=float))
            hl, hu = separation_bounds(sep_now, sep_limits, sep_recover, T)
            G = a[self._g_pos]  # the values on the fixed pattern
        if self._solver is None or has_g != self._has_g:
            self._setup(H, c, G, hl, hu, lb, ub)
            self._has_g = has_g
        elif self.backend == "dense":
            Gd = self._dense_g(G) if G is not None else None  # (G is set exactly when has_g)
            self._solver.update(P=np.asfortranarray(H), c=c, G=Gd, h_l=hl, h_u=hu, x_l=lb, x_u=ub)
        else:
            Gs = self._sparse_g(G) if G is not None else None
            self._solver.update(P=self._sparse_p(H), c=c, G=Gs, h_l=hl, h_u=hu, x_l=lb, x_u=ub)
        solver = self._solver
        if solver is None:
            raise AssertionError("the MPC's QP solver is missing after its set-up")
        status = solver.solve()
        u_bar = np.asarray(solver.result.x, dtype=float).copy()
        iters = int(solver.result.info.iter)
        if status != piqp.PIQP_SOLVED or not np.all(np.isfinite(u_bar)):
            if not np.all(np.isfinite(u_bar)):
                self._solver = None  # a workspace holding NaN would poison the next tick's warm set-up
            return self._fail(zeros, t0, str(status), iters)
        u_bar = np.clip(u_bar, lb, ub)  # solver tolerance must never leak past C7
        sol = MpcSolution(u_bar[:12].copy(), u_bar, (time.perf_counter() - t0) * 1e3, str(status), iters, True)
        self.last = sol
        return sol

    def predicted(self, J: np.ndarray, x: np.ndarray, u_bar: np.ndarray) -> np.ndarray:
        """x̄ `(T, 3 n_x)` = A x + B ū for a plan `u_bar (12T,)`, without forming A or B."""
        steps = np.cumsum(np.asarray(u_bar, dtype=float).reshape(self.T, 12), axis=0)
        return np.asarray(x, dtype=float).ravel()[None, :] + steps @ np.asarray(J, dtype=float).T

    def _fail(self, zeros: np.ndarray, t0: float, status: str, iters: int = 0) -> MpcSolution:
        sol = MpcSolution(zeros[:12].copy(), zeros, (time.perf_counter() - t0) * 1e3, status, iters, False)
        self.last = sol
        return sol

    def _dense_g(self, values: np.ndarray) -> np.ndarray:
        G = np.zeros((self.T, 12 * self.T), order="F")
        G[self._g_rows, self._g_cols] = values
        return G

    def _sparse_g(self, values: np.ndarray) -> sp.csc_matrix:
        # Explicit zeros kept, so the pattern never changes with the axis.
        return sp.csc_matrix((values, (self._g_rows, self._g_cols)), shape=(self.T, 12 * self.T))

    def _sparse_p(self, H: np.ndarray) -> sp.csc_matrix:
        i, j = self._triu
        n = H.shape[0]
        indptr = np.concatenate([[0], np.cumsum(np.bincount(j, minlength=n))])
        return sp.csc_matrix((H[i, j], i, indptr), shape=H.shape)

    def _setup(self, H, c, G, hl, hu, lb, ub) -> None:
        if self.backend == "dense":
            s = piqp.DenseSolver()
            Gm = self._dense_g(G) if G is not None else None
            Pm = np.asfortranarray(H)
        else:
            s = piqp.SparseSolver()
            Gm = self._sparse_g(G) if G is not None else None
            Pm = self._sparse_p(H)
        s.settings.verbose = False
        s.settings.eps_abs = self.eps
        s.settings.eps_rel = self.eps
        s.setup(Pm, c, None, None, Gm, hl, hu, lb, ub)
        self._solver = s


def uncondensed_qp(
    J: np.ndarray,
    x: np.ndarray,
    target: np.ndarray,
    u_max: np.ndarray,
    horizon: int,
    q: float,
    R: np.ndarray,
    sep_axis: np.ndarray,
    sep_now: float,
    sep_limits: tuple[float, float],
    sep_recover: float = 0.0,
) -> dict[str, np.ndarray | sp.csc_matrix]:
    """The same MPC without condensing, for sparse solvers: variables z = [x̄ (3 n_x T), ū (12 T)],
    C8 as equality rows x_{k+1} = x_k + J u_k. Returns P (upper triangle), c, A, b, G, h_l, h_u, x_l, x_u."""
    n, T = J.shape[0], horizon
    x = np.asarray(x, dtype=float).ravel()
    target = np.asarray(target, dtype=float).ravel()
    Qx = sp.kron(sp.eye(n // 3 * T), sp.csc_matrix(q * np.eye(3)))
    P = sp.triu(sp.block_diag([Qx, sp.csc_matrix(np.asarray(R, dtype=float))])).tocsc()
    c = np.concatenate([np.tile(-q * target, T), np.zeros(12 * T)])
    # x_k - x_{k-1} - J u_k = 0 (x_{-1} = x_t): [I - shift] ⊗ I_n on x̄, -I_T ⊗ J on ū. Built from
    # explicit coordinates so the patterns (zeros in J or the axis included) never change.
    k, i = np.meshgrid(np.arange(T), np.arange(n), indexing="ij")
    rows = [(k * n + i).ravel(), (k[1:] * n + i[1:]).ravel()]
    cols = [(k * n + i).ravel(), ((k[1:] - 1) * n + i[1:]).ravel()]
    vals = [np.ones(n * T), -np.ones(n * (T - 1))]
    kk, ii, jj = np.meshgrid(np.arange(T), np.arange(n), np.arange(12), indexing="ij")
    rows.append((kk * n + ii).ravel())
    cols.append((n * T + 12 * kk + jj).ravel())
    vals.append(-np.broadcast_to(J, (T, n, 12)).ravel())
    A = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n * T, n * T + 12 * T))
    b = np.concatenate([x, np.zeros(n * (T - 1))])
    a = separation_gradient(np.asarray(sep_axis, dtype=float))
    gk, gj = np.nonzero(np.tril(np.ones((T, T))))
    g_rows = np.repeat(gk, len(POSITION_COLUMNS))
    g_cols = n * T + (12 * gj[:, None] + np.asarray(POSITION_COLUMNS)[None, :]).ravel()
    g_vals = a[np.tile(POSITION_COLUMNS, len(gj))]
    G = sp.csc_matrix((g_vals, (g_rows, g_cols)), shape=(T, n * T + 12 * T))
    h_l, h_u = separation_bounds(sep_now, sep_limits, sep_recover, T)
    ub = np.concatenate([np.full(n * T, np.inf), np.tile(np.asarray(u_max, float), T)])
    lb = np.concatenate([np.full(n * T, -np.inf), -np.tile(np.asarray(u_max, float), T)])
    return {"P": P, "c": c, "A": A, "b": b, "G": G, "h_l": h_l, "h_u": h_u, "x_l": lb, "x_u": ub}


class MpcController(ServoBase):
    """The paper's controller: MPC along the planned path towards g_next, C6 on the grippers' separation."""

    name = "mpc"

    def __init__(self, params: MethodParams, n_x: int, backend: str = "dense", **kwargs):
        super().__init__(params, n_x, **kwargs)
        self.solver = self._new_solver(backend)

    def _new_solver(self, backend: str) -> MpcSolver:
        c = self.p.controller
        return MpcSolver(c.horizon, c.q_weight, c.r_weight, backend, twist=c.experimental.twist_weight)

    def _on_reset(self) -> None:
        self.solver = self._new_solver(self.solver.backend)

    def _law(self, J, x, target, grippers):
        pl, pr = grippers["left"][:3, 3], grippers["right"][:3, 3]
        sep = float(np.linalg.norm(pr - pl))
        axis = (pr - pl) / max(sep, 1e-9)
        band = self.separation_band(target, axis)
        sol = self.solver.solve(J, x, target, self.u_max, axis, sep, band, servo_mod.SEP_RECOVER_M)
        if not sol.ok:
            return np.zeros(12), sol.solve_ms, f"MPC QP not solved ({sol.status})"
        return sol.u, sol.solve_ms, None
