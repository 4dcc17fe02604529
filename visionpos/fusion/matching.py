"""Cross-view correspondence and the pipeline's fast N-view triangulation.

Two ways a blob gets its meaning:
1. Tracked bodies (the common case): the body's predicted markers are
   projected into the camera at the frame's capture time and blobs are
   associated by nearest neighbour within a gate (`associate`); where two
   predictions compete for a blob, the assignment is solved jointly
   (Hungarian, `min_cost_assignment`), so one blob never feeds two markers
   or two bodies.
2. Acquisition (lost bodies, loose markers): unlabeled blobs matched across
   cameras by their rays (acquisition.py, `match_unlabeled`).

The floor: the ground calibration puts the world's z = 0 on it (docs/calibration.md), and a shiny floor
shows every marker's mirror image (z -> -z). A point triangulated more than BELOW_FLOOR_M under the floor
is a mirror image, never a marker: acquisition drops it. A marker a few centimetres above the floor has its
image and its mirror image's within a blob's width, and the detector sees one blob whose centroid is pulled
towards the reflection, by up to half their separation and by a different amount in each camera (the floor
reflects each at its own angle). `floor_merge_px` is that spread per view; the residual gates of a point
near the floor are widened by it and its weight in the pose fit lowered (measurements.py), so a drone
standing on a shiny floor and taking off stays tracked instead of having its markers refused.

`triangulate` is the per-packet hot path: an iteratively re-weighted
linear triangulation in normalised image coordinates. With the
weights f/z (focal length over depth) its cost is exactly the reprojection
error in pixels, so after 2-3 re-weightings it reaches the maximum-likelihood
point for isotropic pixel noise (up to lens-distortion scale changes). It
accepts per-view offsets (view v observed X + offsets[p, v]) for motion
compensation. Two passes suffice: the first (unit weights) fixes the depths
to ~1e-3 relative, so the second pass's weights are exact for practical
purposes. geometry/triangulation.py does the same job with a Gauss-Newton
refinement for offline work; this one is here because it runs several
thousand times a second. Lens models come from camera/lens.py (the compiled
per-point dispatch over camera/pinhole.py and camera/fisheye.py). The per-frame steps are compiled loops
(visionpos/jit.py); the public functions are thin wrappers that fix the
argument types.
"""

from __future__ import annotations

import math

import numpy as np

from visionpos.camera import lens
from visionpos.camera.model import lens_arrays, undistort_pixels
from visionpos.jit import njit

FLOOR_Z_M = 0.0  # the floor: world z = 0, where the ground calibration puts it
BELOW_FLOOR_M = 0.02  # a point this far under the floor is a mirror image (calibration and noise: mm)
MERGE_MAX_PX = 12.0  # a mirror image this far from its marker's image is a blob of its own, not merged
MERGE_MAX_HEIGHT_M = 0.5  # higher, a marker's mirror image is MERGE_MAX_PX away unless the camera is ~30 m off


@njit
def _merge_px_view(X, R, t, f):
    """floor_merge_px in one view: R (3, 3), t (3,), f px; X (3,) m above the floor."""
    z_c = R[2, 0] * X[0] + R[2, 1] * X[1] + t[2]
    z = z_c + R[2, 2] * X[2]
    zm = z_c + R[2, 2] * (2.0 * FLOOR_Z_M - X[2])  # the mirror image's depth
    if not (z > 0.0 and zm > 0.0):
        return 0.0
    du = (R[0, 0] * X[0] + R[0, 1] * X[1] + t[0] + R[0, 2] * X[2]) / z
    du -= (R[0, 0] * X[0] + R[0, 1] * X[1] + t[0] + R[0, 2] * (2.0 * FLOOR_Z_M - X[2])) / zm
    dv = (R[1, 0] * X[0] + R[1, 1] * X[1] + t[1] + R[1, 2] * X[2]) / z
    dv -= (R[1, 0] * X[0] + R[1, 1] * X[1] + t[1] + R[1, 2] * (2.0 * FLOOR_Z_M - X[2])) / zm
    sep = math.sqrt(du * du + dv * dv) * f
    return 0.5 * sep if sep < MERGE_MAX_PX else 0.0


