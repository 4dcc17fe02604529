"""Fisheye lens: OpenCV's Kannala-Brandt model (cv2.fisheye), coefficients k = (k1, k2, k3, k4).

A ray at angle theta from the optical axis lands at distorted radius

    r_d(theta) = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)

in the direction of its normalised point (x, y) = (X/Z, Y/Z), whose radius is
r = tan(theta): (xd, yd) = (x, y) r_d / r. Undistortion solves r_d(theta) = |xd|
for theta by Newton's method and scales back by tan(theta) / |xd|.

As in camera/pinhole.py, vectorised numpy forms (`distort`,
`distort_with_jacobian`, `undistort`; coefficients broadcast over cameras) and
compiled per-point kernels for the hot path (`distort_point`,
`distort_jacobian_point`, `undistort_point`) live side by side; `radius_from_angle` is one source for
both (plain on arrays, compiled as `radius_from_angle_point`).
"""

from __future__ import annotations

import math

import numpy as np

from visionpos.jit import njit

N_COEFFS = 4


def radius_from_angle(theta, k):
    """Kannala-Brandt polynomial: distorted radius r_d(theta) and d r_d / d theta.

    theta: ray angle(s) from the optical axis (rad), scalar or array; k: (4,) coefficients or
    (4, V) rows broadcasting against theta. Returns (r_d, dr_d) shaped like theta.
    """
    t2 = theta * theta
    r = theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))
    dr = 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
    return r, dr


radius_from_angle_point = njit(radius_from_angle)
radius_from_angle_point.__doc__ = "Compiled `radius_from_angle` for one angle; k (4,) float64."


# ------------------------------------------------------------------ vectorised numpy forms
def _distort(xn: np.ndarray, k: np.ndarray, with_jac: bool):
    # clamp so the on-axis point needs no special case: s -> 1 there, and the
    # cancellation in dsr for tiny r is multiplied by xn xn^T ~ r^2 below
    rr = np.maximum((xn * xn).sum(axis=-1), 1e-300)
    r = np.sqrt(rr)
    th = np.arctan(r)
    rd, drd = radius_from_angle(th, k)
    s = rd / r
    xd = xn * s[..., None]
    if not with_jac:
        return xd, None
    dsr = (drd / (1 + rr) - s) / rr  # (ds/dr) / r
    J = xn[..., :, None] * (xn * dsr[..., None])[..., None, :]
    J[..., 0, 0] += s
    J[..., 1, 1] += s
    return xd, J


def distort(xn: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Normalised points (..., 2) -> distorted normalised points (..., 2).

    k: (4,) coefficients, or (4, V) rows that broadcast against xn[..., 0] (one column
    per camera for xn of shape (..., V, 2)).
    """
    return _distort(xn, k, False)[0]


def distort_with_jacobian(xn: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`distort` and its Jacobian d xd / d xn (..., 2, 2) (analytic)."""
    return _distort(xn, k, True)


def undistort(
    xd: np.ndarray, k: np.ndarray, iterations: int = 20, tol: float = 1e-15, seeded: bool = True
) -> np.ndarray:
    """Inverse of `distort`: distorted normalised (..., 2) -> normalised (..., 2); NaN stays NaN.

    Newton's method on theta, stopping when every step is below tol (rad) or after
    `iterations`; theta is kept in [0, pi/2). seeded: start from the cubic approximation
    r ~ theta (1 + k1 theta^2) (about 3 Newton steps fewer); False starts at theta = |xd|,
    as `undistort_point` does.
    """
    rd = np.sqrt(xd[..., 0] ** 2 + xd[..., 1] ** 2)
    th0 = rd / np.maximum(1.0 + k[0] * rd * rd, 0.5) if seeded else np.maximum(rd, 0.0)
    th = np.minimum(th0, np.pi / 2 - 1e-6)
    for _ in range(iterations):
        r, dr = radius_from_angle(th, k)
        step = (r - rd) / dr
        th = np.maximum(np.minimum(th - step, np.pi / 2 - 1e-9), 0.0)
        if not (np.abs(step) > tol).any():  # NaN (missing) compares False
            break
    small = rd < 1e-12
    scale = np.where(small, 1.0, np.tan(th) / np.where(small, 1.0, rd))
    return xd * scale[..., None]


def max_angle(k: np.ndarray) -> float:
    """Largest ray angle from the optical axis (rad) the model maps one-to-one: where r_d(theta)
    stops increasing, or just below 90 deg."""
    theta = np.linspace(1e-4, np.pi / 2 - 1e-3, 4000)
    _, dr = radius_from_angle(theta, np.asarray(k, dtype=np.float64))
    bad = np.nonzero(dr <= 0)[0]
    return float(theta[max(bad[0] - 1, 0)]) if bad.size else float(np.pi / 2 - 1e-3)


# ------------------------------------------------------------------ compiled per-point forms
@njit
def distort_point(x, y, k):
    """Compiled: one normalised point (x, y) -> distorted (xd, yd); k (4,) float64."""
    r = math.sqrt(x * x + y * y)
    s = radius_from_angle_point(math.atan(r), k)[0] / r if r > 1e-12 else 1.0
    return x * s, y * s


@njit
def distort_jacobian_point(x, y, k):
    """Compiled: d (xd, yd) / d (x, y) at one point as (j00, j01, j10, j11); k (4,) float64
    (as `distort_with_jacobian`: s I + x x^T (ds/dr) / r with s = r_d / r)."""
    rr = max(x * x + y * y, 1e-300)
    r = math.sqrt(rr)
    rd, drd = radius_from_angle_point(math.atan(r), k)
    s = rd / r
    dsr = (drd / (1.0 + rr) - s) / rr
    return s + x * x * dsr, x * y * dsr, x * y * dsr, s + y * y * dsr


@njit
def undistort_point(xd, yd, k):
    """Compiled: distorted normalised (xd, yd) -> (x, y, ok), k (4,) float64.

    Newton on theta to round-off (at most 20 steps); ok is False where r_d(theta) misses
    |xd| by more than 1e-9 (beyond the model's largest angle).
    """
    rd = math.sqrt(xd * xd + yd * yd)
    th = min(max(rd, 0.0), math.pi / 2 - 1e-6)
    for _ in range(20):
        r, dr = radius_from_angle_point(th, k)
        step = (r - rd) / dr
        th = min(max(th - step, 0.0), math.pi / 2 - 1e-9)
        if abs(step) < 1e-15:
            break
    s = math.tan(th) / rd if rd > 1e-12 else 1.0
    ok = abs(radius_from_angle_point(th, k)[0] - rd) <= 1e-9 * (1.0 + max(abs(xd), abs(yd)))
    return xd * s, yd * s, ok


__all__ = [
    "N_COEFFS", "radius_from_angle", "radius_from_angle_point", "distort", "distort_with_jacobian",
    "undistort", "max_angle", "distort_point", "distort_jacobian_point", "undistort_point",
]
