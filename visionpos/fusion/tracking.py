"""Kalman filter/predictor for one rigid body, error-state in orientation.

State (15,): [p (3) m, v (3) m/s, a (3) m/s^2, dtheta (3) rad, w (3) rad/s],
world frame. Position is a constant-acceleration model driven by white jerk;
orientation is a *multiplicative* error state: a nominal rotation R_nom
(body->world) plus a small world-frame rotation-vector error dtheta, driven
by a constant angular rate w with white angular-acceleration noise.

Why error-state: a rotation has 3 degrees of freedom but no global minimal
parameterisation without singularities; keeping the nominal rotation outside
the linear filter and estimating only a small error keeps the filter linear
(a plain linear Kalman filter does the work) and singularity-free. After
every predict/update the error is folded into the nominal rotation and reset
to zero, so dtheta always stays small. Prediction uses the same mechanism:
x = F x makes dtheta = w dt, which the fold turns into
R_nom <- exp(w dt) R_nom.

Why constant acceleration plus adaptive process noise: a drone's
acceleration is smooth, so a constant-acceleration model predicts it well
(a constant-velocity model lags in every turn and must be given a large
process noise, which then lets static jitter through). A fixed process
noise is still a compromise between a hovering and a manoeuvring body, so
the noise is scaled by a running average of the normalised innovation
squared (NIS, separately for position and orientation): while the model fits
the measurements NIS/dof ~ 1 and the floor `jerk_psd` / `angular_accel_psd`
smooths hard; a manoeuvre makes NIS grow and the process noise follows
within a few updates (bounded by `max_noise_scale`). The position scale
also listens to an image-space detector (report_image_nis): each new
frame's markers predicted to its capture time against the blobs found. That
view is uncompensated, so motion compensation (which uses this filter's own
velocity) cannot pull it towards the prediction and hide a lag the way it
can for the fused pose.

The measurement is a 6-DoF pose [p, log(R_meas R_nom^T)] with a covariance
given by the caller (pipeline.py estimates it from the rigid-body fit).
Outliers are gated by the squared Mahalanobis distance of the innovation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from visionpos.geometry.rotations import (
    matrix_from_rotvec_compiled, quat_from_matrix_compiled, rotvec_from_matrix_compiled,
)
from visionpos.jit import matmul3, njit

NX = 15
_NIS_HIGH = 2.0  # averaged NIS/dof above this means the motion model lags
_SCALE_DECAY_S = 0.2  # s, time constant of the process-noise scale's return to its floor


@dataclass(frozen=True)
class KalmanSettings:
    """Noise, adaptation and gating of the body filter (SI units).

    jerk_psd: floor of the white-jerk spectral density (m^2/s^5).
    angular_accel_psd: floor of the white angular-acceleration density (rad^2/s^3).
    max_noise_scale: largest factor the NIS adaptation may apply to them.
    nis_time_constant: s, averaging time of the NIS that drives the adaptation.
    gate_chi2: squared-Mahalanobis threshold of the 6-dof innovation.
    init_*_sigma: prior std of the unmeasured derivatives at (re)initialisation.
    """

    jerk_psd: float = 0.1
    angular_accel_psd: float = 1.0
    max_noise_scale: float = 1e4
    nis_time_constant: float = 0.015
    gate_chi2: float = 40.0
    init_velocity_sigma: float = 2.0
    init_acceleration_sigma: float = 10.0
    init_angular_velocity_sigma: float = 6.0


_POSE = (0, 1, 2, 9, 10, 11)  # the measured states: position, rotation error


@njit
def _add_process_noise(P: np.ndarray, dt: float, qj: float, qw: float) -> None:
    """P (15, 15) += discrete Q over |dt|: white jerk on (p, v, a), white angular acceleration on (dtheta, w)."""
    a = abs(dt)
    a2 = a * a
    a3, a4 = a2 * a, a2 * a2
    a5 = a2 * a3
    cj = np.array([[a5 / 20.0, a4 / 8.0, a3 / 6.0], [a4 / 8.0, a3 / 3.0, a2 / 2.0], [a3 / 6.0, a2 / 2.0, a]]) * qj
    cw = np.array([[a3 / 3.0, a2 / 2.0], [a2 / 2.0, a]]) * qw
    for k in range(3):
        for i in range(3):
            for j in range(3):
                P[i * 3 + k, j * 3 + k] += cj[i, j]
        for i in range(2):
            for j in range(2):
                P[9 + i * 3 + k, 9 + j * 3 + k] += cw[i, j]


@njit
def _predicted_cov(P: np.ndarray, dt: float, qj: float, qw: float) -> np.ndarray:
    """F P F^T + Q (15, 15) over dt, with F's sparsity written out (a 15x15 product costs more)."""
    h = 0.5 * dt * dt
    FP = P.copy()
    for k in range(3):  # rows: F P
        for j in range(NX):
            FP[k, j] = P[k, j] + dt * P[3 + k, j] + h * P[6 + k, j]
            FP[3 + k, j] = P[3 + k, j] + dt * P[6 + k, j]
            FP[9 + k, j] = P[9 + k, j] + dt * P[12 + k, j]
    Pn = FP.copy()
    for k in range(3):  # columns: (F P) F^T
        for i in range(NX):
            Pn[i, k] = FP[i, k] + dt * FP[i, 3 + k] + h * FP[i, 6 + k]
            Pn[i, 3 + k] = FP[i, 3 + k] + dt * FP[i, 6 + k]
            Pn[i, 9 + k] = FP[i, 9 + k] + dt * FP[i, 12 + k]
    _add_process_noise(Pn, dt, qj, qw)
    return Pn


