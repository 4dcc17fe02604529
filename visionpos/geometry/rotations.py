"""Rotation helpers: one home for rotation vectors, matrices, quaternions and ZYX Euler angles.

Conventions: quaternions are (x, y, z, w) (scipy's order), rotation vectors are
axis * angle in rad, a matrix R rotates column vectors (v' = R v). Names follow
`<to>_from_<from>`.

Two forms where the fusion hot path needs one: the `*_compiled` kernels take
float64 contiguous arrays and are called from compiled code (the Kalman
filter's fold, measurement and output steps); the plain-named wrappers accept
any array-like and call them. The rest is numpy for single rotations (the
MAVLink edge, bridge/convert.py) or batches (`skew`, `average_rotations`).
The 3-vector cross product is visionpos.jit.cross3, with the other compiled
3-vector building blocks.
"""

from __future__ import annotations

import math

import numpy as np

from visionpos.geometry.alignment import normalized_weights
from visionpos.jit import njit

__all__ = [
    "skew",
    "left_jacobian_SO3",
    "left_jacobian_SO3_inv",
    "matrix_from_rotvec_compiled",
    "quat_from_matrix_compiled",
    "rotvec_from_matrix_compiled",
    "matrix_from_rotvec",
    "rotvec_from_matrix",
    "quat_from_matrix",
    "matrix_from_quat",
    "quat_from_rotvec",
    "quat_multiply",
    "average_rotations",
    "euler_zyx_from_matrix",
    "euler_rate_matrix",
    "euler_rate_matrix_inverse",
]


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrix: skew(a) @ b == cross(a, b)."""
    v = np.asarray(v, dtype=np.float64)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1] = -v[..., 2]
    S[..., 0, 2] = v[..., 1]
    S[..., 1, 0] = v[..., 2]
    S[..., 1, 2] = -v[..., 0]
    S[..., 2, 0] = -v[..., 1]
    S[..., 2, 1] = v[..., 0]
    return S


SMALL_ANGLE_RAD = 1e-6  # below it the Jacobians' coefficients take their Taylor series (0/0 otherwise)


def left_jacobian_SO3(rotvec: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3): rotation vectors (..., 3) (rad) -> (..., 3, 3).

    exp(rotvec + d) ~= exp(J d) exp(rotvec) for a small d: how a change of the rotation vector
    turns the rotation on the left (in the fixed frame). J = I + (1 - cos t)/t^2 K + (t - sin t)/t^3 K^2
    with t = |rotvec|, K = skew(rotvec) (Barfoot, State Estimation for Robotics, eq. 7.77a).
    """
    rotvec = np.asarray(rotvec, dtype=np.float64)
    th = np.linalg.norm(rotvec, axis=-1)
    K = skew(rotvec)
    K2 = K @ K
    small = th < SMALL_ANGLE_RAD
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th**2 / 24, (1 - np.cos(ths)) / ths**2)
    b = np.where(small, 1.0 / 6 - th**2 / 120, (ths - np.sin(ths)) / ths**3)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * K2


def left_jacobian_SO3_inv(rotvec: np.ndarray) -> np.ndarray:
    """Inverse of left_jacobian_SO3: rotation vectors (..., 3) (rad, |rotvec| < 2 pi) -> (..., 3, 3).

    log(exp(d) exp(rotvec)) ~= rotvec + J^-1 d: J^-1 = I - K/2 + (1 - (t/2) cot(t/2))/t^2 K^2
    (Barfoot, eq. 7.77b), finite up to t = pi and beyond (its pole is at 2 pi).
    """
    rotvec = np.asarray(rotvec, dtype=np.float64)
    th = np.linalg.norm(rotvec, axis=-1)
    K = skew(rotvec)
    small = th < SMALL_ANGLE_RAD
    ths = np.where(small, 1.0, th)
    c = np.where(small, 1.0 / 12 + th**2 / 720, (1 - 0.5 * ths / np.tan(0.5 * ths)) / ths**2)
    return np.eye(3) - 0.5 * K + c[..., None, None] * (K @ K)


# --------------------------------------------------------------- compiled (hot path)
@njit
def matrix_from_rotvec_compiled(rv: np.ndarray) -> np.ndarray:
    """Compiled Rodrigues formula: rotation vector (3,) float64 (rad) -> matrix (3, 3)."""
    x, y, z = rv[0], rv[1], rv[2]
    th2 = x * x + y * y + z * z
    if th2 < 1e-16:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = math.sqrt(th2)
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    R = np.empty((3, 3))
    R[0, 0], R[0, 1], R[0, 2] = 1.0 - b * (y * y + z * z), -a * z + b * x * y, a * y + b * x * z
    R[1, 0], R[1, 1], R[1, 2] = a * z + b * x * y, 1.0 - b * (x * x + z * z), -a * x + b * y * z
    R[2, 0], R[2, 1], R[2, 2] = -a * y + b * x * z, a * x + b * y * z, 1.0 - b * (x * x + y * y)
    return R


