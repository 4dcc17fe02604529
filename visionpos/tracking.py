"""Kalman filter/predictor for one rigid body (filterpy), error-state in orientation.

State (12,): [p (3) m, v (3) m/s, dtheta (3) rad, w (3) rad/s], world frame.
Position/velocity is a constant-velocity model driven by white acceleration
noise; orientation is a *multiplicative* error state: a nominal rotation
R_nom (body->world) plus a small world-frame rotation-vector error dtheta,
driven by a constant angular rate w with white angular-acceleration noise.

Why error-state: a rotation has 3 degrees of freedom but no global minimal
parameterisation without singularities; keeping the nominal rotation outside
the linear filter and estimating only a small error keeps the filter linear
(so filterpy's plain KalmanFilter does the work) and singularity-free. After
every predict/update the error is folded into the nominal rotation and reset
to zero ("reset step"), so dtheta always stays small.

Prediction: filterpy's x = F x makes dtheta = w dt, which the fold then turns
into R_nom <- exp(w dt) R_nom; one mechanism for both update and predict.

The measurement is a 6-DoF pose [p, log(R_meas R_nom^T)] with covariance
from config, scaled by the caller (see pipeline.py: frames reused in
several fusions share their information). Outliers are gated by the squared
Mahalanobis distance of the innovation against a chi-square threshold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from filterpy.kalman import KalmanFilter

# state layout
P_, V_, TH_, W_ = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)
_POSE_IDX = np.array([0, 1, 2, 6, 7, 8])


def rotvec_to_matrix(rv: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vectors (..., 3) -> matrices (..., 3, 3)."""
    rv = np.asarray(rv, dtype=np.float64)
    th = np.linalg.norm(rv, axis=-1)[..., None, None]
    K = skew(rv)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    return np.eye(3) + a * K + b * (K @ K)


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> rotation vector (3,) (angle < pi)."""
    c = np.clip((np.trace(R) - 1.0) * 0.5, -1.0, 1.0)
    th = np.arccos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-6:
        return 0.5 * w
    if th > np.pi - 1e-4:  # near 180 deg: the antisymmetric part vanishes; use the symmetric part
        from scipy.spatial.transform import Rotation

        return Rotation.from_matrix(R).as_rotvec()
    return w * (th / (2.0 * np.sin(th)))


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


@dataclass(frozen=True)
class KalmanSettings:
    """Noise and gating of the body filter (SI units).

    accel_psd: white-acceleration spectral density q_a (m^2/s^3).
    angular_accel_psd: white angular-acceleration spectral density (rad^2/s^3).
    position_sigma: std of one fused position measurement (m).
    rotation_sigma: std of one fused orientation measurement (rad).
    gate_chi2: squared-Mahalanobis threshold of the 6-dof innovation.
    init_velocity_sigma / init_angular_velocity_sigma: prior std at (re)initialisation.
    """

    accel_psd: float = 30.0
    angular_accel_psd: float = 300.0
    position_sigma: float = 0.0005
    rotation_sigma: float = 0.004
    gate_chi2: float = 30.0
    init_velocity_sigma: float = 2.0
    init_angular_velocity_sigma: float = 6.0


def _transition(dt: float) -> np.ndarray:
    F = np.eye(12)
    F[0:3, 3:6] = np.eye(3) * dt
    F[6:9, 9:12] = np.eye(3) * dt
    return F


def _process_noise(dt: float, qa: float, qw: float) -> np.ndarray:
    """Discrete white-noise-acceleration Q for |dt| (both blocks)."""
    a = abs(dt)
    blk = np.array([[a**3 / 3.0, a**2 / 2.0], [a**2 / 2.0, a]])
    Q = np.zeros((12, 12))
    for axis in range(3):
        i, j = axis, 3 + axis
        Q[np.ix_([i, j], [i, j])] = blk * qa
        i, j = 6 + axis, 9 + axis
        Q[np.ix_([i, j], [i, j])] = blk * qw
    return Q


class BodyFilter:
    """Error-state Kalman filter of one body; times are int64 ns (capture clock).

    Wraps filterpy.kalman.KalmanFilter (dim_x=12, dim_z=6) plus the nominal
    rotation R_nom (3, 3) body->world.
    """

    def __init__(self, settings: KalmanSettings):
        self.s = settings
        self.kf = KalmanFilter(dim_x=12, dim_z=6)
        H = np.zeros((6, 12))
        H[0:3, 0:3] = np.eye(3)
        H[3:6, 6:9] = np.eye(3)
        self.kf.H = H
        self.R_nom = np.eye(3)
        self.t_ns = 0
        self.initialized = False
        self._R0 = np.diag([settings.position_sigma**2] * 3 + [settings.rotation_sigma**2] * 3)

    # -------------------------------------------------------------- lifecycle
    def initialize(self, t_ns: int, position: np.ndarray, R: np.ndarray, velocity: np.ndarray | None = None) -> None:
        """Start (or restart) at a measured pose; velocities unknown unless given."""
        x = np.zeros((12, 1))
        x[0:3, 0] = position
        if velocity is not None:
            x[3:6, 0] = velocity
        self.kf.x = x
        s = self.s
        self.kf.P = np.diag(
            [s.position_sigma**2] * 3
            + [s.init_velocity_sigma**2] * 3
            + [s.rotation_sigma**2] * 3
            + [s.init_angular_velocity_sigma**2] * 3
        )
        self.R_nom = np.array(R, dtype=np.float64)
        self.t_ns = int(t_ns)
        self.initialized = True

    def _fold(self) -> None:
        """Move the rotation error into the nominal rotation and zero it."""
        th = self.kf.x[6:9, 0]
        if th.any():
            self.R_nom = rotvec_to_matrix(th) @ self.R_nom
            # re-orthonormalise occasionally-accumulated round-off
            u, _, vt = np.linalg.svd(self.R_nom)
            self.R_nom = u @ vt
            self.kf.x[6:9, 0] = 0.0

    def predict_to(self, t_ns: int) -> None:
        """Advance the filter (mutating) to t_ns; backwards steps are allowed for small reorderings."""
        dt = (int(t_ns) - self.t_ns) * 1e-9
        if dt != 0.0:
            self.kf.predict(F=_transition(dt), Q=_process_noise(dt, self.s.accel_psd, self.s.angular_accel_psd))
            self._fold()
            self.t_ns = int(t_ns)

    # ------------------------------------------------------------ measurement
    def innovation(self, position: np.ndarray, R: np.ndarray, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray, float]:
        """Innovation z (6,), measurement covariance (6, 6) and squared Mahalanobis distance."""
        z = np.empty(6)
        z[0:3] = position
        z[3:6] = matrix_to_rotvec(np.asarray(R) @ self.R_nom.T)
        Rm = self._R0 * scale
        S = self.kf.P[np.ix_(_POSE_IDX, _POSE_IDX)] + Rm
        y = z - self.kf.x[_POSE_IDX, 0]
        d2 = float(y @ np.linalg.solve(S, y))
        return z, Rm, d2

    def update(self, t_ns: int, position: np.ndarray, R: np.ndarray, scale: float = 1.0, gate: bool = True) -> tuple[bool, float]:
        """Predict to t_ns and fuse a pose measurement (position (3,), R (3, 3) body->world).

        scale multiplies the configured measurement covariance. Returns
        (accepted, squared Mahalanobis distance); a gated measurement leaves
        the state predicted but not updated.
        """
        self.predict_to(t_ns)
        z, Rm, d2 = self.innovation(position, R, scale)
        if gate and d2 > self.s.gate_chi2:
            return False, d2
        self.kf.update(z.reshape(6, 1), R=Rm)
        self._fold()
        return True, d2

    # -------------------------------------------------------------- read-outs
    def pose_at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Non-mutating mean prediction: position (3,), R (3, 3), velocity (3,), world angular rate (3,)."""
        dt = (int(t_ns) - self.t_ns) * 1e-9
        x = self.kf.x[:, 0]
        w = x[9:12]
        return x[0:3] + x[3:6] * dt, rotvec_to_matrix(w * dt) @ self.R_nom, x[3:6].copy(), w.copy()

    def state_at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Non-mutating prediction with covariance.

        Returns position (3,), R (3, 3), velocity (3,), world angular rate (3,),
        covariance P (12, 12) of the error state at t_ns.
        """
        dt = (int(t_ns) - self.t_ns) * 1e-9
        F = _transition(dt)
        P = F @ self.kf.P @ F.T + _process_noise(dt, self.s.accel_psd, self.s.angular_accel_psd)
        p, R, v, w = self.pose_at(t_ns)
        return p, R, v, w, P

    @property
    def position(self) -> np.ndarray:
        return self.kf.x[0:3, 0].copy()

    @property
    def velocity(self) -> np.ndarray:
        return self.kf.x[3:6, 0].copy()

    @property
    def angular_velocity(self) -> np.ndarray:
        """World-frame angular rate (3,) rad/s."""
        return self.kf.x[9:12, 0].copy()


def pose_covariance(P: np.ndarray) -> np.ndarray:
    """(12, 12) filter covariance -> (6, 6) over [x, y, z, rx, ry, rz]."""
    return P[np.ix_(_POSE_IDX, _POSE_IDX)].copy()
