"""The vehicle's IMU in the body filter (visionpos/fusion/imu.py): prediction with the measured acceleration and rate,
the bias fits against the optical track, the fallback and the refusal of a bad stream."""

import functools
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from visionpos.fusion.body_filter import BodyFilter
from visionpos.fusion.imu import ImuInput, fit_accel_bias, fit_gyro_bias, imu_measurement
from visionpos.fusion.settings import ImuSettings, KalmanSettings

G = np.array([0.0, 0.0, -9.80665])


def _filter(p0, R0):
    kalman = KalmanSettings()
    f = BodyFilter(kalman)
    f.initialize(0, np.asarray(p0, float), R0)
    return f, kalman


def _feed(inp: ImuInput, R_true, a_world, w_body, accel_bias, gyro_bias, t_end_ns, step_ns=2_500_000):
    """Samples every step_ns from 0 to t_end_ns of a body with constant world acceleration a_world (3,) and body
    rate w_body (3,), rotation R_true(t_s); the IMU reads them with the given biases."""
    for t in range(0, t_end_ns + 1, step_ns):
        R = R_true(t * 1e-9)
        assert inp.push(t, R.T @ (a_world - G) + accel_bias, w_body + gyro_bias)


def test_constant_acceleration_and_rate_with_known_bias_give_the_closed_form():
    p0, a = np.array([1.0, 2.0, 0.5]), np.array([1.0, -0.5, 0.2])  # m, m/s^2 (starting at rest)
    w = np.array([0.3, -0.2, 1.0])  # rad/s, body frame
    R0 = Rotation.from_euler("z", 0.4).as_matrix()

    def R_true(t):
        return R0 @ Rotation.from_rotvec(w * t).as_matrix()

    flt, kalman = _filter(p0, R0)
    inp = ImuInput(ImuSettings(), "quad")
    inp.accel_bias[:] = bias_a = np.array([0.1, 0.05, -0.1])
    inp.gyro_bias[:] = bias_g = np.array([0.004, -0.003, 0.002])
    _feed(inp, R_true, a, w, bias_a, bias_g, 100_000_000)
    inp.before_fusion(flt, kalman, 100_000_000)  # every sample into the filter
    assert inp.stats["used"] == 41 and flt.t_ns == 100_000_000
    p, R, v, _ = flt.pose_at(100_000_000)
    t = 0.1
    np.testing.assert_allclose(p, p0 + 0.5 * a * t * t, atol=2e-6)
    np.testing.assert_allclose(v, a * t, atol=5e-5)
    assert Rotation.from_matrix(R.T @ R_true(t)).magnitude() < 1e-5


def test_outputs_predict_through_pending_samples_and_fall_back_without_a_jump():
    p0, R0 = np.zeros(3), np.eye(3)
    flt, kalman = _filter(p0, R0)
    s = ImuSettings()
    inp = ImuInput(s, "quad")
    a = np.array([2.0, 0.0, 0.0])
    _feed(inp, lambda t: R0, a, np.zeros(3), np.zeros(3), np.zeros(3), 20_000_000)
    inp.before_fusion(flt, kalman, 10_000_000)  # the filter at 10 ms; the samples after it still pending
    # an output at 20 ms takes them: the closed form (the filter alone would hold its acceleration too; here
    # it only checks that the pending samples are taken on a copy, not into the filter)
    p = inp.output_at(flt, kalman, 20_000_000)[0]
    np.testing.assert_allclose(p, 0.5 * a * 0.02**2, atol=2e-6)
    assert flt.t_ns == 10_000_000 and len(inp.pending) == 4
    # the stream stops: past max_age_ms the output is the filter's own, and it does not jump
    t_stale = 20_000_000 + s.max_age_ns + 1
    before = inp.output_at(flt, kalman, t_stale - 2)[0]
    after = inp.output_at(flt, kalman, t_stale)[0]
    np.testing.assert_array_equal(after, flt.output_at(t_stale)[0])
    assert np.linalg.norm(after - before) < 1e-4


def test_a_stream_of_garbage_is_refused_then_dropped_and_leaves_the_filter_alone():
    flt, kalman = _filter(np.zeros(3), np.eye(3))
    s = replace(ImuSettings(), max_refused=5)
    inp = ImuInput(s, "quad")
    _feed(inp, lambda t: np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), 20_000_000)
    inp.before_fusion(flt, kalman, 20_000_000)  # a still body: accepted
    x = flt.x.copy()
    for k in range(6):  # a saturated accelerometer: 16 g on x
        inp.push(22_500_000 + k * 2_500_000, np.array([157.0, 0.0, 9.8]), np.zeros(3))
    inp.before_fusion(flt, kalman, 40_000_000)
    assert inp.stats["refused"] == 5 and inp.dropped
    np.testing.assert_allclose(flt.x[6:9], x[6:9], atol=1e-9)  # the acceleration: not taken from it
    assert not inp.push(50_000_000, np.zeros(3), np.zeros(3))  # optical only from now on


