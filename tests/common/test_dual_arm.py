"""The typed dual-arm increment and the one way it moves gripper poses (common/dual_arm.py)."""

import numpy as np
import pytest

from bagit.common.dual_arm import (
    ROTATION,
    TRANSLATION,
    DualArmIncrement,
    apply_increment,
    check_increment,
    pose_increment,
)
from bagit.common.so3 import rpy_to_matrix
from bagit.services.arm_driver.targets import TargetIntegrator


def _poses(rng):
    out = {}
    for a in ("left", "right"):
        T = np.eye(4)
        T[:3, :3] = rpy_to_matrix(rng.uniform(-1, 1, 3))
        T[:3, 3] = rng.uniform(-0.3, 0.3, 3)
        out[a] = T
    return out


def test_the_increment_round_trips_and_names_its_halves():
    u = np.arange(12.0)
    inc = DualArmIncrement.from_array(u)
    assert np.array_equal(inc.left, u[:6]) and np.array_equal(inc.right, u[6:])
    assert np.array_equal(inc.translation("right"), u[TRANSLATION["right"]])
    assert np.array_equal(inc.rotation("left"), u[ROTATION["left"]])
    assert np.array_equal(inc.to_array(), u)
    assert not np.any(DualArmIncrement.zero().to_array())


@pytest.mark.parametrize("bad", [np.zeros(11), np.zeros((2, 6)), np.zeros(13)])
def test_a_wrong_shape_is_refused_where_it_enters(bad):
    with pytest.raises(ValueError, match="shape"):
        DualArmIncrement.from_array(bad)
    with pytest.raises(ValueError, match="shape"):
        check_increment(bad)
    with pytest.raises(ValueError):
        DualArmIncrement(np.zeros(6), np.zeros(5))


def test_poses_without_both_arms_are_refused():
    with pytest.raises(ValueError, match="right"):
        apply_increment({"left": np.eye(4)}, np.zeros(12))
    with pytest.raises(ValueError, match="left"):
        apply_increment({"left": np.eye(3), "right": np.eye(4)}, np.zeros(12))


def test_pose_increment_inverts_apply_increment():
    rng = np.random.default_rng(3)
    for _ in range(20):
        g = _poses(rng)
        u = rng.normal(size=12) * np.tile([0.01] * 3 + [0.05] * 3, 2)
        after = apply_increment(g, u)
        assert np.allclose(pose_increment(g, after), u, atol=1e-12)
        assert np.array_equal(apply_increment(g, DualArmIncrement.from_array(u))["left"], after["left"])
        for a in ("left", "right"):  # rotations are world-frame increments: R' = exp(drot) R
            assert np.allclose(after[a][:3, :3] @ g[a][:3, :3].T, apply_increment({"left": np.eye(4), "right": np.eye(4)}, u)[a][:3, :3])


def test_the_arm_driver_moves_its_target_by_the_same_function():
    """The driver's target and the controller's prediction are one computation, bit for bit."""
    rng = np.random.default_rng(5)
    g = _poses(rng)
    ti = TargetIntegrator()
    ti.reset(g)
    u = rng.normal(size=12) * 0.01
    end = ti.proposed_end(u)
    want = apply_increment(ti.end(), u)
    for a in ("left", "right"):
        assert np.array_equal(end[a], want[a])
