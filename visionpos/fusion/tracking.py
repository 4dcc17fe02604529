"""Kalman filter/predictor for one rigid body, error-state in orientation.

State (18,): [p (3) m, v (3) m/s, a (3) m/s^2, dtheta (3) rad, w (3) rad/s,
dw/dt (3) rad/s^2], world frame. Position is a constant-acceleration model
driven by white jerk; orientation is a *multiplicative* error state: a nominal
rotation R_nom (body->world) plus a small world-frame rotation-vector error
dtheta, driven by a constant angular rate with white angular-acceleration
noise (angular_accel_psd) and, when angular_jerk_psd > 0 (the default), by a
constant angular acceleration dw/dt with white angular-jerk noise as well (the
same third-order model as the position). With angular_jerk_psd = 0 dw/dt
starts at zero with zero variance and nothing drives it: it stays zero and the
filter is the constant-rate one.

Why error-state: a rotation has 3 degrees of freedom but no global minimal
parameterisation without singularities; keeping the nominal rotation outside
the linear filter and estimating only a small error keeps the filter linear
(a plain linear Kalman filter does the work) and singularity-free. After
every predict/update the error is folded into the nominal rotation and reset
to zero, so dtheta always stays small. Prediction uses the same mechanism:
x = F x makes dtheta = w dt + dw/dt dt^2 / 2, which the fold turns into
R_nom <- exp(dtheta) R_nom.

Why constant acceleration plus adaptive process noise: a drone's
acceleration is smooth, so a constant-acceleration model predicts it well
(a constant-velocity model lags in every turn and must be given a large
process noise, which then lets static jitter through). Its attitude is
the same: a multirotor tilts to accelerate and ramps its yaw rate, so the
angular rate changes steadily over tenths of a second; with a constant-rate
model the rotation error of the issue-15 slalom flight followed the angular
acceleration (it explained half of the error's square), a lag the
angular-acceleration state removes. On a sharp pitch flick the filter at the
flick's end still extrapolates its angular acceleration, the floor noise does
not cover that, and a refused pose would leave the prediction running on while
the NIS average takes tens of ms to open the gate (tests/fusion/test_stall.py):
`gate_retest` (_manoeuvre_retest, on by default) tries such a pose again under
raised process noise and keeps the first scale that fits
(tests/fusion/test_manoeuvre.py). A fixed process
noise is still a compromise between a hovering and a manoeuvring body, so
the noise is scaled by a running average of the normalised innovation
squared (NIS, separately for position and orientation): while the model fits
the measurements NIS/dof ~ 1 and the floor `jerk_psd` / `angular_jerk_psd`
smooths hard; a manoeuvre makes NIS grow and the process noise follows
within a few updates (above `nis_threshold`, bounded by `max_noise_scale`).
A flight is one manoeuvre after another, and a scale that returns to the hover
floor between them lags each onset anew (the position predicted to the output
ticks was 1.3x its snapshot bound on the issue-29 flights): a second, slow
regime, the cruise floor (`cruise_*`), rises under the position scale while the
position NIS averaged over a second stays above `cruise_nis_threshold` and falls
back while it does not, which a still or smoothly moving body's never is.
The rotation block has its own (`cruise_max_rotation_noise_scale`, capped at 10):
a flight of attitude flicks otherwise met each flick at the hover floor, and
the rate predicted on to the output ticks lagged it (dash_sharp: rotation at
the ticks 2.06x its snapshot bound, 1.73x with it); a higher cap makes that
rate noisy between flicks (the dash's ticks got worse above about 10).
Under both scales lie two floors from what a multirotor is (tilt_jerk_ms,
angular_accel_hold_ms): it accelerates by tilting its thrust, so its jerk is
about g x its tilt rate |w x z_body|, and the cameras see the tilt rate in the
attitude before the position shows the change. The NIS sees a lag only after
it has built up; the tilt rate says when the acceleration is changing and by
how much, so the position noise is high through a tilt and at its floor while
the tilt holds (the position at the output ticks: 1.23 -> 1.03x its bound on
dash_sharp). The angular acceleration of a multirotor comes in torque pulses
that end or reverse without warning, so the angular-jerk density is kept at
least |dw/dt|^2 / angular_accel_hold_s. With a floor on, the NIS-driven scale
evolves in its own column and the scale is the larger (the net for a body that
accelerates without tilting).
The adaptation's kernels are in adaptation.py.
The fused pose's NIS is computed with its covariance as the filter takes it,
split over the fusions that share its frames (about 0.28 per dof while the
model fits, so lags barely show); `nis_unsplit_cov` uses the pose's own
covariance for the adaptation's NIS instead. Both scales also
listen to an image-space detector (report_image_nis): each new frame's
markers predicted to its capture time against the blobs found. That view is
uncompensated, so motion compensation (which uses this filter's own velocity
and angular rate) cannot pull it towards the prediction and hide a lag the
way it can for the fused pose. Its residual is split: the markers' common
shift is a position lag and raises the position noise, their spread about it
is an orientation lag and raises the rotation noise. (Sending it all to the
position noise, as before issue 15, left the orientation of a drone flicking
its attitude at ~300 deg/s with its noise at the floor: its rate lagged by
radians per second and the 6-dof gate refused every measurement for 30-40 ms.)

The measurement is a 6-DoF pose [p, log(R_meas R_nom^T)] with a covariance
given by the caller (pipeline.py estimates it from the rigid-body fit).
Outliers are gated by the squared Mahalanobis distance of the innovation.

By default (fusion.single_view.mode always) a triangulated body is not updated
from its motion-compensated pose but from what each camera frame sees at its own
capture time (filter_update_view, below): compensating the frames' different
capture times with this filter's own rates carries the filter's rate error into
the pose (on the issue-15 flights that pose was ~1.2x its snapshot bound). The
triangulated pose still identifies the body, decides the gate (a pose outside it
means the prediction the views were labelled against is off: the pose path and
its retest decide instead) and drives the noise adaptation (pose_nis,
adapt_to_pose): its NIS separates position from rotation lag, which one view's
innovation cannot (driven by the views' own NIS, a still body needed a 200x
higher jerk floor, and lost its smoothing, for the flights' lags to show).
Through occlusion (the body cannot be triangulated) the measurement is likewise
what one camera frame sees (filter_update_view): the pixels of n of the
body's markers at the frame's capture time, h = lens(R_c X + t_c) with
X = p + exp(dtheta) R_nom l, linearised with the lens model's analytic
Jacobian (camera/lens.py) over position and rotation
error. The same linear filter and Joseph update do the rest, so the
covariance shows what one view cannot see (its depth).
"""

