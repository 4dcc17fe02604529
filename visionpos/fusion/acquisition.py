"""Acquisition's cross-view matching of unlabeled blobs (lost bodies, loose markers): `match_unlabeled`.

Unlabeled blobs of different cameras are paired by the closest approach of their rays, each pair is grown
to more views by reprojection, and candidates are accepted greedily by (number of views, residual) so that
every blob is used once. False blobs rarely find a consistent partner in a third view; missing markers
just give fewer points. The pair gate is in pixels, not metres: a pixel of camera v is an angle of about
1/f_v, so at ranges r_a, r_b along the two rays a pixel error moves the closest approach by up to r/f, and
two rays of one marker pass within gate_px * sqrt((r_a/f_a)^2 + (r_b/f_b)^2) of each other. A metric gate
is too tight far away (a marker 8 m off misses by > 1 cm per pixel) and too loose up close. The floor's
mirror images and merged reflections are handled as matching.py says (floor_gate, floor_merge_px).

The stages are compiled loops (visionpos/jit.py), run by match_unlabeled_steps in steps of bounded estimated
work (the pipeline spreads a large acquisition over several fusions; match_unlabeled runs it at once).
Normalised image coordinates; R (V, 3, 3), t (V, 3) world -> camera; f (V,) focal lengths in pixels.
"""

from __future__ import annotations

import math

import numpy as np

from visionpos.fusion.matching import (
    BELOW_FLOOR_M,
    FLOOR_Z_M,
    MERGE_MAX_HEIGHT_M,
    _merge_px_view,
    floor_gate,
    triangulate_irls,
)
from visionpos.fusion.steps import Steps, finish
from visionpos.jit import njit


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
def _ray_pair(c1, d1, c2, d2, w0, dd, px1, px2, mid):
    """Closest approach of ray c1 + s d1 and ray c2 + u d2 (unit directions (3,)); w0 = c1 - c2, dd = d1 . w0;
    px1, px2: the angular size of a pixel of each camera (rad, 1/f). Writes the midpoint into mid (3,) and
    returns the distance in pixels: metres over sqrt((s px1)^2 + (u px2)^2), what one pixel of error moves the
    closest approach at ranges s and u; inf where it lies behind a camera or the rays are parallel."""
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
        return math.sqrt(ss) / math.sqrt((s * px1) ** 2 + (u * px2) ** 2)
    return math.inf


# estimated cost of acquisition's units of work (ns, 2-core AMD EPYC and Xeon hosts of docs/benchmarks.md) for
# the steps' sizes: it is a budget to split the work by, never a measurement
SEED_PAIR_NS = 25  # one pair of rays tried for a seed
GROWTH_NS = 70  # one seed reprojected into one view and its nearest blob found
DEDUPE_NS = 100  # one grown seed compared with the others for copies
POINT_NS = 350  # one distinct grown seed triangulated and its worst view checked
ACCEPT_NS = 250  # one distinct grown seed through the greedy acceptance
STEP_NS = 1_000_000  # match_unlabeled_steps yields after about this much work


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
    return finish(match_unlabeled_steps(xn, R, t, f, ray_gate_px, max_residual_px, step_ns=math.inf))


