"""The vehicle's IMU in a body's filter: its accelerations and rates between camera frames (issue 29).

The bridge (bridge/imu_feed.py) reads the autopilot's HIGHRES_IMU / RAW_IMU / SCALED_IMU, moves each
sample onto the capture clock (the vehicle's measured clock offset and delay) and into the tracked body's
frame, and hands it to FusionPipeline.push_imu; the core never reads MAVLink. Per body an ImuInput keeps
the samples not yet in the filter and the two bias estimates.

How a sample enters the filter (tracking.py's state [p, v, a, dtheta, w, dw/dt], world frame z up): the
filter is predicted to the sample's time, then the sample is a linear measurement of the acceleration and
the angular rate states,

    a = R (f - b_a) + g,    w = R (omega - b_g)          (imu_measurement)

f the specific force and omega the rate in the body frame, R the filter's body->world rotation, g = (0, 0,
-9.80665). So between camera frames the position follows the measured acceleration (held from one sample
to the next) instead of the constant-acceleration model's guess, and the attitude follows the gyro; the
process noise between samples is fusion.imu.jerk_psd / angular_accel_psd (the acceleration may change that
much from one sample to the next). Before each fusion the samples up to its reference time go into the
filter (before_fusion), and the position block's covariance is widened for the acceleration held from the
newest sample to that time (the fusion's own prediction has only the optical model's jerk floor: with
samples at 50 Hz that left the held acceleration trusted for 20 ms and the flights' position error at
0.75-0.84x their bound instead of 0.68-0.71x); an output tick takes the samples after the filter's time on a copy of it
(output_at), so the outputs predict to the tick with the measured accelerations. Without a fresh sample
(none fed, older than max_age_ms, refused) the filter and its outputs are the optical ones, from the same
state: no jump.

Biases: a separate slow estimator against the optical track (fit_accel_bias, fit_gyro_bias). Over each
window of bias_window_ms the raw samples are integrated twice (once for the rates) and the optical poses
(the triangulated Kabsch poses of each fusion) fitted to them by least squares, with the window's initial
position and velocity (rotation) as the other unknowns; the estimate is the running mean of the windows'.
A sample refused by the innovation gate max_refused times in a row, or a fitted accelerometer bias above
max_accel_bias_m_s2, drops the body's IMU input: said once, and the filter goes on optical only.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

from visionpos.fusion.layout import (
    ACC0,
    ADAPT_SCALE_P,
    ADAPT_SCALE_R,
    ANG_ACC0,
    CLOCK_T_NS,
    N_STATE,
    OUT_ACC,
    OUT_POS,
    OUT_POSE_COV,
    OUT_QUAT_XYZW,
    OUT_RATE_BODY,
    OUT_VEL,
    OUT_VEL_COV,
    RATE0,
)
from visionpos.fusion.tracking import (
    _add_process_noise,
    _count_folds,
    _fold,
    _kalman_gain,
    _kf_predict,
    _output_at,
    _spd_inverse,
)
from visionpos.geometry.frames import GRAVITY_M_S2
from visionpos.geometry.rotations import matrix_from_rotvec_compiled, rotvec_from_matrix_compiled
from visionpos.jit import matmul3, njit

log = logging.getLogger(__name__)

GRAVITY_WORLD = np.array([0.0, 0.0, -GRAVITY_M_S2])  # m/s^2, world frame z up
IMU_ROWS = np.r_[ACC0:ACC0 + 3, RATE0:RATE0 + 3]  # the state rows a sample measures: a (3), w (3)
_BIAS_SMOOTHING = 0.3  # weight of each new window's bias fit in the running estimate (the first: 1)
_MAX_PENDING = 4096  # samples held for the filter at most (a stream far ahead of the cameras)
_AT_ORIGIN = np.zeros(3)  # the lever arm of an IMU at the body origin


def _f64(a) -> np.ndarray:
    """a as the contiguous float64 array the compiled kernels take (one argument type: one compilation)."""
    return np.ascontiguousarray(a, dtype=np.float64)


@njit
def _measure_into(z: np.ndarray, R: np.ndarray, accel_body: np.ndarray, gyro_body: np.ndarray,
                  accel_bias: np.ndarray, gyro_bias: np.ndarray, lever_arm_body: np.ndarray, rate_world: np.ndarray,
                  ang_acc_world: np.ndarray) -> None:
    """imu_measurement into z (6,); lever_arm_body (3,) zeros: the IMU at the body origin."""
    r = np.empty(3)
    for i in range(3):
        z[i] = GRAVITY_WORLD[i]
        z[3 + i] = 0.0
        r[i] = 0.0
        for k in range(3):
            z[i] += R[i, k] * (accel_body[k] - accel_bias[k])
            z[3 + i] += R[i, k] * (gyro_body[k] - gyro_bias[k])
            r[i] += R[i, k] * lever_arm_body[k]
    # dw/dt x r + w x (w x r): what the IMU off the origin reads on top of the origin's acceleration
    wr = np.empty(3)
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        wr[i] = rate_world[j] * r[k] - rate_world[k] * r[j]
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        z[i] -= (ang_acc_world[j] * r[k] - ang_acc_world[k] * r[j]) + (rate_world[j] * wr[k] - rate_world[k] * wr[j])


def warm_up_imu_kernels(bank) -> None:
    """Compile the kernels ImuInput calls (or load them from numba's cache) for the argument types the live path
    gives them: a row of FilterBank `bank` copied, as an output tick's copy is (fusion/warmup.py calls this;
    tests/fusion/test_warmup.py checks that a flight with the IMU compiles nothing more)."""
    x, P, R_nom, clock = bank.x[0].copy(), bank.P[0].copy(), np.eye(3), bank.clock[0].copy()
    a, w = -GRAVITY_WORLD, np.zeros(3)
    imu_step(x, P, R_nom, clock, int(clock[CLOCK_T_NS]) + 5_000_000, 100.0, 3.0, 100.0, a, w, np.zeros(3),
             np.zeros(3), _AT_ORIGIN, np.ones(6), 60.0)
    _fold(x, R_nom)  # output_at's, on its copy
    _add_process_noise(P, 0.001, 1.0, 0.0, 0.0)  # before_fusion's
    # and the bias window's fits, as ImuInput._fit_window calls them: a still body, 10 samples, 4 poses
    t = np.arange(10) * 0.005
    ot = t[1:9:2] + 0.001
    fit_accel_bias(t, np.tile(a, (10, 1)), np.tile(np.eye(3), (10, 1, 1)), ot, np.zeros((4, 3)))
    fit_gyro_bias(t, np.zeros((10, 3)), ot, np.tile(np.eye(3), (4, 1, 1)))


def imu_measurement(R: np.ndarray, accel_body: np.ndarray, gyro_body: np.ndarray, accel_bias: np.ndarray,
                    gyro_bias: np.ndarray, lever_arm_body: np.ndarray | None = None,
                    rate_world: np.ndarray | None = None, ang_acc_world: np.ndarray | None = None) -> np.ndarray:
    """The world-frame acceleration of the body origin (m/s^2) and angular rate (rad/s) one sample measures, (6,):
    R (3, 3) body->world; accel_body (3,) specific force m/s^2 and gyro_body (3,) rad/s in the body frame;
    the biases (3,) in the same units. An IMU lever_arm_body (3,) m from the body origin reads the origin's
    acceleration plus dw/dt x r + w x (w x r): taken off with the filter's rate_world and ang_acc_world (3,)."""
    z = np.empty(6)
    _measure_into(z, _f64(R), _f64(accel_body), _f64(gyro_body), _f64(accel_bias), _f64(gyro_bias),
                  *(_AT_ORIGIN if v is None else _f64(v) for v in (lever_arm_body, rate_world, ang_acc_world)))
    return z


