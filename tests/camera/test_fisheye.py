"""Kannala-Brandt fisheye model (camera/fisheye.py) against cv2.fisheye, finite differences, its compiled form."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from visionpos.camera import fisheye

# thesis Table 4.1, V2 NoIR cameras 1 and 3 (Kannala-Brandt k1..k4)
V2_NOIR_1 = np.array([0.396, 0.634, -2.417, 2.111])
V2_NOIR_3 = np.array([0.276, 2.095, -9.980, 14.192])
MODELS = {"noir1": V2_NOIR_1, "noir3": V2_NOIR_3}


def _points(rng, k, n=300, frac=0.9, theta_max=np.pi / 2):
    """(n, 2) normalised points at angles up to frac of the model's largest angle (and theta_max),
    plus the axis."""
    theta = rng.uniform(0, min(frac * fisheye.max_angle(k), theta_max), n)
    phi = rng.uniform(-np.pi, np.pi, n)
    r = np.tan(theta)
    return np.vstack([np.column_stack([r * np.cos(phi), r * np.sin(phi)]), [[0.0, 0.0]]])


def _cv2_distort(xn, k):
    """cv2.fisheye.distortPoints with K = I: the distorted normalised points."""
    return cv2.fisheye.distortPoints(xn.reshape(-1, 1, 2), np.eye(3), k).reshape(-1, 2)


@pytest.mark.parametrize("name", MODELS)
def test_distort_matches_cv2_fisheye(name):
    k = MODELS[name]
    xn = _points(np.random.default_rng(1), k)
    np.testing.assert_allclose(fisheye.distort(xn, k), _cv2_distort(xn, k), atol=1e-12)
    # and the projection of (x, y, 1) through cv2.fisheye.projectPoints
    X = np.column_stack([xn, np.ones(len(xn))]).reshape(-1, 1, 3)
    uv, _ = cv2.fisheye.projectPoints(X, np.zeros((3, 1)), np.zeros((3, 1)), np.eye(3), k)
    np.testing.assert_allclose(fisheye.distort(xn, k), uv.reshape(-1, 2), atol=1e-12)


@pytest.mark.parametrize("name", MODELS)
def test_undistort_matches_cv2_fisheye_undistort_points(name):
    k = MODELS[name]
    # cv2's solver loses its way beyond ~45 deg on these lenses (ours does not: see the round trip)
    xn = _points(np.random.default_rng(2), k, theta_max=np.radians(35))
    xd = _cv2_distort(xn, k)
    ref = cv2.fisheye.undistortPoints(xd.reshape(-1, 1, 2), np.eye(3), k,
                                      criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15))
    np.testing.assert_allclose(fisheye.undistort(xd, k), ref.reshape(-1, 2), rtol=1e-9, atol=1e-10)
    wide = _points(np.random.default_rng(3), k, frac=0.95)
    np.testing.assert_allclose(fisheye.undistort(fisheye.distort(wide, k), k), wide, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("name", MODELS)
def test_jacobian_matches_central_differences(name):
    k = MODELS[name]
    xn = _points(np.random.default_rng(3), k, 50)
    _, J = fisheye.distort_with_jacobian(xn, k)
    h = 1e-7
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        fd = (_cv2_distort(xn + e, k) - _cv2_distort(xn - e, k)) / (2 * h)
        np.testing.assert_allclose(J[:, :, j], fd, atol=1e-6)
    np.testing.assert_allclose(J[-1], np.eye(2), atol=1e-15)  # on the axis: identity


def test_radius_polynomial_derivative_matches_central_differences():
    theta = np.linspace(0.0, 1.2, 50)
    h = 1e-6
    r, dr = fisheye.radius_from_angle(theta, V2_NOIR_3)
    fd = (fisheye.radius_from_angle(theta + h, V2_NOIR_3)[0] - fisheye.radius_from_angle(theta - h, V2_NOIR_3)[0])
    fd /= 2 * h
    np.testing.assert_allclose(dr, fd, atol=1e-7)
    for i in range(len(theta)):
        assert fisheye.radius_from_angle_point(theta[i], V2_NOIR_3) == (r[i], dr[i])


@pytest.mark.parametrize("name", MODELS)
def test_compiled_forms_equal_vectorised_forms(name):
    k = MODELS[name]
    xn = _points(np.random.default_rng(5), k, 100)
    xd = fisheye.distort(xn, k)
    back = fisheye.undistort(xd, k)
    for i, (x, y) in enumerate(xn):
        np.testing.assert_allclose(fisheye.distort_point(x, y, k), xd[i], rtol=1e-14, atol=1e-16)
        ux, uy, ok = fisheye.undistort_point(xd[i, 0], xd[i, 1], k)
        assert ok
        np.testing.assert_allclose([ux, uy], back[i], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("name", MODELS)
def test_compiled_jacobian_equals_the_vectorised_one(name):
    k = MODELS[name]
    xn = np.vstack([_points(np.random.default_rng(6), k, 100), [[0.0, 0.0], [1e-9, -2e-9]]])  # on the axis too
    _, J = fisheye.distort_with_jacobian(xn, k)
    for i, (x, y) in enumerate(xn):
        np.testing.assert_allclose(np.reshape(fisheye.distort_jacobian_point(x, y, k), (2, 2)), J[i], rtol=1e-12,
                                   atol=1e-12)


def test_largest_angle_and_beyond_it():
    k = V2_NOIR_3
    theta = fisheye.max_angle(k)
    _, dr = fisheye.radius_from_angle(np.linspace(0, theta, 100), k)
    assert (dr > 0).all()  # one-to-one up to the largest angle
    r_max = fisheye.radius_from_angle(theta, k)[0]
    _, _, ok = fisheye.undistort_point(1.5 * r_max, 0.0, k)
    assert not ok  # a radius the lens never reaches has no ray


def test_coefficient_rows_broadcast_over_cameras():
    rng = np.random.default_rng(6)
    xn = np.stack([_points(rng, k, 19) for k in (V2_NOIR_1, V2_NOIR_3)], axis=1)  # (20, 2, 2)
    kT = np.stack([V2_NOIR_1, V2_NOIR_3], axis=1)
    xd, J = fisheye.distort_with_jacobian(xn, kT)
    for v, k in enumerate((V2_NOIR_1, V2_NOIR_3)):
        xd_v, J_v = fisheye.distort_with_jacobian(xn[:, v], k)
        np.testing.assert_array_equal(xd[:, v], xd_v)
        np.testing.assert_array_equal(J[:, v], J_v)
