"""Body Kalman filter (visionpos/tracking.py): smoothing, prediction, gating."""

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos.fusion.body_filter import BodyFilter
from visionpos.fusion.settings import KalmanSettings
from visionpos.geometry.rotations import matrix_from_rotvec as rotvec_to_matrix
from visionpos.geometry.rotations import quat_from_matrix as matrix_to_quat
from visionpos.geometry.rotations import rotvec_from_matrix as matrix_to_rotvec

MS = 1_000_000


def _cov(sp=0.0005, sr=0.003):
    return np.diag([sp**2] * 3 + [sr**2] * 3)


def test_rotation_helpers_match_scipy():
    rng = np.random.default_rng(0)
    for rv in list(rng.normal(0, 1, (20, 3))) + [np.zeros(3), np.array([1e-9, 0, 0])]:
        assert np.allclose(rotvec_to_matrix(rv), Rotation.from_rotvec(rv).as_matrix(), atol=1e-12)
        R = Rotation.from_rotvec(rv).as_matrix()
        assert np.allclose(rotvec_to_matrix(matrix_to_rotvec(R)), R, atol=1e-9)
        q = Rotation.from_matrix(R).as_quat()
        q = -q if q[3] < 0 else q
        assert np.allclose(matrix_to_quat(R), q, atol=1e-12)
    near_pi = np.radians([[179.9, 0, 0], [0, 180.0, 0], [0, 0, 179.0], [0, 120.0, 120.0]])
    for R in Rotation.from_rotvec(near_pi).as_matrix():  # the trace <= 0 branches
        assert np.allclose(Rotation.from_quat(matrix_to_quat(R)).as_matrix(), R, atol=1e-12)
        assert np.allclose(rotvec_to_matrix(matrix_to_rotvec(R)), R, atol=1e-12)
        assert np.linalg.norm(matrix_to_rotvec(R)) <= np.pi + 1e-12