@njit
def quat_from_matrix_compiled(R: np.ndarray) -> tuple[float, float, float, float]:
    """Compiled: rotation matrix (3, 3) float64 -> unit quaternion as a tuple (x, y, z, w), w >= 0
    (Shepperd's method)."""
    m00, m01, m02 = R[0, 0], R[0, 1], R[0, 2]
    m10, m11, m12 = R[1, 0], R[1, 1], R[1, 2]
    m20, m21, m22 = R[2, 0], R[2, 1], R[2, 2]
    tr = m00 + m11 + m22
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        qx, qy, qz, qw = (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s
    elif m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        qx, qy, qz, qw = 0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s
    elif m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        qx, qy, qz, qw = (m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        qx, qy, qz, qw = (m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s
    n = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if qw < 0.0:
        n = -n
    return qx / n, qy / n, qz / n, qw / n


@njit
def rotvec_from_matrix_compiled(R: np.ndarray) -> np.ndarray:
    """Compiled: rotation matrix (3, 3) float64 -> rotation vector (3,) (rad, angle <= pi)."""
    # through the unit quaternion: well conditioned at every angle, 180 deg included
    qx, qy, qz, qw = quat_from_matrix_compiled(R)
    n = math.sqrt(qx * qx + qy * qy + qz * qz)
    out = np.empty(3)
    # angle / sin(angle / 2) -> 2 as the angle -> 0
    k = 2.0 * math.atan2(n, qw) / n if n > 1e-300 else 2.0 / qw
    out[0], out[1], out[2] = k * qx, k * qy, k * qz
    return out


def matrix_from_rotvec(rv: np.ndarray) -> np.ndarray:
    """Rodrigues: one rotation vector (3,) (rad) -> matrix (3, 3)."""
    return matrix_from_rotvec_compiled(np.ascontiguousarray(rv, dtype=np.float64))


def rotvec_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> rotation vector (3,) (rad, angle <= pi)."""
    return rotvec_from_matrix_compiled(np.ascontiguousarray(R, dtype=np.float64))


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> quaternion (4,) x, y, z, w with w >= 0 (Shepperd's method)."""
    return np.array(quat_from_matrix_compiled(np.ascontiguousarray(R, dtype=np.float64)))


# ------------------------------------------------------------- numpy quaternions
def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """(4,) xyzw (any norm) -> (3, 3) rotation matrix."""
    x, y, z, w = q / np.sqrt(q @ q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def quat_from_rotvec(v: np.ndarray) -> np.ndarray:
    """(3,) rotation vector (rad) -> (4,) xyzw."""
    angle = float(np.sqrt(v @ v))
    if angle < 1e-12:
        return np.array([0.5 * v[0], 0.5 * v[1], 0.5 * v[2], 1.0])
    s = np.sin(0.5 * angle) / angle
    return np.array([v[0] * s, v[1] * s, v[2] * s, np.cos(0.5 * angle)])


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(4,) xyzw Hamilton product a * b (apply b, then a)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])


def average_rotations(Rs: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Chordal L2 mean of rotations (N, 3, 3) -> (3, 3): the proper rotation closest
    (Frobenius) to the weighted sum of the matrices."""
    Rs = np.asarray(Rs, dtype=np.float64).reshape(-1, 3, 3)
    w = normalized_weights(weights, len(Rs))
    M = np.einsum("n,nij->ij", w, Rs)
    U, _, Vt = np.linalg.svd(M)
    D = np.array([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return (U * D) @ Vt


# ------------------------------------------------------------ ZYX Euler angles
def euler_zyx_from_matrix(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 3) roll, pitch, yaw (rad) with R = Rz(yaw) Ry(pitch) Rx(roll)
    (aerospace ZYX; pitch in [-pi/2, pi/2])."""
    R = np.asarray(R, dtype=np.float64)
    pitch = -np.arcsin(np.clip(R[..., 2, 0], -1.0, 1.0))
    return np.stack([np.arctan2(R[..., 2, 1], R[..., 2, 2]), pitch, np.arctan2(R[..., 1, 0], R[..., 0, 0])], axis=-1)


def euler_rate_matrix(euler: np.ndarray) -> np.ndarray:
    """(3,) roll, pitch, yaw (ZYX) -> (3, 3) E with spatial angular rate w = E @ d(roll, pitch, yaw)/dt.

    R = Rz(yaw) Ry(pitch) Rx(roll): w = yaw' z + pitch' Rz y + roll' Rz Ry x.
    """
    roll, pitch, yaw = euler
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    col_roll = np.array([cy * cp, sy * cp, -sp])
    col_pitch = np.array([-sy, cy, 0.0])
    col_yaw = np.array([0.0, 0.0, 1.0])
    return np.stack([col_roll, col_pitch, col_yaw], axis=1)


def euler_rate_matrix_inverse(euler: np.ndarray) -> np.ndarray:
    """(3,) roll, pitch, yaw -> (3, 3) inverse of euler_rate_matrix (closed form; pitch kept off +-90 deg)."""
    _, pitch, yaw = euler
    cy, sy, sp = np.cos(yaw), np.sin(yaw), np.sin(pitch)
    cp = np.cos(pitch)
    cp = np.copysign(max(abs(cp), 1e-9), cp)
    return np.array([[cy / cp, sy / cp, 0.0], [-sy, cy, 0.0], [sp * cy / cp, sp * sy / cp, 1.0]])
