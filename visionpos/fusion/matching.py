"""Cross-view correspondence and the pipeline's fast N-view triangulation.

Two ways a blob gets its meaning:
1. Tracked bodies (the common case): the body's predicted markers are
   projected into the camera at the frame's capture time and blobs are
   associated by nearest neighbour within a gate (`associate`); where two
   predictions compete for a blob, the assignment is solved jointly
   (Hungarian, `min_cost_assignment`), so one blob never feeds two markers
   or two bodies.
2. Acquisition (lost bodies, loose markers): unlabeled blobs of different
   cameras are paired by the closest approach of their rays, each pair is
   grown to more views by reprojection, and candidates are accepted greedily
   by (number of views, residual) so that every blob is used once
   (`match_unlabeled`). False blobs rarely find a consistent partner in a
   third view; missing markers just give fewer points.
   The pair gate is in pixels, not metres: a pixel of camera v is an angle of
   about 1/f_v, so at ranges r_a, r_b along the two rays a pixel error moves
   the closest approach by up to r/f, and two rays of one marker pass within
   gate_px * sqrt((r_a/f_a)^2 + (r_b/f_b)^2) of each other. A metric gate
   is too tight far away (a marker 8 m off misses by > 1 cm per pixel) and
   too loose up close.

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


@njit
def _world_rays(xn, R):
    """Normalised coordinates (N, 2) of a camera with world->camera rotation R -> unit world directions (N, 3)."""
    out = np.empty((xn.shape[0], 3))
    for i in range(xn.shape[0]):
        n = 0.0
        for k in range(3):
            out[i, k] = R[0, k] * xn[i, 0] + R[1, k] * xn[i, 1] + R[2, k]
            n += out[i, k] * out[i, k]
        n = math.sqrt(n)
        for k in range(3):
            out[i, k] /= n
    return out


@njit
def _ray_pair(c1, d1, c2, d2, w0, dd, px1, px2, scaled, mid):
    """Closest approach of ray c1 + s d1 and ray c2 + u d2 (unit directions (3,)); w0 = c1 - c2, dd = d1 . w0.
    Writes the midpoint into mid (3,); returns the distance (metres, or pixels when scaled: see ray_distances),
    inf where the closest point lies behind a camera or the rays are parallel."""
    b = d1[0] * d2[0] + d1[1] * d2[1] + d1[2] * d2[2]
    e = d2[0] * w0[0] + d2[1] * w0[1] + d2[2] * w0[2]
    den = 1.0 - b * b
    s = (b * e - dd) / den  # along d1
    u = (e - b * dd) / den  # along d2
    ss = 0.0
    for k in range(3):
        p1 = c1[k] + s * d1[k]
        p2 = c2[k] + u * d2[k]
        mid[k] = 0.5 * (p1 + p2)
        ss += (p1 - p2) * (p1 - p2)
    if den > 1e-10 and s > 0 and u > 0:
        dist = math.sqrt(ss)
        if scaled:
            dist /= math.sqrt((s * px1) ** 2 + (u * px2) ** 2)
        return dist
    return math.inf


@njit
def ray_distances(c1: np.ndarray, d1: np.ndarray, c2: np.ndarray, d2: np.ndarray,
                  px1: float = 0.0, px2: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Closest approach of two bundles of rays from two centres (compiled).

    c1, c2: (3,) centres; d1 (N1, 3), d2 (N2, 3) unit directions. px1, px2:
    the angular size of a pixel of each camera (rad, 1/f); when given, the
    distance is divided by sqrt((s px1)^2 + (u px2)^2), the metres one pixel of
    error moves the closest approach at ranges s and u along the rays, so it
    is in pixels. Returns distance (N1, N2) in metres, or pixels when scaled
    (inf where the closest point lies behind a camera or the rays are
    parallel), and midpoints (N1, N2, 3).
    """
    N1, N2 = d1.shape[0], d2.shape[0]
    dist = np.empty((N1, N2))
    mid = np.empty((N1, N2, 3))
    scaled = px1 > 0.0 or px2 > 0.0
    w0 = c1 - c2
    for i in range(N1):
        dd = d1[i, 0] * w0[0] + d1[i, 1] * w0[1] + d1[i, 2] * w0[2]
        for j in range(N2):
            dist[i, j] = _ray_pair(c1, d1[i], c2, d2[j], w0, dd, px1, px2, scaled, mid[i, j])
    return dist, mid


