"""Kalman filter/predictor for one rigid body (filterpy), error-state in orientation.

State (15,): [p (3) m, v (3) m/s, a (3) m/s^2, dtheta (3) rad, w (3) rad/s],
world frame. Position is a constant-acceleration model driven by white jerk;
orientation is a *multiplicative* error state: a nominal rotation R_nom
(body->world) plus a small world-frame rotation-vector error dtheta, driven
by a constant angular rate w with white angular-acceleration noise.

Why error-state: a rotation has 3 degrees of freedom but no global minimal
parameterisation without singularities; keeping the nominal rotation outside
the linear filter and estimating only a small error keeps the filter linear
(filterpy's plain KalmanFilter does the work) and singularity-free. After
every predict/update the error is folded into the nominal rotation and reset
to zero, so dtheta always stays small. Prediction uses the same mechanism:
filterpy's x = F x makes dtheta = w dt, which the fold turns into
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
from filterpy.kalman import KalmanFilter

NX = 15
_POSE_IDX = np.array([0, 1, 2, 9, 10, 11])
_H = np.zeros((6, NX))
_H[0:3, 0:3] = np.eye(3)
_H[3:6, 9:12] = np.eye(3)
_POSE_IX = np.ix_(_POSE_IDX, _POSE_IDX)
_I3 = np.eye(3)
_NIS_HIGH = 2.0  # averaged NIS/dof above this means the motion model lags
_SCALE_DECAY_S = 0.2  # s, time constant of the process-noise scale's return to its floor


def rotvec_to_matrix(rv: np.ndarray) -> np.ndarray:
    """Rodrigues: one rotation vector (3,) -> matrix (3, 3)."""
    x, y, z = float(rv[0]), float(rv[1]), float(rv[2])
    th2 = x * x + y * y + z * z
    if th2 < 1e-16:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = math.sqrt(th2)
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    return np.array(
        [
            [1.0 - b * (y * y + z * z), -a * z + b * x * y, a * y + b * x * z],
            [a * z + b * x * y, 1.0 - b * (x * x + z * z), -a * x + b * y * z],
            [-a * y + b * x * z, a * x + b * y * z, 1.0 - b * (x * x + y * y)],
        ]
    )


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> rotation vector (3,) (angle < pi)."""
    c = min(1.0, max(-1.0, (R[0, 0] + R[1, 1] + R[2, 2] - 1.0) * 0.5))
    th = math.acos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-6:
        return 0.5 * w
    if th > math.pi - 1e-4:  # near 180 deg the antisymmetric part vanishes; use the symmetric part
        from scipy.spatial.transform import Rotation

        return Rotation.from_matrix(R).as_rotvec()
    return w * (th / (2.0 * math.sin(th)))


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> quaternion (4,) x, y, z, w with w >= 0 (Shepperd's method)."""
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = R.tolist()
    tr = m00 + m11 + m22
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s]
    elif m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        q = [0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s]
    elif m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        q = [(m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        q = [(m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s]
    out = np.array(q)
    out /= np.linalg.norm(out)
    return -out if out[3] < 0 else out


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


_F_DT = tuple(np.array(ix) for ix in zip(*[(k, 3 + k) for k in range(3)] + [(3 + k, 6 + k) for k in range(3)] + [(9 + k, 12 + k) for k in range(3)]))
_F_DT2 = tuple(np.array(ix) for ix in zip(*[(k, 6 + k) for k in range(3)]))


def _transition(dt: float) -> np.ndarray:
    """(15, 15) constant-acceleration / constant-rate transition over dt (s)."""
    F = np.eye(NX)
    F[_F_DT] = dt
    F[_F_DT2] = 0.5 * dt * dt
    return F


def _quad3(S: np.ndarray, y: np.ndarray) -> float:
    """y^T S^-1 y for a symmetric positive-definite 3x3 S (adjugate; cheaper than a LAPACK call)."""
    (a, b, c), (_, d, e), (_, _, f) = S.tolist()
    y0, y1, y2 = y.tolist()
    A00, A01, A02 = d * f - e * e, c * e - b * f, b * e - c * d
    A11, A12, A22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A00 + b * A01 + c * A02
    return (A00 * y0 * y0 + A11 * y1 * y1 + A22 * y2 * y2 + 2.0 * (A01 * y0 * y1 + A02 * y0 * y2 + A12 * y1 * y2)) / det


def _q_index() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flat indices of Q's nonzero entries and which coefficient each takes."""
    flat, coef = [], []
    for d1 in range(3):  # p, v, a blocks (white jerk)
        for d2 in range(3):
            for k in range(3):
                flat.append((d1 * 3 + k) * NX + d2 * 3 + k)
                coef.append(d1 * 3 + d2)
    for d1 in range(2):  # dtheta, w blocks (white angular acceleration)
        for d2 in range(2):
            for k in range(3):
                flat.append((9 + d1 * 3 + k) * NX + 9 + d2 * 3 + k)
                coef.append(9 + d1 * 2 + d2)
    return np.array(flat), np.array(coef), np.zeros(NX * NX)


_Q_FLAT, _Q_COEF, _Q_ZERO = _q_index()


def _process_noise(dt: float, qj: float, qw: float) -> np.ndarray:
    """Discrete Q (15, 15) for |dt|: white jerk on (p, v, a), white angular acceleration on (dtheta, w)."""
    a = abs(dt)
    a2, a3 = a * a, a * a * a
    a4, a5 = a2 * a2, a2 * a3
    c = np.array(
        [
            qj * a5 / 20.0, qj * a4 / 8.0, qj * a3 / 6.0,
            qj * a4 / 8.0, qj * a3 / 3.0, qj * a2 / 2.0,
            qj * a3 / 6.0, qj * a2 / 2.0, qj * a,
            qw * a3 / 3.0, qw * a2 / 2.0, qw * a2 / 2.0, qw * a,
        ]
    )  # fmt: skip
    Q = _Q_ZERO.copy()
    Q[_Q_FLAT] = c[_Q_COEF]
    return Q.reshape(NX, NX)


class BodyFilter:
    """Error-state Kalman filter of one body; times are int64 ns (capture clock).

    Wraps filterpy.kalman.KalmanFilter (dim_x=15, dim_z=6) plus the nominal
    rotation R_nom (3, 3) body->world and the NIS-driven noise scales.
    """

    def __init__(self, settings: KalmanSettings):
        self.s = settings
        self.kf = KalmanFilter(dim_x=NX, dim_z=6)
        self.kf.H = _H.copy()
        self.R_nom = np.eye(3)
        self.t_ns = 0
        self.initialized = False
        self.scale_p = 1.0
        self.scale_r = 1.0
        self._nis_p = 1.0
        self._nis_r = 1.0
        self._nis_img = 1.0
        self._img_ns = 0
        self._folds = 0

    # -------------------------------------------------------------- lifecycle
    def initialize(self, t_ns: int, position: np.ndarray, R: np.ndarray, meas_cov: np.ndarray | None = None) -> None:
        """Start (or restart) at a measured pose; derivatives unknown (zero with a wide prior)."""
        x = np.zeros((NX, 1))
        x[0:3, 0] = position
        self.kf.x = x
        s = self.s
        P = np.zeros((NX, NX))
        if meas_cov is not None:
            P[_POSE_IX] = meas_cov
        else:
            P[0:3, 0:3] = np.eye(3) * 1e-6
            P[9:12, 9:12] = np.eye(3) * 1e-4
        P[3:6, 3:6] = np.eye(3) * s.init_velocity_sigma**2
        P[6:9, 6:9] = np.eye(3) * s.init_acceleration_sigma**2
        P[12:15, 12:15] = np.eye(3) * s.init_angular_velocity_sigma**2
        self.kf.P = P
        self.R_nom = np.array(R, dtype=np.float64)
        self.t_ns = int(t_ns)
        self.initialized = True
        self.scale_p = self.scale_r = 1.0
        self._nis_p = self._nis_r = self._nis_img = 1.0
        self._img_ns = 0

    def _fold(self) -> None:
        """Move the rotation error into the nominal rotation and zero it."""
        th = self.kf.x[9:12, 0]
        if th.any():
            self.R_nom = rotvec_to_matrix(th) @ self.R_nom
            self.kf.x[9:12, 0] = 0.0
            self._folds += 1
            if self._folds % 256 == 0:  # keep R_nom orthonormal against round-off
                u, _, vt = np.linalg.svd(self.R_nom)
                self.R_nom = u @ vt

    def _Q(self, dt: float) -> np.ndarray:
        return _process_noise(dt, self.s.jerk_psd * self.scale_p, self.s.angular_accel_psd * self.scale_r)

    def predict_to(self, t_ns: int) -> None:
        """Advance the filter (mutating) to t_ns; small backward steps are allowed."""
        dt = (int(t_ns) - self.t_ns) * 1e-9
        if dt != 0.0:
            self.kf.predict(F=_transition(dt), Q=self._Q(dt))
            self._fold()
            self.t_ns = int(t_ns)

    @staticmethod
    def _adapt(scale: float, nis: float, alpha: float, decay: float, smax: float) -> float:
        if nis > _NIS_HIGH:
            scale *= (nis / _NIS_HIGH) ** (3.0 * alpha)
        else:
            scale *= decay
        return min(smax, max(1.0, scale))

    # ------------------------------------------------------------ measurement
    def update(self, t_ns: int, position: np.ndarray, R: np.ndarray, meas_cov: np.ndarray, gate: bool = True) -> tuple[bool, float]:
        """Predict to t_ns and fuse a pose measurement.

        position (3,), R (3, 3) body->world, meas_cov (6, 6) over
        [p, world rotation vector]. Returns (accepted, squared Mahalanobis
        distance); a gated measurement leaves the state predicted only.
        """
        dt = (int(t_ns) - self.t_ns) * 1e-9
        self.predict_to(t_ns)
        z = np.empty(6)
        z[0:3] = position
        z[3:6] = matrix_to_rotvec(np.asarray(R) @ self.R_nom.T)
        S = self.kf.P[_POSE_IX] + meas_cov
        y = z - self.kf.x[_POSE_IDX, 0]
        d2 = float(y @ np.linalg.solve(S, y))
        # NIS per block drives the process-noise scale (gated ones too, capped,
        # so that a manoeuvre that starts outside the gate still opens it)
        nis_p = _quad3(S[0:3, 0:3], y[0:3]) / 3.0
        nis_r = _quad3(S[3:6, 3:6], y[3:6]) / 3.0
        cap = self.s.gate_chi2 / 3.0
        alpha = 1.0 - math.exp(-max(dt, 0.0) / self.s.nis_time_constant) if dt > 0 else 0.05
        self._nis_p += alpha * (min(nis_p, cap) - self._nis_p)
        self._nis_r += alpha * (min(nis_r, cap) - self._nis_r)
        # the image-space detector (report_image_nis) sees lag the fused pose can hide
        nis_img = self._nis_img if self.t_ns - self._img_ns < 50_000_000 else 0.0
        smax = self.s.max_noise_scale
        # NIS/dof ~ 1 says nothing about q while the measurement noise dominates the
        # innovation (a hovering body), so only a clear excess (> _NIS_HIGH) raises q:
        # innovations k x too big -> q x k^3 per averaging time (CA/CV scaling laws);
        # otherwise q decays back to its floor
        decay = math.exp(-max(dt, 0.0) / _SCALE_DECAY_S)
        self.scale_p = self._adapt(self.scale_p, max(self._nis_p, nis_img), alpha, decay, smax)
        self.scale_r = self._adapt(self.scale_r, self._nis_r, alpha, decay, smax)
        if gate and d2 > self.s.gate_chi2:
            return False, d2
        self.kf.update(z.reshape(6, 1), R=meas_cov)
        self._fold()
        return True, d2

    def report_image_nis(self, t_ns: int, nis: float) -> None:
        """Feed the manoeuvre detector with one camera frame's prediction residual.

        nis: mean squared pixel distance between the markers predicted to the
        frame's capture time and the blobs associated with them, over its
        expected value, per degree of freedom (~1 while the model fits). It
        comes from a single uncompensated view, so unlike the fused pose it
        cannot be pulled towards the prediction by motion compensation.
        """
        dt = max((int(t_ns) - self._img_ns) * 1e-9, 0.0)
        alpha = 1.0 - math.exp(-dt / self.s.nis_time_constant) if self._img_ns else 1.0
        self._nis_img += alpha * (min(nis, self.s.gate_chi2 / 3.0) - self._nis_img)
        self._img_ns = int(t_ns)

    # -------------------------------------------------------------- read-outs
    def pose_at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Non-mutating mean prediction: position (3,), R (3, 3), velocity (3,), world angular rate (3,)."""
        dt = (int(t_ns) - self.t_ns) * 1e-9
        x = self.kf.x[:, 0]
        w = x[12:15]
        p = x[0:3] + x[3:6] * dt + x[6:9] * (0.5 * dt * dt)
        return p, rotvec_to_matrix(w * dt) @ self.R_nom, x[3:6] + x[6:9] * dt, w.copy()

    def state_at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Non-mutating prediction with covariance.

        Returns position (3,), R (3, 3), velocity (3,), world angular rate
        (3,), covariance P (15, 15) of the error state at t_ns.
        """
        dt = (int(t_ns) - self.t_ns) * 1e-9
        F = _transition(dt)
        P = F @ self.kf.P @ F.T + self._Q(dt)
        p, R, v, w = self.pose_at(t_ns)
        return p, R, v, w, P


def pose_covariance(P: np.ndarray) -> np.ndarray:
    """(15, 15) filter covariance -> (6, 6) over [x, y, z, rx, ry, rz]."""
    return P[_POSE_IX].copy()


def velocity_covariance(P: np.ndarray) -> np.ndarray:
    """(15, 15) filter covariance -> (3, 3) velocity block."""
    return P[3:6, 3:6].copy()