def match_unlabeled_steps(xn: list[np.ndarray], R: np.ndarray, t: np.ndarray, f: np.ndarray, ray_gate_px: float,
                          max_residual_px: float, step_ns: float = STEP_NS) -> Steps[tuple]:
    """match_unlabeled (same arguments and result) as a generator of steps of about step_ns of estimated work
    each (SEED_PAIR_NS and the rest): it yields each step's estimate (ns) and returns the result. The steps cut
    the stages along views and seeds, whose results do not depend on the cut: any step_ns gives the same
    points bit for bit. A caller that must not hold its frames up (the pipeline: a parked fleet's first
    acquisition is 40 ms of work) spreads the steps out; steps.finish runs them all."""
    V = len(xn)
    start = np.zeros(V + 1, dtype=np.int64)
    start[1:] = np.cumsum([len(x) for x in xn])
    pts = np.concatenate([np.asarray(x, dtype=np.float64).reshape(-1, 2) for x in xn]) if V else np.zeros((0, 2))
    pts = np.ascontiguousarray(pts)
    R = np.ascontiguousarray(R, dtype=np.float64)
    t = np.ascontiguousarray(t, dtype=np.float64)
    f = np.ascontiguousarray(f, dtype=np.float64)
    ray_gate_px, max_residual_px = float(ray_gate_px), float(max_residual_px)
    nothing = np.zeros((0, 3)), np.zeros((0, V), dtype=np.int64), np.zeros(0)
    if V == 0:
        return nothing
    centres, rays = _rays(pts, start, R, t)
    # seeds, a run of first views a at a time
    sizes = np.diff(start)
    later = np.cumsum(sizes[::-1])[::-1] - sizes  # blobs in the views after each
    pairs, mids = [], []
    a = 0
    while a < V:
        b, cost = a, 0.0
        while b < V and (b == a or cost + sizes[b] * later[b] * SEED_PAIR_NS <= step_ns):
            cost += sizes[b] * later[b] * SEED_PAIR_NS
            b += 1
        p, m = _seed_pairs(start, centres, rays, R, t, f, ray_gate_px, a, b)
        pairs.append(p)
        mids.append(m)
        a = b
        yield cost
    idx, X0 = _seed_table(np.concatenate(pairs), V), np.concatenate(mids)
    S = idx.shape[0]
    if S == 0:
        return nothing
    # growth, a run of views at a time
    per_view = S * GROWTH_NS
    step_views = _units_per_step(per_view, step_ns, V)
    for v in range(0, V, step_views):
        _grow_seeds(pts, start, R, t, f, max_residual_px, idx, X0, v, min(V, v + step_views))
        yield per_view * (min(V, v + step_views) - v)
    idx = _first_of_each(idx)
    yield S * DEDUPE_NS
    # triangulation and the grown outliers, a block of seeds at a time
    S = idx.shape[0]
    obs = _observations(pts, start, idx)
    X, rms, nv = np.empty((S, 3)), np.empty(S), np.empty(S, dtype=np.int64)
    block = _units_per_step(POINT_NS, step_ns, S)
    for s0 in range(0, S, block):
        s1 = min(S, s0 + block)
        X[s0:s1], rms[s0:s1], nv[s0:s1] = triangulate_irls(obs[s0:s1], R, t, f, np.zeros((0, 0, 3)), False, 2)
        _drop_grown_outliers(R, t, f, max_residual_px, idx, obs, X, rms, nv, s0, s1)
        yield (s1 - s0) * POINT_NS
    out = _accept_greedy(pts.shape[0], start, R, t, f, max_residual_px, idx, obs, X, rms, nv)
    yield S * ACCEPT_NS
    return out