def match_unlabeled(
    xn: list[np.ndarray],
    R: np.ndarray,
    t: np.ndarray,
    f: np.ndarray,
    ray_gate_px: float,
    max_residual_px: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cross-view matching and triangulation of unlabeled blobs.

    xn: per view v an (N_v, 2) array of normalised coordinates. R (V, 3, 3),
    t (V, 3), f (V,) as in `triangulate`. ray_gate_px: pair gate, pixels at
    each ray's range (two rays pass within ray_gate_px * sqrt((r_a/f_a)^2 +
    (r_b/f_b)^2) metres; module docstring). max_residual_px: growth gate and
    final RMS gate.
    Returns points (Q, 3), blob index (Q, V) (-1 = not seen), rms (Q,) px;
    every blob is used by at most one point.
    """
    V = len(xn)
    start = np.zeros(V + 1, dtype=np.int64)
    start[1:] = np.cumsum([len(x) for x in xn])
    pts = np.concatenate([np.asarray(x, dtype=np.float64).reshape(-1, 2) for x in xn]) if V else np.zeros((0, 2))
    return _match_unlabeled(np.ascontiguousarray(pts), start, np.ascontiguousarray(R, dtype=np.float64),
                            np.ascontiguousarray(t, dtype=np.float64), np.ascontiguousarray(f, dtype=np.float64),
                            float(ray_gate_px), float(max_residual_px))


@njit
def _match_unlabeled(pts, start, R, t, f, ray_gate_px, max_residual_px):
    """Compiled core of match_unlabeled; view v's blobs are pts[start[v]:start[v + 1]] (N, 2).
    Stages: seed pairs of rays (_seed_pairs), growth to the other views (_grow_seeds), triangulation with
    the worst wrongly grown view dropped (_drop_grown_outliers), greedy acceptance (_accept_greedy)."""
    V = start.shape[0] - 1
    centres = np.empty((V, 3))
    for v in range(V):
        for k in range(3):
            centres[v, k] = -(R[v, 0, k] * t[v, 0] + R[v, 1, k] * t[v, 1] + R[v, 2, k] * t[v, 2])
    rays = np.empty((pts.shape[0], 3))
    for v in range(V):
        rays[start[v] : start[v + 1]] = _world_rays(pts[start[v] : start[v + 1]], R[v])
    idx, X0 = _seed_pairs(start, centres, rays, R, t, f, ray_gate_px)
    S = idx.shape[0]
    if S == 0:
        return np.zeros((0, 3)), np.zeros((0, V), dtype=np.int64), np.zeros(0)
    _grow_seeds(pts, start, R, t, f, max_residual_px, idx, X0)
    idx = _first_of_each(idx)
    S = idx.shape[0]
    obs = np.full((S, V, 2), np.nan)
    for s in range(S):
        for v in range(V):
            if idx[s, v] >= 0:
                obs[s, v] = pts[start[v] + idx[s, v]]
    X, rms, nv = triangulate_irls(obs, R, t, f, np.zeros((0, 0, 3)), False, 2)
    _drop_grown_outliers(R, t, f, max_residual_px, idx, obs, X, rms, nv)
    return _accept_greedy(pts.shape[0], start, R, t, f, max_residual_px, idx, obs, X, rms, nv)


@njit
def _seed_pairs(start, centres, rays, R, t, f, ray_gate_px):
    """Seeds: pairs of rays of two views that pass within ray_gate_px at their ranges (widened near the floor
    by floor_merge_px at their midpoint; none whose midpoint is under the floor: a mirror image). Returns the
    blob index (S, V) (-1 = not in the seed) and each seed's midpoint X0 (S, 3) m, in the order of the views'
    pairs (a < b), then a's blobs, then b's."""
    V = start.shape[0] - 1
    # seeds are few next to the pairs of rays tried (80 blobs in 12 views: 15,000 of 420,000), so they are
    # collected in arrays that double, not in an (every pair, V) table
    cap = 64
    seed_a = np.empty(cap, dtype=np.int64)
    seed_i = np.empty(cap, dtype=np.int64)
    seed_b = np.empty(cap, dtype=np.int64)
    seed_j = np.empty(cap, dtype=np.int64)
    X0 = np.empty((cap, 3))
    mid = np.empty(3)
    S = 0
    for a in range(V):
        if start[a + 1] == start[a]:
            continue
        for b in range(a + 1, V):
            if start[b + 1] == start[b]:
                continue
            c1, c2 = centres[a], centres[b]
            w0 = c1 - c2
            px1, px2 = 1.0 / f[a], 1.0 / f[b]
            for i in range(start[a + 1] - start[a]):
                d1 = rays[start[a] + i]
                dd = d1[0] * w0[0] + d1[1] * w0[1] + d1[2] * w0[2]
                for j in range(start[b + 1] - start[b]):
                    dist = _ray_pair(c1, d1, c2, rays[start[b] + j], w0, dd, px1, px2, True, mid)
                    if not dist < math.inf or mid[2] < FLOOR_Z_M - BELOW_FLOOR_M:
                        continue
                    ok = dist < ray_gate_px
                    if not ok and 0.0 < mid[2] - FLOOR_Z_M < MERGE_MAX_HEIGHT_M:
                        # near the floor each ray may miss by its merged reflection's pull too
                        sa = _merge_px_view(mid, R[a], t[a], f[a])
                        sb = _merge_px_view(mid, R[b], t[b], f[b])
                        ok = dist**2 < ray_gate_px**2 + sa * sa + sb * sb
                    if not ok:
                        continue
                    if S == cap:
                        cap *= 2
                        seed_a, seed_i = _grown(seed_a, cap), _grown(seed_i, cap)
                        seed_b, seed_j = _grown(seed_b, cap), _grown(seed_j, cap)
                        X0 = _grown_rows(X0, cap)
                    seed_a[S], seed_i[S], seed_b[S], seed_j[S] = a, i, b, j
                    X0[S] = mid
                    S += 1
    idx = np.full((S, V), -1, dtype=np.int64)
    for k in range(S):
        idx[k, seed_a[k]], idx[k, seed_b[k]] = seed_i[k], seed_j[k]
    return idx, X0[:S].copy()


@njit
def _grown(a, n):
    """a (m,) copied into a new array of n >= m entries."""
    out = np.empty(n, dtype=a.dtype)
    out[: a.shape[0]] = a
    return out


@njit
def _grown_rows(a, n):
    """a (m, 3) copied into a new (n, 3) array, n >= m."""
    out = np.empty((n, 3))
    out[: a.shape[0]] = a
    return out


@njit
def _grow_seeds(pts, start, R, t, f, max_residual_px, idx, X0):
    """Each seed grown (idx, in place) to the other views by reprojecting its midpoint onto the nearest
    blob (the lowest index among equally near ones) within 3 x max_residual_px; the growth gate is looser
    than the final one: the seed midpoint is not the maximum-likelihood point. A view's blobs are searched
    in order of their x over the gate's width only (a dozen views of 80 blobs and 15,000 seeds: every blob
    of every view for every seed took 40 ms)."""
    V = start.shape[0] - 1
    S = idx.shape[0]
    gate_px = 3.0 * max_residual_px
    for v in range(V):
        n = start[v + 1] - start[v]
        if n == 0:
            continue
        view = pts[start[v] : start[v + 1]]
        by_x = np.argsort(view[:, 0], kind="mergesort")
        xs = view[by_x, 0]
        half = gate_px / f[v] * (1.0 + 1e-9)  # |du| f <= the distance: no blob outside the band is nearer
        for s in range(S):
            if idx[s, v] >= 0:
                continue
            z = R[v, 2, 0] * X0[s, 0] + R[v, 2, 1] * X0[s, 1] + R[v, 2, 2] * X0[s, 2] + t[v, 2]
            if not z > 0:
                continue
            u = (R[v, 0, 0] * X0[s, 0] + R[v, 0, 1] * X0[s, 1] + R[v, 0, 2] * X0[s, 2] + t[v, 0]) / z
            w = (R[v, 1, 0] * X0[s, 0] + R[v, 1, 1] * X0[s, 1] + R[v, 1, 2] * X0[s, 2] + t[v, 1]) / z
            best, nn = np.inf, -1
            k = np.searchsorted(xs, u - half)
            while k < n and xs[k] <= u + half:
                j = by_x[k]
                du, dw = u - view[j, 0], w - view[j, 1]
                d = math.sqrt(du * du + dw * dw) * f[v]
                if d < best or (d == best and j < nn):
                    best, nn = d, j
                k += 1
            if best < gate_px:
                idx[s, v] = nn


@njit
def _first_of_each(idx):
    """The rows of idx (S, V) without the later copies of a row seen before, in their order. A marker that
    a dozen views see is seeded by up to 66 pairs of them, and most grow into the very same set of blobs:
    their triangulations and their turns in _accept_greedy would be the same (a later copy finds every blob
    taken, or is refused as its first copy was), so only the first is kept."""
    S, V = idx.shape
    h = np.empty(S, dtype=np.int64)
    for s in range(S):
        acc = np.int64(1469598103934665603)
        for v in range(V):
            acc = (acc ^ np.int64(idx[s, v] + 2)) * np.int64(1099511628211)  # FNV-1a over the row; wraps
        h[s] = acc
    by_hash = np.argsort(h, kind="mergesort")  # equal hashes in row order
    keep = np.ones(S, dtype=np.bool_)
    a = 0
    while a < S:
        b = a + 1
        while b < S and h[by_hash[b]] == h[by_hash[a]]:
            b += 1
        for m in range(a + 1, b):  # a later row equal to an earlier kept one of its hash group is a copy
            r = by_hash[m]
            for k in range(a, m):
                q = by_hash[k]
                if keep[q]:
                    same = True
                    for v in range(V):
                        if idx[r, v] != idx[q, v]:
                            same = False
                            break
                    if same:
                        keep[r] = False
                        break
        a = b
    return idx[keep]


@njit
def _drop_grown_outliers(R, t, f, max_residual_px, idx, obs, X, rms, nv):
    """A view whose own residual is over the gate was grown onto a wrong blob: each point's worst such
    view is dropped and the point triangulated again (idx, obs, X, rms, nv in place)."""
    S, V = idx.shape
    no_offsets = np.zeros((0, 0, 3))
    for s in range(S):
        worst, r_worst = -1, -1.0
        for v in range(V):
            if idx[s, v] < 0:
                continue
            z = R[v, 2, 0] * X[s, 0] + R[v, 2, 1] * X[s, 1] + R[v, 2, 2] * X[s, 2] + t[v, 2]
            du = (R[v, 0, 0] * X[s, 0] + R[v, 0, 1] * X[s, 1] + R[v, 0, 2] * X[s, 2] + t[v, 0]) / z - obs[s, v, 0]
            dw = (R[v, 1, 0] * X[s, 0] + R[v, 1, 1] * X[s, 1] + R[v, 1, 2] * X[s, 2] + t[v, 1]) / z - obs[s, v, 1]
            r = math.sqrt(du * du + dw * dw) * f[v]
            if r > r_worst:
                worst, r_worst = v, r
        if worst >= 0 and r_worst > max_residual_px and nv[s] > 2:
            obs[s, worst] = np.nan
            idx[s, worst] = -1
            Xs, rs, ns = triangulate_irls(obs[s : s + 1], R, t, f, no_offsets, False, 2)
            X[s], rms[s], nv[s] = Xs[0], rs[0], ns[0]


@njit
def _accept_greedy(n_blobs, start, R, t, f, max_residual_px, idx, obs, X, rms, nv):
    """Greedy acceptance (most views, then lowest residual), each blob once; a candidate that shares blobs
    with an accepted point keeps its other views if at least two remain. Returns points (Q, 3), blob index
    (Q, V) and rms (Q,) px in acceptance order."""
    S, V = idx.shape
    no_offsets = np.zeros((0, 0, 3))
    gate = np.empty(S)  # max_residual_px, widened near the floor; -1 under it (a mirror image)
    for s in range(S):
        gate[s] = floor_gate(X[s], R, t, f, idx[s] >= 0, max_residual_px)
    by_rms = np.argsort(np.where(rms < gate, rms, np.inf), kind="mergesort")
    order = by_rms[np.argsort(-nv[by_rms], kind="mergesort")]  # stable: views, then residual, then index
    used = np.zeros(n_blobs, dtype=np.bool_)
    keep = np.zeros(S, dtype=np.bool_)
    for s in order:
        if not rms[s] < gate[s]:
            break
        n_views = 0
        n_clash = 0
        for v in range(V):
            if idx[s, v] >= 0:
                n_views += 1
                if used[start[v] + idx[s, v]]:
                    n_clash += 1
        if n_clash:
            if n_views - n_clash < 2:
                continue
            ok = obs[s : s + 1].copy()
            for v in range(V):
                if idx[s, v] >= 0 and used[start[v] + idx[s, v]]:
                    ok[0, v] = np.nan
                    idx[s, v] = -1
            Xs, rs, _ = triangulate_irls(ok, R, t, f, no_offsets, False, 2)
            if not rs[0] < floor_gate(Xs[0], R, t, f, idx[s] >= 0, max_residual_px):
                continue
            X[s], rms[s] = Xs[0], rs[0]
        keep[s] = True
        for v in range(V):
            if idx[s, v] >= 0:
                used[start[v] + idx[s, v]] = True
    Q = 0
    for s in order:
        if keep[s]:
            Q += 1
    out_X = np.empty((Q, 3))
    out_idx = np.empty((Q, V), dtype=np.int64)
    out_rms = np.empty(Q)
    q = 0
    for s in order:
        if keep[s]:
            out_X[q], out_idx[q], out_rms[q] = X[s], idx[s], rms[s]
            q += 1
    return out_X, out_idx, out_rms
