"""Essential matrix and relative pose (geometry/epipolar.py) on synthetic two-view scenes with known truth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from visionpos.camera.model import look_at_rotation
from visionpos.geometry.epipolar import decompose_essential, essential_from_points
from visionpos.geometry.rotations import skew


def _two_view(rng, n=40):
    """Random two-camera configuration looking at a common point cloud.
    Returns x1, x2 (N, 2) normalised, R, t (X2 = R X1 + t), points in camera 1."""
    X = rng.normal(0, 0.6, (n, 3)) + [0, 0, rng.uniform(2.0, 6.0)]  # cloud in front of camera 1
    # camera 2 centre anywhere around (sideways, forward, backward), aimed at the cloud with random roll
    C2 = rng.normal(0, 1.5, 3)
    C2[2] = rng.uniform(-1.0, 1.5)
    R_look = look_at_rotation(C2, X.mean(axis=0), up=np.array([0.0, -1.0, 0.0]))
    R = Rotation.from_rotvec([0, 0, rng.uniform(-np.pi, np.pi)]).as_matrix() @ R_look
    t = -R @ C2
    X2 = X @ R.T + t
    front = (X[:, 2] > 0.1) & (X2[:, 2] > 0.1)
    X, X2 = X[front], X2[front]
    return X[:, :2] / X[:, 2:], X2[:, :2] / X2[:, 2:], R, t


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_cheirality_picks_true_pose(seed):
    rng = np.random.default_rng(seed)
    x1, x2, R, t = _two_view(rng)
    assume(len(x1) >= 8 and np.linalg.norm(t) > 0.05)  # a usable configuration (nearly always)
    tu = t / np.linalg.norm(t)
    for E in (skew(t) @ R, -3.0 * skew(t) @ R, essential_from_points(x1, x2)[0]):
        Re, te, front = decompose_essential(E, x1, x2)
        assert np.abs(Re - R).max() < 1e-6
        assert np.abs(te - tu).max() < 1e-6
        assert front.all()
        assert np.isclose(np.linalg.det(Re), 1.0)


def test_essential_matrix_properties_and_ransac():
    rng = np.random.default_rng(8)
    x1, x2, R, t = _two_view(rng, n=120)
    n_in = len(x1)
    x1n = x1 + rng.normal(0, 2e-4, x1.shape)  # ~0.15 px at f = 720
    x2n = x2 + rng.normal(0, 2e-4, x2.shape)
    # 40 % gross outliers
    n_out = int(0.4 * n_in)
    o1 = rng.uniform(-0.6, 0.6, (n_out, 2))
    o2 = rng.uniform(-0.6, 0.6, (n_out, 2))
    a1 = np.vstack([x1n, o1])
    a2 = np.vstack([x2n, o2])
    E, inl = essential_from_points(a1, a2, threshold=1e-3)
    s = np.linalg.svd(E, compute_uv=False)
    assert np.isclose(s[0], s[1]) and s[2] < 1e-12 and np.isclose(np.linalg.norm(E), 1.0)
    assert inl[:n_in].mean() > 0.95 and inl[n_in:].mean() < 0.05
    Re, te, _ = decompose_essential(E, a1[inl], a2[inl])
    ang = np.degrees(np.linalg.norm(Rotation.from_matrix(Re @ R.T).as_rotvec()))
    assert ang < 0.5
    assert np.degrees(np.arccos(np.clip(te @ t / np.linalg.norm(t), -1, 1))) < 2.0
    # without RANSAC the outliers wreck the estimate
    E_bad, all_in = essential_from_points(a1, a2)
    assert all_in.all()
    Rb, _, _ = decompose_essential(E_bad, a1, a2)
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(Rb @ R.T).as_rotvec())) > ang
    with pytest.raises(ValueError, match="at least 8"):
        essential_from_points(x1[:7], x2[:7])
