"""Pinhole lens model (camera/pinhole.py) against OpenCV, finite differences, and its compiled form."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from visionpos.camera import pinhole

STRONG = np.array([-0.32, 0.12, 0.0015, -0.001, -0.015, 0.0, 0.0, 0.0])  # barrel + tangential
RATIONAL = np.array([0.25, -0.1, 0.001, 0.002, 0.01, 0.1, 0.02, 0.001])
MODELS = {"strong": STRONG, "rational": RATIONAL}


def _points(rng, n=300, r_max=0.6):
    """(n, 2) normalised points inside radius r_max (well inside the fold of both models)."""
    r = r_max * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(-np.pi, np.pi, n)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi)])


def _cv2_distort(xn, k):
    """OpenCV's projection of the points (x, y, 1) with K = I: the distorted normalised points."""
    X = np.column_stack([xn, np.ones(len(xn))]).reshape(-1, 1, 3)
    uv, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), np.eye(3), k)
    return uv.reshape(-1, 2)


@pytest.mark.parametrize("name", MODELS)
def test_distort_matches_cv2_project_points(name):
    k = MODELS[name]
    xn = _points(np.random.default_rng(1))
    np.testing.assert_allclose(pinhole.distort(xn, k), _cv2_distort(xn, k), atol=1e-12)


@pytest.mark.parametrize("name", MODELS)
def test_undistort_matches_cv2_undistort_points(name):
    k = MODELS[name]
    xd = _cv2_distort(_points(np.random.default_rng(2), r_max=0.5), k)
    ref = cv2.undistortPoints(xd.reshape(-1, 1, 2), np.eye(3), k,
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15))
    np.testing.assert_allclose(pinhole.undistort(xd, k), ref.reshape(-1, 2), atol=1e-9)


@pytest.mark.parametrize("name", MODELS)
def test_jacobian_matches_central_differences(name):
    k = MODELS[name]
    xn = _points(np.random.default_rng(3), 50)
    _, J = pinhole.distort_with_jacobian(xn, k)
    h = 1e-6
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        fd = (_cv2_distort(xn + e, k) - _cv2_distort(xn - e, k)) / (2 * h)
        np.testing.assert_allclose(J[:, :, j], fd, atol=1e-8)


def test_coefficient_rows_broadcast_over_cameras():
    """k (8, V) with points (N, V, 2): each view uses its own column, as one-camera calls would."""
    xn = _points(np.random.default_rng(4), 40).reshape(20, 2, 2)
    kT = np.stack([STRONG, RATIONAL], axis=1)
    xd, J = pinhole.distort_with_jacobian(xn, kT)
    for v, k in enumerate((STRONG, RATIONAL)):
        xd_v, J_v = pinhole.distort_with_jacobian(xn[:, v], k)
        np.testing.assert_array_equal(xd[:, v], xd_v)
        np.testing.assert_array_equal(J[:, v], J_v)
        np.testing.assert_allclose(pinhole.undistort(xd, kT)[:, v], xn[:, v], atol=1e-13)


@pytest.mark.parametrize("name", MODELS)
def test_compiled_forms_equal_vectorised_forms(name):
    k = MODELS[name]
    xn = _points(np.random.default_rng(5), 100)
    xd, J = pinhole.distort_with_jacobian(xn, k)
    for i, (x, y) in enumerate(xn):
        np.testing.assert_allclose(pinhole.distort_point(x, y, k), xd[i], rtol=1e-14, atol=1e-16)
        j00, j01, j10, j11 = pinhole.distort_jacobian_point(x, y, k)
        np.testing.assert_allclose([[j00, j01], [j10, j11]], J[i], rtol=1e-13, atol=1e-15)
        ux, uy, ok = pinhole.undistort_point(xd[i, 0], xd[i, 1], k)
        assert ok
        np.testing.assert_allclose([ux, uy], xn[i], atol=1e-13)


def test_fold_is_found_and_beyond_it_the_compiled_inverse_says_so():
    k = STRONG
    theta = pinhole.max_angle(k)
    assert 0.3 < theta < np.pi / 2 - 1e-3  # strong barrel folds over before 90 deg
    # just inside: the Jacobian determinant is positive in every direction
    phi = np.linspace(-np.pi, np.pi, 36, endpoint=False)
    r = np.tan(0.99 * theta)
    _, J = pinhole.distort_with_jacobian(np.column_stack([r * np.cos(phi), r * np.sin(phi)]), k)
    assert (np.linalg.det(J) > 0).all()
    # far beyond: a distorted radius the model never reaches has no preimage
    _, _, ok = pinhole.undistort_point(3.0, 0.0, k)
    assert not ok


def test_zero_distortion_is_the_identity():
    xn = _points(np.random.default_rng(6), 10)
    np.testing.assert_array_equal(pinhole.distort(xn, np.zeros(8)), xn)
    np.testing.assert_array_equal(pinhole.undistort(xn, np.zeros(8)), xn)
