"""Rigid and similarity alignment of corresponding 3-D points (the Kabsch family).

Two algorithms for the same least-squares problem, min sum w |R src + t - dst|^2
over proper rotations R:
- SVD of the weighted cross-covariance (Kabsch; Umeyama adds the scale):
  `kabsch_svd`, `umeyama_svd` in numpy, for offline work (ground plane,
  calibration alignment) where a reflection-safe general method matters more
  than microseconds. `average_rotations` (geometry/rotations.py) is the same
  projection onto SO(3).
- Horn's quaternion method: the rotation is the eigenvector of the largest
  eigenvalue of a symmetric 4x4 matrix, found by a small compiled Jacobi solver
  (`symmetric_eigen_jacobi`). No SVD and no reflection case, and exact for
  coplanar markers. `kabsch_horn_compiled` is the per-body kernel the fusion
  pipeline calls inside its compiled measurement step; `kabsch_horn_batch` runs
  it over B padded problems (weight 0 = missing marker); `kabsch_horn` is one
  problem from numpy (rigid-body identification).
Both agree to round-off; callers keep the one they were tuned and replayed with.
"""

from __future__ import annotations

import math

import numpy as np

from visionpos.jit import njit

__all__ = [
    "normalized_weights",
    "kabsch_svd",
    "umeyama_svd",
    "kabsch_horn",
    "kabsch_horn_batch",
    "kabsch_horn_batch_compiled",
    "kabsch_horn_compiled",
    "symmetric_eigen_jacobi",
]


# ----------------------------------------------------------------- SVD (numpy, offline)
def normalized_weights(w: np.ndarray | None, n: int) -> np.ndarray:
    """(n,) weights summing to 1: uniform for None, else w checked (finite, >= 0, positive sum) and scaled."""
    if w is None:
        return np.full(n, 1.0 / n)
    w = np.asarray(w, dtype=np.float64).ravel()
    if w.shape != (n,) or np.any(w < 0) or not np.all(np.isfinite(w)) or w.sum() <= 0:
        raise ValueError(f"weights must be {n} finite non-negative numbers with a positive sum")
    return w / w.sum()


def _check_pairs(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise ValueError(f"src and dst must both have shape (N, 3), got {src.shape} and {dst.shape}")
    return src, dst


def _align(src: np.ndarray, dst: np.ndarray, weights, with_scale: bool):
    src, dst = _check_pairs(src, dst)
    w = normalized_weights(weights, len(src))
    mu_s = w @ src
    mu_d = w @ dst
    A = src - mu_s
    B = dst - mu_d
    C = (B * w[:, None]).T @ A  # (3,3) cross-covariance sum w b a^T
    U, S, Vt = np.linalg.svd(C)
    d = np.sign(np.linalg.det(U @ Vt))
    if d == 0:
        d = 1.0
    D = np.array([1.0, 1.0, d])
    R = (U * D) @ Vt
    if with_scale:
        var_s = float(w @ np.einsum("ij,ij->i", A, A))
        s = float((S * D).sum() / var_s) if var_s > 0 else 1.0
    else:
        s = 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def kabsch_svd(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Rigid alignment by SVD of the cross-covariance (Kabsch): (R (3,3), t (3,)) minimising
    sum w |R src + t - dst|^2 with det R = +1.

    src, dst: (N, 3) corresponding points; weights: (N,) non-negative or None.
    Reflections are never returned (the best proper rotation is used instead).
    """
    _, R, t = _align(src, dst, weights, with_scale=False)
    return R, t


def umeyama_svd(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity alignment (s, R (3,3), t (3,)) with dst ~ s R src + t (Umeyama 1991), det R = +1.

    src, dst: (N, 3) corresponding points; weights: (N,) non-negative or None.
    """
    return _align(src, dst, weights, with_scale=True)


# ------------------------------------------------ Horn's quaternion method (compiled)
def kabsch_horn_batch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted rigid alignment of B problems at once by Horn's method (compiled): dst ~ R src + t.

    src, dst: (B, M, 3); weights: (B, M) >= 0 (0 = unused; NaN rows must
    carry weight 0). Returns R (B, 3, 3) proper rotations, t (B, 3).
    """
    return kabsch_horn_batch_compiled(
        np.ascontiguousarray(src, dtype=np.float64),
        np.ascontiguousarray(dst, dtype=np.float64),
        np.ascontiguousarray(weights, dtype=np.float64),
    )


@njit
def kabsch_horn_batch_compiled(src, dst, w):
    """Compiled core of `kabsch_horn_batch`: src, dst (B, M, 3), w (B, M) float64 -> R (B, 3, 3), t (B, 3)."""
    B = w.shape[0]
    Rs = np.empty((B, 3, 3))
    ts = np.empty((B, 3))
    for b in range(B):
        Rs[b], ts[b] = kabsch_horn_compiled(src[b], dst[b], w[b])
    return Rs, ts


@njit
def kabsch_horn_compiled(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Compiled weighted rigid alignment (Horn): src, dst (M, 3), w (M,) >= 0 (0 = unused) -> R (3, 3), t (3,).

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
    evals, evecs = symmetric_eigen_jacobi(N)
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
def symmetric_eigen_jacobi(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


def kabsch_horn(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rigid alignment by Horn's quaternion method: src, dst (M, 3) -> R (3, 3), t (3,) with
    dst ~ R src + t; weights (M,) >= 0 or None (all 1). Same result as kabsch_svd to round-off;
    this one runs the compiled kernel (cheap for a few markers)."""
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    R, t = kabsch_horn_batch(np.asarray(src, float)[None], np.asarray(dst, float)[None], w[None])
    return R[0], t[0]
