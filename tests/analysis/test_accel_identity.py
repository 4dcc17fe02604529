"""The accelerometer's identity signal (visionpos/analysis/autopilot.py): an optical track's specific force
against an IMU's. Expected values are worked by hand from the set-up."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from visionpos.analysis.autopilot import accel_residuals, gaussian_kernel, lowpass, optical_specific_force

G = 9.80665
DT = 0.02


def test_a_level_climb_reads_gravity_plus_its_acceleration_down():
    t = np.arange(60) * DT
    p = np.zeros((60, 3))
    p[:, 2] = 0.5 * 2.0 * t**2  # 2 m/s^2 up
    q = np.tile([0.0, 0.0, 0.0, 1.0], (60, 1))
    k = gaussian_kernel(0.05, DT)
    f, mag = optical_specific_force(p, q, DT, k)
    half = len(k) // 2
    inner = slice(half + 1, 60 - half - 1)
    assert f[inner] == pytest.approx(np.tile([0.0, 0.0, -(G + 2.0)], (60 - 2 * half - 2, 1)), abs=1e-9)
    assert mag[inner] == pytest.approx(2.0, abs=1e-9)
    assert np.isnan(f[: half + 1]).all() and np.isnan(f[-half - 1:]).all()  # the low-pass needs both sides


def test_a_rolled_body_at_rest_reads_gravity_in_its_own_axes():
    q = np.tile(Rotation.from_euler("x", 30, degrees=True).as_quat(), (40, 1))  # rolled 30 deg, FLU
    f, _ = optical_specific_force(np.ones((40, 3)), q, DT, gaussian_kernel(0.05, DT))
    # FLU: R^T (0, 0, g) = (0, g sin 30, g cos 30); FRD flips y and z
    assert f[20] == pytest.approx([0.0, -G * 0.5, -G * math.cos(math.radians(30))], abs=1e-9)


def test_the_low_pass_keeps_slow_motion_and_has_no_lag():
    k = gaussian_kernel(0.05, DT)
    assert k.sum() == pytest.approx(1.0) and k == pytest.approx(k[::-1])
    t = np.arange(200) * DT
    x = np.sin(2 * np.pi * 1.0 * t)[:, None]
    y = lowpass(x, k)
    mid = slice(50, 150)
    gain = np.exp(-2 * np.pi**2 * 0.05**2 * 1.0**2)  # a Gaussian's response at 1 Hz
    assert y[mid, 0] == pytest.approx(gain * x[mid, 0], abs=2e-3)
    x[100] = np.nan  # a missing sample spoils every output whose kernel covers it
    assert np.isnan(lowpass(x, k)[100 - len(k) // 2: 100 + len(k) // 2 + 1]).all()


def test_the_accelerometer_bias_is_estimated():
    f_opt = np.array([[0.0, 0.0, -G], [1.0, 0.0, -G], [0.0, 0.0, -G - 1.0]])
    bias = np.array([0.3, -0.2, 0.1])
    # without a prior the mean residual is the bias: all of it is taken away
    r = accel_residuals(f_opt + bias, f_opt, np.zeros(3), 0.3, 0.1, np.inf)
    assert r == pytest.approx(np.zeros((4, 3)))
    # a residual of 0.6 m/s^2 on x at the second instant; sigmas 0.3, 0.4, 0.4 (0.3 + 0.1 * 1 m/s^2): the
    # weighted mean 0.6 / 0.16 / (1 / 0.09 + 2 / 0.16) = 0.158824 is taken away
    f_ap = f_opt.copy()
    f_ap[1, 0] += 0.6
    r = accel_residuals(f_ap, f_opt, np.array([0.0, 1.0, 1.0]), 0.3, 0.1, np.inf)
    assert r[:3, 0] == pytest.approx([-0.158824 / 0.3, (0.6 - 0.158824) / 0.4, -0.158824 / 0.4], abs=1e-5)


def test_a_steady_acceleration_does_not_pass_for_a_bias():
    """4 instants 2 m/s^2 apart on z (a climb against a drone at rest), sigma 0.5, a bias prior of 0.5 m/s^2:
    with w = 1/0.25 per instant the bias estimate is 4 * 4 * 2 / (16 + 4) = 1.6 and the cost
    16 * 0.4^2 + 1.6^2 / 0.25 = 12.8 (= 2^2 / (1/16 + 0.25)); without the prior it would be 0."""
    f_opt = np.tile([0.0, 0.0, -G], (4, 1))
    f_ap = f_opt + [0.0, 0.0, 2.0]
    r = accel_residuals(f_ap, f_opt, np.zeros(4), 0.5, 0.1, 0.5)
    assert r.shape == (5, 3)
    assert float(np.sum(r**2)) == pytest.approx(12.8)
    assert r[-1] == pytest.approx([0.0, 0.0, 1.6 / 0.5])
    assert float(np.sum(accel_residuals(f_ap, f_opt, np.zeros(4), 0.5, 0.1, np.inf) ** 2)) == pytest.approx(0.0)


def test_every_pair_at_once_is_each_pair_alone():
    rng = np.random.default_rng(1)
    f_ap, f_opt, acc = rng.normal(0, 1, (3, 5, 3)), rng.normal(0, 1, (2, 5, 3)), rng.uniform(0, 3, (2, 5))
    both = accel_residuals(f_ap[None], f_opt[:, None], acc[:, None], 0.3, 0.15, 0.5)  # (2, 3, 6, 3)
    for b in range(2):
        for v in range(3):
            assert both[b, v] == pytest.approx(accel_residuals(f_ap[v], f_opt[b], acc[b], 0.3, 0.15, 0.5))
