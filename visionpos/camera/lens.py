"""The one dispatch over the lens models (camera/pinhole.py, camera/fisheye.py), compiled and vectorised.

Each lens module holds its model's forward map (`distort`), its Jacobian and its inverse
(`undistort`), vectorised and as compiled per-point kernels. Everything that projects through a
lens, or needs the projection's Jacobian, picks the model here:

- `lens_module(fisheye)`: the module, for the vectorised forms (camera/model.py, geometry/triangulation.py);
- `depth_scaled_projection_jacobian(xn, Jd)`: the projection's Jacobian through a lens, vectorised, shared by
  camera/model.py (one camera) and geometry/triangulation.py (a rig, on the triangulation's hot path);
- compiled, per point, for the fusion hot path: `distort_point`, `undistort_point`,
  `pixel_from_normalized` (normalised point -> pixel) and `project_with_jacobian` (camera-frame
  point -> pixel and d pixel / d point), on the arrays camera/model.py's `lens_arrays` packs:
  intrinsics (fx, fy, cx, cy, width, height), dist (8,) and the fisheye flag.

The hot path's arithmetic order is part of its contract (replays are compared byte for byte).
"""

from __future__ import annotations

import numpy as np

from visionpos.camera import fisheye as fisheye_lens
from visionpos.camera import pinhole as pinhole_lens
from visionpos.jit import njit


def lens_module(fisheye: bool):
    """camera.fisheye (Kannala-Brandt) when fisheye, else camera.pinhole (OpenCV rational + tangential)."""
    return fisheye_lens if fisheye else pinhole_lens


def depth_scaled_projection_jacobian(xn: np.ndarray, Jd: np.ndarray | None) -> np.ndarray:
    """z * d xd / d Xc (..., 2, 3) = [Jd | -Jd xn]: the Jacobian of a lens's output xd (normalised, or pixels
    when Jd carries the focal lengths) with respect to the camera-frame point Xc = z (xn, 1), times its depth z.

    xn: (..., 2) normalised undistorted coordinates; Jd: (..., 2, 2) d xd / d xn, or None for no lens (identity).
    From d xn / d Xc = [[1, 0, -x], [0, 1, -y]] / z. The caller divides by z (its own order of operations is
    part of its byte-for-byte contract)."""
    A = np.empty(xn.shape + (3,))
    if Jd is None:
        A[..., :2] = np.eye(2)
        A[..., 2] = -xn
    else:
        A[..., :2] = Jd
        A[..., 2] = -(Jd @ xn[..., None])[..., 0]
    return A


@njit
def distort_point(x: float, y: float, dist: np.ndarray, fisheye: bool) -> tuple[float, float]:
    """Compiled: normalised point (x, y) -> distorted normalised (xd, yd) through the lens model."""
    if fisheye:
        return fisheye_lens.distort_point(x, y, dist)
    return pinhole_lens.distort_point(x, y, dist)


@njit
def distort_jacobian_point(x: float, y: float, dist: np.ndarray,
                           fisheye: bool) -> tuple[float, float, float, float]:
    """Compiled: d (xd, yd) / d (x, y) at one normalised point as (j00, j01, j10, j11)."""
    if fisheye:
        return fisheye_lens.distort_jacobian_point(x, y, dist)
    return pinhole_lens.distort_jacobian_point(x, y, dist)


@njit
def undistort_point(xd: float, yd: float, dist: np.ndarray, fisheye: bool) -> tuple[float, float, bool]:
    """Compiled: distorted normalised (xd, yd) -> normalised (x, y, ok); ok is False beyond the model's fold."""
    if fisheye:
        return fisheye_lens.undistort_point(xd, yd, dist)
    return pinhole_lens.undistort_point(xd, yd, dist)


@njit
def pixel_from_normalized(xn: float, yn: float, intrinsics: np.ndarray, dist: np.ndarray,
                          fisheye: bool) -> tuple[float, float]:
    """Compiled: normalised (undistorted) coordinates -> pixel (u, v), the inverse of the undistortion."""
    xd, yd = distort_point(xn, yn, dist, fisheye)
    return intrinsics[0] * xd + intrinsics[2], intrinsics[1] * yd + intrinsics[3]


@njit
def project_with_jacobian(Xc: np.ndarray, intrinsics: np.ndarray, dist: np.ndarray,
                          fisheye: bool) -> tuple[float, float, np.ndarray]:
    """Compiled: pixel (u, v) of a camera-frame point Xc (3,) (z > 0, m) and d (u, v) / d Xc (2, 3) (px / m),
    through the lens model's distortion and its analytic Jacobian."""
    iz = 1.0 / Xc[2]
    x, y = Xc[0] * iz, Xc[1] * iz
    xd, yd = distort_point(x, y, dist, fisheye)
    j00, j01, j10, j11 = distort_jacobian_point(x, y, dist, fisheye)
    fx, fy = intrinsics[0], intrinsics[1]
    J = np.empty((2, 3))  # diag(fx, fy) (d xd / d xn) (d xn / d Xc), d xn / d Xc = [[1, 0, -x], [0, 1, -y]] / z
    a00, a01, a10, a11 = fx * j00 * iz, fx * j01 * iz, fy * j10 * iz, fy * j11 * iz
    J[0, 0], J[0, 1], J[0, 2] = a00, a01, -(a00 * x + a01 * y)
    J[1, 0], J[1, 1], J[1, 2] = a10, a11, -(a10 * x + a11 * y)
    return fx * xd + intrinsics[2], fy * yd + intrinsics[3], J


__all__ = ["lens_module", "depth_scaled_projection_jacobian",
           "distort_point", "distort_jacobian_point", "undistort_point", "pixel_from_normalized",
           "project_with_jacobian"]