@njit
def floor_merge_px(X, R, t, f):
    """How far (px) a marker at X (3,) m may be pulled towards its mirror image in each view (V,): half the
    separation of the two images where it is under MERGE_MAX_PX (one merged blob; a reflection is never
    brighter than its marker), else 0; 0 for a point not above the floor, higher than MERGE_MAX_HEIGHT_M or
    behind a camera. R (V, 3, 3), t (V, 3) world->camera; f (V,) focal lengths px."""
    V = R.shape[0]
    out = np.zeros(V)
    h = X[2] - FLOOR_Z_M
    if not 0.0 < h < MERGE_MAX_HEIGHT_M:
        return out
    for v in range(V):
        out[v] = _merge_px_view(X, R[v], t[v], f[v])
    return out


@njit
def floor_gate(X, R, t, f, seen, gate_px):
    """The RMS residual gate (px) of a point X (3,) m seen in views `seen` (V,) bool: gate_px widened by the
    mean squared floor_merge_px of those views (exactly gate_px away from the floor); -1 (nothing passes)
    for a point under the floor: a mirror image."""
    if X[2] < FLOOR_Z_M - BELOW_FLOOR_M:
        return -1.0
    if not X[2] - FLOOR_Z_M < MERGE_MAX_HEIGHT_M:
        return gate_px
    s = floor_merge_px(X, R, t, f)
    extra, n = 0.0, 0
    for v in range(s.shape[0]):
        if seen[v]:
            extra += s[v] * s[v]
            n += 1
    if extra > 0.0:
        return math.sqrt(gate_px * gate_px + extra / n)
    return gate_px


class Projector:
    """Fast world -> pixel projection for one camera (the lens models of camera/, compiled).

    camera.model.Camera.project is exact but built from many small numpy steps;
    this runs per packet, so it is one compiled loop over the points.
    """

    def __init__(self, camera):
        self.camera = camera
        m = camera.model
        self.R = np.ascontiguousarray(camera.R, dtype=np.float64)
        self.t = np.ascontiguousarray(camera.t, dtype=np.float64).reshape(3)
        self.intrinsics, self.dist, self.fisheye = lens_arrays(m)
        # beyond this angle from the axis the lens model folds back: not visible
        self.cos_max = float(np.cos(m.max_theta))
        # all of it in one array for the compiled per-frame call: R (9), t (3), intrinsics (6),
        # dist (8), cos_max, fisheye (1.0 / 0.0)
        self.packed = np.concatenate(
            [self.R.ravel(), self.t, self.intrinsics, self.dist, [self.cos_max, float(self.fisheye)]]
        )

    def undistort(self, pixels: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) float64 -> normalised coordinates (N, 2), as camera.model.undistort_points."""
        return undistort_pixels(pixels, self.intrinsics, self.dist, self.fisheye)

    def project(self, points_world: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N, 3) world points -> (N, 2) pixels; NaN when behind, outside the lens model or off the
        sensor (+ margin)."""
        X = np.ascontiguousarray(points_world, dtype=np.float64).reshape(-1, 3)
        return project_points(X, self.R, self.t, self.intrinsics, self.dist, self.fisheye, self.cos_max, float(margin))


@njit
def project_points(X, R, t, intrinsics, dist, fisheye, cos_max, margin):
    """World points X (N, 3) -> pixels (N, 2) through camera pose R (3, 3), t (3,).

    intrinsics: fx, fy, cx, cy, width, height; dist (8,): OpenCV pinhole
    k1, k2, p1, p2, k3, k4, k5, k6, or Kannala-Brandt k1..k4 when fisheye.
    NaN where the point is behind, beyond the lens model's angle (cos_max) or
    off the sensor by more than margin px.
    """
    fx, fy, cx, cy, w, h = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3], intrinsics[4], intrinsics[5]
    N = X.shape[0]
    uv = np.full((N, 2), np.nan)
    for i in range(N):
        pc0 = R[0, 0] * X[i, 0] + R[0, 1] * X[i, 1] + R[0, 2] * X[i, 2] + t[0]
        pc1 = R[1, 0] * X[i, 0] + R[1, 1] * X[i, 1] + R[1, 2] * X[i, 2] + t[1]
        pc2 = R[2, 0] * X[i, 0] + R[2, 1] * X[i, 1] + R[2, 2] * X[i, 2] + t[2]
        if not pc2 > cos_max * math.sqrt(pc0 * pc0 + pc1 * pc1 + pc2 * pc2):
            continue
        x, y = pc0 / pc2, pc1 / pc2
        xd, yd = lens.distort_point(x, y, dist, fisheye)
        u, v = fx * xd + cx, fy * yd + cy
        if -0.5 - margin < u < w - 0.5 + margin and -0.5 - margin < v < h - 0.5 + margin:
            uv[i, 0], uv[i, 1] = u, v
    return uv