@njit
def _fold(x: np.ndarray, R_nom: np.ndarray) -> bool:
    """Move the rotation error x[9:12] into R_nom (in place) and zero it; False if it was zero."""
    if x[9] == 0.0 and x[10] == 0.0 and x[11] == 0.0:
        return False
    R_nom[:, :] = matmul3(matrix_from_rotvec_compiled(x[9:12]), R_nom)
    x[9:12] = 0.0
    return True


@njit
def _kf_predict(x: np.ndarray, P: np.ndarray, R_nom: np.ndarray, dt: float, qj: float, qw: float) -> bool:
    """Advance state x (15,), covariance P (15, 15) and R_nom (3, 3) in place by dt; True if it folded."""
    for k in range(3):
        x[k] += x[3 + k] * dt + x[6 + k] * (0.5 * dt * dt)
        x[3 + k] += x[6 + k] * dt
        x[9 + k] += x[12 + k] * dt
    P[:, :] = _predicted_cov(P, dt, qj, qw)
    return _fold(x, R_nom)


@njit
def _quad3(S: np.ndarray, y: np.ndarray) -> float:
    """y^T S^-1 y for a symmetric positive-definite 3x3 S (adjugate)."""
    a, b, c, d, e, f = S[0, 0], S[0, 1], S[0, 2], S[1, 1], S[1, 2], S[2, 2]
    y0, y1, y2 = y[0], y[1], y[2]
    A00, A01, A02 = d * f - e * e, c * e - b * f, b * e - c * d
    A11, A12, A22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A00 + b * A01 + c * A02
    return (A00 * y0 * y0 + A11 * y1 * y1 + A22 * y2 * y2 + 2.0 * (A01 * y0 * y1 + A02 * y0 * y2 + A12 * y1 * y2)) / det


@njit
def _kf_update(
    x: np.ndarray, P: np.ndarray, R_nom: np.ndarray, position: np.ndarray, R: np.ndarray, cov: np.ndarray, gate_chi2: float
) -> tuple[bool, float, float, float]:
    """Fuse a pose measurement into x (15,), P (15, 15), R_nom (3, 3) in place (Joseph form).

    position (3,), R (3, 3) body->world, cov (6, 6) over [p, world rotation
    vector]. gate_chi2 <= 0 disables the gate. Returns (accepted, squared
    Mahalanobis distance, position NIS / 3, rotation NIS / 3).
    """
    z = np.empty(6)
    z[0:3] = position
    z[3:6] = rotvec_from_matrix_compiled(matmul3(R, R_nom.T))
    S = np.empty((6, 6))
    y = np.empty(6)
    PHt = np.empty((NX, 6))  # P H^T: the measured columns
    for j in range(6):
        y[j] = z[j] - x[_POSE[j]]
        for i in range(NX):
            PHt[i, j] = P[i, _POSE[j]]
        for i in range(6):
            S[i, j] = P[_POSE[i], _POSE[j]] + cov[i, j]
    Sinv = _spd_inverse(S)
    d2 = 0.0
    for i in range(6):
        for j in range(6):
            d2 += y[i] * Sinv[i, j] * y[j]
    nis_p = _quad3(S[0:3, 0:3], y[0:3]) / 3.0
    nis_r = _quad3(S[3:6, 3:6], y[3:6]) / 3.0
    if gate_chi2 > 0.0 and d2 > gate_chi2:
        return False, d2, nis_p, nis_r
    K = np.zeros((NX, 6))  # P H^T S^-1
    for i in range(NX):
        for j in range(6):
            acc = 0.0
            for l in range(6):
                acc += PHt[i, l] * Sinv[l, j]
            K[i, j] = acc
    for i in range(NX):
        for j in range(6):
            x[i] += K[i, j] * y[j]
    # Joseph form (I - K H) P (I - K H)^T + K C K^T, with H selecting the _POSE states
    AP = P.copy()
    for i in range(NX):
        for j in range(NX):
            acc = 0.0
            for l in range(6):
                acc += K[i, l] * P[_POSE[l], j]
            AP[i, j] -= acc
    KC = np.zeros((NX, 6))
    for i in range(NX):
        for j in range(6):
            for l in range(6):
                KC[i, j] += K[i, l] * cov[l, j]
    for i in range(NX):
        for j in range(NX):
            acc = AP[i, j]
            for l in range(6):
                acc += -AP[i, _POSE[l]] * K[j, l] + KC[i, l] * K[j, l]
            P[i, j] = acc
    _fold(x, R_nom)
    return True, d2, nis_p, nis_r