from __future__ import annotations

import math

import numpy as np

from visionpos.camera.lens import pixel_from_normalized, project_with_jacobian
from visionpos.fusion.adaptation import adapt_noise_scales
from visionpos.fusion.layout import (
    ACC0,
    ADAPT_NIS_SCALE_P,
    ADAPT_NIS_SCALE_R,
    ADAPT_SCALE_P,
    ADAPT_SCALE_R,
    ANG_ACC0,
    CAMERA_DIST,
    CAMERA_FISHEYE,
    CAMERA_INTRINSICS,
    CAMERA_R,
    CAMERA_T,
    CLOCK_FOLDS,
    CLOCK_IMG_T_NS,
    CLOCK_T_NS,
    KALMAN_ANG_ACC_PSD,
    KALMAN_ANG_JERK_PSD,
    KALMAN_GATE_CHI2,
    KALMAN_GATE_RETEST,
    KALMAN_INIT_ACC_VAR,
    KALMAN_INIT_ANG_ACC_VAR,
    KALMAN_INIT_RATE_VAR,
    KALMAN_INIT_VEL_VAR,
    KALMAN_JERK_PSD,
    KALMAN_MAX_SCALE,
    KALMAN_NIS_THRESHOLD,
    N_OUT,
    N_STATE,
    OUT_ACC,
    OUT_POS,
    OUT_POSE_COV0,
    OUT_QUAT0,
    OUT_RATE_BODY0,
    OUT_VEL,
    OUT_VEL_COV0,
    POS0,
    POSE_P,
    POSE_ROT,
    RATE0,
    ROT_ERR0,
    VEL0,
    X_ACC,
    X_ANG_ACC,
    X_POS,
    X_POSE,
    X_RATE,
    X_ROT_ERR,
    X_VEL,
)
from visionpos.geometry.rotations import (
    matrix_from_rotvec_compiled,
    quat_from_matrix_compiled,
    rotvec_from_matrix_compiled,
)
from visionpos.jit import matmul3, matvec3, njit


@njit
def white_jerk_coefficients(dt: float) -> np.ndarray:
    """Discrete covariance (3, 3) of (position, velocity, acceleration) on one axis per unit white-jerk density
    over t = |dt| s: [[t^5/20, t^4/8, t^3/6], [t^4/8, t^3/3, t^2/2], [t^3/6, t^2/2, t]]."""
    a = abs(dt)
    a2 = a * a
    a3, a4, a5 = a2 * a, a2 * a2, a2 * (a2 * a)
    return np.array([[a5 / 20.0, a4 / 8.0, a3 / 6.0], [a4 / 8.0, a3 / 3.0, a2 / 2.0], [a3 / 6.0, a2 / 2.0, a]])


@njit
def _add_process_noise(P: np.ndarray, dt: float, qj: float, qw: float, qaj: float) -> None:
    """P (18, 18) += discrete Q over |dt|: white jerk qj on (p, v, a); on the rotation white angular
    acceleration qw on (dtheta, w) plus white angular jerk qaj on (dtheta, w, dw/dt)."""
    a = abs(dt)
    a2, a3 = a * a, a * a * a
    c = white_jerk_coefficients(dt)
    for k in range(3):
        for i in range(3):
            for j in range(3):
                P[POS0 + i * 3 + k, POS0 + j * 3 + k] += c[i, j] * qj  # blocks p, v, a
                P[ROT_ERR0 + i * 3 + k, ROT_ERR0 + j * 3 + k] += c[i, j] * qaj  # blocks dtheta, w, dw/dt
        P[ROT_ERR0 + k, ROT_ERR0 + k] += qw * a3 / 3.0
        P[ROT_ERR0 + k, RATE0 + k] += qw * a2 / 2.0
        P[RATE0 + k, ROT_ERR0 + k] += qw * a2 / 2.0
        P[RATE0 + k, RATE0 + k] += qw * a