def test_predict_and_update_match_filterpy():
    """The compiled predict / Joseph update equal filterpy's KalmanFilter with the textbook
    F, continuous white-noise Q (filterpy's Q_continuous_white_noise) and H, on random states."""
    from filterpy.common import Q_continuous_white_noise
    from filterpy.kalman import KalmanFilter

    rng = np.random.default_rng(7)
    s = KalmanSettings(jerk_psd=0.7, angular_accel_psd=1.5, angular_jerk_psd=3.0)
    H = np.zeros((6, 18))
    H[0:3, 0:3] = np.eye(3)
    H[3:6, 9:12] = np.eye(3)
    for trial in range(5):
        f = BodyFilter(s)
        R0 = Rotation.random(random_state=trial).as_matrix()
        f.initialize(0, rng.normal(0, 1, 3), R0, np.diag(rng.uniform(1e-6, 1e-4, 6)))
        f.x[3:9] = rng.normal(0, 1, 6)
        f.x[12:18] = rng.normal(0, 1, 6)
        A = rng.normal(0, 0.1, (18, 18))
        f.P = f.P + A @ A.T
        f.scale_p, f.scale_r = 2.0, 5.0
        ref = KalmanFilter(dim_x=18, dim_z=6)
        ref.x, ref.P, ref.H = f.x.copy()[:, None], f.P.copy(), H
        R_nom = f.R_nom.copy()
        dt = 0.004 + 0.01 * trial
        F = np.eye(18)
        for k in range(3):
            F[k, 3 + k] = F[3 + k, 6 + k] = F[9 + k, 12 + k] = F[12 + k, 15 + k] = dt
            F[k, 6 + k] = F[9 + k, 15 + k] = 0.5 * dt * dt
        Q = np.zeros((18, 18))
        Q[0:9, 0:9] = Q_continuous_white_noise(3, dt, s.jerk_psd * 2.0, block_size=3, order_by_dim=False)
        Q[9:18, 9:18] = Q_continuous_white_noise(3, dt, s.angular_jerk_psd * 5.0, block_size=3, order_by_dim=False)
        Q[9:15, 9:15] += Q_continuous_white_noise(2, dt, s.angular_accel_psd * 5.0, block_size=3, order_by_dim=False)
        ref.predict(F=F, Q=Q)
        t = int(round(dt * 1e9))
        f.predict_to(t)
        R_nom = rotvec_to_matrix(ref.x[9:12, 0]) @ R_nom  # the filter folds the rotation error
        assert np.allclose(f.P, ref.P, rtol=1e-9, atol=1e-12)
        keep = np.r_[0:9, 12:18]  # the rotation error is folded into R_nom
        assert np.allclose(f.x[keep], ref.x[keep, 0])
        assert np.allclose(f.R_nom, R_nom, atol=1e-12)
        ref.x[9:12] = 0.0
        # a measurement near the prediction
        p_meas = f.x[0:3] + rng.normal(0, 0.01, 3)
        dth = rng.normal(0, 0.01, 3)
        R_meas = rotvec_to_matrix(dth) @ R_nom
        cov = np.diag(rng.uniform(1e-6, 1e-4, 6))
        ok, _ = f.update(t, p_meas, R_meas, cov, gate=False)
        assert ok
        ref.update(np.concatenate([p_meas, matrix_to_rotvec(R_meas @ R_nom.T)])[:, None], R=cov)
        assert np.allclose(f.P, ref.P, rtol=1e-7, atol=1e-14)
        assert np.allclose(f.x[keep], ref.x[keep, 0], rtol=1e-9, atol=1e-12)
        assert np.allclose(f.R_nom, rotvec_to_matrix(ref.x[9:12, 0]) @ R_nom, atol=1e-12)
        # the outputs predicted 7 ms ahead, without changing the filter
        R_nom = rotvec_to_matrix(ref.x[9:12, 0]) @ R_nom
        ref.x[9:12] = 0.0
        x_before = f.x.copy()
        p, q, v, w_body, cov, vcov, acc = f.output_at(t + 7_000_000)
        assert np.array_equal(f.x, x_before)
        h = 0.007
        F = np.eye(18)
        for k in range(3):
            F[k, 3 + k] = F[3 + k, 6 + k] = F[9 + k, 12 + k] = F[12 + k, 15 + k] = h
            F[k, 6 + k] = F[9 + k, 15 + k] = 0.5 * h * h
        Q = np.zeros((18, 18))
        Q[0:9, 0:9] = Q_continuous_white_noise(3, h, f.s.jerk_psd * f.scale_p, block_size=3, order_by_dim=False)
        Q[9:18, 9:18] = Q_continuous_white_noise(
            3, h, f.s.angular_jerk_psd * f.scale_r, block_size=3, order_by_dim=False
        )
        Q[9:15, 9:15] += Q_continuous_white_noise(
            2, h, f.s.angular_accel_psd * f.scale_r, block_size=3, order_by_dim=False
        )
        ref.predict(F=F, Q=Q)
        pose = [0, 1, 2, 9, 10, 11]
        assert np.allclose(cov, ref.P[np.ix_(pose, pose)], rtol=1e-9, atol=1e-15)
        assert np.allclose(vcov, ref.P[3:6, 3:6], rtol=1e-9, atol=1e-15)
        assert np.allclose(p, ref.x[0:3, 0]) and np.allclose(v, ref.x[3:6, 0])
        assert np.allclose(acc, ref.x[6:9, 0])  # filterpy's acceleration state, predicted
        R_out = Rotation.from_rotvec(ref.x[9:12, 0]).as_matrix() @ R_nom
        assert np.allclose(Rotation.from_quat(q).as_matrix(), R_out, atol=1e-12) and q[3] >= 0
        assert np.allclose(w_body, R_out.T @ ref.x[12:15, 0], atol=1e-12)


def test_static_jitter_drops_well_below_raw():
    rng = np.random.default_rng(1)
    f = BodyFilter(KalmanSettings())
    R0 = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    p0 = np.array([0.1, 0.2, 1.0])
    f.initialize(0, p0, R0, _cov())
    raw_p, out_p, raw_r, out_r = [], [], [], []
    for k in range(1, 1000):
        t = k * 10 * MS
        zp = p0 + rng.normal(0, 0.0005, 3)
        zR = rotvec_to_matrix(rng.normal(0, 0.003, 3)) @ R0
        f.update(t, zp, zR, _cov())
        if k > 300:
            p, R, _, _ = f.pose_at(t + 5 * MS)  # output predicted 5 ms ahead, as the server does
            raw_p.append(zp - p0)
            out_p.append(p - p0)
            raw_r.append(matrix_to_rotvec(zR @ R0.T))
            out_r.append(matrix_to_rotvec(R @ R0.T))
    jit = lambda a: float(np.sqrt((np.array(a) ** 2).sum(1).mean()))  # noqa: E731
    # the process-noise floor is set for drones (a hovering body still drifts), not for
    # a bolted-down one, so the gain is moderate but must be clear
    assert jit(out_p) < 0.65 * jit(raw_p)
    assert jit(out_r) < 0.85 * jit(raw_r)