def associate(predicted: np.ndarray, blobs: np.ndarray, gate: float) -> np.ndarray:
    """Assign blobs to predicted marker positions, each blob at most once.

    predicted: (M, 2) predicted pixels (NaN rows = not visible); blobs:
    (N, 2+) pixels; gate: max distance (px). Returns (M,) blob index or -1.
    Nearest neighbour when unambiguous; minimum total squared distance
    (Hungarian) over the gated pairs when two predictions want the same blob
    or one prediction has two blobs inside its gate.
    """
    M = len(predicted)
    if M == 0 or len(blobs) == 0:
        return np.full(M, -1, dtype=np.int64)
    return associate_blobs(np.ascontiguousarray(predicted, dtype=np.float64),
                          np.ascontiguousarray(blobs[:, :2], dtype=np.float64),
                      float(gate) * float(gate))


@njit
def associate_blobs(pred, blobs, g2):
    """Compiled core of `associate`: pred (M, 2), blobs (N, 2) float64, g2 the squared gate."""
    M, N = pred.shape[0], blobs.shape[0]
    d2 = np.empty((M, N))
    for m in range(M):
        for n in range(N):
            dx, dy = pred[m, 0] - blobs[n, 0], pred[m, 1] - blobs[n, 1]
            d2[m, n] = dx * dx + dy * dy  # NaN (invisible) fails every `< g2`
    out = np.full(M, -1, dtype=np.int64)
    taken = np.zeros(N, dtype=np.bool_)
    ambiguous = False
    for m in range(M):
        inside = 0
        for n in range(N):
            if d2[m, n] < g2:
                inside += 1
                out[m] = n
        if inside > 1 or (inside == 1 and taken[out[m]]):
            ambiguous = True
            break
        if inside == 1:
            taken[out[m]] = True
    if not ambiguous:
        return out
    # Hungarian on the rows and columns that have a pair inside the gate
    rows = np.array([m for m in range(M) if (d2[m] < g2).any()])
    cols = np.array([n for n in range(N) if (d2[:, n] < g2).any()])
    cost = np.empty((len(rows), len(cols)))
    for i in range(len(rows)):
        for j in range(len(cols)):
            c = d2[rows[i], cols[j]]
            cost[i, j] = c if c < g2 else g2 * 1e3
    out[:] = -1
    if len(rows) <= len(cols):
        col_of = min_cost_assignment(cost)
        for i in range(len(rows)):
            if cost[i, col_of[i]] < g2:
                out[rows[i]] = cols[col_of[i]]
    else:
        row_of = min_cost_assignment(cost.T.copy())
        for j in range(len(cols)):
            if cost[row_of[j], j] < g2:
                out[rows[row_of[j]]] = cols[j]
    return out


@njit
def min_cost_assignment(C: np.ndarray) -> np.ndarray:
    """Rectangular assignment problem, compiled: C (n, m) finite costs, n <= m.

    Returns the column (n,) of each row that minimises the total cost
    (Hungarian method with potentials, shortest augmenting paths, O(n^2 m)).
    """
    n, m = C.shape
    u = np.zeros(n + 1)
    v = np.zeros(m + 1)
    match = np.zeros(m + 1, dtype=np.int64)  # row (1-based) assigned to column j; 0 = free
    way = np.zeros(m + 1, dtype=np.int64)
    for i in range(1, n + 1):
        match[0] = i
        j0 = 0
        minv = np.full(m + 1, np.inf)
        used = np.zeros(m + 1, dtype=np.bool_)
        while True:
            used[j0] = True
            i0 = match[j0]
            delta = np.inf
            j1 = 0
            for j in range(1, m + 1):
                if not used[j]:
                    cur = C[i0 - 1, j - 1] - u[i0] - v[j]
                    if cur < minv[j]:
                        minv[j] = cur
                        way[j] = j0
                    if minv[j] < delta:
                        delta = minv[j]
                        j1 = j
            for j in range(m + 1):
                if used[j]:
                    u[match[j]] += delta
                    v[j] -= delta
                else:
                    minv[j] -= delta
            j0 = j1
            if match[j0] == 0:
                break
        while j0 != 0:  # flip the augmenting path
            j1 = way[j0]
            match[j0] = match[j1]
            j0 = j1
    col_of = np.full(n, -1, dtype=np.int64)
    for j in range(1, m + 1):
        if match[j] != 0:
            col_of[match[j] - 1] = j - 1
    return col_of


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
    xn = np.ascontiguousarray(xn, dtype=np.float64)
    off = _NO_OFFSETS if offsets is None else np.ascontiguousarray(offsets, dtype=np.float64)
    return triangulate_irls(xn, np.ascontiguousarray(R, dtype=np.float64), np.ascontiguousarray(t, dtype=np.float64),
                        np.ascontiguousarray(f, dtype=np.float64), off, offsets is not None, int(iterations))