@njit
def _predicted_cov(P: np.ndarray, dt: float, qj: float, qw: float, qaj: float) -> np.ndarray:
    """F P F^T + Q (18, 18) over dt, with F's sparsity written out (an 18x18 product costs more)."""
    h = 0.5 * dt * dt
    FP = P.copy()
    for k in range(3):  # rows: F P
        for j in range(N_STATE):
            FP[POS0 + k, j] = P[POS0 + k, j] + dt * P[VEL0 + k, j] + h * P[ACC0 + k, j]
            FP[VEL0 + k, j] = P[VEL0 + k, j] + dt * P[ACC0 + k, j]
            FP[ROT_ERR0 + k, j] = P[ROT_ERR0 + k, j] + dt * P[RATE0 + k, j] + h * P[ANG_ACC0 + k, j]
            FP[RATE0 + k, j] = P[RATE0 + k, j] + dt * P[ANG_ACC0 + k, j]
    Pn = FP.copy()
    for k in range(3):  # columns: (F P) F^T
        for i in range(N_STATE):
            Pn[i, POS0 + k] = FP[i, POS0 + k] + dt * FP[i, VEL0 + k] + h * FP[i, ACC0 + k]
            Pn[i, VEL0 + k] = FP[i, VEL0 + k] + dt * FP[i, ACC0 + k]
            Pn[i, ROT_ERR0 + k] = FP[i, ROT_ERR0 + k] + dt * FP[i, RATE0 + k] + h * FP[i, ANG_ACC0 + k]
            Pn[i, RATE0 + k] = FP[i, RATE0 + k] + dt * FP[i, ANG_ACC0 + k]
    _add_process_noise(Pn, dt, qj, qw, qaj)
    return Pn


@njit
def _fold(x: np.ndarray, R_nom: np.ndarray) -> bool:
    """Move the rotation error x[X_ROT_ERR] into R_nom (in place) and zero it; False if it was zero."""
    if x[ROT_ERR0] == 0.0 and x[ROT_ERR0 + 1] == 0.0 and x[ROT_ERR0 + 2] == 0.0:
        return False
    R_nom[:, :] = matmul3(matrix_from_rotvec_compiled(x[X_ROT_ERR]), R_nom)
    x[X_ROT_ERR] = 0.0
    return True


@njit
def _kf_predict(x: np.ndarray, P: np.ndarray, R_nom: np.ndarray, dt: float, qj: float, qw: float,
                qaj: float) -> bool:
    """Advance state x (18,), covariance P (18, 18) and R_nom (3, 3) in place by dt; True if it folded."""
    for k in range(3):
        x[POS0 + k] += x[VEL0 + k] * dt + x[ACC0 + k] * (0.5 * dt * dt)
        x[VEL0 + k] += x[ACC0 + k] * dt
        x[ROT_ERR0 + k] += x[RATE0 + k] * dt + x[ANG_ACC0 + k] * (0.5 * dt * dt)
        x[RATE0 + k] += x[ANG_ACC0 + k] * dt
    P[:, :] = _predicted_cov(P, dt, qj, qw, qaj)
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
def _kalman_gain(PHt: np.ndarray, Sinv: np.ndarray) -> np.ndarray:
    """K = P H^T S^-1 (N_STATE, m) from P H^T (N_STATE, m) and S^-1 (m, m)."""
    m = Sinv.shape[0]
    K = np.zeros((N_STATE, m))
    for i in range(N_STATE):
        for c in range(m):
            acc = 0.0
            for a in range(m):
                acc += PHt[i, a] * Sinv[a, c]
            K[i, c] = acc
    return K


