"""CR5 kinematics: Dobot's own numbers, forward/inverse round trips, reach, limits, self-collision, pose convention."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bagit.common import cr5


def _urdf_chain(q: np.ndarray) -> np.ndarray:
    """The CR5 URDF's joint origins (xyz, rpy) and z axes, chained independently of the DH model."""
    joints = [
        ((0, 0, 0.147), (0, 0, 0)),
        ((0, 0, 0), (np.pi / 2, np.pi / 2, 0)),
        ((-0.427, 0, 0), (0, 0, 0)),
        ((-0.357, 0, 0.141), (0, 0, -np.pi / 2)),
        ((0, -0.116, 0), (np.pi / 2, 0, 0)),
        ((0, 0.105, 0), (-np.pi / 2, 0, 0)),
    ]
    T = np.eye(4)
    for (xyz, rpy), qi in zip(joints, q, strict=False):
        J = np.eye(4)
        J[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix() @ Rotation.from_euler("z", qi).as_matrix()
        J[:3, 3] = xyz
        T = T @ J
    return T


def test_dh_model_equals_the_urdf_chain():
    rng = np.random.default_rng(3)
    for q in rng.uniform(-np.pi, np.pi, (50, 6)):
        assert np.allclose(cr5.fk(q), _urdf_chain(q), atol=1e-12)


def test_zero_is_upright_and_dobots_positivekin_example():
    T = cr5.fk(np.zeros(6))
    assert T[2, 3] == pytest.approx(cr5.D1 - cr5.A2 - cr5.A3 + cr5.D5)  # straight up: 1.047 m
    # Dobot's manual: PositiveKin(0,0,-90,0,90,0) -> {473,-141,469,-180,0,-90}
    pose = cr5.matrix_to_pose6(cr5.fk(np.radians([0, 0, -90, 0, 90, 0])))
    assert np.allclose(pose[:3], [473, -141, 469], atol=1e-6)
    R_doc = cr5.pose6_to_matrix([0, 0, 0, -180, 0, -90])[:3, :3]
    assert np.allclose(cr5.fk(np.radians([0, 0, -90, 0, 90, 0]))[:3, :3], R_doc, atol=1e-9)


def test_analytic_ik_contains_the_true_angles_and_all_solutions_are_exact():
    rng = np.random.default_rng(0)
    for _ in range(200):
        q = rng.uniform(-np.pi, np.pi, 6)
        q[2] = rng.uniform(-2.7, 2.7)
        T = cr5.fk(q)
        sols = cr5.ik_all(T)
        assert 1 <= len(sols) <= 8
        assert any(np.allclose((s - q + np.pi) % (2 * np.pi) - np.pi, 0, atol=1e-6) for s in sols)
        for s in sols:
            assert np.allclose(cr5.fk(s), T, atol=1e-6)


def test_ik_picks_the_solution_nearest_the_seed():
    rng = np.random.default_rng(1)
    hits = 0
    for _ in range(100):
        q = rng.uniform(-2.5, 2.5, 6)
        q[2] = rng.uniform(-2.6, 2.6)
        sol = cr5.ik(cr5.fk(q), q + rng.normal(0, 0.1, 6))
        assert sol is not None and cr5.within_limits(sol)
        assert np.allclose(cr5.fk(sol), cr5.fk(q), atol=1e-6)
        hits += bool(np.allclose(sol, q, atol=1e-6))
    assert hits >= 95
    # whole turns: a seed near +300 deg on J1 keeps J1 near +300 deg
    q = np.radians([300.0, 10, 60, -30, 80, 0])
    assert cr5.ik(cr5.fk(q), q) == pytest.approx(q, abs=1e-6)


def test_out_of_reach_and_bad_input():
    far = np.eye(4)
    far[:3, 3] = [1.5, 0.0, 0.3]
    assert cr5.ik(far, np.zeros(6)) is None
    assert len(cr5.ik_all(far)) == 0
    assert cr5.ik(np.full((4, 4), np.nan), np.zeros(6)) is None
    assert cr5.ik(np.eye(3), np.zeros(6)) is None
    assert cr5.ik(cr5.fk(np.ones(6)), np.full(6, np.inf)) is None
    assert not cr5.within_limits(np.radians([0, 0, 170, 0, 0, 0]))
    assert cr5.within_limits(np.radians([350, -350, 159, 0, 0, 0]))
    # reach: nothing the arm reaches is farther than 0.9 m + the flange from the shoulder
    rng = np.random.default_rng(2)
    shoulder = np.array([0, 0, cr5.D1])
    d = [np.linalg.norm(cr5.fk(q)[:3, 3] - shoulder) for q in rng.uniform(-np.pi, np.pi, (500, 6))]
    assert max(d) <= cr5.REACH_M + cr5.D6


def test_self_collision_model():
    # a comfortable working pose is free; the flange folded back onto the base column (J3 near its limit) is not
    assert not cr5.self_collision(np.radians([0, 0, -90, 0, 90, 0]))
    assert not cr5.self_collision(np.radians([0, 30, -100, -20, 90, 0]))
    folded = np.radians([0, 35, 157, 32, -146, -127])
    assert cr5.self_collision(folded)
    rng = np.random.default_rng(4)
    free = sum(not cr5.self_collision(q) for q in rng.uniform(-np.pi, np.pi, (200, 6)))
    assert 100 < free < 200  # most random poses are free, some are not


def test_ik_can_refuse_self_colliding_solutions():
    folded = np.radians([0, 35, 157, 32, -146, -127])
    T = cr5.fk(folded)
    plain = cr5.ik(T, folded)
    assert plain == pytest.approx(folded, abs=1e-6)
    safe = cr5.ik(T, folded, avoid_self_collision=True)
    assert safe is None or not cr5.self_collision(safe)


def test_pose6_convention_round_trip():
    pose = np.array([350.0, -120.0, 420.0, 170.0, -10.0, 45.0])
    T = cr5.pose6_to_matrix(pose)
    assert np.allclose(T[:3, 3], [0.35, -0.12, 0.42])
    # fixed-axis X-Y-Z: R = Rz(rz) Ry(ry) Rx(rx)
    Rx, Ry, Rz = (Rotation.from_euler(a, np.radians(v)).as_matrix() for a, v in zip("xyz", pose[3:], strict=False))
    assert np.allclose(T[:3, :3], Rz @ Ry @ Rx)
    assert np.allclose(cr5.matrix_to_pose6(T), pose)
