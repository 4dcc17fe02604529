"""Cross-view correspondence and the pipeline's fast N-view triangulation.

Two ways a blob gets its meaning:
1. Tracked bodies (the common case): the body's predicted markers are
   projected into the camera at the frame's capture time and blobs are
   associated by nearest neighbour within a gate (`associate`); where two
   predictions compete for a blob, the assignment is solved jointly
   (Hungarian, scipy.optimize.linear_sum_assignment), so one blob never
   feeds two markers or two bodies.
2. Acquisition (lost bodies, loose markers): unlabeled blobs of different
   cameras are paired by the closest approach of their rays, each pair is
   grown to more views by reprojection, and candidates are accepted greedily
   by (number of views, residual) so that every blob is used once
   (`match_unlabeled`). False blobs rarely find a consistent partner in a
   third view; missing markers just give fewer points.

`triangulate` is the per-packet hot path: a vectorised, iteratively
re-weighted linear triangulation in normalised image coordinates. With the
weights f/z (focal length over depth) its cost is exactly the reprojection
error in pixels, so after 2-3 re-weightings it reaches the maximum-likelihood
point for isotropic pixel noise (up to lens-distortion scale changes). It
accepts per-view offsets (view v observed X + offsets[p, v]) for motion
compensation. Two passes suffice: the first (unit weights) fixes the depths
to ~1e-3 relative, so the second pass's weights are exact for practical
purposes. geometry.triangulate_* does the same job with a Gauss-Newton
refinement for offline work; this one is here because it runs several
thousand times a second and has to stay a handful of numpy calls.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from visionpos.camera import FISHEYE, CameraModel

_CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14)


def undistort_points(model: CameraModel, pixels: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) -> normalised image coordinates (N, 2), same model as camera.py.

    OpenCV's iterative undistortion runs to 1e-14 here (agrees with
    CameraModel.undistort to ~1e-12 px) at a fraction of the cost.
    """
    px = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
    if len(px) == 0:
        return np.zeros((0, 2))
    if model.kind == FISHEYE:
        out = cv2.fisheye.undistortPoints(px, model.K, model.dist[:4], criteria=_CRIT)
    else:
        out = cv2.undistortPoints(px, model.K, model.dist, criteria=_CRIT)
    return out.reshape(-1, 2)


