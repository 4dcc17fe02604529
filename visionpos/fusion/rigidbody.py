"""Rigid bodies: identification from unlabeled 3D points and 6-DoF pose.

Identification uses only geometry: a body's markers have fixed pairwise
distances. For a body we take each marker triangle (a, b, c) as a seed,
find point triples whose three pairwise distances match within a
tolerance, fit the pose of the triple (Kabsch), predict the remaining
markers and collect points within tolerance. Hypotheses are scored by the
number of markers explained, then by the Kabsch RMS. Several bodies are
identified at once by greedy acceptance over all bodies' best hypotheses
with disjoint point sets; a 3-point hypothesis that fits more than one
body equally well is ambiguous and refused (tracking, not identification,
is what continues with 3 of 4 markers).

Poses come from `kabsch_weighted` (compiled; the pipeline calls it per
tracked body inside its measurement kernel) and `kabsch_batch`, the same
over several bodies at once (padded marker sets, weight 0 = missing): the
rotation from Horn's quaternion method, the eigenvector of a 4x4 symmetric
matrix, computed by a small Jacobi solver (`symmetric_eigen`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import permutations

import numpy as np

from visionpos.jit import njit


@dataclass(frozen=True)
class BodyModel:
    """markers: (M, 3) body-frame marker positions (m)."""

    name: str
    id: int
    markers: np.ndarray

    @property
    def distances(self) -> np.ndarray:
        """(M, M) pairwise marker distances."""
        m = self.markers
        return np.linalg.norm(m[:, None] - m[None], axis=-1)


@dataclass(frozen=True)
class Identification:
    """A body found among points.

    body: index into the model list; point_index: (M,) index of the point
    that is marker m, -1 when the marker was not found; R (3, 3), t (3,)
    body->world pose; rms: Kabsch residual (m).
    """

    body: int
    point_index: np.ndarray
    R: np.ndarray
    t: np.ndarray
    rms: float

    @property
    def n_markers(self) -> int:
        return int((self.point_index >= 0).sum())


def kabsch_batch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted Kabsch for B problems at once: dst ~ R src + t.

    src, dst: (B, M, 3); weights: (B, M) >= 0 (0 = unused; NaN rows must
    carry weight 0). Returns R (B, 3, 3) proper rotations, t (B, 3).
    """
    return _kabsch_batch(np.ascontiguousarray(src, dtype=np.float64), np.ascontiguousarray(dst, dtype=np.float64),
                         np.ascontiguousarray(weights, dtype=np.float64))


@njit
def _kabsch_batch(src, dst, w):
    B = w.shape[0]
    Rs = np.empty((B, 3, 3))
    ts = np.empty((B, 3))
    for b in range(B):
        Rs[b], ts[b] = kabsch_weighted(src[b], dst[b], w[b])
    return Rs, ts


