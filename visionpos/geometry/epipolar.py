"""Two-view (epipolar) geometry: the essential matrix from correspondences and the relative pose in it.

Used by the extrinsic calibration to start from nothing: normalised
correspondences of two cameras -> E with x2^T E x1 = 0 (normalised 8-point,
optionally inside RANSAC on the Sampson distance) -> (R, t) by the cheirality
test. Coordinates are normalised image coordinates (x/z, y/z).
"""

from __future__ import annotations

import numpy as np

__all__ = ["essential_from_points", "decompose_essential"]


def _hartley(x: np.ndarray) -> np.ndarray:
    """(3,3) similarity moving the centroid to 0 and the mean distance to sqrt(2)."""
    mu = x.mean(axis=0)
    d = np.linalg.norm(x - mu, axis=1).mean()
    s = np.sqrt(2.0) / d if d > 0 else 1.0
    return np.array([[s, 0, -s * mu[0]], [0, s, -s * mu[1]], [0, 0, 1.0]])


def _project_essential(E: np.ndarray) -> np.ndarray:
    """Closest essential matrix: singular values (s, s, 0)."""
    U, S, Vt = np.linalg.svd(E)
    s = 0.5 * (S[..., 0] + S[..., 1])
    D = np.zeros(S.shape)
    D[..., 0] = s
    D[..., 1] = s
    return (U * D[..., None, :]) @ Vt