@njit
def _kf_update(
    x: np.ndarray,
    P: np.ndarray,
    R_nom: np.ndarray,
    position: np.ndarray,
    R: np.ndarray,
    cov: np.ndarray,
    gate_chi2: float,
    h_vel: float,
    h_acc: float,
    nis_cov_scale: float = 1.0,
) -> tuple[bool, float, float, float]:
    """Fuse a pose measurement into x (18,), P (18, 18), R_nom (3, 3) in place (Joseph form).

    position (3,), R (3, 3) body->world, cov (6, 6) over [p, world rotation
    vector]. gate_chi2 <= 0 disables the gate. h_vel (s), h_acc (s^2): how much
    of the velocity (and rate) and of the acceleration (and angular acceleration)
    error the measurement carries, the columns of H beside the pose's own (0, 0: a plain pose; see
    measurements._tracked_measurements: a motion-compensated one). nis_cov_scale: the NIS per block
    (not the gate's distance) is taken with cov times this (1 / reuse: the pose's own covariance,
    fusion.kalman.nis_unsplit_cov). Returns (accepted, squared Mahalanobis distance, position
    NIS / 3, rotation NIS / 3).
    """
    z = np.empty(6)
    z[POSE_P] = position
    z[POSE_ROT] = rotvec_from_matrix_compiled(matmul3(R, R_nom.T))
    # H row j: 1 at X_POSE[j], h_vel at the velocity (rate) column, h_acc at the (angular) acceleration one
    c_rate = np.empty(6, dtype=np.int64)
    c_acc = np.empty(6, dtype=np.int64)
    w_acc = np.empty(6)
    for k in range(3):
        c_rate[k], c_acc[k], w_acc[k] = VEL0 + k, ACC0 + k, h_acc
        c_rate[3 + k], c_acc[3 + k], w_acc[3 + k] = RATE0 + k, ANG_ACC0 + k, h_acc
    S = np.empty((6, 6))
    y = np.empty(6)
    PHt = np.empty((N_STATE, 6))  # P H^T
    for j in range(6):
        y[j] = z[j] - x[X_POSE[j]]  # the compensation already took H's other columns at the estimate
        for i in range(N_STATE):
            PHt[i, j] = P[i, X_POSE[j]] + h_vel * P[i, c_rate[j]] + w_acc[j] * P[i, c_acc[j]]
    for i in range(6):
        for j in range(6):
            S[i, j] = PHt[X_POSE[i], j] + h_vel * PHt[c_rate[i], j] + w_acc[i] * PHt[c_acc[i], j] + cov[i, j]
    Sinv = _spd_inverse(S)
    d2 = 0.0
    for i in range(6):
        for j in range(6):
            d2 += y[i] * Sinv[i, j] * y[j]
    if nis_cov_scale == 1.0:
        nis_p = _quad3(S[POSE_P, POSE_P], y[POSE_P]) / 3.0
        nis_r = _quad3(S[POSE_ROT, POSE_ROT], y[POSE_ROT]) / 3.0
    else:
        Sn = S - (1.0 - nis_cov_scale) * cov
        nis_p = _quad3(Sn[POSE_P, POSE_P], y[POSE_P]) / 3.0
        nis_r = _quad3(Sn[POSE_ROT, POSE_ROT], y[POSE_ROT]) / 3.0
    if gate_chi2 > 0.0 and d2 > gate_chi2:
        return False, d2, nis_p, nis_r
    K = _kalman_gain(PHt, Sinv)
    for i in range(N_STATE):
        for j in range(6):
            x[i] += K[i, j] * y[j]
    # Joseph form (I - K H) P (I - K H)^T + K C K^T
    HP = np.empty((6, N_STATE))
    for m in range(6):
        for j in range(N_STATE):
            HP[m, j] = P[X_POSE[m], j] + h_vel * P[c_rate[m], j] + w_acc[m] * P[c_acc[m], j]
    AP = P.copy()
    for i in range(N_STATE):
        for j in range(N_STATE):
            acc = 0.0
            for m in range(6):
                acc += K[i, m] * HP[m, j]
            AP[i, j] -= acc
    APHt = np.empty((N_STATE, 6))
    for i in range(N_STATE):
        for m in range(6):
            APHt[i, m] = AP[i, X_POSE[m]] + h_vel * AP[i, c_rate[m]] + w_acc[m] * AP[i, c_acc[m]]
    KC = np.zeros((N_STATE, 6))
    for i in range(N_STATE):
        for j in range(6):
            for m in range(6):
                KC[i, j] += K[i, m] * cov[m, j]
    for i in range(N_STATE):
        for j in range(N_STATE):
            acc = AP[i, j]
            for m in range(6):
                acc += -APHt[i, m] * K[j, m] + KC[i, m] * K[j, m]
            P[i, j] = acc
    for i in range(N_STATE):  # rounding leaves P a little asymmetric; left alone that grows
        for j in range(i):
            P[i, j] = P[j, i] = 0.5 * (P[i, j] + P[j, i])
    _fold(x, R_nom)
    return True, d2, nis_p, nis_r


@njit
def _kf_predict_update(x: np.ndarray, P: np.ndarray, R_nom: np.ndarray, dt: float, qj: float, qw: float, qaj: float,
                       position: np.ndarray, R: np.ndarray, cov: np.ndarray,
                       gate_chi2: float, h_vel: float, h_acc: float,
                       nis_cov_scale: float = 1.0) -> tuple[int, bool, float, float, float]:
    """_kf_predict over dt (when dt != 0) then _kf_update, in one call; returns
    (folds done, accepted, squared Mahalanobis distance, position NIS / 3, rotation NIS / 3)."""
    folds = 0
    if dt != 0.0 and _kf_predict(x, P, R_nom, dt, qj, qw, qaj):
        folds += 1
    accepted, d2, nis_p, nis_r = _kf_update(x, P, R_nom, position, R, cov, gate_chi2, h_vel, h_acc, nis_cov_scale)
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
    """The mean of state x (18,) with nominal rotation R_nom (3, 3) predicted by dt (s):
    position (3,), rotation body->world (3, 3), velocity (3,)."""
    p = x[X_POS] + x[X_VEL] * dt + x[X_ACC] * (0.5 * dt * dt)
    R = matmul3(matrix_from_rotvec_compiled(x[X_RATE] * dt + x[X_ANG_ACC] * (0.5 * dt * dt)), R_nom)
    return p, R, x[X_VEL] + x[X_ACC] * dt