def test_samples_out_of_order_or_not_finite_are_refused():
    inp = ImuInput(ImuSettings(), "quad")
    assert inp.push(10, np.zeros(3), np.zeros(3))
    assert not inp.push(10, np.zeros(3), np.zeros(3))
    assert not inp.push(20, np.array([np.nan, 0, 0]), np.zeros(3))
    assert len(inp.pending) == 1


def test_lever_arm_takes_off_the_rotation_of_an_imu_off_the_origin():
    # an IMU 0.1 m along body x on a body spinning at 2 rad/s about z: centripetal -w^2 r
    R, r, w = np.eye(3), np.array([0.1, 0.0, 0.0]), np.array([0.0, 0.0, 2.0])
    f = -(w[2] ** 2) * r - G  # what it reads with the origin still
    z = imu_measurement(R, f, w, np.zeros(3), np.zeros(3), r, w, np.zeros(3))
    np.testing.assert_allclose(z[:3], 0.0, atol=1e-12)


@functools.cache
def _truth():
    """1 s of a body turning and accelerating, from a fine (0.25 ms, midpoint) integration of its rates: sample
    times every 4 ms (N,), rotations (N, 3, 3), body rates (N, 3), world accelerations (N, 3), positions (N, 3)."""
    h = 2.5e-4

    def w(t):
        return np.stack([np.sin(3 * t), 0.5 * np.cos(2 * t), 1.0 + 0 * t], -1)

    steps = Rotation.from_rotvec(w(np.arange(4000) * h + 0.5 * h) * h).as_matrix()
    R, Rs = Rotation.from_euler("z", 0.3).as_matrix(), []
    for k in range(4000):
        if k % 16 == 0:
            Rs.append(R)
        R = R @ steps[k]
    t = np.arange(0, 4000, 16) * h
    a_w = np.stack([np.cos(t), np.sin(2 * t), 0.3 * t], -1)
    p = np.stack([1.0 - np.cos(t), -np.sin(2 * t) / 4 + t / 2, 0.05 * t**3], 1) + [1.0, 2.0, 3.0]
    return t, np.array(Rs), w(t), a_w, p


def _spinning_window(rng, noise_pos=0.0, noise_rot=0.0):
    """_truth with optical positions and rotations every 8 ms (noise std in m and rad)."""
    t, Rm, w, a_w, p = _truth()
    obs = np.arange(2, len(t), 2)
    p_obs = p[obs] + rng.normal(0, noise_pos, (len(obs), 3))
    R_obs = Rm[obs] @ Rotation.from_rotvec(rng.normal(0, noise_rot, (len(obs), 3))).as_matrix()
    return t, Rm, w, a_w, obs, p_obs, R_obs


@pytest.mark.parametrize("noise", [False, True])
def test_bias_fits_recover_the_drawn_biases(noise):
    rng = np.random.default_rng(3)
    t, Rm, w, a_w, obs, p_obs, R_obs = _spinning_window(rng, 5e-4 if noise else 0.0, 1e-3 if noise else 0.0)
    b_a, b_g = rng.normal(0, 0.1, 3), rng.normal(0, 0.005, 3)
    f = np.einsum("nji,nj->ni", Rm, a_w - G) + b_a
    tol_a, tol_g = (0.01, 1e-3) if noise else (2e-4, 3e-5)
    (ba, rms_p), (bg, rms_r) = fit_accel_bias(t, f, Rm, t[obs], p_obs), fit_gyro_bias(t, w + b_g, t[obs], R_obs)
    np.testing.assert_allclose(ba, b_a, atol=tol_a)
    np.testing.assert_allclose(bg, b_g, atol=tol_g)
    # the residuals (RMS distance): the optical noise (0.5 mm and 1 mrad per axis here: 0.87 mm, 1.7 mrad), nothing
    # when there is none
    assert rms_p < (1e-3 if noise else 1e-5) and rms_r < (2e-3 if noise else 1e-5)


def test_the_running_estimate_converges_over_windows():
    rng = np.random.default_rng(5)
    s = replace(ImuSettings(), bias_window_ns=990_000_000)
    b_a = np.array([0.12, -0.08, 0.05])
    errors = []
    for _ in range(4):  # four noisy windows of the same body, fitted by an ImuInput as the pipeline feeds it
        t, Rm, w, a_w, obs, p_obs, R_obs = _spinning_window(rng, 5e-4, 1e-3)
        f = np.einsum("nji,nj->ni", Rm, a_w - G) + b_a
        inp_fit = [(ti, fi, wi, Ri) for ti, fi, wi, Ri in zip(t, f, w, Rm)]
        if not errors:
            inp = ImuInput(s, "quad")
        inp._win_imu, inp._win_obs, inp._win_start_ns = inp_fit, [], 0
        for k, i in enumerate(obs):
            inp.observe_pose(int(round(t[i] * 1e9)), p_obs[k], R_obs[k])
        errors.append(np.linalg.norm(inp.accel_bias - b_a))
    assert inp.bias_fits == 4
    assert errors[-1] < 0.01


