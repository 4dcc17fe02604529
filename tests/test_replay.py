"""Replay: metrics against independent values, deterministic byte-identical outputs."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from visionpos import metrics as M

# ---------------------------------------------------------------- metrics (pure)


def test_interpolate_truth_matches_analytic_motion():
    # truth: straight line at 1 m/s and a constant yaw rate of 90 deg/s, sampled at 10 Hz
    t = np.arange(0, 11) * 100_000_000
    s = t * 1e-9
    pos = np.stack([s, 2 * s, np.ones_like(s)], axis=1)
    quat = Rotation.from_euler("z", 90 * s[:, None], degrees=True).as_quat()
    at = np.array([50_000_000, 333_000_000, 999_999_999, -1, 2_000_000_000])
    p, q, valid = M.interpolate_truth(t, pos, quat, at)
    assert valid.tolist() == [True, True, True, False, False]
    sa = at[:3] * 1e-9
    np.testing.assert_allclose(p[:3], np.stack([sa, 2 * sa, np.ones(3)], axis=1), atol=1e-12)
    yaw = Rotation.from_quat(q[:3]).as_euler("zyx", degrees=True)[:, 0]
    np.testing.assert_allclose(yaw, 90 * sa, atol=1e-9)


def test_rotation_errors_geodesic_and_sign_invariant():
    rng = np.random.default_rng(3)
    base = Rotation.random(50, random_state=4)
    angles = rng.uniform(0, np.pi, 50)
    axes = rng.normal(size=(50, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    est = Rotation.from_rotvec(axes * angles[:, None]) * base
    q = est.as_quat()
    q[::2] *= -1  # the same rotations with the other quaternion sign
    np.testing.assert_allclose(M.rotation_errors(q, base.as_quat()), angles, atol=1e-7)


def test_position_jitter_recovers_white_noise_on_smooth_motion():
    rng = np.random.default_rng(0)
    t = np.arange(2000, dtype=np.int64) * 10_000_000  # 100 Hz for 20 s
    s = t * 1e-9
    smooth = np.stack([0.5 * np.sin(0.5 * s), 0.3 * np.cos(0.4 * s), 1 + 0.1 * s], axis=1)
    sigma = 0.0007
    noisy = smooth + rng.normal(0, sigma, smooth.shape)
    assert M.position_jitter(t, noisy) == pytest.approx(sigma, rel=0.05)
    # a dropout gap is not counted as noise
    gap = np.concatenate([t[:1000], t[1000:] + 2_000_000_000])
    assert M.position_jitter(gap, smooth) < 1e-5


def test_body_metrics_against_hand_computed_values():
    t = np.arange(100, dtype=np.int64) * 10_000_000
    truth_p = np.zeros((100, 3))
    truth_q = np.tile([0, 0, 0, 1.0], (100, 1))
    est_p = truth_p.copy()
    est_p[:, 0] = np.where(np.arange(100) % 2 == 0, 0.003, -0.004)  # rms = sqrt((9+16)/2) mm
    est_q = Rotation.from_euler("x", np.full((100, 1), 2.0), degrees=True).as_quat()
    tracked = np.ones(100, bool)
    tracked[90:] = False
    lat = np.full(100, 5_000_000)
    m = M.body_metrics("b", t, tracked, est_p, est_q, lat, (t, truth_p, truth_q), n_ticks=100)
    assert m.tracked_fraction == pytest.approx(0.9)
    assert m.position_rmse_mm == pytest.approx(np.sqrt(12.5), rel=1e-9)
    assert m.rotation_rmse_deg == pytest.approx(2.0, rel=1e-6)
    assert m.latency_ms["p50"] == pytest.approx(5.0)
    assert m.n_scored == 90