class Projector:
    """Fast world -> pixel projection for one camera through OpenCV (same model as camera.py).

    camera.Camera.project is exact but built from many small numpy steps;
    this runs per packet, so it goes through cv2.projectPoints /
    cv2.fisheye.projectPoints (the same OpenCV/Kannala-Brandt models).
    """

    def __init__(self, camera):
        self.camera = camera
        self.R = camera.R
        self.t = camera.t
        self.rvec = cv2.Rodrigues(camera.R)[0]
        self.tvec = camera.t.reshape(3, 1).astype(np.float64)
        self.K = camera.model.K
        self.fisheye = camera.model.kind == FISHEYE
        self.dist = camera.model.dist[:4] if self.fisheye else camera.model.dist
        self.w, self.h = camera.model.width, camera.model.height
        # beyond this angle from the axis the lens model folds back: not visible
        self.cos_max = float(np.cos(camera.model.max_theta))

    def project(self, points_world: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N, 3) world points -> (N, 2) pixels; NaN when behind, outside the lens model or off the sensor (+ margin)."""
        X = np.ascontiguousarray(points_world, dtype=np.float64).reshape(-1, 1, 3)
        if self.fisheye:
            uv = cv2.fisheye.projectPoints(X, self.rvec, self.tvec, self.K, self.dist)[0].reshape(-1, 2)
        else:
            uv = cv2.projectPoints(X, self.rvec, self.tvec, self.K, self.dist)[0].reshape(-1, 2)
        pc = X[:, 0] @ self.R.T + self.t
        n = np.sqrt((pc * pc).sum(1))
        ok = (pc[:, 2] > self.cos_max * n) & (uv[:, 0] > -0.5 - margin) & (uv[:, 0] < self.w - 0.5 + margin)
        ok &= (uv[:, 1] > -0.5 - margin) & (uv[:, 1] < self.h - 0.5 + margin)
        uv[~ok] = np.nan
        return uv


def associate(predicted: np.ndarray, blobs: np.ndarray, gate: float) -> np.ndarray:
    """Assign blobs to predicted marker positions, each blob at most once.

    predicted: (M, 2) predicted pixels (NaN rows = not visible); blobs:
    (N, 2) pixels; gate: max distance (px). Returns (M,) blob index or -1.
    Nearest neighbour when unambiguous; Hungarian on the gated costs when
    two predictions want the same blob.
    """
    M = len(predicted)
    out = np.full(M, -1, dtype=np.int64)
    if M == 0 or len(blobs) == 0:
        return out
    d2 = ((predicted[:, None, :] - blobs[None, :, :2]) ** 2).sum(-1)  # (M, N); NaN for invisible
    d2 = np.where(np.isfinite(d2), d2, np.inf)
    g2 = gate * gate
    best = np.argmin(d2, axis=1)
    ok = d2[np.arange(M), best] < g2
    cand = best[ok]
    # ambiguous: a blob wanted twice, or a prediction with a second blob inside the gate
    inside = d2 < g2
    ambiguous = bool((inside.sum(axis=1) > 1).any()) or (len(cand) > 1 and int(np.bincount(cand).max()) > 1)
    if not ambiguous:
        out[ok] = cand
        return out
    rows = np.nonzero(inside.any(axis=1))[0]
    cols = np.nonzero(inside.any(axis=0))[0]
    sub = d2[np.ix_(rows, cols)]
    big = g2 * 1e3
    cost = np.where(sub < g2, sub, big)
    r, c = linear_sum_assignment(cost)
    keep = cost[r, c] < g2
    out[rows[r[keep]]] = cols[c[keep]]
    return out


def triangulate(
    xn: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    f: np.ndarray,
    offsets: np.ndarray | None = None,
    iterations: int = 2,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Iteratively re-weighted linear N-view triangulation.

    xn: (P, V, 2) normalised image coordinates, NaN where view v does not see
    point p. R (V, 3, 3), t (V, 3): world->camera poses. f: (V,) focal length
    in pixels (sqrt(fx fy)), which makes residuals pixels. offsets: (P, V, 3)
    or None; view v observed X + offsets[p, v] (motion compensation).
    Returns points (P, 3) (NaN with fewer than 2 views), rms residual (P,)
    px, n_views (P,).
    """
    P, V = xn.shape[:2]
    valid = ~np.isnan(xn[..., 0])  # (P, V)
    n_views = valid.sum(1)
    x = np.where(valid[..., None], xn, 0.0)
    # rows: (R0 - u R2) . X = -(t0 - u t2), same for v; A (P, V, 2, 3), b (P, V, 2)
    A = R[None, :, :2, :] - x[..., None] * R[None, :, 2:3, :]
    b = x * t[None, :, 2:3] - t[None, :, :2]
    if offsets is not None:
        b = b - (A * offsets[:, :, None, :]).sum(-1)
    A2 = A.reshape(P, 2 * V, 3)
    b2 = b.reshape(P, 2 * V)
    R2 = R[:, 2, :]  # (V, 3)
    w = valid * f[None, :]  # weight f / z, z = 1 to start
    few = n_views < 2
    for _ in range(iterations):
        ww = np.repeat(w, 2, axis=1)  # (P, 2V)
        Aw = A2 * ww[..., None]
        AwT = Aw.transpose(0, 2, 1)
        N = AwT @ Aw
        rhs = AwT @ (b2 * ww)[..., None]
        if few.any():
            N[few] = np.eye(3)
        X = np.linalg.solve(N, rhs)[..., 0]
        z = X @ R2.T + t[None, :, 2]  # (P, V)
        if offsets is not None:
            z = z + (offsets * R2[None]).sum(-1)
        w = valid * f[None, :] / np.maximum(z, 1e-6)
    r = (A2 @ X[..., None])[..., 0] - b2  # z * (u_proj - u), (P, 2V)
    r = r * np.repeat(w, 2, axis=1)  # pixels
    ss = (r * r).sum(1)
    rms = np.sqrt(ss / np.maximum(n_views, 1))
    if few.any():
        X[few] = np.nan
        rms[few] = np.nan
    return X, rms, n_views