@njit
def _output_at(x: np.ndarray, P: np.ndarray, R_nom: np.ndarray, dt: float, qj: float, qw: float,
               qaj: float) -> np.ndarray:
    """Prediction by dt for the outputs, packed in one array (N_OUT,) (columns OUT_*): position (3,),
    quaternion xyzw (4,), velocity (3,), body-frame angular rate (3,), pose covariance (6, 6) over
    [p, rotation vector], velocity covariance (3, 3), row-major, and world acceleration (3,) (see
    BodyFilter.output_at)."""
    Pn = _predicted_cov(P, dt, qj, qw, qaj)
    w = x[X_RATE] + x[X_ANG_ACC] * dt
    p, R, v = predict_mean(x, R_nom, dt)
    out = np.empty(N_OUT)
    out[OUT_POS] = p
    out[OUT_QUAT0], out[OUT_QUAT0 + 1], out[OUT_QUAT0 + 2], out[OUT_QUAT0 + 3] = quat_from_matrix_compiled(R)
    out[OUT_VEL] = v
    for i in range(3):
        out[OUT_RATE_BODY0 + i] = R[0, i] * w[0] + R[1, i] * w[1] + R[2, i] * w[2]
    for i in range(6):
        for j in range(6):
            out[OUT_POSE_COV0 + 6 * i + j] = Pn[X_POSE[i], X_POSE[j]]
    for i in range(3):
        for j in range(3):
            out[OUT_VEL_COV0 + 3 * i + j] = Pn[VEL0 + i, VEL0 + j]
    out[OUT_ACC] = x[X_ACC]  # the constant-acceleration model's: unchanged by the prediction
    return out


_ORTHO_EVERY = 256  # folds between re-orthonormalisations of R_nom


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
        clock[CLOCK_FOLDS] += 1
        if clock[CLOCK_FOLDS] % _ORTHO_EVERY == 0:  # keep R_nom orthonormal against round-off
            _orthonormalize(R_nom)


_RETEST_STEP = 10.0  # the manoeuvre hypotheses' process-noise scales grow by this factor ...
_RETEST_MAX_FACTOR = 1000.0  # ... up to this (10^4 would admit a 17 deg jump within 10 ms of a hover)


@njit
def _manoeuvre_retest(x: np.ndarray, P: np.ndarray, R_nom: np.ndarray, adapt: np.ndarray, params: np.ndarray,
                      dt: float, x0: np.ndarray, P0: np.ndarray, R0: np.ndarray, nis_p: float, nis_r: float,
                      position: np.ndarray, R: np.ndarray, cov: np.ndarray, h_vel: float, h_acc: float,
                      nis_cov_scale: float, folds: int) -> tuple[int, bool, float, float, float]:
    """A pose measurement the gate refused, tried again under manoeuvre hypotheses (fusion.kalman.gate_retest).

    x0, P0, R0: the state before the prediction over dt (s); x, P, R_nom hold the refused
    attempt; nis_p, nis_r its NIS per block. The process noise of the lagging block(s) (NIS
    above the threshold; both when neither is) is raised _RETEST_STEP, ... up to _RETEST_MAX_FACTOR
    times (and at most to max_noise_scale) over this prediction; the first hypothesis the gate admits is taken
    and its scales kept (the adaptation decays them from there). Why: a model that lags a
    sudden manoeuvre (a flick that ends while the angular acceleration is extrapolated) is
    refused by the gate, and a refused measurement leaves the prediction running away, so the
    NIS average alone takes tens of ms to reopen the gate. An outlier fits no hypothesis: then
    the state is the refused attempt's prediction, as without the retest.
    Returns _kf_predict_update's (folds, accepted, d2, position NIS / 3, rotation NIS / 3).
    """
    smax = params[KALMAN_MAX_SCALE]
    raise_p, raise_r = nis_p > params[KALMAN_NIS_THRESHOLD], nis_r > params[KALMAN_NIS_THRESHOLD]
    if not (raise_p or raise_r):
        raise_p = raise_r = True
    xr, Pr, Rr = x.copy(), P.copy(), R_nom.copy()
    factor = _RETEST_STEP
    while True:
        sp = min(adapt[ADAPT_SCALE_P] * factor, smax) if raise_p else adapt[ADAPT_SCALE_P]
        sr = min(adapt[ADAPT_SCALE_R] * factor, smax) if raise_r else adapt[ADAPT_SCALE_R]
        x[:] = x0
        P[:, :] = P0
        R_nom[:, :] = R0
        f, ok, d2, np_, nr = _kf_predict_update(x, P, R_nom, dt, params[KALMAN_JERK_PSD] * sp,
                                                params[KALMAN_ANG_ACC_PSD] * sr, params[KALMAN_ANG_JERK_PSD] * sr,
                                                position, R, cov, params[KALMAN_GATE_CHI2], h_vel, h_acc,
                                                nis_cov_scale)
        if ok:
            adapt[ADAPT_SCALE_P], adapt[ADAPT_SCALE_R] = sp, sr
            adapt[ADAPT_NIS_SCALE_P], adapt[ADAPT_NIS_SCALE_R] = sp, sr  # with a multirotor floor: its NIS part
            return f, ok, d2, np_, nr
        if factor >= _RETEST_MAX_FACTOR or ((not raise_p or sp >= smax) and (not raise_r or sr >= smax)):
            break
        factor *= _RETEST_STEP
    x[:] = xr
    P[:, :] = Pr
    R_nom[:, :] = Rr
    return folds, False, d2, nis_p, nis_r


