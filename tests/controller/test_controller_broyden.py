"""Broyden's Jacobian estimate (paper eq. 16 + guards) and the exploration that seeds it."""

import numpy as np
import pytest

from bagit.common.dual_arm import apply_increment
from bagit.common.errors import NumericalFailure
from bagit.common.params import MethodParams
from bagit.services.controller import BroydenJacobian, Exploration, c7_limits
from bagit.services.controller.broyden import exploration_inputs, jacobian_from_exploration, rigid_pair_motions, rigid_pair_response
from bagit.services.controller.synthetic import SyntheticRim


def test_converges_to_a_linear_model_under_random_inputs():
    rng = np.random.default_rng(0)
    J_true = rng.normal(size=(48, 12)) * 0.5
    est = BroydenJacobian(np.zeros((48, 12)), epsilon=1.0)
    errors = []
    for _ in range(400):
        u = rng.normal(size=12) * 0.01
        est.update(u, J_true @ u)
        errors.append(np.linalg.norm(est.J - J_true) / np.linalg.norm(J_true))
    assert errors[-1] < 1e-3
    assert errors[50] > errors[-1]  # it got there by learning, not by starting there


@pytest.mark.parametrize("epsilon", [0.3, 1.0])
def test_converges_with_partial_rate_from_a_wrong_start(epsilon):
    rng = np.random.default_rng(4)
    J_true = rng.normal(size=(30, 12))
    est = BroydenJacobian(J_true + rng.normal(size=J_true.shape), epsilon=epsilon)
    for _ in range(1500):
        u = rng.normal(size=12) * 0.01
        est.update(u, J_true @ u)
    assert np.linalg.norm(est.J - J_true) / np.linalg.norm(J_true) < 1e-2


def _synthetic_jacobian(m: SyntheticRim, g: dict, eps: float = 1e-6) -> np.ndarray:
    f0 = m.rim(g).ravel()
    return np.stack([(m.rim(apply_increment(g, e * eps)).ravel() - f0) / eps for e in np.eye(12)], axis=1)


def test_tracks_the_local_jacobian_of_a_nonlinear_model():
    """The synthetic rim is nonlinear in the grippers' poses: small random moves about one pose
    make Broyden's estimate the local Jacobian there."""
    m = SyntheticRim(16)
    g = apply_increment(m.home(), np.array([0.01, 0.0, 0.05, 0.0, 0.1, 0.0, -0.01, 0.0, 0.05, 0.0, -0.1, 0.0]))
    J_true = _synthetic_jacobian(m, g)
    x0 = m.rim(g).ravel()
    est = BroydenJacobian(np.zeros_like(J_true), epsilon=1.0)
    rng = np.random.default_rng(1)
    for _ in range(300):
        u = rng.normal(size=12) * 2e-4
        est.update(u, m.rim(apply_increment(g, u)).ravel() - x0)
    assert np.linalg.norm(est.J - J_true) / np.linalg.norm(J_true) < 0.05


def test_follows_the_jacobian_along_a_nonlinear_trajectory():
    """Moving on (each update from the step actually taken), the estimate keeps up with J as it changes."""
    m = SyntheticRim(16)
    g = m.home()
    est = BroydenJacobian(_synthetic_jacobian(m, g), epsilon=0.5)
    rng = np.random.default_rng(5)
    drift = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0]) * 5e-4
    for _ in range(200):
        u = drift + rng.normal(size=12) * 5e-4
        g2 = apply_increment(g, u)
        est.update(u, (m.rim(g2) - m.rim(g)).ravel())
        g = g2
    J_now = _synthetic_jacobian(m, g)
    J_start = _synthetic_jacobian(m, m.home())
    err = np.linalg.norm(est.J - J_now)
    assert err < 0.1 * np.linalg.norm(J_now)
    assert err < 0.5 * np.linalg.norm(J_start - J_now)  # closer to today's J than the initial one was