def test_an_implausible_bias_drops_the_imu():
    # an accelerometer off by 1.5 m/s^2 (over max_accel_bias_m_s2, 1): not an IMU's bias, the input is dropped
    t, Rm, w, a_w, obs, p_obs, R_obs = _spinning_window(np.random.default_rng(6))
    f = np.einsum("nji,nj->ni", Rm, a_w - G) + [1.5, 0.0, 0.0]
    inp = ImuInput(replace(ImuSettings(), bias_window_ns=990_000_000), "quad")
    inp._win_imu, inp._win_start_ns = [(ti, fi, wi, Ri) for ti, fi, wi, Ri in zip(t, f, w, Rm)], 0
    for k, i in enumerate(obs):
        inp.observe_pose(int(round(t[i] * 1e9)), p_obs[k], R_obs[k])
    assert inp.dropped and inp.bias_fits == 0 and not inp.accel_bias.any()


@pytest.mark.parametrize("fault", ["stuck accelerometer", "stuck gyro"])
def test_an_imu_that_misses_the_optical_track_is_dropped(fault):
    t, Rm, w, a_w, obs, p_obs, R_obs = _spinning_window(np.random.default_rng(7), 5e-4, 1e-3)
    f = np.einsum("nji,nj->ni", Rm, a_w - G)
    if fault == "stuck accelerometer":
        f[:] = f[0]
    else:
        w = np.repeat(w[:1], len(w), 0)
    inp = ImuInput(replace(ImuSettings(), bias_window_ns=990_000_000), "quad")
    inp._win_imu, inp._win_start_ns = [(ti, fi, wi, Ri) for ti, fi, wi, Ri in zip(t, f, w, Rm)], 0
    for k, i in enumerate(obs):
        inp.observe_pose(int(round(t[i] * 1e9)), p_obs[k], R_obs[k])
    assert inp.dropped and inp.bias_fits == 0


def test_the_server_hands_its_outputs_imu_sources_to_the_pipeline():
    # a sink with IMU samples (as the MAVLink bridge, bridge/imu_feed.py): the server registers its source, the
    # pipeline drains it before each tick into the body's input
    from visionpos.server.service import FusionServer, load_config_with_overrides
    from visionpos.server.sinks import Sink

    arena = load_config_with_overrides("thesis", ["fusion.imu.enabled=true", "server.insecure=true"])

    class ImuSink(Sink):
        def imu_sources(self):
            return [lambda push: push("quad", 5_000_000, np.array([0.0, 0.0, 9.8]), np.zeros(3))]

    server = FusionServer(arena, sinks=[ImuSink()], port=0)
    server.tick(10_000_000)
    assert server.pipeline.stats()["imu"]["quad"]["samples"] == 1


def test_the_compiled_sample_update_matches_filterpy_and_a_refused_one_changes_nothing():
    """imu_update (a compiled kernel) against filterpy's KalmanFilter.update with H picking the acceleration and
    rate rows and R = diag(var), on a random state; over the gate, x and P stay as they were."""
    from filterpy.kalman import KalmanFilter

    from visionpos.fusion.imu import IMU_ROWS, imu_update

    rng = np.random.default_rng(7)
    A = rng.normal(size=(18, 18))
    P = A @ A.T * 0.01 + np.eye(18) * 1e-3
    x = rng.normal(size=18)
    var = np.array([0.05**2] * 3 + [0.003**2] * 3)
    z = x[IMU_ROWS] + rng.normal(scale=0.05, size=6)
    kf = KalmanFilter(dim_x=18, dim_z=6)
    kf.x, kf.P, kf.R = x.copy(), P.copy(), np.diag(var)
    kf.H = np.zeros((6, 18))
    kf.H[np.arange(6), IMU_ROWS] = 1.0
    kf.update(z)
    x1, P1 = x.copy(), P.copy()
    ok, d2 = imu_update(x1, P1, z, var, 0.0)
    y = z - x[IMU_ROWS]
    assert ok and d2 == pytest.approx(float(y @ np.linalg.solve(kf.S, y)), rel=1e-9)
    assert np.allclose(x1, kf.x, rtol=1e-9, atol=1e-12)
    assert np.allclose(P1, kf.P, rtol=1e-7, atol=1e-12)
    x2, P2 = x.copy(), P.copy()
    ok, d2 = imu_update(x2, P2, z + 10.0, var, 60.0)
    assert not ok and d2 > 60.0
    assert np.array_equal(x2, x) and np.array_equal(P2, P)