@njit
def filter_update(x: np.ndarray, P: np.ndarray, R_nom: np.ndarray, adapt: np.ndarray, clock: np.ndarray,
                  params: np.ndarray, t_ns: int, position: np.ndarray, R: np.ndarray, cov: np.ndarray,
                  gate: bool, h_vel: float, h_acc: float, nis_cov_scale: float = 1.0) -> tuple[bool, float]:
    """Predict one body filter to t_ns (int ns) and fuse a pose measurement, in place (compiled).

    x (18,), P (18, 18), R_nom (3, 3), adapt (12,), clock (3,): the body's rows of a
    FilterBank; params (N_KALMAN_PARAMS,) its settings (FilterBank.params). position (3,), R (3, 3) body->world,
    cov (6, 6) over [p, world rotation vector]; gate: apply the innovation gate; h_vel (s),
    h_acc (s^2): the velocity (rate) and acceleration columns of H (_kf_update; 0 for a pose
    measured at t_ns); nis_cov_scale: as _kf_update.
    Returns (accepted, squared Mahalanobis distance); a gated measurement leaves
    the state predicted only (retried first under manoeuvre hypotheses when
    params say gate_retest: _manoeuvre_retest). Then adapts the process-noise scales to the NIS.
    """
    dt = (t_ns - clock[CLOCK_T_NS]) * 1e-9
    retest = gate and params[KALMAN_GATE_RETEST] != 0.0 and dt > 0.0
    if retest:
        x0, P0, R0 = x.copy(), P.copy(), R_nom.copy()
    folds, accepted, d2, nis_p, nis_r = _kf_predict_update(
        x, P, R_nom, dt,
        params[KALMAN_JERK_PSD] * adapt[ADAPT_SCALE_P], params[KALMAN_ANG_ACC_PSD] * adapt[ADAPT_SCALE_R],
        params[KALMAN_ANG_JERK_PSD] * adapt[ADAPT_SCALE_R],
        position, R, cov, params[KALMAN_GATE_CHI2] if gate else 0.0, h_vel, h_acc, nis_cov_scale,
    )
    if retest and not accepted:
        folds, accepted, d2, nis_p, nis_r = _manoeuvre_retest(x, P, R_nom, adapt, params, dt, x0, P0, R0, nis_p, nis_r,
                                                              position, R, cov, h_vel, h_acc, nis_cov_scale, folds)
    clock[CLOCK_T_NS] = t_ns
    _count_folds(R_nom, clock, folds)
    adapt_noise_scales(adapt, clock, params, t_ns, dt, nis_p, nis_r, True, x, P, R_nom)
    return accepted, d2


@njit
def pose_nis(x: np.ndarray, P: np.ndarray, R_nom: np.ndarray, adapt: np.ndarray, clock: np.ndarray,
             params: np.ndarray, t_ns: int, position: np.ndarray, R: np.ndarray, cov: np.ndarray, h_vel: float,
             h_acc: float, nis_cov_scale: float) -> tuple[float, float, float]:
    """A pose measurement (as filter_update takes it) against the filter predicted to t_ns: the squared
    Mahalanobis distance of its innovation and its NIS per dof per block (position, rotation); the
    filter is left as it is."""
    xc, Pc, Rc = x.copy(), P.copy(), R_nom.copy()
    dt = (t_ns - clock[CLOCK_T_NS]) * 1e-9
    # a gate no innovation passes: _kf_update returns after the NIS, before the update
    _, _, d2, nis_p, nis_r = _kf_predict_update(
        xc, Pc, Rc, dt, params[KALMAN_JERK_PSD] * adapt[ADAPT_SCALE_P],
        params[KALMAN_ANG_ACC_PSD] * adapt[ADAPT_SCALE_R], params[KALMAN_ANG_JERK_PSD] * adapt[ADAPT_SCALE_R],
        position, R, cov, 1e-300, h_vel, h_acc, nis_cov_scale)
    return d2, nis_p, nis_r