def test_prediction_cancels_latency_at_constant_velocity():
    rng = np.random.default_rng(2)
    f = BodyFilter(KalmanSettings())
    v = np.array([2.0, -1.0, 0.5])
    w = np.array([0.0, 0.0, 3.0])  # yaw rate, rad/s
    p0 = np.array([0.0, 0.0, 1.0])
    f.initialize(0, p0, np.eye(3), _cov())
    errs, lag = [], []
    for k in range(1, 400):
        t = k * 5 * MS
        f.update(t, p0 + v * t * 1e-9 + rng.normal(0, 0.0003, 3), rotvec_to_matrix(w * t * 1e-9), _cov(0.0003, 0.002))
        if k > 200:
            ahead = t + 20 * MS  # 20 ms of pipeline latency to cancel
            p, R, vel, wr = f.pose_at(ahead)
            truth = p0 + v * ahead * 1e-9
            errs.append(np.linalg.norm(p - truth))
            lag.append(np.linalg.norm(f.pose_at(t)[0] - truth))
            ang = Rotation.from_matrix(R @ rotvec_to_matrix(w * ahead * 1e-9).T).magnitude()
            assert ang < np.radians(0.5)
    assert np.mean(lag) > 0.04  # not predicting would be 45 mm off
    assert np.mean(errs) < 0.001
    assert np.allclose(vel, v, atol=0.02)
    assert np.allclose(wr, w, atol=0.05)


def test_spin_up_at_constant_angular_acceleration_is_followed_without_lag():
    """A spin-up at a constant 20 rad/s^2 (a drone starting a turn), measured without noise every
    10 ms: with angular_jerk_psd > 0 the model carries the angular acceleration, so after it has
    converged the output predicted 10 ms ahead is on the true attitude and the rate is the true one.
    (The constant-rate model lags by a fixed angle while the rate keeps growing: 0.5 deg.)"""
    f = BodyFilter(KalmanSettings(angular_jerk_psd=100.0))
    axis = np.array([0.0, 0.6, 0.8])
    alpha_rad_s2 = 20.0
    f.initialize(0, np.zeros(3), np.eye(3), _cov())
    for k in range(1, 60):
        t_s = k * 0.01
        f.update(k * 10 * MS, np.zeros(3), rotvec_to_matrix(axis * 0.5 * alpha_rad_s2 * t_s**2), _cov())
    ahead_s = 0.6
    _, R, _, w = f.pose_at(int(ahead_s * 1e9))
    truth = rotvec_to_matrix(axis * 0.5 * alpha_rad_s2 * ahead_s**2)
    assert np.degrees(Rotation.from_matrix(R @ truth.T).magnitude()) < 0.05
    assert np.allclose(w, axis * alpha_rad_s2 * ahead_s, atol=0.05)


def test_without_angular_jerk_the_angular_acceleration_stays_unmodelled():
    """angular_jerk_psd = 0 is the constant-rate model: the angular acceleration is held at zero with
    no variance, so a spin-up lags (the figure the test above removes)."""
    f = BodyFilter(KalmanSettings(angular_jerk_psd=0.0))
    axis = np.array([0.0, 0.6, 0.8])
    f.initialize(0, np.zeros(3), np.eye(3), _cov())
    for k in range(1, 60):
        f.update(k * 10 * MS, np.zeros(3), rotvec_to_matrix(axis * 10.0 * (k * 0.01) ** 2), _cov())
    assert np.all(f.x[15:18] == 0.0) and np.all(f.P[15:18] == 0.0)
    _, R, _, _ = f.pose_at(600 * MS)
    assert np.degrees(Rotation.from_matrix(R @ rotvec_to_matrix(axis * 10.0 * 0.36).T).magnitude()) > 0.3


def test_outlier_is_gated_and_state_kept():
    f = BodyFilter(KalmanSettings())
    p0 = np.array([0.0, 0.0, 1.0])
    f.initialize(0, p0, np.eye(3), _cov())
    rng = np.random.default_rng(3)
    for k in range(1, 100):
        f.update(k * 10 * MS, p0 + rng.normal(0, 0.0005, 3), np.eye(3), _cov())
    before = f.pose_at(100 * 10 * MS)[0]
    ok, d2 = f.update(100 * 10 * MS, p0 + np.array([0.05, 0.0, 0.0]), np.eye(3), _cov())
    assert not ok and d2 > f.s.gate_chi2
    assert np.linalg.norm(f.pose_at(100 * 10 * MS)[0] - before) < 1e-9
    ok, _ = f.update(101 * 10 * MS, p0, rotvec_to_matrix(np.array([0.0, 0.0, 0.3])), _cov())
    assert not ok  # a 17 deg orientation jump is an outlier too


def test_covariance_grows_with_prediction_horizon():
    f = BodyFilter(KalmanSettings())
    f.initialize(0, np.zeros(3), np.eye(3), _cov())
    for k in range(1, 50):
        f.update(k * 10 * MS, np.zeros(3), np.eye(3), _cov())
    P1 = f.output_at(50 * 10 * MS)[4]
    P2 = f.output_at(60 * 10 * MS)[4]
    assert np.trace(P2[:3, :3]) > np.trace(P1[:3, :3]) > 0
    assert np.all(np.linalg.eigvalsh(P2) > -1e-15)
