"""The Kabsch family (geometry/alignment.py): SVD (Kabsch, Umeyama) and Horn's compiled quaternion method.

References: a generic scipy optimiser over rotation vectors, scipy's
Rotation.align_vectors, numpy's eigh; never the library itself.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from visionpos.geometry.alignment import (
    kabsch_horn,
    kabsch_horn_batch,
    kabsch_horn_compiled,
    kabsch_svd,
    symmetric_eigen_jacobi,
    umeyama_svd,
)


def _rigid_cost(R, t, src, dst, w):
    return float(np.sum(w * np.sum((src @ R.T + t - dst) ** 2, axis=1)))


def _best_proper_rigid_by_search(src, dst, w):
    """Independent reference: minimise the weighted cost over rotation vectors (scipy)."""
    best = np.inf
    for rv0 in np.random.default_rng(0).normal(0, 1.5, (12, 3)):
        def f(rv):
            R = Rotation.from_rotvec(rv).as_matrix()
            t = (w @ (dst - src @ R.T)) / w.sum()
            return _rigid_cost(R, t, src, dst, w)
        r = minimize(f, rv0, method="BFGS", options={"gtol": 1e-12})
        best = min(best, r.fun)
    return best


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(3, 60))
def test_kabsch_recovers_random_pose(seed, n):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    t = rng.normal(0, 3, 3)
    src = rng.normal(0, 1, (n, 3))
    dst = src @ R.T + t
    Re, te = kabsch_svd(src, dst)
    assert np.abs(Re - R).max() < 1e-9 and np.abs(te - t).max() < 1e-9
    # weights: points with weight 0 may be anything
    w = rng.uniform(0.5, 2.0, n)
    bad = rng.random(n) < 0.3
    bad[:3] = False
    w[bad] = 0.0
    dst_c = dst.copy()
    dst_c[bad] += rng.normal(0, 5, (bad.sum(), 3))
    Rw, tw = kabsch_svd(src, dst_c, weights=w)
    assert np.abs(Rw - R).max() < 1e-9 and np.abs(tw - t).max() < 1e-9


def test_weighted_kabsch_is_optimal_with_noise():
    rng = np.random.default_rng(9)
    src = rng.normal(0, 1, (25, 3))
    R = Rotation.random(random_state=1).as_matrix()
    dst = src @ R.T + [0.3, -1, 2] + rng.normal(0, 0.1, (25, 3))
    w = rng.uniform(0.1, 3.0, 25)
    Re, te = kabsch_svd(src, dst, w)
    assert _rigid_cost(Re, te, src, dst, w) <= _best_proper_rigid_by_search(src, dst, w) + 1e-9


def test_kabsch_never_returns_a_reflection():
    rng = np.random.default_rng(10)
    src = rng.normal(0, 1, (30, 3)) * [2.0, 1.0, 0.3]
    dst = src * [1.0, 1.0, -1.0] + [0.5, 0.0, 1.0]  # mirror image: best orthogonal map is a reflection
    Re, te = kabsch_svd(src, dst)
    assert np.isclose(np.linalg.det(Re), 1.0) and np.allclose(Re @ Re.T, np.eye(3))
    w = np.ones(30)
    assert _rigid_cost(Re, te, src, dst, w) <= _best_proper_rigid_by_search(src, dst, w) + 1e-9


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_umeyama_recovers_similarity(seed):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    s = rng.uniform(0.05, 20.0)
    t = rng.normal(0, 3, 3)
    src = rng.normal(0, 1, (12, 3))
    s_e, R_e, t_e = umeyama_svd(src, s * src @ R.T + t)
    assert abs(s_e - s) < 1e-9 * s and np.abs(R_e - R).max() < 1e-9 and np.abs(t_e - t).max() < 1e-8


def test_alignment_input_errors():
    with pytest.raises(ValueError, match="shape"):
        kabsch_svd(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="weights"):
        kabsch_svd(np.eye(3), np.eye(3), weights=[1, -1, 1])


# ------------------------------------------------------------ Horn's method (compiled)
def test_horn_matches_scipy_align_vectors_and_svd():
    """Reference: scipy's Rotation.align_vectors (Wahba's problem on the centred points)."""
    rng = np.random.default_rng(31)
    for n in (3, 4, 7, 40):
        src = rng.normal(0, 0.2, (n, 3))
        R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
        dst = src @ R.T + rng.normal(0, 1, 3) + rng.normal(0, 0.01, (n, 3))
        w = rng.uniform(0.2, 2.0, n)
        Rh, th = kabsch_horn(src, dst, w)
        ref, _ = Rotation.align_vectors(dst - w @ dst / w.sum(), src - w @ src / w.sum(), weights=w)
        np.testing.assert_allclose(Rh, ref.as_matrix(), atol=1e-10)
        np.testing.assert_allclose(th, (w @ dst - (w @ src) @ Rh.T) / w.sum(), atol=1e-12)
        Rs, ts = kabsch_svd(src, dst, w)
        np.testing.assert_allclose(Rh, Rs, atol=1e-10)
        np.testing.assert_allclose(th, ts, atol=1e-10)


def test_horn_handles_coplanar_markers_and_mirror_images():
    rng = np.random.default_rng(32)
    src = np.column_stack([rng.normal(0, 0.1, (5, 2)), np.zeros(5)])  # flat marker set
    R = Rotation.random(random_state=5).as_matrix()
    Rh, _ = kabsch_horn(src, src @ R.T)
    np.testing.assert_allclose(Rh, R, atol=1e-12)
    mirror = rng.normal(0, 1, (30, 3)) * [2.0, 1.0, 0.3]
    Rh, th = kabsch_horn(mirror, mirror * [1.0, 1.0, -1.0])
    assert np.isclose(np.linalg.det(Rh), 1.0)
    Rs, ts = kabsch_svd(mirror, mirror * [1.0, 1.0, -1.0])
    np.testing.assert_allclose(Rh, Rs, atol=1e-9)


def test_horn_batch_equals_single_kernel_and_ignores_zero_weights():
    rng = np.random.default_rng(33)
    B, M = 6, 5
    src = rng.normal(0, 0.2, (B, M, 3))
    Rs = Rotation.random(B, random_state=6).as_matrix()
    t = rng.normal(0, 1, (B, 3))
    dst = np.einsum("bij,bmj->bmi", Rs, src) + t[:, None]
    w = np.ones((B, M))
    w[:, 4] = 0.0
    dst[:, 4] = np.nan  # missing marker: weight 0, value never read
    R_b, t_b = kabsch_horn_batch(src, dst, w)
    np.testing.assert_allclose(R_b, Rs, atol=1e-12)
    np.testing.assert_allclose(t_b, t, atol=1e-12)
    for b in range(B):
        R1, t1 = kabsch_horn_compiled(src[b], dst[b], w[b])
        np.testing.assert_array_equal(R1, R_b[b])  # the batch is the same kernel, bit for bit
        np.testing.assert_array_equal(t1, t_b[b])


def test_symmetric_eigen_jacobi_matches_numpy_eigh():
    rng = np.random.default_rng(34)
    for n in (2, 4, 6):
        A = rng.normal(size=(n, n))
        A = A + A.T
        evals, V = symmetric_eigen_jacobi(A)
        np.testing.assert_allclose(np.sort(evals), np.linalg.eigh(A)[0], atol=1e-12)
        np.testing.assert_allclose(V.T @ V, np.eye(n), atol=1e-12)
        np.testing.assert_allclose(A @ V, V * evals, atol=1e-12)