@njit
def imu_update(x: np.ndarray, P: np.ndarray, z: np.ndarray, var: np.ndarray, gate_chi2: float) -> tuple[bool, float]:
    """Fuse one sample's measurement z (6,) of the acceleration and rate states (IMU_ROWS) into x (18,) and
    P (18, 18) in place (Joseph form); var (6,) the measurement variances. gate_chi2 <= 0: no gate.
    Returns (accepted, squared Mahalanobis distance of the innovation); refused: x, P unchanged."""
    y = np.empty(6)
    S = np.empty((6, 6))
    PHt = np.empty((N_STATE, 6))  # P H^T: H picks the rows IMU_ROWS
    for j in range(6):
        y[j] = z[j] - x[IMU_ROWS[j]]
        for i in range(N_STATE):
            PHt[i, j] = P[i, IMU_ROWS[j]]
    for i in range(6):
        for j in range(6):
            S[i, j] = PHt[IMU_ROWS[i], j]
        S[i, i] += var[i]
    Sinv = _spd_inverse(S)
    d2 = 0.0
    for i in range(6):
        for j in range(6):
            d2 += y[i] * Sinv[i, j] * y[j]
    if gate_chi2 > 0.0 and d2 > gate_chi2:
        return False, d2
    K = _kalman_gain(PHt, Sinv)
    for i in range(N_STATE):
        for j in range(6):
            x[i] += K[i, j] * y[j]
    # Joseph form: A P A^T + K diag(var) K^T with A = I - K H
    AP = P.copy()
    for i in range(N_STATE):
        for j in range(N_STATE):
            acc = 0.0
            for m in range(6):
                acc += K[i, m] * P[IMU_ROWS[m], j]
            AP[i, j] -= acc
    for i in range(N_STATE):
        for j in range(i + 1):
            acc = AP[i, j]
            for m in range(6):
                acc += -AP[i, IMU_ROWS[m]] * K[j, m] + K[i, m] * var[m] * K[j, m]
            P[i, j] = acc
    for i in range(N_STATE):  # the lower triangle, mirrored: P stays symmetric
        for j in range(i):
            P[j, i] = P[i, j]
    return True, d2