def ray_distances(c1: np.ndarray, d1: np.ndarray, c2: np.ndarray, d2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest approach of two bundles of rays from two centres.

    c1, c2: (3,) centres; d1 (N1, 3), d2 (N2, 3) unit directions. Returns
    distance (N1, N2) in metres (inf where the closest point lies behind a
    camera or the rays are parallel) and midpoints (N1, N2, 3).
    """
    w0 = c1 - c2
    a = 1.0
    b = d1 @ d2.T  # (N1, N2)
    dd = d1 @ w0  # (N1,)
    e = d2 @ w0  # (N2,)
    den = a - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (b * e[None, :] - dd[:, None]) / den  # along d1
        u = (e[None, :] - b * dd[:, None]) / den  # along d2
    p1 = c1 + s[..., None] * d1[:, None, :]
    p2 = c2 + u[..., None] * d2[None, :, :]
    dist = np.linalg.norm(p1 - p2, axis=-1)
    dist = np.where((den > 1e-10) & (s > 0) & (u > 0), dist, np.inf)
    return dist, 0.5 * (p1 + p2)


def match_unlabeled(
    xn: list[np.ndarray],
    R: np.ndarray,
    t: np.ndarray,
    f: np.ndarray,
    max_ray_distance: float,
    max_residual_px: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cross-view matching and triangulation of unlabeled blobs.

    xn: per view v an (N_v, 2) array of normalised coordinates. R (V, 3, 3),
    t (V, 3), f (V,) as in `triangulate`. max_ray_distance: pair gate (m).
    max_residual_px: growth gate and final RMS gate.
    Returns points (Q, 3), blob index (Q, V) (-1 = not seen), rms (Q,) px;
    every blob is used by at most one point.
    """
    V = len(xn)
    centres = -np.einsum("vji,vj->vi", R, t)
    rays = []
    for v in range(V):
        n = len(xn[v])
        d = np.column_stack([xn[v], np.ones(n)]) @ R[v]  # camera -> world directions
        rays.append(d / np.linalg.norm(d, axis=1, keepdims=True) if n else np.zeros((0, 3)))
    # 1. seed pairs
    seeds = []
    for a in range(V):
        if len(rays[a]) == 0:
            continue
        for b in range(a + 1, V):
            if len(rays[b]) == 0:
                continue
            dist, mid = ray_distances(centres[a], rays[a], centres[b], rays[b])
            ia, ib = np.nonzero(dist < max_ray_distance)
            for i, j in zip(ia, ib):
                seeds.append((a, int(i), b, int(j), mid[i, j]))
    if not seeds:
        return np.zeros((0, 3)), np.zeros((0, V), dtype=np.int64), np.zeros(0)
    # 2. grow every seed to the other views by reprojection (vectorised over seeds)
    S = len(seeds)
    X0 = np.array([s[4] for s in seeds])  # (S, 3)
    idx = np.full((S, V), -1, dtype=np.int64)
    for k, (a, i, b, j, _) in enumerate(seeds):
        idx[k, a] = i
        idx[k, b] = j
    for v in range(V):
        if len(xn[v]) == 0:
            continue
        pc = X0 @ R[v].T + t[v]
        with np.errstate(divide="ignore", invalid="ignore"):
            proj = pc[:, :2] / pc[:, 2:3]
        d = np.linalg.norm(proj[:, None, :] - xn[v][None], axis=-1) * f[v]  # (S, N_v) px
        d = np.where(pc[:, 2:3] > 0, d, np.inf)
        nn = np.argmin(d, axis=1)
        # growth gate is looser than the final one: the seed midpoint is not the ML point
        take = (idx[:, v] < 0) & (d[np.arange(S), nn] < 3.0 * max_residual_px)
        idx[take, v] = nn[take]
    obs = np.full((S, V, 2), np.nan)
    for v in range(V):
        sel = idx[:, v] >= 0
        obs[sel, v] = xn[v][idx[sel, v]]
    X, rms, nv = triangulate(obs, R, t, f)
    # a view whose own residual is over the gate was grown onto a wrong blob: drop the worst such view
    r = _view_residuals_all(X, obs, R, t, f)  # (S, V)
    worst = np.argmax(np.where(np.isnan(r), -1.0, r), axis=1)
    bad = (r[np.arange(S), worst] > max_residual_px) & (nv > 2)
    if bad.any():
        obs[bad, worst[bad]] = np.nan
        idx[bad, worst[bad]] = -1
        X[bad], rms[bad], nv[bad] = triangulate(obs[bad], R, t, f)
    # 3. greedy acceptance, each blob once; a candidate that shares blobs with an
    # accepted point keeps its other views if at least two remain
    good = np.nonzero(rms < max_residual_px)[0]
    order = sorted(good.tolist(), key=lambda k: (-int(nv[k]), float(rms[k]), k))
    used = [set() for _ in range(V)]
    keep_X, keep_idx, keep_rms = [], [], []
    for k in order:
        views = [v for v in range(V) if idx[k, v] >= 0]
        clash = [v for v in views if int(idx[k, v]) in used[v]]
        Xk, rk, ik = X[k], float(rms[k]), idx[k].copy()
        if clash:
            if len(views) - len(clash) < 2:
                continue
            ok = obs[k].copy()
            ok[clash] = np.nan
            ik[clash] = -1
            Xs, rs, _ = triangulate(ok[None], R, t, f)
            if not rs[0] < max_residual_px:
                continue
            Xk, rk = Xs[0], float(rs[0])
        keep_X.append(Xk)
        keep_idx.append(ik)
        keep_rms.append(rk)
        for v in range(V):
            if ik[v] >= 0:
                used[v].add(int(ik[v]))
    if not keep_X:
        return np.zeros((0, 3)), np.zeros((0, V), dtype=np.int64), np.zeros(0)
    return np.array(keep_X), np.array(keep_idx, dtype=np.int64), np.array(keep_rms)


def _view_residuals_all(X: np.ndarray, obs: np.ndarray, R: np.ndarray, t: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Per-view reprojection errors (S, V) px of points X (S, 3) against obs (S, V, 2); NaN = missing."""
    pc = np.einsum("vij,sj->svi", R, X) + t[None]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = pc[..., :2] / pc[..., 2:3]
    return np.linalg.norm(proj - obs, axis=-1) * f[None, :]
