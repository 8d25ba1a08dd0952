"""The MPC QP: the condensed form equals the paper's A/B form, C7 and C6 hold on every solve, and
the dense, sparse and uncondensed formulations agree."""

import numpy as np
import piqp
import pytest

from bagit.common.dual_arm import apply_increment
from bagit.common.params import MethodParams
from bagit.services.controller import MpcSolver, c7_limits
from bagit.services.controller.mpc import prediction_matrices, separation_gradient, uncondensed_qp
from bagit.services.controller.synthetic import SyntheticRim

U_MAX = c7_limits(MethodParams())
AXIS = np.array([0.0, 1.0, 0.0])


def _problem(rng, n_x=32):
    """A realistic J from the synthetic rim at a random pose, and a target a few cm away."""
    m = SyntheticRim(n_x)
    g = apply_increment(m.home(), rng.normal(size=12) * np.tile([0.02] * 3 + [0.1] * 3, 2))
    x = m.rim(g).ravel()
    J = np.stack([(m.rim(apply_increment(g, e * 1e-6)).ravel() - x) / 1e-6 for e in np.eye(12)], axis=1)
    return J, x, x + rng.normal(size=x.size) * 0.02, g


@pytest.mark.parametrize("twist", [0.0, 40.0])
def test_condensed_cost_is_the_papers_cost(twist):
    """(x̄ - k̄)ᵀQ(x̄ - k̄) + ūᵀRū with x̄ = A x + B ū equals ½ūᵀ(2H)ū + 2cᵀū + const for every ū;
    R is the rotation-weighted diagonal plus twist |ω_L - ω_R|² per tick."""
    rng = np.random.default_rng(0)
    T, q, r = 4, 2.0, 0.1
    J = rng.normal(size=(18, 12))
    x, k = rng.normal(size=18), rng.normal(size=18)
    s = MpcSolver(T, q, r, twist=twist)
    H, c = s.condensed(J, x, k)
    A, B = prediction_matrices(J, T)
    assert A.shape == (18 * T, 18) and B.shape == (18 * T, 12 * T)
    R = s.R
    for _ in range(3):  # R's own meaning, term by term
        u = rng.normal(size=(T, 12))
        diag = sum(r * (ui[[0, 1, 2, 6, 7, 8]] @ ui[[0, 1, 2, 6, 7, 8]]) + 10 * r * (ui[[3, 4, 5, 9, 10, 11]] @ ui[[3, 4, 5, 9, 10, 11]]) for ui in u)
        assert np.isclose(u.ravel() @ R @ u.ravel(), diag + twist * sum(np.sum((ui[3:6] - ui[9:12]) ** 2) for ui in u))
    assert np.allclose(H, q * B.T @ B + R)
    assert np.allclose(c, q * B.T @ (A @ x - np.tile(k, T)))
    for _ in range(5):
        u = rng.normal(size=12 * T)
        xb = A @ x + B @ u
        paper = q * (xb - np.tile(k, T)) @ (xb - np.tile(k, T)) + u @ R @ u
        const = q * (A @ x - np.tile(k, T)) @ (A @ x - np.tile(k, T))
        assert np.isclose(paper, u @ H @ u + 2 * c @ u + const)
        assert np.allclose(s.predicted(J, x, u).ravel(), xb)


def test_unconstrained_solution_is_the_least_squares_one():
    """With bounds far away the QP's answer is H⁻¹(-c)."""
    rng = np.random.default_rng(1)
    J, x, target, _ = _problem(rng)
    s = MpcSolver(10, 1.0, 0.05)
    sol = s.solve(J, x, target, np.full(12, 10.0))
    H, c = s.condensed(J, x, target)
    assert sol.ok and np.allclose(sol.u_bar, np.linalg.solve(H, -c), atol=1e-6)


def test_twist_weight_makes_the_grippers_turn_together():
    """A target that only turning the two grippers in opposite ways reaches: without the twist term
    the MPC does just that, with it the two hardly turn differently (it settles for less)."""
    rng = np.random.default_rng(11)
    J = rng.normal(size=(96, 12)) * 0.02  # a turn of 0.01 rad moves a rim point by a fraction of a mm
    x = rng.normal(size=96) * 0.05
    turn = np.zeros(12)
    turn[3:6], turn[9:12] = 0.01, -0.01  # one tick's differential turn at the C7 limit
    target = x + 5 * J @ turn
    twist = lambda sol: np.abs(sol.u[3:6] - sol.u[9:12]).max()  # noqa: E731
    free = MpcSolver(10, 1.0, 0.05).solve(J, x, target, U_MAX)
    tied = MpcSolver(10, 1.0, 0.05, twist=1000.0).solve(J, x, target, U_MAX)
    assert free.ok and tied.ok
    assert twist(free) > U_MAX[3]  # the differential turn was the answer
    assert twist(tied) < 0.1 * twist(free)
    with pytest.raises(ValueError, match="twist"):
        MpcSolver(10, 1.0, 0.05, twist=-1.0)