@njit
def filter_update_view(x: np.ndarray, P: np.ndarray, R_nom: np.ndarray, adapt: np.ndarray, clock: np.ndarray,
                       params: np.ndarray, t_ns: int, local: np.ndarray, obs_xn: np.ndarray, camera: np.ndarray,
                       var_px: float, gate_per_dof: float, adapt_noise: bool = True) -> tuple[bool, float, np.ndarray]:
    """Fuse what ONE camera frame sees of one body: the reprojection measurement (compiled).

    x, P, R_nom, adapt, clock, params: the body's FilterBank rows (as filter_update).
    t_ns: the frame's capture time; local (n, 3): body-frame markers it sees, obs_xn (n, 2)
    their undistorted normalised observations; camera (N_CAMERA,): packed as
    matching.Projector.packed; var_px: per-axis pixel noise variance (px^2); gate_per_dof:
    the squared Mahalanobis distance of the 2n-dof innovation may be at most 2n gate_per_dof.

    The measurement is the n pixels, h = lens(R_c (p + exp(dtheta) R_nom l) + t_c) predicted
    to t_ns, with its analytic Jacobian over the error state: position A, rotation error
    -A [R l]x, and (for a frame older than the filter, dt < 0) velocity A dt, acceleration
    A dt^2 / 2, angular rate -A [R l]x dt, angular acceleration -A [R l]x dt^2 / 2,
    A = d pixel / d world point. A newer frame
    predicts the filter to t_ns first. Joseph-form update; the NIS per dof drives the noise
    adaptation of both blocks (not the image-space detector: this innovation is one).
    Returns (accepted, NIS per dof, the frame's pose information H^T H / var_px (6, 6) over
    [p, rotation error]); a point behind the camera rejects it.
    """
    dt_f = (t_ns - clock[CLOCK_T_NS]) * 1e-9
    dt = 0.0  # capture time - filter time after the prediction
    if dt_f > 0.0:
        folded = _kf_predict(x, P, R_nom, dt_f, params[KALMAN_JERK_PSD] * adapt[ADAPT_SCALE_P],
                             params[KALMAN_ANG_ACC_PSD] * adapt[ADAPT_SCALE_R],
                             params[KALMAN_ANG_JERK_PSD] * adapt[ADAPT_SCALE_R])
        clock[CLOCK_T_NS] = t_ns
        _count_folds(R_nom, clock, int(folded))
    else:
        dt = dt_f
    p, Rb, _ = predict_mean(x, R_nom, dt)
    ok, y, H = _view_measurement(p, Rb, dt, local, obs_xn, camera)
    if not ok:
        return False, np.inf, np.zeros((6, 6))
    info = _pose_information(H, var_px)
    accepted, nis = _update_isotropic(x, P, H, y, var_px, gate_per_dof)
    if not accepted:
        return False, nis, info
    _count_folds(R_nom, clock, int(_fold(x, R_nom)))
    if adapt_noise:
        adapt_noise_scales(adapt, clock, params, t_ns, max(dt_f, 0.0), nis, nis, False, x, P, R_nom)
    return True, nis, info


@njit
def _view_measurement(p: np.ndarray, Rb: np.ndarray, dt: float, local: np.ndarray, obs_xn: np.ndarray,
                      camera: np.ndarray) -> tuple[bool, np.ndarray, np.ndarray]:
    """One frame's reprojection innovation y (2n,) px and its Jacobian H (2n, N_STATE) over the error state,
    for the body at p (3,) m, Rb (3, 3) predicted dt s from the filter's time (filter_update_view's docstring);
    False when a marker is behind the camera."""
    n = local.shape[0]
    m = 2 * n
    Rc, tc = camera[CAMERA_R].reshape((3, 3)), camera[CAMERA_T]
    intrinsics, dist, fisheye = camera[CAMERA_INTRINSICS], camera[CAMERA_DIST], camera[CAMERA_FISHEYE] != 0.0
    y = np.empty(m)
    H = np.zeros((m, N_STATE))
    for k in range(n):
        r = matvec3(Rb, local[k])  # lever arm, world
        Xc = matvec3(Rc, p + r) + tc
        if not Xc[2] > 1e-3:
            return False, y, H
        u, v, J = project_with_jacobian(Xc, intrinsics, dist, fisheye)
        uo, vo = pixel_from_normalized(obs_xn[k, 0], obs_xn[k, 1], intrinsics, dist, fisheye)
        y[2 * k], y[2 * k + 1] = uo - u, vo - v
        A = np.empty((2, 3))  # d pixel / d world point
        for i in range(2):
            for j in range(3):
                A[i, j] = J[i, 0] * Rc[0, j] + J[i, 1] * Rc[1, j] + J[i, 2] * Rc[2, j]
        for i in range(2):
            row = 2 * k + i
            # d X / d dtheta = -[r]x (X = p + exp(dtheta) r), so the rotation columns are -A [r]x
            ar0 = A[i, 2] * r[1] - A[i, 1] * r[2]
            ar1 = A[i, 0] * r[2] - A[i, 2] * r[0]
            ar2 = A[i, 1] * r[0] - A[i, 0] * r[1]
            for j in range(3):
                H[row, POS0 + j] = A[i, j]
                H[row, VEL0 + j] = A[i, j] * dt
                H[row, ACC0 + j] = A[i, j] * (0.5 * dt * dt)
            H[row, ROT_ERR0], H[row, ROT_ERR0 + 1], H[row, ROT_ERR0 + 2] = ar0, ar1, ar2
            H[row, RATE0], H[row, RATE0 + 1], H[row, RATE0 + 2] = ar0 * dt, ar1 * dt, ar2 * dt
            h = 0.5 * dt * dt
            H[row, ANG_ACC0], H[row, ANG_ACC0 + 1], H[row, ANG_ACC0 + 2] = ar0 * h, ar1 * h, ar2 * h
    return True, y, H


