"""Pinhole lens with OpenCV's rational + tangential distortion (cv2.projectPoints' model).

Coefficients k = (k1, k2, p1, p2, k3, k4, k5, k6). With r2 = x^2 + y^2 of the
normalised point (x, y) = (X/Z, Y/Z):

    radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
    xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

All functions map normalised coordinates to distorted normalised coordinates
(pixels are fx xd + cx, fy yd + cy; camera/model.py does that step). Two forms
of each function live side by side:
- vectorised numpy (`distort`, `distort_with_jacobian`, `undistort`) for offline
  work; coefficients broadcast, so one call can serve many cameras at once;
- compiled per-point kernels (`distort_point`, `distort_jacobian_point`,
  `undistort_point`) for the per-packet hot path, called from compiled loops.
The two agree to round-off; their operation order differs, and the hot path's
must stay as it is (replays are compared byte for byte).
"""

from __future__ import annotations

import numpy as np

from visionpos.jit import njit

N_COEFFS = 8


# ------------------------------------------------------------------ vectorised numpy forms
def _distort(xn: np.ndarray, k: np.ndarray, with_jac: bool):
    k1, k2, p1, p2, k3, k4, k5, k6 = k
    x, y = xn[..., 0], xn[..., 1]
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    rad = num / den
    xd = np.empty_like(xn)
    xd[..., 0] = x * rad + 2 * p1 * xy + p2 * (r2 + 2 * xx)
    xd[..., 1] = y * rad + p1 * (r2 + 2 * yy) + 2 * p2 * xy
    if not with_jac:
        return xd, None
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    drad2 = 2 * (dnum * den - num * dden) / (den * den)  # d rad / d r2, times 2
    J = np.empty(xn.shape + (2,))
    J[..., 0, 0] = rad + xx * drad2 + 2 * p1 * y + 6 * p2 * x
    J[..., 0, 1] = xy * drad2 + 2 * p1 * x + 2 * p2 * y
    J[..., 1, 0] = xy * drad2 + 2 * p1 * x + 2 * p2 * y
    J[..., 1, 1] = rad + yy * drad2 + 6 * p1 * y + 2 * p2 * x
    return xd, J


def distort(xn: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Normalised points (..., 2) -> distorted normalised points (..., 2).

    k: (8,) coefficients, or (8, V) rows that broadcast against xn[..., 0] (one column
    per camera for xn of shape (..., V, 2)).
    """
    return _distort(xn, k, False)[0]


def distort_with_jacobian(xn: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`distort` and its Jacobian d xd / d xn (..., 2, 2) (analytic)."""
    return _distort(xn, k, True)


def undistort(
    xd: np.ndarray, k: np.ndarray, iterations: int = 20, tol: float = 1e-15, seeded: bool = True
) -> np.ndarray:
    """Inverse of `distort` by Newton's method: distorted normalised (..., 2) -> normalised (..., 2).

    k as in `distort`. Stops when every point's step is below tol (normalised units) or after
    `iterations`; NaN stays NaN. Beyond the fold of the distortion the result is not a preimage:
    callers that need to know check it by distorting again (CameraModel.undistort does).
    seeded: start from one radial fixed-point step (~2 Newton steps fewer); False starts at xd,
    as `undistort_point` does, so that both find the same preimages beyond the fold.
    """
    if not np.any(k):
        return xd.copy()
    if seeded:
        # one fixed-point step x = xd / radial(xd) (radial part only)
        k1, k2, _, _, k3, k4, k5, k6 = k
        r2 = (xd * xd).sum(axis=-1)
        rad = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        x = xd / np.maximum(rad, 0.25)[..., None]
    else:
        x = np.array(xd, dtype=np.float64)
    for _ in range(iterations):
        f, J = _distort(x, k, True)
        r = f - xd
        det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
        dx = (J[..., 1, 1] * r[..., 0] - J[..., 0, 1] * r[..., 1]) / det
        dy = (-J[..., 1, 0] * r[..., 0] + J[..., 0, 0] * r[..., 1]) / det
        x[..., 0] -= dx
        x[..., 1] -= dy
        if not (np.abs(dx) + np.abs(dy) > tol).any():  # NaN compares False
            break
    return x


def max_angle(k: np.ndarray) -> float:
    """Largest ray angle from the optical axis (rad) that the distortion maps one-to-one.

    Where the Jacobian determinant first reaches zero in any direction (the image folds over
    there) or the distorted radius stops growing along a ray; just below 90 deg if never.
    """
    theta = np.linspace(1e-4, np.pi / 2 - 1e-3, 4000)
    # tangential terms make the fold direction-dependent: check 36 azimuths
    phi = np.linspace(-np.pi, np.pi, 36, endpoint=False)
    r = np.tan(theta)[:, None]
    xn = np.stack([r * np.cos(phi), r * np.sin(phi)], axis=-1).reshape(-1, 2)
    xd, J = distort_with_jacobian(xn, np.asarray(k, dtype=np.float64))
    det = (J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]).reshape(len(theta), len(phi))
    rd = np.linalg.norm(xd.reshape(len(theta), len(phi), 2), axis=-1)
    grow = np.diff(rd, axis=0, prepend=0.0) > 0
    bad = np.nonzero(((det <= 0) | ~grow).any(axis=1))[0]
    return float(theta[max(bad[0] - 1, 0)]) if bad.size else float(np.pi / 2 - 1e-3)


