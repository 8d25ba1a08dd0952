"""Controller: Broyden estimate, MPC constraints, subgoal tracking, guards, and the closed loop on a synthetic rim."""

import numpy as np
import pytest

from bagit.common.params import MethodParams
from bagit.services.controller import BroydenJacobian, MpcSolver, ShapeServo, SubgoalTracker
from bagit.services.controller.broyden import exploration_inputs, jacobian_from_exploration
from bagit.services.controller.guard import SoiGuard
from bagit.services.controller.synthetic import SyntheticRim, apply_increment


def test_broyden_converges_to_a_linear_model():
    rng = np.random.default_rng(0)
    J_true = rng.normal(size=(48, 12)) * 0.5
    est = BroydenJacobian(np.zeros((48, 12)), epsilon=1.0)
    for _ in range(400):
        u = rng.normal(size=12) * 0.01
        est.update(u, J_true @ u)
    assert np.linalg.norm(est.J - J_true) / np.linalg.norm(J_true) < 1e-3


def test_broyden_tracks_the_local_jacobian_of_a_nonlinear_model():
    m = SyntheticRim(16)
    g = m.home()
    f = lambda u: m.rim(apply_increment(g, u)).ravel()  # noqa: E731
    x0 = f(np.zeros(12))
    eps = 1e-5
    J_true = np.stack([(f(e * eps) - x0) / eps for e in np.eye(12)], axis=1)
    est = BroydenJacobian(np.zeros_like(J_true), epsilon=1.0)
    rng = np.random.default_rng(1)
    for _ in range(300):
        u = rng.normal(size=12) * 1e-4
        est.update(u, f(u) - x0)
    assert np.linalg.norm(est.J - J_true) / np.linalg.norm(J_true) < 0.05


def test_exploration_finite_differences_give_the_jacobian():
    rng = np.random.default_rng(2)
    J_true = rng.normal(size=(30, 12))
    U = exploration_inputs()
    assert U.shape == (24, 12) and np.abs(U).max() <= 0.04
    assert np.allclose(jacobian_from_exploration(U, U @ J_true.T), J_true)


def test_broyden_guards():
    est = BroydenJacobian(np.ones((6, 12)), epsilon=0.5, max_norm=5.0)
    J = est.J.copy()
    assert not est.update(np.zeros(12), np.ones(6))  # tiny step
    assert not est.update(np.full(12, np.nan), np.ones(6))
    assert not est.update(np.ones(12) * 0.01, np.full(6, np.inf))
    assert np.array_equal(est.J, J) and est.skipped == 3
    est.update(np.ones(12) * 0.01, np.ones(6) * 1e6)  # a glitch cannot blow J up
    assert np.linalg.norm(est.J) <= 5.0 + 1e-9
    with pytest.raises(ValueError):
        BroydenJacobian(J, epsilon=0.0)


def test_mpc_respects_c7_and_c6_every_tick():
    rng = np.random.default_rng(3)
    solver = MpcSolver(horizon=10, q=1.0, r=0.05)
    u_max = np.array([0.0017] * 3 + [0.01] * 3 + [0.0017] * 3 + [0.01] * 3)
    axis = np.array([0.0, 1.0, 0.0])
    for _ in range(50):
        J = rng.normal(size=(96, 12))
        x = rng.normal(size=96) * 0.1
        sep = 0.28
        sol = solver.solve(J, x, np.zeros(96), u_max, axis, sep, (0.06, 0.29))
        assert np.all(np.abs(sol.u_bar) <= np.tile(u_max, 10) + 1e-12)
        d_sep = np.cumsum(sol.u_bar.reshape(10, 12)[:, 7] - sol.u_bar.reshape(10, 12)[:, 1])
        assert np.all(sep + d_sep <= 0.29 + 1e-6)
        assert np.all(np.isfinite(sol.u))


def _synthetic_path(m: SyntheticRim, n_nodes: int = 8):
    u_goal = np.array([0.05, 0.03, 0.15, 0, 0, 0.2, 0.05, -0.03, 0.15, 0, 0, 0.2])
    g = m.home()
    return np.stack([m.rim(apply_increment(g, u_goal * s)) for s in np.linspace(0, 1, n_nodes)])


@pytest.mark.parametrize("kind", ["mpc", "ibvs", "ssvs"])
def test_closed_loop_reaches_the_goal_on_a_synthetic_rim(kind):
    m = SyntheticRim(32)
    path = _synthetic_path(m)
    params = MethodParams()
    c = ShapeServo(kind, params, path, dagger_index=5, perimeter=0.68)
    grippers, t = m.home(), 0.0
    lim = np.array([params.max_linear_speed_mps] * 3 + [params.max_angular_speed_rps] * 3) / params.control_rate_hz
    out = None
    for _ in range(900):
        out = c.step(m.rim(grippers), t, grippers)
        assert np.all(np.abs(out.u) <= np.tile(lim, 2) + 1e-12)  # C7 in every tick, every controller
        grippers = apply_increment(grippers, out.u)
        t += 1 / params.control_rate_hz
        if out.done:
            break
    assert out.done, (out.mode, out.error_to_goal)
    assert out.error_to_goal <= params.goal_tol_m


def test_subgoal_tracker_never_skips_past_dagger():
    path = np.stack([np.full((4, 3), k, float) for k in range(6)])
    tr = SubgoalTracker(path, dagger_index=2, subgoal_tol=0.1, goal_tol=0.1)
    assert tr.update(path[5]) == 2  # already at g*: still must reach g† first
    assert tr.stage == "pre-bagging"
    assert tr.update(path[2]) == 3 and tr.stage == "bagging"
    assert tr.update(path[5]) == 5 and tr.done(path[5])


def test_guard_holds_on_missing_stale_and_jumping_soi():
    g = SoiGuard(timeout_s=0.2, max_age_s=0.3)
    x = np.zeros((8, 3))
    assert g.check(None, 0.0) == "no SOI received"
    assert g.check(x, 1.0) is None
    assert "stopped arriving" in g.check(None, 1.5)
    assert "stale" in g.check(x, 2.0, source_stamp=1.0)
    assert g.check(x, 2.0, source_stamp=1.95) is None
    assert "jumped" in g.check(x + [0.5, 0, 0], 2.033)
    assert "NaN" in g.check(np.full((8, 3), np.nan), 2.1)


def test_controller_commands_zero_when_soi_stops():
    m = SyntheticRim(16)
    path = _synthetic_path(m, 4)
    c = ShapeServo("mpc", MethodParams(), path, 2, 0.68)
    grippers = m.home()
    c.step(m.rim(grippers), 0.0, grippers)
    out = c.step(None, 1.0, grippers)
    assert out.mode == "hold" and np.all(out.u == 0) and "stopped" in out.reason
    with pytest.raises(ValueError):
        ShapeServo("pid", MethodParams(), path, 2, 0.68)