@njit
def kabsch_weighted(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Compiled weighted Kabsch: src, dst (M, 3), w (M,) >= 0 (0 = unused) -> R (3, 3), t (3,).

    The best proper rotation comes from Horn's quaternion form: the unit
    eigenvector of the largest eigenvalue of a symmetric 4x4 matrix built
    from the cross-covariance (no SVD and no reflection case; exact for
    coplanar markers too).
    """
    M = w.shape[0]
    ws = 0.0
    cs = np.zeros(3)
    cd = np.zeros(3)
    for m in range(M):
        if w[m] > 0:
            ws += w[m]
            for i in range(3):
                cs[i] += w[m] * src[m, i]
                cd[i] += w[m] * dst[m, i]
    if ws <= 0:
        ws = 1.0
    cs /= ws
    cd /= ws
    S = np.zeros((3, 3))  # cross-covariance sum w (src - cs)(dst - cd)^T
    for m in range(M):
        if w[m] > 0:
            for i in range(3):
                si = w[m] * (src[m, i] - cs[i])
                for j in range(3):
                    S[i, j] += si * (dst[m, j] - cd[j])
    N = np.empty((4, 4))
    N[0, 0] = S[0, 0] + S[1, 1] + S[2, 2]
    N[1, 1] = S[0, 0] - S[1, 1] - S[2, 2]
    N[2, 2] = -S[0, 0] + S[1, 1] - S[2, 2]
    N[3, 3] = -S[0, 0] - S[1, 1] + S[2, 2]
    N[0, 1] = N[1, 0] = S[1, 2] - S[2, 1]
    N[0, 2] = N[2, 0] = S[2, 0] - S[0, 2]
    N[0, 3] = N[3, 0] = S[0, 1] - S[1, 0]
    N[1, 2] = N[2, 1] = S[0, 1] + S[1, 0]
    N[1, 3] = N[3, 1] = S[2, 0] + S[0, 2]
    N[2, 3] = N[3, 2] = S[1, 2] + S[2, 1]
    evals, evecs = symmetric_eigen(N)
    k = np.argmax(evals)
    qw, qx, qy, qz = evecs[0, k], evecs[1, k], evecs[2, k], evecs[3, k]
    n2 = qw * qw + qx * qx + qy * qy + qz * qz
    R = np.empty((3, 3))
    R[0, 0] = (qw * qw + qx * qx - qy * qy - qz * qz) / n2
    R[1, 1] = (qw * qw - qx * qx + qy * qy - qz * qz) / n2
    R[2, 2] = (qw * qw - qx * qx - qy * qy + qz * qz) / n2
    R[0, 1] = 2.0 * (qx * qy - qw * qz) / n2
    R[1, 0] = 2.0 * (qx * qy + qw * qz) / n2
    R[0, 2] = 2.0 * (qx * qz + qw * qy) / n2
    R[2, 0] = 2.0 * (qx * qz - qw * qy) / n2
    R[1, 2] = 2.0 * (qy * qz - qw * qx) / n2
    R[2, 1] = 2.0 * (qy * qz + qw * qx) / n2
    t = np.empty(3)
    for i in range(3):
        t[i] = cd[i] - (R[i, 0] * cs[0] + R[i, 1] * cs[1] + R[i, 2] * cs[2])
    return R, t


@njit
def symmetric_eigen(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (n,) and eigenvectors (columns, (n, n)) of a small symmetric matrix (cyclic Jacobi).

    Converges quadratically; for 4x4 a handful of sweeps reach round-off, and
    a library call's fixed overhead would cost more than the arithmetic.
    """
    n = A.shape[0]
    a = A.copy()
    V = np.eye(n)
    scale = 0.0
    for i in range(n):
        for j in range(n):
            scale += a[i, j] * a[i, j]
    for _ in range(50):
        off = 0.0
        for i in range(n):
            for j in range(i + 1, n):
                off += a[i, j] * a[i, j]
        if off <= 1e-32 * scale or off == 0.0:
            break
        for p in range(n):
            for q in range(p + 1, n):
                if a[p, q] == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * a[p, q])
                tt = (1.0 if theta >= 0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(tt * tt + 1.0)
                s = tt * c
                for k in range(n):  # A <- J^T A J
                    akp, akq = a[k, p], a[k, q]
                    a[k, p], a[k, q] = c * akp - s * akq, s * akp + c * akq
                for k in range(n):
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k], a[q, k] = c * apk - s * aqk, s * apk + c * aqk
                for k in range(n):
                    vkp, vkq = V[k, p], V[k, q]
                    V[k, p], V[k, q] = c * vkp - s * vkq, s * vkp + c * vkq
    evals = np.empty(n)
    for i in range(n):
        evals[i] = a[i, i]
    return evals, V


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Single weighted Kabsch: src, dst (M, 3) -> R (3, 3), t (3,) with dst ~ R src + t."""
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    R, t = kabsch_batch(np.asarray(src, float)[None], np.asarray(dst, float)[None], w[None])
    return R[0], t[0]


def _hypotheses(points: np.ndarray, D: np.ndarray, model: BodyModel, tol: float) -> list[tuple[int, float, np.ndarray, np.ndarray, np.ndarray]]:
    """All consistent placements of one body among points.

    Returns (n_markers, rms, point_index (M,), R, t) tuples.
    """
    mk = model.markers
    M = len(mk)
    Dm = model.distances
    out = []
    seen: set[tuple[int, ...]] = set()
    # seed triangles: every ordered marker triple would repeat work; the
    # unordered triple with point permutations covers all assignments
    for a in range(M):
        for b in range(a + 1, M):
            for c in range(b + 1, M):
                pij = np.argwhere(np.abs(D - Dm[a, b]) < tol)
                for i, j in pij:
                    if i == j:
                        continue
                    ks = np.nonzero((np.abs(D[i] - Dm[a, c]) < tol) & (np.abs(D[j] - Dm[b, c]) < tol))[0]
                    for k in ks:
                        if k == i or k == j:
                            continue
                        R, t = kabsch(mk[[a, b, c]], points[[i, j, k]])
                        pred = mk @ R.T + t
                        dist = np.linalg.norm(pred[:, None] - points[None], axis=-1)  # (M, K)
                        idx = np.full(M, -1)
                        idx[[a, b, c]] = [i, j, k]
                        used = {i, j, k}
                        for m in range(M):
                            if idx[m] >= 0:
                                continue
                            order = np.argsort(dist[m])
                            for q in order:
                                if dist[m, q] >= tol:
                                    break
                                if q not in used:
                                    idx[m] = q
                                    used.add(int(q))
                                    break
                        key = tuple(int(v) for v in idx)
                        if key in seen:
                            continue
                        seen.add(key)
                        sel = idx >= 0
                        R, t = kabsch(mk[sel], points[idx[sel]])
                        res = points[idx[sel]] - (mk[sel] @ R.T + t)
                        rms = float(np.sqrt((res**2).sum(axis=1).mean()))
                        if rms < tol:
                            out.append((int(sel.sum()), rms, idx, R, t))
    return out


def identify(
    points: np.ndarray,
    models: list[BodyModel],
    tolerance: float = 0.008,
    min_markers: int = 3,
    only: list[int] | None = None,
) -> list[Identification]:
    """Find bodies among unlabeled points by their marker geometry.

    points: (K, 3) world points (m). models: the bodies. tolerance: max
    distance mismatch and Kabsch RMS (m). min_markers: fewest markers for a
    detection (>= 3). only: indices of the models to look for (default all).
    Returns at most one Identification per body, with disjoint points.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) < 3:
        return []
    D = np.linalg.norm(points[:, None] - points[None], axis=-1)
    wanted = list(range(len(models))) if only is None else list(only)
    cands = []
    for bi in wanted:
        for n, rms, idx, R, t in _hypotheses(points, D, models[bi], tolerance):
            if n >= max(3, min_markers):
                cands.append((n, rms, bi, idx, R, t))
    # more markers first, then smaller residual; deterministic tie-break by body index
    cands.sort(key=lambda c: (-c[0], c[1], c[2]))
    taken: set[int] = set()
    found: dict[int, Identification] = {}
    for n, rms, bi, idx, R, t in cands:
        if bi in found:
            continue
        pts = set(int(v) for v in idx[idx >= 0])
        if pts & taken:
            continue
        # a minimal (3-point) fit that another body explains as well is ambiguous
        if n == 3:
            rivals = [c for c in cands if c[2] != bi and c[0] >= 3 and set(int(v) for v in c[3][c[3] >= 0]) == pts]
            if rivals:
                continue
        found[bi] = Identification(bi, idx, R, t, rms)
        taken |= pts
    return [found[b] for b in sorted(found)]


def layout_ambiguities(models: list[BodyModel], tolerance: float) -> list[str]:
    """Describe marker layouts the identification cannot tell apart (config check).

    Reports bodies whose full layouts match each other and bodies with a
    non-trivial self-symmetry (a marker permutation that is a rigid motion),
    both within `tolerance` (m).
    """
    problems = []
    for i, a in enumerate(models):
        M = len(a.markers)
        if M <= 6:
            for perm in permutations(range(M)):
                if list(perm) == list(range(M)):
                    continue
                R, t = kabsch(a.markers, a.markers[list(perm)])
                res = a.markers[list(perm)] - (a.markers @ R.T + t)
                if np.sqrt((res**2).sum(axis=1).mean()) < tolerance:
                    problems.append(f"body '{a.name}' is symmetric: its orientation is ambiguous")
                    break
        for b in models[i + 1 :]:
            if len(b.markers) != M:
                continue
            D = np.linalg.norm(b.markers[:, None] - b.markers[None], axis=-1)
            if any(h[0] == M for h in _hypotheses(b.markers, D, a, tolerance)):
                problems.append(f"bodies '{a.name}' and '{b.name}' have the same marker layout: they can be swapped")
    return problems
