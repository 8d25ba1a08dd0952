"""The SO(3) helpers of the per-packet loops against scipy's Rotation, the reference they replace for speed."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bagit.common.so3 import left_jacobian, matrix_to_quat_wxyz, matrix_to_rpy, rotvec_between, rpy_to_matrix, so3_exp, so3_log


def test_so3_helpers_match_scipy_and_the_left_jacobian_maps_rates():
    rng = np.random.default_rng(0)
    for _ in range(50):
        r = rng.normal(size=3) * rng.uniform(0, 3.0)
        assert np.allclose(so3_exp(r), Rotation.from_rotvec(r).as_matrix(), atol=1e-12)
        assert np.allclose(so3_exp(so3_log(so3_exp(r))), so3_exp(r), atol=1e-9)
        R0 = Rotation.random(random_state=int(rng.integers(1e6))).as_matrix()
        assert np.allclose(so3_exp(rotvec_between(R0, so3_exp(r) @ R0)) @ R0, so3_exp(r) @ R0, atol=1e-9)
        # omega = J_l(r) r_dot, by finite differences of exp(r(t))
        rdot, h = rng.normal(size=3), 1e-6
        W = (so3_exp(r + h * rdot) - so3_exp(r - h * rdot)) / (2 * h) @ so3_exp(r).T
        omega = np.array([W[2, 1], W[0, 2], W[1, 0]])
        assert np.allclose(omega, left_jacobian(r) @ rdot, atol=1e-6)
    assert np.allclose(so3_log(np.diag([1.0, -1.0, -1.0])), [np.pi, 0, 0])  # at pi the axis still comes out


def _awkward_rotations(rng: np.random.Generator) -> list[np.ndarray]:
    """Random rotations plus the ones closed forms get wrong: identity, half turns, gimbal lock."""
    Rs = [Rotation.random(random_state=int(s)).as_matrix() for s in rng.integers(1e6, size=200)]
    Rs += [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    for pitch in (np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-10):
        Rs.append(Rotation.from_euler("xyz", [0.4, pitch, -1.2]).as_matrix())
    return Rs


def test_euler_and_quaternion_conversions_match_scipy():
    rng = np.random.default_rng(3)
    for R in _awkward_rotations(rng):
        rpy = matrix_to_rpy(R)
        assert np.allclose(rpy_to_matrix(rpy), R, atol=1e-8)  # round trip, gimbal lock included
        assert abs(rpy[1]) <= np.pi / 2 + 1e-12
        if abs(R[2, 0]) < 1 - 1e-6:  # away from gimbal lock the angles are unique: scipy's
            assert np.allclose(rpy, Rotation.from_matrix(R).as_euler("xyz"), atol=1e-9)
        q = matrix_to_quat_wxyz(R)
        x, y, z, w = Rotation.from_matrix(R).as_quat()
        ref = np.array([w, x, y, z])
        assert np.isclose(np.linalg.norm(q), 1.0) and q[0] >= 0
        assert np.allclose(q, ref, atol=1e-9) or np.allclose(q, -ref, atol=1e-9)
    for rpy in rng.uniform(-np.pi, np.pi, size=(100, 3)):
        assert np.allclose(rpy_to_matrix(rpy), Rotation.from_euler("xyz", rpy).as_matrix(), atol=1e-12)


@pytest.mark.parametrize("f", [matrix_to_rpy, matrix_to_quat_wxyz])
def test_conversions_of_a_slightly_non_orthogonal_matrix_stay_finite(f):
    R = Rotation.from_euler("xyz", [0.0, np.pi / 2, 0.0]).as_matrix() * (1 + 1e-12)
    assert np.all(np.isfinite(f(R)))