def test_guards_skip_tiny_and_non_finite_steps_and_bound_the_norm():
    est = BroydenJacobian(np.ones((6, 12)), epsilon=0.5, max_norm=5.0)
    J = est.J.copy()
    assert np.linalg.norm(J) <= 5.0 + 1e-12  # the start is bounded too
    assert not est.update(np.full(12, 1e-6), np.ones(6))  # tiny step: noise / ~0
    assert not est.update(np.full(12, np.nan), np.ones(6))
    assert not est.update(np.ones(12) * 0.01, np.full(6, np.inf))
    assert np.array_equal(est.J, J) and est.skipped == 3 and est.updates == 0
    assert est.update(np.ones(12) * 0.01, np.ones(6) * 1e6)  # a glitch cannot blow J up
    assert np.linalg.norm(est.J) <= 5.0 + 1e-9 and est.clamped == 1
    assert np.all(np.isfinite(est.J))
    with pytest.raises(ValueError):
        est.update(np.ones(11), np.ones(6))
    with pytest.raises(ValueError):
        BroydenJacobian(J, epsilon=0.0)
    with pytest.raises(ValueError):
        BroydenJacobian(J, epsilon=1.5)
    with pytest.raises(ValueError):
        BroydenJacobian(np.full((6, 12), np.nan))


def test_finite_differences_from_pushes_give_the_jacobian():
    rng = np.random.default_rng(2)
    J_true = rng.normal(size=(30, 12))
    U = exploration_inputs()
    assert U.shape == (24, 12) and np.abs(U).max() <= 0.04
    assert np.allclose(jacobian_from_exploration(U, U @ J_true.T), J_true)


def test_exploration_is_short_bounded_returns_home_and_measures_j():
    rng = np.random.default_rng(3)
    u_max = c7_limits(MethodParams())
    J_true = rng.normal(size=(24, 12))
    ex = Exploration(u_max, push_ticks=4, settle_ticks=2)
    r = np.zeros(12)  # the accumulated pose offset
    x = rng.normal(size=24)
    ticks = calls = 0
    while True:
        calls += 1
        if calls % 7 == 3:  # a held tick (no valid SOI): the caller does not call the exploration
            continue
        u = ex.next_input(x)
        if u is None:
            break
        assert np.all(np.abs(u) <= u_max + 1e-15)  # C7 every tick
        r += u
        assert np.all(np.abs(r) <= 4 * u_max + 1e-12)  # never more than one push away from the start
        x = x + J_true @ u + rng.normal(size=24) * 1e-9
        ticks += 1
    assert ex.done and ticks == ex.total_ticks == 24 * 6
    assert np.allclose(r, 0.0, atol=1e-15)  # back where it started
    assert np.allclose(ex.jacobian(), J_true, atol=1e-5)
    assert ex.next_input(x) is None


def test_exploration_jacobian_of_the_synthetic_rim_is_close_to_the_true_one():
    """Pushes of a few mm on a nonlinear rim: central differences land within 10 % of the true J."""
    m = SyntheticRim(32)
    g = m.home()
    ex = Exploration(c7_limits(MethodParams()))
    while (u := ex.next_input(m.rim(g).ravel())) is not None:
        g = apply_increment(g, u)
    J_true = _synthetic_jacobian(m, m.home())
    assert np.linalg.norm(ex.jacobian() - J_true) / np.linalg.norm(J_true) < 0.1


def test_scaled_update_keeps_the_secant_condition_and_converges():
    """In units of each input's limit the update still satisfies J_new u = J u + eps (s - J u), and
    corrections no longer pile onto the inputs with the larger raw numbers (radians)."""
    rng = np.random.default_rng(8)
    scale = c7_limits(MethodParams())
    J_true = rng.normal(size=(30, 12)) / scale * 1e-3  # every input moves the SOI about equally per tick
    est = BroydenJacobian(np.zeros((30, 12)), epsilon=0.5, input_scale=scale, min_step=0.5, max_norm=1e6)
    u = rng.normal(size=12) * scale
    J_before = est.J.copy()
    assert est.update(u, J_true @ u)
    assert np.allclose(est.J @ u, J_before @ u + 0.5 * (J_true @ u - J_before @ u))
    assert not est.update(0.1 * scale * np.eye(12)[0], np.ones(30))  # a tenth of one tick: too small to learn
    for _ in range(800):
        u = rng.normal(size=12) * scale
        est.update(u, J_true @ u)
    assert np.linalg.norm((est.J - J_true) * scale) / np.linalg.norm(J_true * scale) < 1e-3
    with pytest.raises(ValueError):
        BroydenJacobian(np.zeros((30, 12)), input_scale=np.zeros(12))


