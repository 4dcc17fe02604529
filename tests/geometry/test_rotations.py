"""Rotation helpers (geometry/rotations.py) against scipy's Rotation and finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from visionpos.geometry.rotations import (
    average_rotations,
    euler_rate_matrix,
    euler_rate_matrix_inverse,
    euler_zyx_from_matrix,
    left_jacobian_SO3,
    left_jacobian_SO3_inv,
    matrix_from_quat,
    matrix_from_rotvec,
    matrix_from_rotvec_compiled,
    quat_from_matrix,
    quat_from_matrix_compiled,
    quat_from_rotvec,
    quat_multiply,
    rotvec_from_matrix,
    rotvec_from_matrix_compiled,
    skew,
)


def _rotvecs(rng, n=200):
    """Rotation vectors over all angles, plus the awkward ones: tiny, zero, exactly and nearly pi."""
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi, n - 6), [0.0, 1e-9, 1e-5, np.pi - 1e-7, np.pi, np.pi]])
    rv = axes * angles[:, None]
    rv[-1] = [0.0, 0.0, np.pi]  # half turn about an axis (trace -1: the quaternion's w is 0)
    return rv


def test_matrix_from_rotvec_matches_scipy():
    for rv in _rotvecs(np.random.default_rng(1)):
        np.testing.assert_allclose(matrix_from_rotvec(rv), Rotation.from_rotvec(rv).as_matrix(), atol=1e-14)


def test_rotvec_from_matrix_matches_scipy_and_inverts():
    for rv in _rotvecs(np.random.default_rng(2)):
        R = Rotation.from_rotvec(rv).as_matrix()
        got = rotvec_from_matrix(R)
        assert np.linalg.norm(got) <= np.pi + 1e-12
        # at exactly pi +axis and -axis are the same rotation
        if np.linalg.norm(rv) > np.pi - 1e-6:
            np.testing.assert_allclose(matrix_from_rotvec(got), R, atol=1e-12)
        else:
            np.testing.assert_allclose(got, Rotation.from_matrix(R).as_rotvec(), atol=1e-12)


def test_quaternions_match_scipy():
    rng = np.random.default_rng(3)
    for rv in _rotvecs(rng):
        ref = Rotation.from_rotvec(rv)
        q = ref.as_quat()
        q = -q if q[3] < 0 else q
        got = quat_from_matrix(ref.as_matrix())
        assert got[3] >= 0
        if q[3] > 1e-6:  # away from w = 0 the sign convention makes the quaternion unique
            np.testing.assert_allclose(got, q, atol=1e-12)
        np.testing.assert_allclose(Rotation.from_quat(got).as_matrix(), ref.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(quat_from_rotvec(rv), ref.as_quat() * np.sign(ref.as_quat()[3] or 1.0),
                                   atol=1e-12)
        np.testing.assert_allclose(matrix_from_quat(3.0 * q), ref.as_matrix(), atol=1e-12)  # any norm
    a, b = Rotation.random(2, random_state=4)
    ab = quat_multiply(a.as_quat(), b.as_quat())
    np.testing.assert_allclose(Rotation.from_quat(ab).as_matrix(), (a * b).as_matrix(), atol=1e-12)


def test_compiled_kernels_are_what_the_wrappers_return():
    rng = np.random.default_rng(5)
    for rv in _rotvecs(rng, 20):
        R = matrix_from_rotvec_compiled(np.ascontiguousarray(rv))
        np.testing.assert_array_equal(R, matrix_from_rotvec(list(rv)))
        np.testing.assert_array_equal(rotvec_from_matrix_compiled(R), rotvec_from_matrix(R))
        np.testing.assert_array_equal(np.array(quat_from_matrix_compiled(R)), quat_from_matrix(R))


def test_skew_is_the_cross_product_batched():
    rng = np.random.default_rng(6)
    a, b = rng.normal(size=(2, 7, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", skew(a), b), np.cross(a, b), atol=1e-14)
    np.testing.assert_array_equal(skew(a[0]), -skew(a[0]).T)


@pytest.mark.parametrize("seed", range(4))
def test_euler_zyx_matches_scipy(seed):
    R = Rotation.random(random_state=seed)
    np.testing.assert_allclose(euler_zyx_from_matrix(R.as_matrix()), R.as_euler("ZYX")[::-1], atol=1e-12)
    Rs = Rotation.random(6, random_state=seed)
    np.testing.assert_allclose(euler_zyx_from_matrix(Rs.as_matrix()), Rs.as_euler("ZYX")[:, ::-1], atol=1e-12)


def test_euler_rate_matrix_matches_finite_differences_and_its_inverse():
    """w = E(e) de/dt: the spatial angular velocity of R(e(t)) = Rz Ry Rx, from scipy, by central differences."""
    rng = np.random.default_rng(7)
    for _ in range(5):
        e = rng.uniform([-3, -1.2, -3], [3, 1.2, 3])
        de = rng.normal(size=3)
        h = 1e-6
        R = lambda x: Rotation.from_euler("ZYX", x[::-1])  # noqa: E731
        w = (R(e + h * de) * R(e - h * de).inv()).as_rotvec() / (2 * h)
        np.testing.assert_allclose(euler_rate_matrix(e) @ de, w, atol=1e-7)
        np.testing.assert_allclose(euler_rate_matrix_inverse(e) @ euler_rate_matrix(e), np.eye(3), atol=1e-12)


def test_average_rotations_recovers_centre():
    rng = np.random.default_rng(12)
    R0 = Rotation.random(random_state=3)
    d = rng.normal(0, 0.05, (50, 3))
    Rs = (R0 * Rotation.from_rotvec(np.vstack([d, -d]))).as_matrix()  # symmetric spread
    assert np.abs(average_rotations(Rs) - R0.as_matrix()).max() < 1e-3


def test_average_rotations_weights_pick_the_rotation():
    Rs = Rotation.random(2, random_state=8).as_matrix()
    np.testing.assert_allclose(average_rotations(Rs, weights=[0.0, 1.0]), Rs[1], atol=1e-12)
    with pytest.raises(ValueError, match="weights"):
        average_rotations(Rs, weights=[-1.0, 1.0])


def _numerical_left_jacobian(rotvec: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """d/dd log(exp(rotvec + d) exp(rotvec)^-1) at d = 0 by central differences of scipy's exponential map."""
    R0inv = Rotation.from_rotvec(rotvec).inv()
    J = np.zeros((3, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        plus = (Rotation.from_rotvec(rotvec + d) * R0inv).as_rotvec()
        minus = (Rotation.from_rotvec(rotvec - d) * R0inv).as_rotvec()
        J[:, k] = (plus - minus) / (2 * h)
    return J


def _numerical_left_jacobian_inv(rotvec: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """d/dd log(exp(d) exp(rotvec)) at d = 0: how the rotation vector moves when the rotation turns on the left."""
    R0 = Rotation.from_rotvec(rotvec)
    J = np.zeros((3, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        plus = (Rotation.from_rotvec(d) * R0).as_rotvec()
        minus = (Rotation.from_rotvec(-d) * R0).as_rotvec()
        J[:, k] = (plus - minus) / (2 * h)
    return J


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-4, 0.3, 1.5, 3.0])
def test_left_jacobian_matches_finite_differences_of_the_exponential_map(angle):
    rng = np.random.default_rng(7)
    for _ in range(5):
        axis = rng.normal(size=3)
        rv = axis / np.linalg.norm(axis) * angle
        assert np.allclose(left_jacobian_SO3(rv), _numerical_left_jacobian(rv), atol=1e-7)
        assert np.allclose(left_jacobian_SO3_inv(rv), _numerical_left_jacobian_inv(rv), atol=1e-7)


def test_left_jacobian_batches_and_its_inverse_inverts_it():
    rng = np.random.default_rng(8)
    rvs = rng.normal(size=(4, 5, 3))
    rvs *= (rng.uniform(0.0, 3.1, size=(4, 5)) / np.linalg.norm(rvs, axis=-1))[..., None]
    J, Jinv = left_jacobian_SO3(rvs), left_jacobian_SO3_inv(rvs)
    assert J.shape == Jinv.shape == (4, 5, 3, 3)
    assert np.allclose(J @ Jinv, np.eye(3), atol=1e-12)
    assert np.allclose(J[2, 3], left_jacobian_SO3(rvs[2, 3]))
    # the left Jacobian turns the rotation vector itself into itself (rotations about one axis commute)
    assert np.allclose(np.einsum("abij,abj->abi", J, rvs), rvs)