@njit
def _pose_information(H: np.ndarray, var_px: float) -> np.ndarray:
    """The measurement's information over [p, rotation error]: H_pose^T H_pose / var_px (6, 6)."""
    m = H.shape[0]
    info = np.zeros((6, 6))
    for i in range(6):
        for j in range(6):
            acc = 0.0
            for row in range(m):
                acc += H[row, X_POSE[i]] * H[row, X_POSE[j]]
            info[i, j] = acc / var_px
    return info


@njit
def _update_isotropic(x: np.ndarray, P: np.ndarray, H: np.ndarray, y: np.ndarray, var_px: float,
                      gate_per_dof: float) -> tuple[bool, float]:
    """Kalman update (in place, Joseph form) with innovation y (m,), Jacobian H (m, N_STATE) and noise var_px
    on every row; refused (x, P untouched) when the NIS per dof is over gate_per_dof or NaN. Returns
    (accepted, NIS per dof)."""
    m = H.shape[0]
    PHt = np.zeros((N_STATE, m))
    for i in range(N_STATE):
        for row in range(m):
            acc = 0.0
            for j in range(N_STATE):
                acc += P[i, j] * H[row, j]
            PHt[i, row] = acc
    S = np.empty((m, m))
    for a in range(m):
        for c in range(m):
            acc = 0.0
            for j in range(N_STATE):
                acc += H[a, j] * PHt[j, c]
            S[a, c] = acc
        S[a, a] += var_px
    Sinv = _spd_inverse(S)
    d2 = 0.0
    for a in range(m):
        for c in range(m):
            d2 += y[a] * Sinv[a, c] * y[c]
    nis = d2 / m
    if not nis <= gate_per_dof:  # NaN too
        return False, nis
    K = _kalman_gain(PHt, Sinv)
    for i in range(N_STATE):
        acc = 0.0
        for a in range(m):
            acc += K[i, a] * y[a]
        x[i] += acc
    # Joseph form (I - K H) P (I - K H)^T + var K K^T
    IKH = np.zeros((N_STATE, N_STATE))
    for i in range(N_STATE):
        IKH[i, i] = 1.0
        for j in range(N_STATE):
            acc = 0.0
            for a in range(m):
                acc += K[i, a] * H[a, j]
            IKH[i, j] -= acc
    AP = np.zeros((N_STATE, N_STATE))
    for i in range(N_STATE):
        for j in range(N_STATE):
            acc = 0.0
            for k in range(N_STATE):
                acc += IKH[i, k] * P[k, j]
            AP[i, j] = acc
    for i in range(N_STATE):
        for j in range(i + 1):
            acc = 0.0
            for k in range(N_STATE):
                acc += AP[i, k] * IKH[j, k]
            kk = 0.0
            for a in range(m):
                kk += K[i, a] * K[j, a]
            P[i, j] = P[j, i] = acc + var_px * kk
    return True, nis


@njit
def filter_initialize(x: np.ndarray, P: np.ndarray, R_nom: np.ndarray, adapt: np.ndarray, clock: np.ndarray,
                      params: np.ndarray, t_ns: int, position: np.ndarray, R: np.ndarray, cov: np.ndarray) -> None:
    """(Re)start one body filter (its FilterBank rows, params as in filter_update) at a
    measured pose: position (3,), R (3, 3) body->world with covariance cov (6, 6) over
    [p, world rotation vector] at t_ns; the derivatives are unknown: zero, with the prior
    variances of params. The noise scales and NIS averages start afresh."""
    x[:] = 0.0
    x[X_POS] = position
    P[:, :] = 0.0
    for i in range(6):
        for j in range(6):
            P[X_POSE[i], X_POSE[j]] = cov[i, j]
    for k in range(3):
        P[VEL0 + k, VEL0 + k] = params[KALMAN_INIT_VEL_VAR]
        P[ACC0 + k, ACC0 + k] = params[KALMAN_INIT_ACC_VAR]
        P[RATE0 + k, RATE0 + k] = params[KALMAN_INIT_RATE_VAR]
        P[ANG_ACC0 + k, ANG_ACC0 + k] = params[KALMAN_INIT_ANG_ACC_VAR]
    R_nom[:, :] = R
    adapt[:] = 1.0
    clock[CLOCK_T_NS] = t_ns
    clock[CLOCK_IMG_T_NS] = 0