@njit
def imu_step(x: np.ndarray, P: np.ndarray, R_nom: np.ndarray, clock: np.ndarray, t_ns: int, qj: float, qw: float,
             qaj: float, accel_body: np.ndarray, gyro_body: np.ndarray, accel_bias: np.ndarray,
             gyro_bias: np.ndarray, lever_arm_body: np.ndarray, var: np.ndarray,
             gate_chi2: float) -> tuple[bool, float]:
    """One sample into a filter row (x (18,), P (18, 18), R_nom (3, 3), clock (3,): in place): predicted to t_ns
    (int ns) with the process noise between samples (qj, qw, qaj as tracking._kf_predict's), the sample's
    measurement (imu_measurement, the IMU lever_arm_body (3,) m, zeros: at the origin) fused (imu_update) and,
    accepted, the rotation error folded. Returns imu_update's (accepted, squared Mahalanobis distance)."""
    dt = (t_ns - clock[CLOCK_T_NS]) * 1e-9
    if dt != 0.0:
        _count_folds(R_nom, clock, int(_kf_predict(x, P, R_nom, dt, qj, qw, qaj)))
        clock[CLOCK_T_NS] = t_ns
    z = np.empty(6)
    _measure_into(z, R_nom, accel_body, gyro_body, accel_bias, gyro_bias, lever_arm_body, x[RATE0:RATE0 + 3],
                  x[ANG_ACC0:ANG_ACC0 + 3])
    ok, d2 = imu_update(x, P, z, var, gate_chi2)
    if ok:
        _count_folds(R_nom, clock, int(_fold(x, R_nom)))
    return ok, d2


@njit
def _integrate_accel(t_s: np.ndarray, a_w: np.ndarray, R: np.ndarray) -> tuple:
    """fit_accel_bias's integrals at each sample time t_s (N,) s of the world acceleration a_w (N, 3) m/s^2 and of
    the rotations R (N, 3, 3): D (N, 3) and VD (N, 3), the double and single integrals of a_w, and M, VM
    (N, 3, 3) those of R. Between samples a and R are linear (trapezoid: holding each sample until the next would
    lag by half a sample, centimetres over a window in a manoeuvre)."""
    n = len(t_s)
    D, VD = np.zeros((n, 3)), np.zeros((n, 3))
    M, VM = np.zeros((n, 3, 3)), np.zeros((n, 3, 3))
    for i in range(1, n):
        h = t_s[i] - t_s[i - 1]
        c = h * h / 6.0
        for r in range(3):
            D[i, r] = D[i - 1, r] + VD[i - 1, r] * h + (2.0 * a_w[i - 1, r] + a_w[i, r]) * c
            VD[i, r] = VD[i - 1, r] + (a_w[i - 1, r] + a_w[i, r]) * (0.5 * h)
            for q in range(3):
                M[i, r, q] = M[i - 1, r, q] + VM[i - 1, r, q] * h + (2.0 * R[i - 1, r, q] + R[i, r, q]) * c
                VM[i, r, q] = VM[i - 1, r, q] + (R[i - 1, r, q] + R[i, r, q]) * (0.5 * h)
    return D, VD, M, VM