# ------------------------------------------------------------------ compiled per-point forms
@njit
def _distort_point_radial(x, y, k):
    """One normalised point -> distorted (xd, yd), plus the radial factor and its derivative
    by r^2, which the Jacobian needs."""
    k1, k2, p1, p2, k3, k4, k5, k6 = k[0], k[1], k[2], k[3], k[4], k[5], k[6], k[7]
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    drad = ((k1 + r2 * (2 * k2 + 3 * k3 * r2)) * den - num * (k4 + r2 * (2 * k5 + 3 * k6 * r2))) / (den * den)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd, radial, drad


@njit
def _jacobian_entries(x, y, radial, drad, p1, p2):
    """d (xd, yd) / d (x, y) from the radial factor and its r^2 derivative: j00, j01 (== j10), j11."""
    j00 = radial + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
    j01 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    j11 = radial + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    return j00, j01, j11


@njit
def distort_point(x, y, k):
    """Compiled: one normalised point (x, y) -> distorted (xd, yd); k (8,) float64."""
    xd, yd, _, _ = _distort_point_radial(x, y, k)
    return xd, yd


@njit
def distort_jacobian_point(x, y, k):
    """Compiled: d (xd, yd) / d (x, y) at one point as (j00, j01, j10, j11); k (8,) float64."""
    _, _, radial, drad = _distort_point_radial(x, y, k)
    j00, j01, j11 = _jacobian_entries(x, y, radial, drad, k[2], k[3])
    return j00, j01, j01, j11


@njit
def undistort_point(xd, yd, k):
    """Compiled: distorted normalised (xd, yd) -> (x, y, ok), k (8,) float64.

    Newton from (xd, yd) to round-off (at most 20 steps); ok is False where the result does
    not distort back to (xd, yd) within 1e-9 (beyond the fold of the model).
    """
    p1, p2 = k[2], k[3]
    x, y = xd, yd
    for _ in range(20):
        ux, uy, radial, drad = _distort_point_radial(x, y, k)
        ex, ey = ux - xd, uy - yd
        if max(abs(ex), abs(ey)) < 1e-15:
            break
        j00, j01, j11 = _jacobian_entries(x, y, radial, drad, p1, p2)
        det = j00 * j11 - j01 * j01
        x -= (j11 * ex - j01 * ey) / det
        y -= (-j01 * ex + j00 * ey) / det
    ux, uy, _, _ = _distort_point_radial(x, y, k)
    ok = max(abs(ux - xd), abs(uy - yd)) <= 1e-9 * (1.0 + max(abs(xd), abs(yd)))
    return x, y, ok


__all__ = [
    "N_COEFFS", "distort", "distort_with_jacobian", "undistort", "max_angle",
    "distort_point", "distort_jacobian_point", "undistort_point",
]
