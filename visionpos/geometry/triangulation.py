"""N-view triangulation of points seen by calibrated cameras, and its Cramer-Rao bounds.

Conventions (see visionpos/camera/model.py and docs/architecture.md):
- A camera pose (R, t) maps world to camera: x_cam = R @ x_world + t.
- Normalised image coordinates are (x/z, y/z) of the camera-frame point.
- Missing observations are NaN; everything is vectorised over points P and views V.

Normalised DLT for the start, then Levenberg-Marquardt on the reprojection error,
in normalised units (triangulate_normalized) or in each camera's pixel space
through its lens model (triangulate_pixels, analytic Jacobians). This is the
offline, maximum-likelihood triangulation (calibration, benchmarks); the fusion
hot path uses the compiled re-weighted linear one in fusion/matching.py.
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Sequence

import numpy as np

from visionpos.camera import fisheye, pinhole
from visionpos.camera.lens import depth_scaled_projection_jacobian
from visionpos.camera.model import FISHEYE, PINHOLE, Camera

__all__ = ["TriangulationResult", "CameraRig", "triangulate_normalized", "triangulate_pixels", "triangulation_crb",
           "pose_crb"]


class TriangulationResult(NamedTuple):
    """points: (P, 3) world metres (NaN where fewer than 2 views);
    residuals: (P, V) reprojection error norm per view (NaN where missing);
    n_views: (P,) int number of views that observed the point."""

    points: np.ndarray
    residuals: np.ndarray
    n_views: np.ndarray



# ------------------------------------------------------------------ rig / camera stack
class CameraRig:
    """V cameras stacked into arrays so projection, its Jacobian and undistortion
    run over (P, V) in one vectorised pass. Build once per arena and reuse:
    triangulate_pixels accepts either a CameraRig or a sequence of Camera.

    Attributes: R (V,3,3), t (V,3), f (V,2) = (fx, fy), c (V,2) = (cx, cy),
    fisheye (V,) bool, kp (V,8) pinhole coefficients, kf (V,4) fisheye coefficients.
    """

    def __init__(self, cameras: Sequence[Camera]):
        cams = list(cameras)
        if not cams:
            raise ValueError("CameraRig needs at least one camera")
        self.cameras = tuple(cams)
        self.V = len(cams)
        self.R = np.stack([c.R for c in cams])
        self.t = np.stack([c.t for c in cams])
        self.f = np.array([[c.model.fx, c.model.fy] for c in cams])
        self.c = np.array([[c.model.cx, c.model.cy] for c in cams])
        self.fisheye = np.array([c.model.kind == FISHEYE for c in cams])
        self.kp = np.zeros((self.V, 8))
        self.kf = np.zeros((self.V, 4))
        for i, c in enumerate(cams):
            if c.model.kind == PINHOLE:
                self.kp[i] = c.model.dist
            else:
                self.kf[i] = c.model.dist
        self.fisheye_idx = np.flatnonzero(self.fisheye)
        self.pinhole_idx = np.flatnonzero(~self.fisheye)
        self.any_fisheye = bool(self.fisheye.any())
        self.any_pinhole = bool((~self.fisheye).any())
        # pinhole with zero distortion needs no polynomial at all
        self.pinhole_plain = not self.any_fisheye and not np.any(self.kp)
        # coefficient-major contiguous copies (whole rig, and each model's own views) so
        # that each coefficient broadcasts from a contiguous (V,) row
        self._kpT = np.ascontiguousarray(self.kp.T)
        self._kfT = np.ascontiguousarray(self.kf.T)
        self._kpT_own = np.ascontiguousarray(self.kp[self.pinhole_idx].T)
        self._kfT_own = np.ascontiguousarray(self.kf[self.fisheye_idx].T)

    def distort(self, xn: np.ndarray, with_jac: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Normalised coords (..., V, 2) -> pixels (..., V, 2) and d pixels / d xn (..., V, 2, 2)."""
        if self.pinhole_plain:
            uv = xn * self.f + self.c
            if not with_jac:
                return uv, None
            J = np.zeros(xn.shape + (2,))
            J[..., 0, 0] = self.f[:, 0]
            J[..., 1, 1] = self.f[:, 1]
            return uv, J
        if self.any_pinhole and self.any_fisheye:
            # mixed rig: run each model on its own views only
            fi, pi = self.fisheye_idx, self.pinhole_idx
            xd = np.empty_like(xn)
            xd_f, J_f = _distort(fisheye, xn[..., fi, :], self._kfT_own, with_jac)
            xd_p, J_p = _distort(pinhole, xn[..., pi, :], self._kpT_own, with_jac)
            xd[..., fi, :] = xd_f
            xd[..., pi, :] = xd_p
            J = None
            if with_jac:
                J = np.empty(xn.shape + (2,))
                J[..., fi, :, :] = J_f
                J[..., pi, :, :] = J_p
        elif self.any_fisheye:
            xd, J = _distort(fisheye, xn, self._kfT, with_jac)
        else:
            xd, J = _distort(pinhole, xn, self._kpT, with_jac)
        uv = xd * self.f + self.c
        if with_jac:
            J = J * self.f[:, :, None]
        return uv, J

    def undistort(self, pixels: np.ndarray, iterations: int = 20, tol: float = 1e-15) -> np.ndarray:
        """Pixels (..., V, 2) -> normalised coords (..., V, 2); NaN stays NaN. Newton stops when
        its step is below tol (normalised units)."""
        xd = (np.asarray(pixels, dtype=np.float64) - self.c) / self.f
        if self.pinhole_plain:
            return xd
        if self.any_pinhole and self.any_fisheye:
            fi, pi = self.fisheye_idx, self.pinhole_idx
            out = np.empty_like(xd)
            out[..., fi, :] = fisheye.undistort(xd[..., fi, :], self._kfT_own, iterations, tol)
            out[..., pi, :] = pinhole.undistort(xd[..., pi, :], self._kpT_own, iterations, tol)
            return out
        if self.any_fisheye:
            return fisheye.undistort(xd, self._kfT, iterations, tol)
        return pinhole.undistort(xd, self._kpT, iterations, tol)

    def project(self, points: np.ndarray, offsets: np.ndarray | None = None) -> np.ndarray:
        """World points (P, 3) -> pixels (P, V, 2); NaN behind a camera. offsets (P, V, 3)
        displace each point per view (see triangulate_pixels)."""
        X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        Xw = X[:, None, :] if offsets is None else X[:, None, :] + offsets
        Xc = np.einsum("vij,pvj->pvi", self.R, np.broadcast_to(Xw, (len(X), self.V, 3))) + self.t
        z = Xc[..., 2:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = Xc[..., :2] / z
        uv, _ = self.distort(xn, with_jac=False)
        uv[(z[..., 0] <= 0)] = np.nan
        return uv


_RIG_CACHE: dict[tuple[int, ...], tuple[tuple[Camera, ...], CameraRig]] = {}


def _as_rig(cameras: Sequence[Camera] | CameraRig) -> CameraRig:
    """The CameraRig for these cameras; rigs for recently used camera lists are reused
    (keyed by object identity, so a changed calibration -- a new Camera -- gets a new rig)."""
    if isinstance(cameras, CameraRig):
        return cameras
    cams = tuple(cameras)
    key = tuple(map(id, cams))
    hit = _RIG_CACHE.get(key)
    if hit is not None and all(a is b for a, b in zip(hit[0], cams)):
        return hit[1]
    rig = CameraRig(cams)
    if len(_RIG_CACHE) >= 16:
        _RIG_CACHE.pop(next(iter(_RIG_CACHE)))
    _RIG_CACHE[key] = (cams, rig)
    return rig


def _distort(lens, xn: np.ndarray, kT: np.ndarray, with_jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """lens.distort (and its Jacobian when with_jac) for coefficient rows kT (n_coeffs, V)."""
    if with_jac:
        return lens.distort_with_jacobian(xn, kT)
    return lens.distort(xn, kT), None


# -------------------------------------------------------------------- triangulation
def _dlt(xn: np.ndarray, mask: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear triangulation per point. xn (P,V,2), mask (P,V), R (V,3,3), t (P,V,3) -> (P,3).

    DLT rows x*P3 - P1 and y*P3 - P2 of each observing view (P = [R | t]), each scaled
    to unit norm so no view dominates by its coordinate scale. With the homogeneous
    coordinate fixed to 1 (arena points are never at infinity) the null vector is the
    solution of 3x3 normal equations, solved in closed form for all points at once,
    which is ~10x cheaper than a batched SVD of the (P, 2V, 4) systems.
    """
    x = np.where(mask, xn[..., 0], 0.0)[..., None]
    y = np.where(mask, xn[..., 1], 0.0)[..., None]
    R2 = R[:, 2]  # (V,3)
    ax = x * R2 - R[:, 0]  # (P,V,3)
    ay = y * R2 - R[:, 1]
    bx = x[..., 0] * t[..., 2] - t[..., 0]  # (P,V)
    by = y[..., 0] * t[..., 2] - t[..., 1]
    wx = mask / np.sqrt(np.einsum("pvi,pvi->pv", ax, ax) + bx * bx)
    wy = mask / np.sqrt(np.einsum("pvi,pvi->pv", ay, ay) + by * by)
    wx2 = wx * wx
    wy2 = wy * wy
    # sum_rows w^2 a a^T X = -sum_rows w^2 a b
    H = np.einsum("pv,pvi,pvj->pij", wx2, ax, ax) + np.einsum("pv,pvi,pvj->pij", wy2, ay, ay)
    g = -(np.einsum("pv,pvi->pi", wx2 * bx, ax) + np.einsum("pv,pvi->pi", wy2 * by, ay))
    return _solve3(H, g)


def _solve3(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Batched symmetric 3x3 solve H x = g (H (P,3,3), g (P,3)). Singular or non-finite
    systems give inf/NaN rows instead of raising for the whole batch."""
    try:
        return np.linalg.solve(H, g[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return _solve3_adjugate(H, g)


def _solve3_adjugate(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """_solve3 by the adjugate, row by row independent (inf/NaN where singular)."""
    a, b, c = H[:, 0, 0], H[:, 0, 1], H[:, 0, 2]
    d, e, f = H[:, 1, 1], H[:, 1, 2], H[:, 2, 2]
    A00 = d * f - e * e
    A01 = c * e - b * f
    A02 = b * e - c * d
    A11 = a * f - c * c
    A12 = b * c - a * e
    A22 = a * d - b * b
    det = a * A00 + b * A01 + c * A02
    g0, g1, g2 = g[:, 0], g[:, 1], g[:, 2]
    out = np.empty_like(g)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        out[:, 0] = (A00 * g0 + A01 * g1 + A02 * g2) * inv
        out[:, 1] = (A01 * g0 + A11 * g1 + A12 * g2) * inv
        out[:, 2] = (A02 * g0 + A12 * g1 + A22 * g2) * inv
    return out


def _residual_jac(
    X: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    obs: np.ndarray,
    mask: np.ndarray,
    distort: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None,
):
    """Residual (P,V,2) and Jacobian d residual / d X (P,V,2,3), both zero where missing,
    and (P,) bool: the point is behind a camera that observed it.

    X must be finite. Call under np.errstate(divide/invalid ignored)."""
    Xc = np.einsum("vij,pj->pvi", R, X) + t
    z = Xc[..., 2]
    iz = 1.0 / z
    xn = Xc[..., :2] * iz[..., None]
    pred, Jd = (xn, None) if distort is None else distort(xn)
    A = depth_scaled_projection_jacobian(xn, Jd)
    valid = mask & (z > 0)
    J = (A @ R) * np.where(valid, iz, 0.0)[..., None, None]  # (P,V,2,3)
    r = np.where(valid[..., None], pred - obs, 0.0)
    behind = (mask & ~valid).any(axis=1)
    return r, J, behind


def _lm_refine(
    X: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    obs: np.ndarray,
    mask: np.ndarray,
    distort,
    max_iter: int = 20,
    tol: float = 1e-6,
) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on sum_v |pred_v(X) - obs_v|^2, independently per point, vectorised.

    X: (P,3) start; R (V,3,3); t (P,V,3); obs (P,V,2) zero where missing; mask (P,V).
    Points with non-finite X are left as they are. A point stops when its step is below
    tol * (1 + |X|_1) (metres: a few um in an arena; Gauss-Newton converges fast on
    these small-residual problems, so the next step would be ~1000x smaller still).
    Call under np.errstate(ignore). Returns refined X (P,3) and residual vectors (P,V,2).
    """
    X = X.copy()
    r_all = np.zeros(obs.shape)
    fin = np.isfinite(X).all(axis=1)
    if not fin.all():
        idx = np.flatnonzero(fin)
        Xs, r_s = _lm_refine(X[idx], R, t[idx], obs[idx], mask[idx], distort, max_iter, tol)
        X[idx] = Xs
        r_all[idx] = r_s
        r_all[~fin] = np.nan
        return X, r_all
    r, J, behind = _residual_jac(X, R, t, obs, mask, distort)
    cost = np.where(behind, np.inf, (r * r).sum(axis=(1, 2)))
    lam = np.full(len(X), 1e-6)
    active = np.ones(len(X), bool)
    diag = (slice(None), [0, 1, 2], [0, 1, 2])
    for _ in range(max_iter):
        H = np.einsum("pvia,pvib->pab", J, J)
        g = np.einsum("pvia,pvi->pa", J, r)
        H[diag] *= 1.0 + lam[:, None]
        dx = _solve3(H, g)
        ok = active & np.isfinite(dx).all(axis=1)
        dx[~ok] = 0.0
        step = np.abs(dx).sum(axis=1)
        if ok.all() and (step <= tol * (1.0 + np.abs(X).sum(axis=1))).all():
            # every step is negligible: take it without another evaluation; the
            # linearised residual is exact to second order in a sub-micron step
            return X - dx, r - np.einsum("pvia,pa->pvi", J, dx)
        Xn = X - dx
        rn, Jn, behind_n = _residual_jac(Xn, R, t, obs, mask, distort)
        cost_n = np.where(behind_n, np.inf, (rn * rn).sum(axis=(1, 2)))
        better = ok & (cost_n <= cost)
        if better.all():
            X, r, J = Xn, rn, Jn
        else:
            X = np.where(better[:, None], Xn, X)
            r = np.where(better[:, None, None], rn, r)
            J = np.where(better[:, None, None, None], Jn, J)
        # converged: negligible step (accepted or not: at the optimum rounding can make the
        # cost tie or rise by an ulp), or an accepted step that no longer lowers the cost
        conv = (step <= tol * (1.0 + np.abs(X).sum(axis=1))) | (better & (cost - cost_n <= 1e-14 * cost))
        cost = np.where(better, cost_n, cost)
        lam = np.where(better, np.maximum(lam * 0.1, 1e-12), lam * 10.0)
        # also stop points whose damping blew up (no descent direction left)
        active &= ~conv & (lam < 1e8) & ok
        if not active.any():
            break
    return X, r


def _refine(
    X: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    obs: np.ndarray,
    mask: np.ndarray,
    distort,
    tol: float = 1e-6,
) -> tuple[np.ndarray, np.ndarray]:
    """Minimise the reprojection error per point: plain Gauss-Newton first (triangulation
    from a linear start is a small-residual problem where it converges in 1-2 steps),
    Levenberg-Marquardt (_lm_refine) if any point's step fails to lower its cost, lands
    behind a camera or does not converge in 3 steps. Same contract as _lm_refine."""
    fin = np.isfinite(X).all(axis=1)
    if not fin.all():  # refine the triangulable points only
        X = X.copy()
        r_all = np.full(obs.shape, np.nan)
        idx = np.flatnonzero(fin)
        X[idx], r_all[idx] = _refine(X[idx], R, t[idx], obs[idx], mask[idx], distort, tol)
        return X, r_all
    r, J, behind = _residual_jac(X, R, t, obs, mask, distort)
    if behind.any():
        return _lm_refine(X, R, t, obs, mask, distort, tol=tol)
    cost = (r * r).sum(axis=(1, 2))
    for _ in range(3):
        dx = _solve3(np.einsum("pvia,pvib->pab", J, J), np.einsum("pvia,pvi->pa", J, r))
        if not np.isfinite(dx).all():
            break
        if (np.abs(dx).sum(axis=1) <= tol * (1.0 + np.abs(X).sum(axis=1))).all():
            # negligible steps: take them; the linearised residual is exact to second order
            return X - dx, r - np.einsum("pvia,pa->pvi", J, dx)
        Xn = X - dx
        rn, Jn, behind = _residual_jac(Xn, R, t, obs, mask, distort)
        cost_n = (rn * rn).sum(axis=(1, 2))
        if behind.any() or (cost_n > cost * (1.0 + 1e-12) + 1e-300).any():
            break
        X, r, J, cost = Xn, rn, Jn, cost_n
    return _lm_refine(X, R, t, obs, mask, distort, tol=tol)


def _prepare_t(t: np.ndarray, P: int, V: int) -> np.ndarray:
    t = np.asarray(t, dtype=np.float64)
    if t.shape == (V, 3):
        return np.broadcast_to(t, (P, V, 3))
    if t.shape == (P, V, 3):
        return t
    raise ValueError(f"t must have shape (V, 3) = ({V}, 3) or (P, V, 3) = ({P}, {V}, 3), got {t.shape}")


def _finish(X: np.ndarray, r: np.ndarray, mask: np.ndarray, n_views: np.ndarray) -> TriangulationResult:
    res = np.where(mask, np.linalg.norm(r, axis=-1), np.nan)
    bad = (n_views < 2) | ~np.isfinite(X).all(axis=1)
    X = X.copy()
    X[bad] = np.nan
    res[bad] = np.nan
    return TriangulationResult(X, res, n_views)


@np.errstate(divide="ignore", invalid="ignore")
def triangulate_normalized(
    xn: np.ndarray, R: np.ndarray, t: np.ndarray, refine: bool = True
) -> TriangulationResult:
    """N-view triangulation from normalised image coordinates.

    xn: (P, V, 2) (x/z, y/z) per view, NaN where view v does not see point p.
    R: (V, 3, 3) world->camera rotations. t: (V, 3), or (P, V, 3) per point and view
    (e.g. motion compensation folded in as t + R @ offset).
    Returns points (P, 3), residuals (P, V) in normalised units, n_views (P,).
    DLT (batched SVD), then Levenberg-Marquardt on the reprojection error when refine.
    Points seen by fewer than 2 views are NaN.
    """
    xn = np.asarray(xn, dtype=np.float64)
    if xn.ndim != 3 or xn.shape[-1] != 2:
        raise ValueError(f"xn must have shape (P, V, 2), got {xn.shape}")
    P, V, _ = xn.shape
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (V, 3, 3):
        raise ValueError(f"R must have shape (V, 3, 3) = ({V}, 3, 3), got {R.shape}")
    t = _prepare_t(t, P, V)
    mask = np.isfinite(xn).all(axis=-1)
    n_views = mask.sum(axis=1)
    if P == 0:
        return TriangulationResult(np.zeros((0, 3)), np.zeros((0, V)), n_views)
    X = _dlt(xn, mask, R, t)
    X[n_views < 2] = np.nan
    obs = np.where(mask[..., None], xn, 0.0)
    if refine:
        X, r = _refine(X, R, t, obs, mask, None)
    else:
        r, _, _ = _residual_jac(np.nan_to_num(X), R, t, obs, mask, None)
    return _finish(X, r, mask, n_views)


@np.errstate(divide="ignore", invalid="ignore")
def triangulate_pixels(
    cameras: Sequence[Camera] | CameraRig,
    pixels: np.ndarray,
    refine: bool = True,
    offsets: np.ndarray | None = None,
    normalized: np.ndarray | None = None,
) -> TriangulationResult:
    """N-view triangulation from distorted pixel observations.

    cameras: V cameras (or a prebuilt CameraRig, cheaper per call).
    pixels: (P, V, 2), NaN where view v does not see point p.
    offsets: (P, V, 3) or None; offsets[p, v] is the world displacement of point p
    between the reference time and view v's capture time, i.e. view v observed
    X + offsets[p, v] (motion-compensated triangulation of asynchronous cameras).
    Returns points (P, 3) at the reference time, residuals (P, V) in pixels, n_views (P,).
    normalized: (P, V, 2) or None; the same observations already undistorted (e.g. by
    the matching stage), which skips the undistortion here.
    Undistort -> normalised DLT -> maximum-likelihood LM refinement in each camera's
    pixel space through its distortion model (analytic Jacobians).
    """
    rig = _as_rig(cameras)
    pixels = np.asarray(pixels, dtype=np.float64)
    if pixels.ndim != 3 or pixels.shape[1:] != (rig.V, 2):
        raise ValueError(f"pixels must have shape (P, V, 2) with V = {rig.V} cameras, got {pixels.shape}")
    P = pixels.shape[0]
    if offsets is None:
        t = np.broadcast_to(rig.t, (P, rig.V, 3))
    else:
        offsets = np.asarray(offsets, dtype=np.float64)
        if offsets.shape != (P, rig.V, 3):
            raise ValueError(f"offsets must have shape (P, V, 3) = ({P}, {rig.V}, 3), got {offsets.shape}")
        # view v sees X + o: R (X + o) + t = R X + (t + R o)
        t = rig.t + np.einsum("vij,pvj->pvi", rig.R, np.nan_to_num(offsets))
    if P == 0:
        return TriangulationResult(np.zeros((0, 3)), np.zeros((0, rig.V)), np.zeros(0, dtype=np.int64))
    if normalized is None:
        # the start point only seeds the pixel-space refinement, so a loose undistortion suffices
        xn = rig.undistort(pixels, iterations=10, tol=1e-5 if refine else 1e-15)
    else:
        xn = np.asarray(normalized, dtype=np.float64)
        if xn.shape != pixels.shape:
            raise ValueError(f"normalized must have the shape of pixels {pixels.shape}, got {xn.shape}")
    mask = np.isfinite(pixels).all(axis=-1) & np.isfinite(xn).all(axis=-1)
    n_views = mask.sum(axis=1)
    X = _dlt(xn, mask, rig.R, t)
    X[n_views < 2] = np.nan
    obs = np.where(mask[..., None], pixels, 0.0)
    if refine:
        X, r = _refine(X, rig.R, t, obs, mask, rig.distort)
    else:
        r, _, _ = _residual_jac(np.nan_to_num(X), rig.R, t, obs, mask, rig.distort)
    return _finish(X, r, mask, n_views)


@np.errstate(divide="ignore", invalid="ignore")
def pixel_jacobians(cameras: Sequence[Camera] | CameraRig, points: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """d pixel / d X (P, V, 2, 3), pixels per metre, through each camera's distortion; zero where a
    point is not visible in a view or is behind it. points: (P, 3) world, finite; visible: (P, V) bool."""
    rig = _as_rig(cameras)
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    visible = np.asarray(visible, dtype=bool)
    if visible.shape != (len(X), rig.V):
        raise ValueError(f"visible must have shape (P, V) = ({len(X)}, {rig.V}), got {visible.shape}")
    t = np.broadcast_to(rig.t, (len(X), rig.V, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        _, J, _ = _residual_jac(X, rig.R, t, np.zeros((len(X), rig.V, 2)), visible, rig.distort)
    return J


def triangulation_crb(
    cameras: Sequence[Camera] | CameraRig,
    points: np.ndarray,
    sigma_px: float,
    visible: np.ndarray | None = None,
) -> np.ndarray:
    """Cramer-Rao lower bound (P, 3, 3) on the covariance of a triangulated point.

    Isotropic Gaussian pixel noise sigma_px in each observing view: Fisher
    information F = sum_v J_v^T J_v / sigma^2 with J_v = d pixel / d X (2x3) through
    the camera's distortion; CRB = F^-1. points: (P, 3) world; visible: (P, V) bool
    (default: each camera's field-of-view test). Points with singular F get NaN.
    """
    rig = _as_rig(cameras)
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if visible is None:
        visible = np.stack([c.visible(X) for c in rig.cameras], axis=1)
    J = pixel_jacobians(rig, X, visible)
    F = np.einsum("pvia,pvib->pab", J, J) / float(sigma_px) ** 2
    out = np.full((len(X), 3, 3), np.nan)
    ok = np.asarray(visible, bool).sum(axis=1) >= 2
    if ok.any():
        cond = np.linalg.cond(F[ok])
        good = np.zeros(len(X), bool)
        good[np.flatnonzero(ok)[cond < 1e12]] = True
        if good.any():
            out[good] = np.linalg.inv(F[good])
    return out


def pose_crb(
    cameras: Sequence[Camera] | CameraRig,
    markers_world: np.ndarray,
    origin: np.ndarray,
    sigma_px: float,
    visible: np.ndarray,
) -> np.ndarray:
    """Cramer-Rao bound (6, 6) of a rigid body's pose [position (m), world rotation vector (rad)] from
    one snapshot of its markers: every (marker, camera) pair in `visible` contributes its projection's
    information, Fisher F = sum J^T J / sigma_px^2 with J = d pixel / d X (2x3) @ [I, -skew(X - origin)].

    markers_world: (M, 3) m; origin: (3,) the body origin the position refers to; visible: (M, V)
    bool: unlike a triangulated pose, a marker seen by one camera counts too, so this bounds what one
    camera seeing >= 3 markers, or several cameras seeing 1-2 markers each, tell about the pose. All +inf
    when F is singular (the views do not fix all six degrees of freedom, e.g. one camera seeing 1-2
    markers). The position block's trace bounds the mean squared position error (m^2).
    """
    X = np.asarray(markers_world, dtype=np.float64).reshape(-1, 3)
    J = pixel_jacobians(cameras, X, visible)  # (M, V, 2, 3)
    r = X - np.asarray(origin, dtype=np.float64).reshape(3)
    G = np.zeros((len(X), 3, 6))  # d X / d pose
    G[:, :, :3] = np.eye(3)
    G[:, 0, 4], G[:, 0, 5] = r[:, 2], -r[:, 1]  # -skew(r)
    G[:, 1, 3], G[:, 1, 5] = -r[:, 2], r[:, 0]
    G[:, 2, 3], G[:, 2, 4] = r[:, 1], -r[:, 0]
    H = np.einsum("mvia,mab->mvib", J, G)  # (M, V, 2, 6)
    F = np.einsum("mvia,mvib->ab", H, H) / float(sigma_px) ** 2
    if not np.isfinite(F).all() or np.linalg.matrix_rank(F, tol=1e-9 * max(np.abs(F).max(), 1e-300)) < 6:
        return np.full((6, 6), np.inf)
    return np.linalg.inv(F)