@njit
def _gyro_rows(t_s: np.ndarray, gyro_body: np.ndarray, obs_t_s: np.ndarray, obs_R: np.ndarray) -> tuple:
    """fit_gyro_bias's least-squares system: rows (K, 3, 6) and right-hand sides (K, 3), one per optical rotation
    obs_R (K, 3, 3) at obs_t_s (K,) s, from the rates gyro_body (N, 3) rad/s at t_s (N,) s (see fit_gyro_bias).
    Between samples the rate is linear: each step turns by the mean of its ends (holding a sample until the next
    lags by half a sample, milliradians over a window in a flick)."""
    n = len(t_s)
    Q, S = np.zeros((n, 3, 3)), np.zeros((n, 3, 3))
    Q[0] = np.eye(3)
    for i in range(1, n):
        h = t_s[i] - t_s[i - 1]
        S[i] = S[i - 1] + (Q[i - 1] + matmul3(Q[i - 1], matrix_from_rotvec_compiled(gyro_body[i - 1] * h))) * (0.5 * h)
        Q[i] = matmul3(Q[i - 1], matrix_from_rotvec_compiled((gyro_body[i - 1] + gyro_body[i]) * (0.5 * h)))
    K = len(obs_t_s)
    Qs, Ss = np.empty((K, 3, 3)), np.empty((K, 3, 3))
    for j in range(K):  # Q and S at each observation's time
        i = min(max(np.searchsorted(t_s, obs_t_s[j], side="right") - 1, 0), n - 2)
        h = obs_t_s[j] - t_s[i]
        w = gyro_body[i] + (gyro_body[i + 1] - gyro_body[i]) * (0.5 * h / (t_s[i + 1] - t_s[i]))
        Qs[j] = matmul3(Q[i], matrix_from_rotvec_compiled(w * h))
        Ss[j] = S[i] + (Q[i] + Qs[j]) * (0.5 * h)
    R0 = matmul3(obs_R[0], Qs[0].T.copy())  # the optical rotation at t0, brought back from the first by the rates
    rows = np.zeros((K, 3, 6))
    rhs = np.zeros((K, 3))
    for j in range(K):
        QjT = Qs[j].T.copy()
        rows[j, :, :3] = QjT
        rows[j, :, 3:] = -matmul3(QjT, Ss[j])
        rhs[j] = rotvec_from_matrix_compiled(matmul3(matmul3(QjT, R0.T.copy()), obs_R[j]))
    return rows, rhs