@njit
def _kf_predict_update(x, P, R_nom, dt, qj, qw, position, R, cov, gate_chi2):
    """_kf_predict over dt (when dt != 0) then _kf_update, in one call; returns
    (folds done, accepted, squared Mahalanobis distance, position NIS / 3, rotation NIS / 3)."""
    folds = 0
    if dt != 0.0 and _kf_predict(x, P, R_nom, dt, qj, qw):
        folds += 1
    accepted, d2, nis_p, nis_r = _kf_update(x, P, R_nom, position, R, cov, gate_chi2)
    if accepted:
        folds += 1
    return folds, accepted, d2, nis_p, nis_r


@njit
def _spd_inverse(S: np.ndarray) -> np.ndarray:
    """Inverse of a small symmetric positive-definite matrix (Cholesky, no library call)."""
    n = S.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        d = S[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        L[j, j] = math.sqrt(d)
        for i in range(j + 1, n):
            v = S[i, j]
            for k in range(j):
                v -= L[i, k] * L[j, k]
            L[i, j] = v / L[j, j]
    Li = np.zeros((n, n))  # L^-1, lower triangular
    for i in range(n):
        Li[i, i] = 1.0 / L[i, i]
        for j in range(i):
            v = 0.0
            for k in range(j, i):
                v -= L[i, k] * Li[k, j]
            Li[i, j] = v / L[i, i]
    out = np.empty((n, n))
    for i in range(n):
        for j in range(i + 1):
            v = 0.0
            for k in range(i, n):
                v += Li[k, i] * Li[k, j]
            out[i, j] = out[j, i] = v
    return out


@njit
def predict_mean(x: np.ndarray, R_nom: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mean of state x (15,) with nominal rotation R_nom (3, 3) predicted by dt (s):
    position (3,), rotation body->world (3, 3), velocity (3,)."""
    p = x[0:3] + x[3:6] * dt + x[6:9] * (0.5 * dt * dt)
    return p, matmul3(matrix_from_rotvec_compiled(x[12:15] * dt), R_nom), x[3:6] + x[6:9] * dt


@njit
def _output_at(x, P, R_nom, dt, qj, qw):
    """Prediction by dt for the outputs, packed in one array (58,): position (3,), quaternion
    xyzw (4,), velocity (3,), body-frame angular rate (3,), pose covariance (6, 6) over
    [p, rotation vector] and velocity covariance (3, 3), row-major (see BodyFilter.output_at)."""
    Pn = _predicted_cov(P, dt, qj, qw)
    w = x[12:15]
    p, R, v = predict_mean(x, R_nom, dt)
    out = np.empty(58)
    out[0:3] = p
    out[3], out[4], out[5], out[6] = quat_from_matrix_compiled(R)
    out[7:10] = v
    for i in range(3):
        out[10 + i] = R[0, i] * w[0] + R[1, i] * w[1] + R[2, i] * w[2]
    for i in range(6):
        for j in range(6):
            out[13 + 6 * i + j] = Pn[_POSE[i], _POSE[j]]
    for i in range(3):
        for j in range(3):
            out[49 + 3 * i + j] = Pn[3 + i, 3 + j]
    return out


# packed filter state: one row per body in FilterBank.adapt / .clock, one entry in .params
_SCALE_P, _SCALE_R, _NIS_P, _NIS_R, _NIS_IMG = range(5)  # adapt (float)
CLOCK_T, _IMG_T, _FOLDS = range(3)  # clock (int64 ns, count)
_JERK, _ANG_ACC, _MAX_SCALE, _NIS_TAU, _GATE, _INIT_V, _INIT_A, _INIT_W = range(8)  # params
_ORTHO_EVERY = 256  # folds between re-orthonormalisations of R_nom
_IMG_NIS_FRESH_NS = 50_000_000  # an image-space NIS older than this no longer drives the noise scale


@njit
def _orthonormalize(R: np.ndarray) -> None:
    """R (3, 3) <- its nearest rotation, in place, for R already orthonormal to round-off
    (one Newton step of the polar decomposition, R (3 I - R^T R) / 2: quadratic convergence)."""
    RtR = matmul3(R.T, R)
    M = -0.5 * RtR
    for i in range(3):
        M[i, i] += 1.5
    R[:, :] = matmul3(R, M)


@njit
def _count_folds(R_nom: np.ndarray, clock: np.ndarray, folds: int) -> None:
    for _ in range(folds):
        clock[_FOLDS] += 1
        if clock[_FOLDS] % _ORTHO_EVERY == 0:  # keep R_nom orthonormal against round-off
            _orthonormalize(R_nom)


@njit
def _adapt_scale(scale: float, nis: float, alpha: float, decay: float, smax: float) -> float:
    if nis > _NIS_HIGH:
        scale *= (nis / _NIS_HIGH) ** (3.0 * alpha)
    else:
        scale *= decay
    return min(smax, max(1.0, scale))


@njit
def filter_update(x, P, R_nom, adapt, clock, params, t_ns, position, R, cov, gate):
    """Predict one body filter to t_ns (int ns) and fuse a pose measurement, in place (compiled).

    x (15,), P (15, 15), R_nom (3, 3), adapt (5,), clock (3,): the body's rows of a
    FilterBank; params (8,) its settings (FilterBank.params). position (3,), R (3, 3) body->world,
    cov (6, 6) over [p, world rotation vector]; gate: apply the innovation gate.
    Returns (accepted, squared Mahalanobis distance); a gated measurement leaves
    the state predicted only. Then adapts the process-noise scales to the NIS.
    """
    dt = (t_ns - clock[CLOCK_T]) * 1e-9
    folds, accepted, d2, nis_p, nis_r = _kf_predict_update(
        x, P, R_nom, dt, params[_JERK] * adapt[_SCALE_P], params[_ANG_ACC] * adapt[_SCALE_R],
        position, R, cov, params[_GATE] if gate else 0.0,
    )
    clock[CLOCK_T] = t_ns
    _count_folds(R_nom, clock, folds)
    # NIS per block drives the process-noise scale (gated ones too, capped, so that a
    # manoeuvre that starts outside the gate still opens it)
    cap = params[_GATE] / 3.0
    alpha = 1.0 - math.exp(-dt / params[_NIS_TAU]) if dt > 0.0 else 0.05
    adapt[_NIS_P] += alpha * (min(nis_p, cap) - adapt[_NIS_P])
    adapt[_NIS_R] += alpha * (min(nis_r, cap) - adapt[_NIS_R])
    # the image-space detector (report_image_nis) sees lag the fused pose can hide
    nis_img = adapt[_NIS_IMG] if t_ns - clock[_IMG_T] < _IMG_NIS_FRESH_NS else 0.0
    # NIS/dof ~ 1 says nothing about q while the measurement noise dominates the
    # innovation (a hovering body), so only a clear excess (> _NIS_HIGH) raises q:
    # innovations k x too big -> q x k^3 per averaging time (CA/CV scaling laws);
    # otherwise q decays back to its floor
    decay = math.exp(-max(dt, 0.0) / _SCALE_DECAY_S)
    adapt[_SCALE_P] = _adapt_scale(adapt[_SCALE_P], max(adapt[_NIS_P], nis_img), alpha, decay, params[_MAX_SCALE])
    adapt[_SCALE_R] = _adapt_scale(adapt[_SCALE_R], adapt[_NIS_R], alpha, decay, params[_MAX_SCALE])
    return accepted, d2


@njit
def filter_initialize(x, P, R_nom, adapt, clock, params, t_ns, position, R, cov):
    """(Re)start one body filter (its FilterBank rows, params as in filter_update) at a
    measured pose: position (3,), R (3, 3) body->world with covariance cov (6, 6) over
    [p, world rotation vector] at t_ns; the derivatives are unknown: zero, with the prior
    variances of params. The noise scales and NIS averages start afresh."""
    x[:] = 0.0
    x[0:3] = position
    P[:, :] = 0.0
    for i in range(6):
        for j in range(6):
            P[_POSE[i], _POSE[j]] = cov[i, j]
    for k in range(3):
        P[3 + k, 3 + k] = params[_INIT_V]
        P[6 + k, 6 + k] = params[_INIT_A]
        P[12 + k, 12 + k] = params[_INIT_W]
    R_nom[:, :] = R
    adapt[:] = 1.0
    clock[CLOCK_T] = t_ns
    clock[_IMG_T] = 0


@njit
def report_image_nis(adapt, clock, params, t_ns, nis):
    """Feed one body's manoeuvre detector (adapt (5,), clock (3,): its FilterBank rows)
    with one camera frame's prediction residual nis at t_ns (see BodyFilter.report_image_nis)."""
    dt = max((t_ns - clock[_IMG_T]) * 1e-9, 0.0)
    alpha = 1.0 - math.exp(-dt / params[_NIS_TAU]) if clock[_IMG_T] != 0 else 1.0
    adapt[_NIS_IMG] += alpha * (min(nis, params[_GATE] / 3.0) - adapt[_NIS_IMG])
    clock[_IMG_T] = t_ns


class FilterBank:
    """The states of n body filters, one row each, so that compiled kernels update them in place.

    x (n, 15), P (n, 15, 15), R_nom (n, 3, 3); adapt (n, 5): process-noise scales
    and NIS averages [scale_p, scale_r, nis_p, nis_r, nis_img]; clock (n, 3) int64:
    [filter time ns, last image-NIS time ns, folds]; params (8,): [jerk_psd,
    angular_accel_psd, max_noise_scale, nis_time_constant, gate_chi2, then the prior
    variances of velocity, acceleration and angular velocity at (re)initialisation].
    filters[i] is the BodyFilter over row i.
    """

    def __init__(self, n: int, settings: KalmanSettings, make_filters: bool = True):
        self.x = np.zeros((n, NX))
        self.P = np.tile(np.eye(NX), (n, 1, 1))
        self.R_nom = np.tile(np.eye(3), (n, 1, 1))
        self.adapt = np.ones((n, 5))
        self.clock = np.zeros((n, 3), dtype=np.int64)
        self.params = np.array([settings.jerk_psd, settings.angular_accel_psd, settings.max_noise_scale,
                                settings.nis_time_constant, settings.gate_chi2, settings.init_velocity_sigma**2,
                                settings.init_acceleration_sigma**2, settings.init_angular_velocity_sigma**2])
        self.filters = [BodyFilter(settings, self, i) for i in range(n)] if make_filters else []


def array_field(row: str, col, kind, doc: str = "") -> property:
    """An attribute kept in cell `col` of the array attribute `row` (a view of a packed state
    row, so compiled kernels read and write the same value), read through `kind`; assigning
    writes the cell. col = ... : the whole row (kind np.asarray: the view itself)."""

    def get(self):
        return kind(getattr(self, row)[col])

    def put(self, value):
        getattr(self, row)[col] = value

    return property(get, put, doc=doc)


class BodyFilter:
    """Error-state Kalman filter of one body; times are int64 ns (capture clock).

    State x (15,) and covariance P (15, 15) as in the module docstring, plus
    the nominal rotation R_nom (3, 3) body->world and the NIS-driven noise
    scales. They live in a row of a FilterBank (a bank of one when none is
    given). The linear algebra is in compiled kernels (visionpos.jit): the
    standard predict and Joseph-form update, checked against filterpy's
    KalmanFilter in the tests.
    """

    x = array_field("_x", ..., np.asarray, "state (15,)")
    P = array_field("_P", ..., np.asarray, "covariance (15, 15)")
    R_nom = array_field("_R_nom", ..., np.asarray, "nominal rotation (3, 3) body->world")
    t_ns = array_field("_clock", CLOCK_T, int, "filter time, ns")
    scale_p = array_field("_adapt", _SCALE_P, float, "process-noise scale of the position block")
    scale_r = array_field("_adapt", _SCALE_R, float, "process-noise scale of the rotation block")

    def __init__(self, settings: KalmanSettings, bank: FilterBank | None = None, row: int = 0):
        self.s = settings
        if bank is None:  # a bank of its own
            bank, row = FilterBank(1, settings, make_filters=False), 0
            bank.filters.append(self)
        self.bank = bank
        self.row = row
        self._x, self._P, self._R_nom = bank.x[row], bank.P[row], bank.R_nom[row]
        self._adapt, self._clock = bank.adapt[row], bank.clock[row]

    # -------------------------------------------------------------- lifecycle
    def initialize(self, t_ns: int, position: np.ndarray, R: np.ndarray, meas_cov: np.ndarray | None = None) -> None:
        """Start (or restart) at a measured pose (filter_initialize); derivatives unknown (zero
        with a wide prior). meas_cov (6, 6) over [p, world rotation vector]; None: 1 mm, 0.6 deg."""
        if meas_cov is None:
            meas_cov = np.diag([1e-6] * 3 + [1e-4] * 3)
        filter_initialize(self.x, self.P, self.R_nom, self._adapt, self._clock, self.bank.params, int(t_ns),
                          np.asarray(position, dtype=np.float64), np.ascontiguousarray(R, dtype=np.float64),
                          np.ascontiguousarray(meas_cov, dtype=np.float64))

    def predict_to(self, t_ns: int) -> None:
        """Advance the filter (mutating) to t_ns; small backward steps are allowed."""
        dt = (int(t_ns) - self.t_ns) * 1e-9
        if dt != 0.0:
            folded = _kf_predict(self.x, self.P, self.R_nom, dt, self.s.jerk_psd * self.scale_p,
                                 self.s.angular_accel_psd * self.scale_r)
            _count_folds(self.R_nom, self._clock, int(folded))
            self.t_ns = int(t_ns)

    # ------------------------------------------------------------ measurement
    def update(self, t_ns: int, position: np.ndarray, R: np.ndarray, meas_cov: np.ndarray, gate: bool = True) -> tuple[bool, float]:
        """Predict to t_ns and fuse a pose measurement (filter_update on this row).

        position (3,), R (3, 3) body->world, meas_cov (6, 6) over
        [p, world rotation vector]. Returns (accepted, squared Mahalanobis
        distance); a gated measurement leaves the state predicted only.
        """
        accepted, d2 = filter_update(
            self.x, self.P, self.R_nom, self._adapt, self._clock, self.bank.params, int(t_ns),
            np.asarray(position, dtype=np.float64), np.ascontiguousarray(R, dtype=np.float64),
            np.ascontiguousarray(meas_cov, dtype=np.float64), bool(gate),
        )
        return bool(accepted), float(d2)

    def report_image_nis(self, t_ns: int, nis: float) -> None:
        """Feed the manoeuvre detector with one camera frame's prediction residual.

        nis: mean squared pixel distance between the markers predicted to the
        frame's capture time and the blobs associated with them, over its
        expected value, per degree of freedom (~1 while the model fits). It
        comes from a single uncompensated view, so unlike the fused pose it
        cannot be pulled towards the prediction by motion compensation.
        """
        report_image_nis(self._adapt, self._clock, self.bank.params, int(t_ns), float(nis))

    # -------------------------------------------------------------- read-outs
    def pose_at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Non-mutating mean prediction: position (3,), R (3, 3), velocity (3,), world angular rate (3,)."""
        p, R, v = predict_mean(self.x, self.R_nom, (int(t_ns) - self.t_ns) * 1e-9)
        return p, R, v, self.x[12:15].copy()

    def output_at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Non-mutating prediction for the outputs: position (3,), quaternion xyzw (4,),
        velocity (3,), body-frame angular rate (3,), pose covariance (6, 6) over
        [p, world rotation vector] and velocity covariance (3, 3)."""
        a = self._adapt
        o = _output_at(self._x, self._P, self._R_nom, (int(t_ns) - int(self._clock[CLOCK_T])) * 1e-9,
                       self.s.jerk_psd * a[_SCALE_P], self.s.angular_accel_psd * a[_SCALE_R])
        return o[0:3], o[3:7], o[7:10], o[10:13], o[13:49].reshape(6, 6), o[49:58].reshape(3, 3)