def _units_per_step(unit_ns: float, step_ns: float, n: int) -> int:
    """How many units of unit_ns estimated work make a step of step_ns (at least 1, at most all n)."""
    return n if unit_ns * n <= step_ns else max(1, int(step_ns // unit_ns))


def still_seen(markers: list[np.ndarray], xn: list[np.ndarray], R: np.ndarray, t: np.ndarray, f: np.ndarray,
               gate_px: float, min_markers: int) -> np.ndarray:
    """Whether each body is still where it was: at least min_markers of its markers (markers[b] (M_b, 3) m,
    world) have a blob within gate_px of their projection in two views or more. Per view v its blobs xn[v]
    (N_v, 2), normalised; R (V, 3, 3), t (V, 3), f (V,) as in match_unlabeled. Returns (B,) bool. The pipeline
    asks it of the bodies that an acquisition in steps found in older frames."""
    points = np.concatenate(markers) if markers else np.zeros((0, 3))
    views = np.zeros(len(points), dtype=np.int64)
    for v, blobs in enumerate(xn):
        if not len(blobs):
            continue
        cam = points @ R[v].T + t[v]
        ahead = cam[:, 2] > 0
        uv = cam[:, :2] / np.where(ahead, cam[:, 2], 1.0)[:, None]
        d2 = ((uv[:, None, :] - blobs[None, :, :]) ** 2).sum(-1).min(axis=1)
        views += ahead & (d2 * f[v] ** 2 <= gate_px**2)
    if not markers:
        return np.zeros(0, dtype=bool)
    first = np.cumsum([0] + [len(m) for m in markers[:-1]])
    return np.add.reduceat((views >= 2).astype(np.int64), first) >= min_markers


@njit
def _rays(pts, start, R, t):
    """The cameras' centres (V, 3) m and each blob's unit world ray (N, 3); view v's blobs are
    pts[start[v]:start[v + 1]] (N, 2), normalised."""
    V = start.shape[0] - 1
    centres = np.empty((V, 3))
    for v in range(V):
        for k in range(3):
            centres[v, k] = -(R[v, 0, k] * t[v, 0] + R[v, 1, k] * t[v, 1] + R[v, 2, k] * t[v, 2])
    rays = np.empty((pts.shape[0], 3))
    for v in range(V):
        rays[start[v] : start[v + 1]] = _world_rays(pts[start[v] : start[v + 1]], R[v])
    return centres, rays


@njit
def _observations(pts, start, idx):
    """Each seed's blobs (S, V, 2), normalised; NaN where idx (S, V) is -1."""
    S, V = idx.shape
    obs = np.full((S, V, 2), np.nan)
    for s in range(S):
        for v in range(V):
            if idx[s, v] >= 0:
                obs[s, v] = pts[start[v] + idx[s, v]]
    return obs


@njit
def _seed_pairs(start, centres, rays, R, t, f, ray_gate_px, a0, a1):
    """Seeds: pairs of rays of two views that pass within ray_gate_px at their ranges (widened near the floor
    by floor_merge_px at their midpoint; none whose midpoint is under the floor: a mirror image), for the
    first views a0 <= a < a1. Returns (view a, its blob, view b, its blob) (S, 4) and each seed's midpoint X0
    (S, 3) m, in the order of the views' pairs (a < b), then a's blobs, then b's."""
    V = start.shape[0] - 1
    # seeds are few next to the pairs of rays tried (80 blobs in 12 views: 15,000 of 420,000), so they are
    # collected in arrays that double, not in an (every pair, V) table
    pairs = np.empty((64, 4), dtype=np.int64)  # (view a, its blob, view b, its blob)
    X0 = np.empty((64, 3))
    mid = np.empty(3)
    S = 0
    for a in range(a0, a1):
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
                    dist = _ray_pair(c1, d1, c2, rays[start[b] + j], w0, dd, px1, px2, mid)
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
                    if S == pairs.shape[0]:
                        pairs, X0 = _doubled(pairs), _doubled(X0)
                    pairs[S, 0], pairs[S, 1], pairs[S, 2], pairs[S, 3] = a, i, b, j
                    X0[S] = mid
                    S += 1
    return pairs[:S].copy(), X0[:S].copy()


@njit
def _seed_table(pairs, V):
    """The seeds' blob index (S, V) (-1 = not in the seed) from their (view a, blob, view b, blob) (S, 4)."""
    idx = np.full((pairs.shape[0], V), -1, dtype=np.int64)
    for k in range(pairs.shape[0]):
        idx[k, pairs[k, 0]], idx[k, pairs[k, 2]] = pairs[k, 1], pairs[k, 3]
    return idx


@njit
def _doubled(a):
    """a (m, k) copied into the first rows of a new (2m, k) array of its dtype."""
    out = np.empty((2 * a.shape[0], a.shape[1]), dtype=a.dtype)
    out[: a.shape[0]] = a
    return out


@njit
def _grow_seeds(pts, start, R, t, f, max_residual_px, idx, X0, v0, v1):
    """Each seed grown (idx, in place) to the other views v0 <= v < v1 by reprojecting its midpoint onto the nearest
    blob (the lowest index among equally near ones) within 3 x max_residual_px; the growth gate is looser
    than the final one: the seed midpoint is not the maximum-likelihood point. A view's blobs are searched
    in order of their x over the gate's width only (a dozen views of 80 blobs and 15,000 seeds: every blob
    of every view for every seed took 40 ms)."""
    S = idx.shape[0]
    gate_px = 3.0 * max_residual_px
    for v in range(v0, v1):
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
def _drop_grown_outliers(R, t, f, max_residual_px, idx, obs, X, rms, nv, s0, s1):
    """A view whose own residual is over the gate was grown onto a wrong blob: each point s0 <= s < s1 has its
    worst such view dropped and is triangulated again (idx, obs, X, rms, nv in place)."""
    V = idx.shape[1]
    no_offsets = np.zeros((0, 0, 3))
    for s in range(s0, s1):
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