def fit_accel_bias(t_s: np.ndarray, accel_body: np.ndarray, R: np.ndarray, obs_t_s: np.ndarray,
                   obs_pos: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The accelerometer bias (3,) m/s^2 (body frame) that best explains optical positions by the samples, and
    the RMS distance (m) of the positions from that fit (the optical noise when the IMU is this body's and sane).

    t_s (N,) sample times, accel_body (N, 3) raw specific force, R (N, 3, 3) body->world at each sample,
    each held until the next; obs_t_s (K,) and obs_pos (K, 3) m optical positions within the samples' span.
    Model: p(t) = p0 + v0 (t - t0) + D(t) - M(t) b, D the double integral of R f + g and M that of R;
    least squares over p0, v0, b. None with fewer than 4 positions."""
    if len(obs_t_s) < 4 or len(t_s) < 2:
        return None
    a_w = np.einsum("nij,nj->ni", R, accel_body) + GRAVITY_WORLD
    n = len(t_s)
    D, VD, M, VM = _integrate_accel(_f64(t_s), a_w, _f64(R))
    k = np.clip(np.searchsorted(t_s, obs_t_s, side="right") - 1, 0, n - 2)
    h = obs_t_s - t_s[k]  # into the interval [t_k, t_k+1]
    c2, c3 = 0.5 * h * h, h**3 / (6.0 * (t_s[k + 1] - t_s[k]))
    Dk = D[k] + VD[k] * h[:, None] + a_w[k] * c2[:, None] + (a_w[k + 1] - a_w[k]) * c3[:, None]
    Mk = (M[k] + VM[k] * h[:, None, None] + R[k] * c2[:, None, None]
          + (R[k + 1] - R[k]) * c3[:, None, None])
    tau = obs_t_s - t_s[0]
    rows = np.zeros((len(obs_t_s), 3, 9))
    rows[:, :, 0:3] = np.eye(3)
    rows[:, :, 3:6] = np.eye(3) * tau[:, None, None]
    rows[:, :, 6:9] = -Mk
    A, y = rows.reshape(-1, 9), (obs_pos - Dk).reshape(-1)
    sol = np.linalg.lstsq(A, y, rcond=None)[0]
    return sol[6:9], float(np.sqrt(np.mean((A @ sol - y) ** 2) * 3.0))


def fit_gyro_bias(t_s: np.ndarray, gyro_body: np.ndarray, obs_t_s: np.ndarray,
                  obs_R: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The gyro bias (3,) rad/s (body frame) that best explains optical rotations by the samples, and the RMS
    angle (rad) of the rotations from that fit.

    t_s (N,) sample times, gyro_body (N, 3) raw rates, each held until the next; obs_t_s (K,) and obs_R
    (K, 3, 3) body->world optical rotations within the samples' span. Q(t): the rotation the raw rates
    integrate to from t0; with a bias b the body-frame error of R0 Q grows as -Q(t)^T S(t) b, S the integral
    of Q (first order). Least squares over the rotation error at t0 and b, against log((R0 Q_k)^T R_k),
    R0 the first optical rotation. None with fewer than 4 rotations."""
    if len(obs_t_s) < 4 or len(t_s) < 2:
        return None
    rows, rhs = _gyro_rows(_f64(t_s), _f64(gyro_body), _f64(obs_t_s), _f64(obs_R))
    A, y = rows.reshape(-1, 6), rhs.reshape(-1)
    sol = np.linalg.lstsq(A, y, rcond=None)[0]
    return sol[3:], float(np.sqrt(np.mean((A @ sol - y) ** 2) * 3.0))


class ImuInput:
    """One body's IMU samples and bias estimates (see the module docstring); settings: fusion.imu's
    ImuSettings. Times are int64 ns on the capture clock."""

    def __init__(self, settings, name: str):
        self.s = settings
        self.name = name
        self.pending: deque[tuple[int, np.ndarray, np.ndarray]] = deque()
        self.accel_bias = np.zeros(3)
        self.gyro_bias = np.zeros(3)
        self.bias_fits = 0  # windows fitted so far
        self.lever_arm_m: np.ndarray | None = None  # body frame, from the origin to the IMU (None: at the origin)
        self.last_t_ns: int | None = None  # newest sample pushed
        self.last_used_ns: int | None = None  # newest sample in the filter (or its output)
        self.dropped = False  # refused or implausible: optical only from then on
        self.refused_in_row = 0
        self.stats = {"samples": 0, "used": 0, "refused": 0, "late": 0, "invalid": 0}
        self._var = np.array([settings.accel_noise_m_s2**2] * 3 + [settings.gyro_noise_rad_s**2] * 3)
        # the current bias window: raw samples as used (time s, f, omega, R) and optical poses (time s, p, R)
        self._win_imu: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = []
        self._win_obs: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._win_start_ns: int | None = None

    # ------------------------------------------------------------------ input
    def push(self, t_ns: int, accel_body: np.ndarray, gyro_body: np.ndarray) -> bool:
        """Queue one sample (body frame: specific force m/s^2, rate rad/s); False if refused (not finite, not
        after the last one, or this body's input was dropped): nothing changes then."""
        a = _f64(accel_body).reshape(3)
        w = _f64(gyro_body).reshape(3)
        if self.dropped or not (np.isfinite(a).all() and np.isfinite(w).all()):
            self.stats["invalid"] += 1
            return False
        if self.last_t_ns is not None and t_ns <= self.last_t_ns:
            self.stats["invalid"] += 1
            return False
        self.last_t_ns = int(t_ns)
        self.stats["samples"] += 1
        self.pending.append((int(t_ns), a, w))
        while len(self.pending) > _MAX_PENDING:
            self.pending.popleft()
        return True

    def fresh(self, t_ns: int) -> bool:
        """Whether the stream is live at t_ns: a sample within max_age_ms, and the input not dropped."""
        return not self.dropped and self.last_t_ns is not None and t_ns - self.last_t_ns <= self.s.max_age_ns

    # ----------------------------------------------------------- the filter
    def _step(self, x, P, R_nom, clock, scale_p: float, scale_r: float, kalman, t_ns: int, a: np.ndarray,
              w: np.ndarray, record: bool) -> None:
        """Predict x, P, R_nom, clock (a filter row or a copy) to t_ns with the process noise between samples,
        then fuse the sample (a, w) (imu_step); record: count it and keep it for the bias window."""
        ok, _ = imu_step(x, P, R_nom, clock, t_ns, max(self.s.jerk_psd, kalman.jerk_psd * scale_p),
                         max(self.s.angular_accel_psd, kalman.angular_accel_psd * scale_r),
                         kalman.angular_jerk_psd * scale_r, a, w, self.accel_bias, self.gyro_bias,
                         _AT_ORIGIN if self.lever_arm_m is None else self.lever_arm_m, self._var, self.s.gate_chi2)
        if not record:
            return
        if not ok:
            self.stats["refused"] += 1
            self.refused_in_row += 1
            if self.refused_in_row >= self.s.max_refused:
                self._drop(f"{self.refused_in_row} samples in a row disagree with the optical track")
            return
        self.refused_in_row = 0
        self.stats["used"] += 1
        if self._win_start_ns is None:
            self._win_start_ns = t_ns
        self._win_imu.append((t_ns * 1e-9, a, w, R_nom.copy()))

    def before_fusion(self, flt, kalman, ref_ns: int) -> None:
        """Put the samples up to ref_ns into filter `flt` (a BodyFilter, mutated), in time order; samples
        older than the filter's time are late (counted, left out). While the stream is fresh, the position
        block's covariance is widened for the acceleration held from the newest sample to ref_ns."""
        while self.pending and self.pending[0][0] <= ref_ns:
            t, a, w = self.pending.popleft()
            if self.dropped:
                continue
            if t < flt.t_ns:
                self.stats["late"] += 1
                continue
            self._step(flt._x, flt._P, flt._R_nom, flt._clock, flt.scale_p, flt.scale_r, kalman, t, a, w, True)
            self.last_used_ns = t
        if self.fresh(ref_ns) and ref_ns > flt.t_ns:
            # the fusion predicts on from the newest sample with the optical model's jerk floor; the acceleration
            # held since that sample may change as much as between samples: the difference goes into P (position
            # block; times untouched, so the fusion's views at their own capture times step no further back)
            qj = max(self.s.jerk_psd - kalman.jerk_psd * flt.scale_p, 0.0)
            _add_process_noise(flt._P, (ref_ns - flt.t_ns) * 1e-9, qj, 0.0, 0.0)

    def output_at(self, flt, kalman, t_ns: int) -> tuple:
        """BodyFilter.output_at(t_ns) with the pending samples up to t_ns taken on a copy of the filter (the
        outputs predict with the measured accelerations); the model's output when the stream is not fresh."""
        if not self.fresh(t_ns) or not self.pending or self.pending[0][0] > t_ns:
            return flt.output_at(t_ns)
        x, P, R_nom, clock = flt._x.copy(), flt._P.copy(), flt._R_nom.copy(), flt._clock.copy()
        sp, sr = flt.scale_p, flt.scale_r
        for t, a, w in self.pending:
            if t > t_ns:
                break
            if t >= clock[CLOCK_T_NS]:
                self._step(x, P, R_nom, clock, sp, sr, kalman, t, a, w, False)
                _fold(x, R_nom)
        adapt = flt._adapt
        o = _output_at(x, P, R_nom, (t_ns - int(clock[CLOCK_T_NS])) * 1e-9, kalman.jerk_psd * adapt[ADAPT_SCALE_P],
                       kalman.angular_accel_psd * adapt[ADAPT_SCALE_R], kalman.angular_jerk_psd * adapt[ADAPT_SCALE_R])
        return (o[OUT_POS], o[OUT_QUAT_XYZW], o[OUT_VEL], o[OUT_RATE_BODY], o[OUT_POSE_COV].reshape(6, 6),
                o[OUT_VEL_COV].reshape(3, 3), o[OUT_ACC])

    # ------------------------------------------------------------- the biases
    def observe_pose(self, t_ns: int, position: np.ndarray, R: np.ndarray) -> None:
        """An optical pose (the fusion's triangulated pose at t_ns): kept for the bias fit; a full window
        is fitted and a new one begun."""
        if self.dropped or self._win_start_ns is None:
            return
        self._win_obs.append((t_ns * 1e-9, np.array(position, float), np.array(R, float)))
        if t_ns - self._win_start_ns >= self.s.bias_window_ns:
            self._fit_window()

    def _fit_window(self) -> None:
        imu, obs = self._win_imu, self._win_obs
        self._win_imu, self._win_obs, self._win_start_ns = [], [], None
        if len(imu) < 2:
            return
        t = np.array([s[0] for s in imu])
        t0 = t[0]
        ot = np.array([o[0] for o in obs])
        inside = (ot >= t[0]) & (ot <= t[-1])
        if inside.sum() < 4:
            return
        f, w, R = np.array([s[1] for s in imu]), np.array([s[2] for s in imu]), np.array([s[3] for s in imu])
        op, oR = np.array([o[1] for o in obs])[inside], np.array([o[2] for o in obs])[inside]
        fa = fit_accel_bias(t - t0, f, R, ot[inside] - t0, op)
        fg = fit_gyro_bias(t - t0, w, ot[inside] - t0, oR)
        if fa is None or fg is None:
            return
        (ba, rms_p), (bg, rms_r) = fa, fg
        if rms_p > self.s.max_fit_residual_mm * 1e-3 or rms_r > np.radians(self.s.max_fit_residual_deg):
            self._drop(f"integrated over {t[-1] - t0:.1f} s it misses the optical track by {rms_p * 1e3:.1f} mm and "
                       f"{np.degrees(rms_r):.2f} deg RMS (fusion.imu.max_fit_residual_mm "
                       f"{self.s.max_fit_residual_mm}, max_fit_residual_deg {self.s.max_fit_residual_deg}): stuck, "
                       "another vehicle's, or a clock that jumped")
            return
        if np.linalg.norm(ba) > self.s.max_accel_bias_m_s2:
            self._drop(f"its fitted accelerometer bias {np.linalg.norm(ba):.2f} m/s^2 is above "
                       f"fusion.imu.max_accel_bias_m_s2 ({self.s.max_accel_bias_m_s2})")
            return
        k = 1.0 if self.bias_fits == 0 else _BIAS_SMOOTHING
        self.accel_bias += k * (ba - self.accel_bias)
        self.gyro_bias += k * (bg - self.gyro_bias)
        self.bias_fits += 1

    def _drop(self, why: str) -> None:
        if not self.dropped:
            log.warning("body %s: IMU input dropped, optical only from now on: %s", self.name, why)
        self.dropped = True
        self.pending.clear()


class ImuInputs:
    """The IMU inputs of a pipeline's bodies, by body index (FusionPipeline.imu; None when fusion.imu is off)."""

    def __init__(self, settings, names: list[str], kalman):
        self.kalman = kalman
        self.bodies = [ImuInput(settings, n) for n in names]
        self.index = {n: i for i, n in enumerate(names)}
        self.live = False  # a sample was taken: until then the pipeline skips these (no cost without an IMU)

    def push(self, name: str, t_ns: int, accel_body: np.ndarray, gyro_body: np.ndarray,
             lever_arm_m: np.ndarray | None = None) -> bool:
        """One sample for body `name` (ImuInput.push), from an IMU lever_arm_m (3,) from its origin (body frame;
        None: at the origin); False for an unknown body."""
        b = self.index.get(name)
        if b is None:
            return False
        body = self.bodies[b]
        if lever_arm_m is not None:
            arm = np.asarray(lever_arm_m, dtype=np.float64).reshape(3)
            body.lever_arm_m = arm if np.isfinite(arm).all() and arm.any() else None
        taken = body.push(int(t_ns), accel_body, gyro_body)
        self.live |= taken
        return taken

    def before_fusion(self, tracked: tuple[int, ...], filters, ref_ns: int) -> None:
        """The tracked bodies' samples up to ref_ns into their filters (ImuInput.before_fusion)."""
        for b in tracked:
            if self.bodies[b].pending or self.bodies[b].fresh(ref_ns):
                self.bodies[b].before_fusion(filters[b], self.kalman, ref_ns)

    def after_fusion(self, tracked: tuple[int, ...], last_raw: dict, ref_ns: int) -> None:
        """The fusion's triangulated poses (last_raw: body -> (ref, position, R)) to the bias estimators."""
        for b in tracked:
            raw = last_raw.get(b)
            if raw is not None and raw[0] == ref_ns:
                self.bodies[b].observe_pose(ref_ns, raw[1], raw[2])

    def output_at(self, b: int, flt, t_ns: int) -> tuple:
        """Body b's output at t_ns (ImuInput.output_at)."""
        return self.bodies[b].output_at(flt, self.kalman, t_ns)
