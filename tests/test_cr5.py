"""CR5 kinematics: forward/inverse round trips, reach, limits, Dobot's pose convention."""

import numpy as np
import pytest

from bagit.common import cr5


def test_zero_pose_matches_the_link_offsets():
    T = cr5.fk(np.zeros(6))
    # UR-style zero pose: arm stretched along -x of the base, flange offset by d4 and d6
    assert T[0, 3] == pytest.approx(cr5.A2 + cr5.A3)
    assert T[2, 3] == pytest.approx(cr5.D1 - cr5.D5)
    assert abs(T[1, 3]) == pytest.approx(cr5.D4 + cr5.D6)


def test_ik_round_trip_on_random_reachable_poses():
    rng = np.random.default_rng(0)
    ok = 0
    for _ in range(30):
        q = rng.uniform(-2.5, 2.5, 6)
        q[2] = rng.uniform(-2.6, 2.6)
        T = cr5.fk(q)
        seed = q + rng.normal(0, 0.15, 6)
        sol = cr5.ik(T, seed)
        if sol is None:
            continue
        ok += 1
        assert np.allclose(cr5.fk(sol)[:3, 3], T[:3, 3], atol=2e-4)
        assert cr5.within_limits(sol)
    assert ok >= 27


def test_out_of_reach_and_bad_input():
    far = np.eye(4)
    far[:3, 3] = [1.5, 0.0, 0.3]
    assert cr5.ik(far, np.zeros(6)) is None
    bad = np.full((4, 4), np.nan)
    assert cr5.ik(bad, np.zeros(6)) is None
    assert not cr5.within_limits(np.radians([0, 0, 170, 0, 0, 0]))


def test_pose6_convention_round_trip():
    pose = np.array([350.0, -120.0, 420.0, 170.0, -10.0, 45.0])
    T = cr5.pose6_to_matrix(pose)
    assert np.allclose(T[:3, 3], [0.35, -0.12, 0.42])
    assert np.allclose(cr5.matrix_to_pose6(T), pose)