def _eight_point(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Batched normalised 8-point: x1, x2 (B, N, 2) -> E (B, 3, 3), unit Frobenius norm."""
    B, N, _ = x1.shape
    E = np.empty((B, 3, 3))
    T1 = np.stack([_hartley(a) for a in x1])
    T2 = np.stack([_hartley(a) for a in x2])
    h1 = np.einsum("bij,bnj->bni", T1, np.concatenate([x1, np.ones((B, N, 1))], axis=2))
    h2 = np.einsum("bij,bnj->bni", T2, np.concatenate([x2, np.ones((B, N, 1))], axis=2))
    # x2^T E x1 = 0 -> kron(x2, x1) . vec(E) = 0
    A = (h2[:, :, :, None] * h1[:, :, None, :]).reshape(B, N, 9)
    # a thin SVD for N >= 9 (the full one also builds an N x N U, which dominated a calibration's time);
    # a minimal 8-point sample needs the full V for its null vector
    _, _, Vt = np.linalg.svd(A, full_matrices=N < 9)
    En = Vt[:, -1, :].reshape(B, 3, 3)
    # in Hartley coordinates only rank 2 holds (it is a fundamental matrix there)
    U, S, Vt2 = np.linalg.svd(En)
    S[:, 2] = 0.0
    En = (U * S[:, None, :]) @ Vt2
    E = np.einsum("bji,bjk,bkl->bil", T2, En, T1)  # T2^T En T1
    E = _project_essential(E)
    return E / np.linalg.norm(E, axis=(1, 2), keepdims=True)


def sampson_distance(E: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distance (first-order geometric error, normalised units) of correspondences x1, x2 (N, 2)
    under an essential matrix E (3, 3) -> (N,), or under a batch E (B, 3, 3) -> (B, N)."""
    Eb = np.asarray(E, dtype=np.float64)
    single = Eb.ndim == 2
    Eb = Eb[None] if single else Eb
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], axis=1)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], axis=1)
    Ex1 = np.einsum("bij,nj->bni", Eb, h1)
    Etx2 = np.einsum("bji,nj->bni", Eb, h2)
    num = np.einsum("ni,bni->bn", h2, Ex1)
    den = Ex1[..., 0] ** 2 + Ex1[..., 1] ** 2 + Etx2[..., 0] ** 2 + Etx2[..., 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.abs(num) / np.sqrt(den)
    return d[0] if single else d


def essential_from_points(
    xn1: np.ndarray,
    xn2: np.ndarray,
    threshold: float | None = None,
    confidence: float = 0.999,
    max_iters: int = 2000,
    rng: np.random.Generator | int | None = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Essential matrix from N >= 8 correspondences in normalised coordinates.

    xn1, xn2: (N, 2) with x2^T E x1 = 0 for homogeneous x = (x, y, 1).
    threshold: None -> plain normalised 8-point on all points (all inliers); else
    RANSAC over 8-point minimal samples with this Sampson-distance threshold
    (normalised units, i.e. pixels / focal length), refit on the inliers.
    Returns E (3, 3) (rank 2, equal singular values, unit Frobenius norm) and inliers (N,) bool.
    """
    x1 = np.asarray(xn1, dtype=np.float64)
    x2 = np.asarray(xn2, dtype=np.float64)
    if x1.ndim != 2 or x1.shape[1] != 2 or x1.shape != x2.shape:
        raise ValueError(f"xn1 and xn2 must both have shape (N, 2), got {x1.shape} and {x2.shape}")
    ok = np.isfinite(x1).all(axis=1) & np.isfinite(x2).all(axis=1)
    N = int(ok.sum())
    if N < 8:
        raise ValueError(f"essential matrix needs at least 8 finite correspondences, got {N}")
    idx = np.flatnonzero(ok)
    if threshold is None:
        E = _eight_point(x1[idx][None], x2[idx][None])[0]
        return E, ok
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    best_inl = np.zeros(len(x1), bool)
    best_n = 0
    needed = max_iters
    done = 0
    batch = 64
    while done < min(needed, max_iters):
        samples = np.stack([gen.choice(idx, 8, replace=False) for _ in range(batch)])
        Es = _eight_point(x1[samples], x2[samples])
        d = sampson_distance(Es, x1, x2)
        inl = (d < threshold) & ok
        counts = inl.sum(axis=1)
        b = int(np.argmax(counts))
        if counts[b] > best_n:
            best_n = int(counts[b])
            best_inl = inl[b]
            frac = best_n / N
            # iterations so that an all-inlier sample is drawn with `confidence`
            p_good = frac**8
            needed = max_iters if p_good <= 0 else int(np.ceil(np.log(1 - confidence) / np.log(max(1e-12, 1 - p_good))))
        done += batch
    if best_n < 8:
        raise ValueError(f"RANSAC found only {best_n} inliers at threshold {threshold}; raise the threshold")
    E = _eight_point(x1[best_inl][None], x2[best_inl][None])[0]
    inl = (sampson_distance(E[None], x1, x2)[0] < threshold) & ok
    if inl.sum() >= 8 and inl.sum() >= best_n:
        E = _eight_point(x1[inl][None], x2[inl][None])[0]
        best_inl = inl
    return E, best_inl


def decompose_essential(
    E: np.ndarray, xn1: np.ndarray, xn2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Relative pose from an essential matrix by the cheirality check.

    E: (3, 3) with x2^T E x1 = 0; xn1, xn2: (N, 2) normalised correspondences.
    Returns R (3, 3), t (3,) unit vector with X2 = R X1 + t (camera-1 frame to camera-2
    frame, translation up to scale), and in_front (N,) bool: the point triangulates
    in front of both cameras. Of the four (R, t) candidates the one with the most
    points in front wins.
    """
    E = np.asarray(E, dtype=np.float64)
    x1 = np.asarray(xn1, dtype=np.float64).reshape(-1, 2)
    x2 = np.asarray(xn2, dtype=np.float64).reshape(-1, 2)
    if E.shape != (3, 3):
        raise ValueError(f"E must be (3, 3), got {E.shape}")
    U, _, Vt = np.linalg.svd(E)
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Ra = U @ W @ Vt
    Rb = U @ W.T @ Vt
    u3 = U[:, 2] / np.linalg.norm(U[:, 2])
    candidates = [(Ra, u3), (Ra, -u3), (Rb, u3), (Rb, -u3)]
    h1 = np.column_stack([x1, np.ones(len(x1))])
    h2 = np.column_stack([x2, np.ones(len(x2))])
    best = None
    for R, t in candidates:
        # depths d1, d2 solving d2 h2 = d1 R h1 + t in least squares (midpoint-style)
        a = h1 @ R.T  # (N,3) = R h1
        A = np.stack([a, -h2], axis=2)  # (N,3,2): [R h1, -h2] [d1, d2]^T = -t
        AtA = np.einsum("nki,nkj->nij", A, A)
        Atb = np.einsum("nki,k->ni", A, -t)
        det = AtA[:, 0, 0] * AtA[:, 1, 1] - AtA[:, 0, 1] ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            d1 = (AtA[:, 1, 1] * Atb[:, 0] - AtA[:, 0, 1] * Atb[:, 1]) / det
            d2 = (-AtA[:, 0, 1] * Atb[:, 0] + AtA[:, 0, 0] * Atb[:, 1]) / det
        front = (d1 > 0) & (d2 > 0)
        n = int(front.sum())
        if best is None or n > best[0]:
            best = (n, R, t, front)
    _, R, t, front = best
    return R, t, front
