"""BimaManip's learned SOI dynamics (services/controller/soi_gnn.py) and its MPC controller, without a
simulator: the graph network's shapes and symmetry, a training run on a tiny set, the weights' round
trip through a file without pickle, and the controller with the versioned model on a toy bag whose rim
follows the mounts at once. Skipped without the `learn` extra (JAX, Equinox, Optax)."""

import json

import numpy as np
import pytest

pytest.importorskip("jax")
pytest.importorskip("equinox")

import equinox as eqx  # noqa: E402
import jax  # noqa: E402

from bagit.common.geometry import make_transform  # noqa: E402
from bagit.common.params import MethodParams  # noqa: E402
from bagit.services.controller import make_controller, soi_gnn  # noqa: E402
from bagit.services.controller.bimamanip import MODEL_TICKS  # noqa: E402
from bagit.services.controller.servo import c7_limits  # noqa: E402

N_X = 16
P = MethodParams()


def ring(centre: np.ndarray, radius: float = 0.1, n: int = N_X) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.asarray(centre, dtype=float) + radius * np.stack([np.cos(t), np.sin(t), np.zeros(n)], axis=1)


def grippers_of(rim: np.ndarray) -> np.ndarray:
    """The mounts `(2, 3)` at the rim's ends along y (left at -y)."""
    return np.stack([rim[np.argmin(rim[:, 1])], rim[np.argmax(rim[:, 1])]])


predict = eqx.filter_jit(lambda m, x, g, a: m(x, g, a))  # one compilation, not one per operation


def tiny_model(seed: int = 0) -> soi_gnn.SoiGnn:
    return soi_gnn.SoiGnn(jax.random.PRNGKey(seed), hidden=16, rounds=1)


def rigid_set(n: int, seed: int) -> soi_gnn.Transitions:
    """Transitions of a rim that moves with its mounts' mean motion (the rigid part of the bag's response)."""
    rng = np.random.default_rng(seed)
    x = np.stack([ring(rng.uniform(-0.1, 0.1, 3) + [0, 0, 0.5]) for _ in range(n)])
    g = np.stack([grippers_of(r) for r in x])
    a = rng.uniform(-0.008, 0.008, (n, 2, 3))
    u = np.zeros((n, 12))
    u[:, 0:3], u[:, 6:9] = a[:, 0], a[:, 1]
    return soi_gnn.Transitions(x, g, u, x + a.mean(axis=1)[:, None, :])


def test_the_model_predicts_a_displacement_per_rim_point_and_ignores_where_the_numbering_starts():
    m = tiny_model()
    x = ring([0.1, 0.0, 0.5])
    g, a = grippers_of(x), np.array([[0.004, 0.0, 0.002], [0.004, 0.0, -0.001]])
    d = np.asarray(predict(m, x, g, a))
    assert d.shape == (N_X, 3) and np.all(np.isfinite(d))
    shifted = np.asarray(predict(m, np.roll(x, 5, axis=0), g, a))  # perception's points start anywhere along the rim
    np.testing.assert_allclose(shifted, np.roll(d, 5, axis=0), atol=1e-6)
    xs = np.asarray(eqx.filter_jit(soi_gnn.rollout)(m, x, g, np.stack([a, a, a])))
    assert xs.shape == (3, N_X, 3)
    np.testing.assert_allclose(xs[0], x + d, atol=1e-6)


def test_training_lowers_the_loss_and_the_held_out_error_below_standing_still():
    """A few epochs on a tiny set of rigid moves: the loss halves, and on other moves the model beats the rim standing still."""
    data, heldout = rigid_set(96, 0), rigid_set(32, 1)
    m, losses = soi_gnn.train(data, seed=0, epochs=10, batch=16, lr=1e-2, noise_m=0.0)
    assert len(losses) == 10 and losses[-1] < 0.5 * losses[0]
    err = soi_gnn.prediction_error_mm(m, heldout)
    assert err["model_mm"] < err["still_mm"]


def test_weights_round_trip_through_npy_bytes_and_a_json_record(tmp_path):
    m = tiny_model(3)
    w, rec = tmp_path / "m.eqx", tmp_path / "m.json"
    soi_gnn.save(m, {"seed": 3}, w, rec)
    assert w.read_bytes()[:6] == b"\x93NUMPY"  # numpy's array format, not a pickle
    assert json.loads(rec.read_text()) == {"seed": 3, "architecture": {"hidden": 16, "rounds": 1}}
    back = soi_gnn.load(w, rec)
    x = ring([0.0, 0.0, 0.5])
    a = np.full((2, 3), 0.003)
    np.testing.assert_array_equal(np.asarray(predict(back, x, grippers_of(x), a)), np.asarray(predict(m, x, grippers_of(x), a)))


def test_the_controller_streams_finite_translations_within_c7_and_brings_the_toy_rim_to_g_dagger():
    """The versioned model on a rim that follows its mounts at once, g† 5 cm aside: every command finite,
    within C7 and without rotation, one plan per MODEL_TICKS ticks of servoing, then the settle at g†."""
    start = ring([0.15, 0.0, 0.475], 0.1, 32)
    dagger = ring([0.10, 0.0, 0.475], 0.1, 32)
    path = np.stack([start, dagger, dagger + [0, 0, 0.05]])
    c = make_controller("bimamanip", P, 32)
    poses = {arm: make_transform(np.eye(3), p) for arm, p in zip(("left", "right"), grippers_of(start), strict=True)}
    c.reset(start, path, poses, dagger_index=1)
    u_max = c7_limits(P)
    x, modes, plans, errors = start, [], 0, []
    for k in range(90):
        out = c.step(x, k / 30.0, poses)
        modes.append(out.mode)
        errors.append(out.error_to_subgoal)
        assert out.reason is None, out.reason
        assert np.all(np.isfinite(out.u)) and np.all(np.abs(out.u) <= u_max + 1e-12)
        assert np.all(out.u[3:6] == 0) and np.all(out.u[9:12] == 0)
        plans += out.solve_ms > 0
        for arm, sl in (("left", slice(0, 3)), ("right", slice(6, 9))):
            poses[arm] = poses[arm].copy()
            poses[arm][:3, 3] += out.u[sl]
        x = x + 0.5 * (out.u[0:3] + out.u[6:9])
        if out.mode == "settle":
            break
    servo = modes.count("servo")
    assert modes == ["servo"] * servo + ["settle"] and servo > 0, modes
    assert plans == -(-servo // MODEL_TICKS)
    assert errors[0] > 0.04 and errors[-1] <= P.controller.subgoal_tol_m