def test_c7_and_c6_hold_on_every_solve():
    rng = np.random.default_rng(3)
    s = MpcSolver(horizon=10, q=1.0, r=0.05)
    active_c7 = active_c6 = 0
    for i in range(60):
        J, x, target, g = _problem(rng)
        if i % 2:
            J = rng.normal(size=J.shape)  # also arbitrary models
        sep = 0.28
        sol = s.solve(J, x, target, U_MAX, AXIS, sep, (0.06, 0.29))
        assert sol.ok and np.all(np.isfinite(sol.u_bar))
        assert np.all(np.abs(sol.u_bar) <= np.tile(U_MAX, 10) + 1e-15)  # C7, every input of the plan
        plan = sol.u_bar.reshape(10, 12)
        d_sep = np.cumsum(plan @ separation_gradient(AXIS))
        assert np.all(sep + d_sep <= 0.29 + 1e-7) and np.all(sep + d_sep >= 0.06 - 1e-7)  # C6
        active_c7 += np.any(np.abs(plan) > 0.999 * np.tile(U_MAX, (10, 1)))
        active_c6 += np.any(sep + d_sep > 0.29 - 1e-4)
    assert active_c7 > 30 and active_c6 >= 3  # the constraints did bind: the test checks something


def test_c6_already_violated_asks_only_for_no_worse():
    rng = np.random.default_rng(6)
    J, x, target, _ = _problem(rng)
    s = MpcSolver(10, 1.0, 0.05)
    sol = s.solve(J, x, target, U_MAX, AXIS, 0.35, (0.06, 0.29))  # 6 cm too far apart already
    assert sol.ok
    d_sep = np.cumsum(sol.u_bar.reshape(10, 12) @ separation_gradient(AXIS))
    assert np.all(d_sep <= 1e-7)


def test_dense_sparse_and_uncondensed_agree():
    rng = np.random.default_rng(2)
    dense, sparse = MpcSolver(10, 1.0, 0.05, "dense"), MpcSolver(10, 1.0, 0.05, "sparse")
    tol = 1e-3 * np.tile(U_MAX, 10)  # a thousandth of each input's range (the solver's eps is 1e-7)
    for i in range(6):
        J, x, target, _ = _problem(rng)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        # half the cases: 3 cm short of the C6 band with a recovery rate
        sep, recover = (0.28, 0.0) if i % 2 == 0 else (0.15, 0.001)
        args = (J, x, target, U_MAX, axis, sep, (0.18, 0.285), recover)
        a, b = dense.solve(*args), sparse.solve(*args)
        assert a.ok and b.ok and np.all(np.abs(a.u_bar - b.u_bar) <= tol)
        qp = uncondensed_qp(J, x, target, U_MAX, 10, 1.0, dense.R, axis, sep, (0.18, 0.285), recover)
        solver = piqp.SparseSolver()
        solver.settings.verbose = False
        solver.settings.eps_abs = solver.settings.eps_rel = 1e-9
        solver.setup(qp["P"], qp["c"], qp["A"], qp["b"], qp["G"], qp["h_l"], qp["h_u"], qp["x_l"], qp["x_u"])
        assert solver.solve() == piqp.PIQP_SOLVED
        assert np.all(np.abs(solver.result.x[-120:] - a.u_bar) <= 5 * tol)  # other scaling, same optimum


def test_bad_model_gives_no_input_instead_of_nan():
    s = MpcSolver(10, 1.0, 0.05)
    J = np.full((96, 12), np.nan)
    sol = s.solve(J, np.zeros(96), np.zeros(96), U_MAX, AXIS, 0.2, (0.06, 0.3))
    assert not sol.ok and np.all(sol.u == 0)
    with pytest.raises(ValueError):
        MpcSolver(10, 1.0, 0.05, backend="gpu")


def test_outside_the_c6_band_the_plan_heads_back_at_the_asked_rate():
    from bagit.services.controller.mpc import separation_bounds

    lo, hi = separation_bounds(0.15, (0.18, 0.30), 0.001, 10)
    assert np.allclose(lo, 0.001 * np.arange(1, 11)) and np.all(hi >= lo)  # 3 cm short: +1 mm per step
    lo, hi = separation_bounds(0.20, (0.18, 0.30), 0.001, 10)
    assert np.allclose(lo, -0.02) and np.allclose(hi, 0.10)  # inside: anywhere in the band
    rng = np.random.default_rng(9)
    J, x, target, _ = _problem(rng)
    s = MpcSolver(10, 1.0, 0.05)
    sol = s.solve(J, x, x, U_MAX, AXIS, 0.15, (0.18, 0.30), sep_recover=0.001)  # target = here: no wish to move
    d_sep = np.cumsum(sol.u_bar.reshape(10, 12) @ separation_gradient(AXIS))
    assert sol.ok and np.all(d_sep >= 0.001 * np.arange(1, 11) - 1e-7)