_NO_OFFSETS = np.zeros((0, 0, 3))


@njit
def triangulate_irls(xn, R, t, f, offsets, has_offsets, iterations):
    """Compiled core of `triangulate` (same arrays; offsets (P, V, 3) read only if has_offsets)."""
    # Each view gives two linear equations (R0 - u R2) . X = u t2 - t0 (and v), weighted
    # by f / depth so that residuals are pixels; the depth comes from the previous
    # solution (1 to start), which turns the algebraic error into the reprojection error.
    P, V = xn.shape[0], xn.shape[1]
    X = np.full((P, 3), np.nan)
    rms = np.full(P, np.nan)
    n_views = np.zeros(P, dtype=np.int64)
    A = np.empty((V, 2, 3))
    b = np.empty((V, 2))
    w = np.empty(V)
    seen = np.empty(V, dtype=np.bool_)
    for p in range(P):
        n = 0
        for v in range(V):
            seen[v] = not np.isnan(xn[p, v, 0])
            if not seen[v]:
                continue
            n += 1
            for j in range(2):
                u = xn[p, v, j]
                bj = u * t[v, 2] - t[v, j]
                for k in range(3):
                    A[v, j, k] = R[v, j, k] - u * R[v, 2, k]
                    if has_offsets:
                        bj -= A[v, j, k] * offsets[p, v, k]
                b[v, j] = bj
            w[v] = f[v]
        n_views[p] = n
        if n < 2:
            continue
        x0 = x1 = x2 = 0.0
        for _ in range(iterations):
            n00 = n01 = n02 = n11 = n12 = n22 = r0 = r1 = r2 = 0.0
            for v in range(V):
                if not seen[v]:
                    continue
                ww = w[v] * w[v]
                for j in range(2):
                    a0, a1, a2, bj = A[v, j, 0], A[v, j, 1], A[v, j, 2], b[v, j]
                    n00 += ww * a0 * a0
                    n01 += ww * a0 * a1
                    n02 += ww * a0 * a2
                    n11 += ww * a1 * a1
                    n12 += ww * a1 * a2
                    n22 += ww * a2 * a2
                    r0 += ww * a0 * bj
                    r1 += ww * a1 * bj
                    r2 += ww * a2 * bj
            # symmetric 3x3 solve by the adjugate
            c00, c01, c02 = n11 * n22 - n12 * n12, n02 * n12 - n01 * n22, n01 * n12 - n02 * n11
            c11, c12, c22 = n00 * n22 - n02 * n02, n01 * n02 - n00 * n12, n00 * n11 - n01 * n01
            det = n00 * c00 + n01 * c01 + n02 * c02
            x0 = (c00 * r0 + c01 * r1 + c02 * r2) / det
            x1 = (c01 * r0 + c11 * r1 + c12 * r2) / det
            x2 = (c02 * r0 + c12 * r1 + c22 * r2) / det
            for v in range(V):
                if seen[v]:
                    z = R[v, 2, 0] * x0 + R[v, 2, 1] * x1 + R[v, 2, 2] * x2 + t[v, 2]
                    if has_offsets:
                        z += (
                            R[v, 2, 0] * offsets[p, v, 0]
                            + R[v, 2, 1] * offsets[p, v, 1]
                            + R[v, 2, 2] * offsets[p, v, 2]
                        )
                    w[v] = f[v] / max(z, 1e-6)
        ss = 0.0
        for v in range(V):
            if seen[v]:
                for j in range(2):
                    r = (A[v, j, 0] * x0 + A[v, j, 1] * x1 + A[v, j, 2] * x2 - b[v, j]) * w[v]  # pixels
                    ss += r * r
        X[p, 0], X[p, 1], X[p, 2] = x0, x1, x2
        rms[p] = math.sqrt(ss / n)
    return X, rms, n_views


