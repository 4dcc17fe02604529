"""camera/lens.py: the one dispatch over the lens models, against the vectorised models and OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from visionpos.camera import fisheye, lens, pinhole
from visionpos.camera.model import CameraModel, lens_arrays

FISHEYE = CameraModel("fisheye", 960, 640, 720.313, 719.521, 481.014, 360.991, [0.396, 0.634, -2.417, 2.111])
PINHOLE = CameraModel("pinhole", 1280, 800, 800.0, 810.0, 650.0, 390.0, [-0.32, 0.12, 0.0015, -0.001, -0.015])
MODELS = [FISHEYE, PINHOLE]
# camera-frame points (m) inside both fields of view, off-axis in every quadrant
POINTS = np.array([[0.3, -0.2, 2.0], [-0.5, 0.4, 3.0], [0.05, 0.02, 1.0], [-0.9, -0.6, 2.5], [0.0, 0.0, 4.0]])


def test_lens_module_picks_the_model():
    assert lens.lens_module(True) is fisheye and lens.lens_module(False) is pinhole
    assert FISHEYE.lens is fisheye and PINHOLE.lens is pinhole


@pytest.mark.parametrize("m", MODELS, ids=lambda m: m.kind)
def test_project_with_jacobian_matches_opencv_and_finite_differences(m):
    intrinsics, dist, is_fisheye = lens_arrays(m)
    K = m.K
    for X in POINTS:
        u, v, J = lens.project_with_jacobian(X, intrinsics, dist, is_fisheye)
        if is_fisheye:
            ref = cv2.fisheye.projectPoints(X.reshape(1, 1, 3), np.zeros(3), np.zeros(3), K, m.dist[:4])[0]
        else:
            ref = cv2.projectPoints(X.reshape(1, 3), np.zeros(3), np.zeros(3), K, m.dist[:5])[0]
        assert np.allclose([u, v], ref.reshape(2), atol=1e-6)
        h = 1e-6
        for k in range(3):
            dX = np.zeros(3)
            dX[k] = h
            up, vp, _ = lens.project_with_jacobian(X + dX, intrinsics, dist, is_fisheye)
            um, vm, _ = lens.project_with_jacobian(X - dX, intrinsics, dist, is_fisheye)
            assert np.allclose(J[:, k], [(up - um) / (2 * h), (vp - vm) / (2 * h)], rtol=1e-5, atol=1e-3)


@pytest.mark.parametrize("m", MODELS, ids=lambda m: m.kind)
def test_per_point_forms_equal_the_vectorised_model(m):
    intrinsics, dist, is_fisheye = lens_arrays(m)
    xn = POINTS[:, :2] / POINTS[:, 2:]
    px = m.distort(xn)
    for (x, y), (u, v) in zip(xn, px):
        assert np.allclose(lens.pixel_from_normalized(x, y, intrinsics, dist, is_fisheye), (u, v), atol=1e-9)
        xd, yd = lens.distort_point(x, y, dist, is_fisheye)
        xb, yb, ok = lens.undistort_point(xd, yd, dist, is_fisheye)
        assert ok and np.allclose((xb, yb), (x, y), atol=1e-12)
    J = m.project_jacobian(POINTS)
    for X, Jm in zip(POINTS, J):
        assert np.allclose(lens.project_with_jacobian(X, intrinsics, dist, is_fisheye)[2], Jm, rtol=1e-9)