def test_rigid_pair_response_is_the_rim_carried_by_both_grippers():
    """Moving both grippers as one body (a few mm, a few hundredths of a radian about their midpoint,
    turned off the rest pose) moves the synthetic rim, which follows its clamps, as predicted."""
    m = SyntheticRim(32)
    g = apply_increment(m.home(), np.array([0.01, -0.02, 0.03, 0.1, -0.2, 0.15, -0.01, 0.02, -0.01, 0.1, -0.2, 0.15]))
    pl, pr = g["left"][:3, 3], g["right"][:3, 3]
    B = rigid_pair_motions(pl, pr)
    R = rigid_pair_response(m.rim(g), pl, pr)
    assert B.shape == (12, 6) and R.shape == (96, 6)
    h = 1e-5
    for k in range(6):
        fd = (m.rim(apply_increment(g, h * B[:, k])) - m.rim(apply_increment(g, -h * B[:, k]))).ravel() / (2 * h)
        assert np.allclose(fd, R[:, k], atol=1e-6), k


def test_the_measured_turns_are_the_lines_turn_in_place_then_two_across_it_and_the_rim_follows_them():
    """`turns="measured"`: the three translations, the turn about the grippers' line, which moves neither
    gripper (it turns each in place), then the horizontal turn across the line and the one across both;
    the synthetic rim follows each as predicted. Grippers at one point have no line: a clear error, not
    a NaN in J."""
    m = SyntheticRim(32)
    g = apply_increment(m.home(), np.array([0.01, -0.02, 0.03, 0.1, -0.2, 0.15, -0.01, 0.02, -0.01, 0.1, -0.2, 0.15]))
    pl, pr = g["left"][:3, 3], g["right"][:3, 3]
    B, R = rigid_pair_motions(pl, pr, "measured"), rigid_pair_response(m.rim(g), pl, pr, "measured")
    assert B.shape == (12, 6) and R.shape == (96, 6)
    assert np.allclose(B[:, :3], rigid_pair_motions(pl, pr)[:, :3]) and np.allclose(B[[0, 1, 2, 6, 7, 8], 3], 0.0)
    line = (pr - pl) / np.linalg.norm(pr - pl)
    axes = B[3:6, 3:].T  # (3, 3): the line, the horizontal axis across it, the one across both
    assert np.allclose(axes[0], line) and np.allclose(B[9:12, 3:], B[3:6, 3:])
    assert np.allclose(axes @ axes.T, np.eye(3)) and abs(axes[1, 2]) < 1e-12  # orthonormal; the second horizontal
    h = 1e-5
    for k in range(6):
        fd = (m.rim(apply_increment(g, h * B[:, k])) - m.rim(apply_increment(g, -h * B[:, k]))).ravel() / (2 * h)
        assert np.allclose(fd, R[:, k], atol=1e-6), k
    with pytest.raises(NumericalFailure, match="no line"):
        rigid_pair_motions(pl, pl, "measured")


def test_pin_sets_the_pinned_directions_and_keeps_the_rest():
    """After `pin`, J maps the basis to the response exactly; its action on inputs orthogonal to the
    basis (in the update's C7 units) is J's before."""
    rng = np.random.default_rng(9)
    u_max = c7_limits(MethodParams())
    est = BroydenJacobian(rng.normal(size=(96, 12)), input_scale=u_max)
    J_before = est.J.copy()
    B, R = rng.normal(size=(12, 6)), rng.normal(size=(96, 6))
    est.pin(B, R)
    assert np.allclose(est.J @ B, R)
    v = rng.normal(size=12)
    W = 1.0 / u_max**2
    v -= B @ np.linalg.solve((B.T * W) @ B, (B.T * W) @ v)  # the share of v orthogonal to B
    assert np.allclose(est.J @ v, J_before @ v) and not np.allclose(est.J, J_before)
    with pytest.raises(ValueError):
        est.pin(B[:, :3], R)