@njit
def refine_in_pixels(X, px, offsets, has_offsets, R, t, intrinsics, dist, fisheye, iterations):
    """Gauss-Newton on each point's reprojection error in its views' pixels, through each lens (compiled).

    X (P, 3) start (triangulate's points, m; NaN rows stay NaN); px (P, V, 2) observed pixels, NaN where view
    v does not see point p; offsets (P, V, 3) as triangulate's, read only if has_offsets; R (V, 3, 3),
    t (V, 3) world->camera; intrinsics (V, 6), dist (V, 8), fisheye (V,) bool: each camera as lens_arrays
    packs it. At most `iterations` steps per point (from the linear start one or two suffice). Returns the
    points (P, 3) (NaN where a view sees the point from behind) and their residual (P,): the RMS over the
    seen views of the reprojection error's length, px. The linear start's residual is in focal-scaled
    normalised units, which a fisheye's edge compresses: this one is the maximum-likelihood point under pixel
    noise."""
    P, V = px.shape[0], px.shape[1]
    out = np.full((P, 3), np.nan)
    rms = np.full(P, np.nan)
    Pc = np.empty(3)
    for p in range(P):
        x0, x1, x2 = X[p, 0], X[p, 1], X[p, 2]
        if not (math.isfinite(x0) and math.isfinite(x1) and math.isfinite(x2)):
            continue
        ok = True
        ss = 0.0
        n = 0
        for it in range(iterations + 1):
            h00 = h01 = h02 = h11 = h12 = h22 = g0 = g1 = g2 = ss = 0.0
            n = 0
            for v in range(V):
                if math.isnan(px[p, v, 0]):
                    continue
                w0, w1, w2 = x0, x1, x2
                if has_offsets:
                    w0, w1, w2 = x0 + offsets[p, v, 0], x1 + offsets[p, v, 1], x2 + offsets[p, v, 2]
                for a in range(3):
                    Pc[a] = R[v, a, 0] * w0 + R[v, a, 1] * w1 + R[v, a, 2] * w2 + t[v, a]
                if not Pc[2] > 0.0:
                    ok = False
                    break
                u, w, Jc = lens.project_with_jacobian(Pc, intrinsics[v], dist[v], fisheye[v])
                r0, r1 = px[p, v, 0] - u, px[p, v, 1] - w
                ss += r0 * r0 + r1 * r1
                n += 1
                # d pixel / d X = Jc R (2, 3)
                a0 = Jc[0, 0] * R[v, 0, 0] + Jc[0, 1] * R[v, 1, 0] + Jc[0, 2] * R[v, 2, 0]
                a1 = Jc[0, 0] * R[v, 0, 1] + Jc[0, 1] * R[v, 1, 1] + Jc[0, 2] * R[v, 2, 1]
                a2 = Jc[0, 0] * R[v, 0, 2] + Jc[0, 1] * R[v, 1, 2] + Jc[0, 2] * R[v, 2, 2]
                b0 = Jc[1, 0] * R[v, 0, 0] + Jc[1, 1] * R[v, 1, 0] + Jc[1, 2] * R[v, 2, 0]
                b1 = Jc[1, 0] * R[v, 0, 1] + Jc[1, 1] * R[v, 1, 1] + Jc[1, 2] * R[v, 2, 1]
                b2 = Jc[1, 0] * R[v, 0, 2] + Jc[1, 1] * R[v, 1, 2] + Jc[1, 2] * R[v, 2, 2]
                h00 += a0 * a0 + b0 * b0
                h01 += a0 * a1 + b0 * b1
                h02 += a0 * a2 + b0 * b2
                h11 += a1 * a1 + b1 * b1
                h12 += a1 * a2 + b1 * b2
                h22 += a2 * a2 + b2 * b2
                g0 += a0 * r0 + b0 * r1
                g1 += a1 * r0 + b1 * r1
                g2 += a2 * r0 + b2 * r1
            if not ok or n < 2 or it == iterations:
                break
            c00, c01, c02 = h11 * h22 - h12 * h12, h02 * h12 - h01 * h22, h01 * h12 - h02 * h11
            c11, c12, c22 = h00 * h22 - h02 * h02, h01 * h02 - h00 * h12, h00 * h11 - h01 * h01
            det = h00 * c00 + h01 * c01 + h02 * c02
            if not abs(det) > 0.0:
                break
            d0 = (c00 * g0 + c01 * g1 + c02 * g2) / det
            d1 = (c01 * g0 + c11 * g1 + c12 * g2) / det
            d2 = (c02 * g0 + c12 * g1 + c22 * g2) / det
            x0, x1, x2 = x0 + d0, x1 + d1, x2 + d2
        if ok and n >= 2:
            out[p, 0], out[p, 1], out[p, 2] = x0, x1, x2
            rms[p] = math.sqrt(ss / n)
    return out, rms
