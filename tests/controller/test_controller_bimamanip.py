"""BimaManip's learned SOI dynamics (services/controller/soi_gnn.py) and its MPC controller, without a
simulator: the graph network's shapes and symmetry, a training run on a tiny set, the weights' round
trip through a file without pickle, the versioned weights, and the controller (with the tiny trained
model: compiling the MPC through the versioned one costs seconds) on a toy bag whose rim follows the
mounts at once. Skipped without the `learn` extra (JAX, Equinox, Optax)."""

import json
import sys

import numpy as np
import pytest

pytest.importorskip("jax")
pytest.importorskip("equinox")

import equinox as eqx  # noqa: E402
import jax  # noqa: E402

from bagit.common.errors import BadControlInput  # noqa: E402
from bagit.common.geometry import make_transform  # noqa: E402
from bagit.common.params import MethodParams  # noqa: E402
from bagit.services.controller import make_controller, soi_gnn  # noqa: E402
from bagit.services.controller.bimamanip import (  # noqa: E402
    MODEL_TICKS,
    BimaManipController,  # noqa: E402
    planner,
)
from bagit.services.controller.servo import c7_limits  # noqa: E402

N_X = 16
P = MethodParams()
rollout = eqx.filter_jit(soi_gnn.rollout)  # one compilation per model shape, not one per operation


def ring(centre: np.ndarray, radius: float = 0.1, n: int = N_X) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.asarray(centre, dtype=float) + radius * np.stack([np.cos(t), np.sin(t), np.zeros(n)], axis=1)


def grippers_of(rim: np.ndarray) -> np.ndarray:
    """The mounts `(2, 3)` at the rim's ends along y (left at -y)."""
    return np.stack([rim[np.argmin(rim[:, 1])], rim[np.argmax(rim[:, 1])]])


def rigid_set(n: int, seed: int) -> soi_gnn.Transitions:
    """Transitions of a rim that moves with its mounts' mean motion (the rigid part of the bag's response)."""
    rng = np.random.default_rng(seed)
    x = np.stack([ring(rng.uniform(-0.1, 0.1, 3) + [0, 0, 0.5]) for _ in range(n)])
    g = np.stack([grippers_of(r) for r in x])
    a = rng.uniform(-0.008, 0.008, (n, 2, 3))
    u = np.zeros((n, 12))
    u[:, 0:3], u[:, 6:9] = a[:, 0], a[:, 1]
    return soi_gnn.Transitions(x, g, u, x + a.mean(axis=1)[:, None, :])


@pytest.fixture(scope="module")
def trained() -> tuple[soi_gnn.SoiGnn, list[float]]:
    """A tiny model trained on rigid moves (shared: its training is the costly part)."""
    return soi_gnn.train(rigid_set(96, 0), seed=0, epochs=8, batch=8, lr=1e-2, noise_m=0.0, hidden=32, rounds=1)


A = np.array([[0.004, 0.0, 0.002], [0.004, 0.0, -0.001]])


def test_the_model_predicts_a_displacement_per_rim_point_and_ignores_where_the_numbering_starts():
    m = soi_gnn.SoiGnn(jax.random.PRNGKey(0), hidden=16, rounds=1)
    x = ring([0.1, 0.0, 0.5])
    g = grippers_of(x)
    xs = np.asarray(rollout(m, x, g, np.stack([A, A, A])))
    assert xs.shape == (3, N_X, 3) and np.all(np.isfinite(xs))
    shifted = np.asarray(rollout(m, np.roll(x, 5, axis=0), g, np.stack([A, A, A])))  # perception's points start anywhere along the rim
    np.testing.assert_allclose(shifted, np.roll(xs, 5, axis=1), atol=1e-6)


def test_training_lowers_the_loss_and_the_held_out_error_below_standing_still(trained):
    """A few epochs on a tiny set of rigid moves: the loss falls by a quarter at least, and on other moves the
    model beats the rim standing still."""
    m, losses = trained
    assert len(losses) == 8 and losses[-1] < 0.75 * losses[0]
    err = soi_gnn.prediction_error_mm(m, rigid_set(32, 1))
    assert err["model_mm"] < err["still_mm"]


def test_weights_round_trip_through_npy_bytes_and_a_json_record(tmp_path, trained):
    m = trained[0]
    w, rec = tmp_path / "m.eqx", tmp_path / "m.json"
    soi_gnn.save(m, {"seed": 0}, w, rec)
    assert w.read_bytes()[:6] == b"\x93NUMPY"  # numpy's array format, not a pickle
    assert json.loads(rec.read_text()) == {"seed": 0, "architecture": {"hidden": 32, "rounds": 1}}
    x = ring([0.0, 0.0, 0.5])
    acts = np.stack([A, A, A])
    np.testing.assert_array_equal(np.asarray(rollout(soi_gnn.load(w, rec), x, grippers_of(x), acts)),
                                  np.asarray(rollout(m, x, grippers_of(x), acts)))


def test_the_versioned_weights_load_and_move_a_hung_rim_with_its_grippers():
    """services/controller/data/bimamanip.eqx with its record: a rim whose two mounts move 5 mm along x
    (nothing else changing) is predicted to follow them most of the way (the sign and size of the physics)."""
    record = json.loads(soi_gnn.RECORD_FILE.read_text())
    assert record["heldout_error"]["model_mm"] < record["heldout_error"]["with_grippers_mm"]
    m = soi_gnn.load()
    x = ring([0.15, 0.0, 0.475], 0.108, 32)
    a = np.array([[0.005, 0.0, 0.0], [0.005, 0.0, 0.0]])
    d = (np.asarray(rollout(m, x, grippers_of(x), a[None]))[0] - x).mean(axis=0)
    assert 0.0025 < d[0] < 0.0075 and abs(d[1]) < 0.002, d


def test_the_controller_streams_finite_translations_within_c7_and_brings_the_toy_rim_to_g_dagger(tmp_path, trained):
    """A rim that follows its mounts at once, g† 5 cm aside: every command finite, within C7 and without
    rotation, one plan per MODEL_TICKS ticks of servoing, then the settle at g†."""
    soi_gnn.save(trained[0], {}, tmp_path / "m.eqx", tmp_path / "m.json")
    start = ring([0.15, 0.0, 0.475], 0.1, 32)
    dagger = ring([0.10, 0.0, 0.475], 0.1, 32)
    path = np.stack([start, dagger, dagger + [0, 0, 0.05]])
    c = BimaManipController(P, 32, weights=tmp_path / "m.eqx")
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
    assert make_controller("bimamanip", P, 32).name == "bimamanip"  # the same controller by name, as every host makes it


def test_without_the_learn_extra_or_the_weights_the_run_is_refused_with_what_to_do(monkeypatch, tmp_path):
    import bagit.services.controller as package

    monkeypatch.delattr(package, "soi_gnn")
    monkeypatch.setitem(sys.modules, "bagit.services.controller.soi_gnn", None)  # as if JAX were not installed
    with pytest.raises(BadControlInput, match=r"pip install 'bagit\[learn\]'"):
        planner(None, 2, 1, 0.008)
    monkeypatch.undo()
    with pytest.raises(BadControlInput, match="bagit bench bimamanip --train"):
        planner(tmp_path / "none.eqx", 2, 1, 0.008)
