"""Frames at the MAVLink edge: world z-up <-> NED, body FLU <-> FRD, and attitudes between them.

visionpos works in a z-up world (x, y, z) with bodies in FLU (x forward, y
left, z up); autopilots want NED and FRD. Both turns are the same half turn
about x (diag(1, -1, -1)), so vectors flip two signs, rotations are conjugated
(F R F) and quaternions flip (qx, qy, qz, qw) -> (qx, -qy, -qz, qw). The
arena's heading enters as a yaw about NED down (`yaw_matrix_ned`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos.geometry.rotations import euler_zyx_from_matrix

GRAVITY_M_S2 = 9.80665  # standard gravity; the world's z axis points up, against it

__all__ = [
    "FLU_FRD",
    "world_to_ned",
    "ned_to_world",
    "flu_to_frd",
    "frd_to_flu",
    "quat_world_body_to_ned_frd",
    "quat_ned_frd_to_world_body",
    "rotation_world_body_to_ned_frd",
    "euler_ned_frd",
    "yaw_matrix_ned",
]

FLU_FRD = np.diag([1.0, -1.0, -1.0])
"""Matrix taking body FLU (x forward, y left, z up) to FRD, and world z-up (x, y, z) to
NED (N = x, E = -y, D = -z): a 180 deg turn about x; it is its own inverse."""

_FLIP = np.array([1.0, -1.0, -1.0])


def world_to_ned(v: np.ndarray) -> np.ndarray:
    """World z-up vectors (..., 3) -> NED (N = x, E = -y, D = -z)."""
    return np.asarray(v, dtype=np.float64) * _FLIP


def ned_to_world(v: np.ndarray) -> np.ndarray:
    """NED vectors (..., 3) -> world z-up."""
    return np.asarray(v, dtype=np.float64) * _FLIP


def flu_to_frd(v: np.ndarray) -> np.ndarray:
    """Body FLU vectors (..., 3) -> FRD."""
    return np.asarray(v, dtype=np.float64) * _FLIP


def frd_to_flu(v: np.ndarray) -> np.ndarray:
    """Body FRD vectors (..., 3) -> FLU."""
    return np.asarray(v, dtype=np.float64) * _FLIP


def quat_world_body_to_ned_frd(q: np.ndarray) -> np.ndarray:
    """(..., 4) xyzw rotation body FLU -> world z-up  ->  (..., 4) xyzw rotation body FRD -> NED.

    R_ned_frd = F R_world_flu F with F = diag(1, -1, -1) (180 deg about x). Conjugating a
    rotation by a half turn about x maps its axis (ax, ay, az) to (ax, -ay, -az), so the
    quaternion becomes (qx, -qy, -qz, qw). Sign is normalised to qw >= 0.
    """
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1] != 4:
        raise ValueError(f"quaternion must have shape (..., 4) xyzw, got {q.shape}")
    out = q * np.array([1.0, -1.0, -1.0, 1.0])
    out = out / np.linalg.norm(out, axis=-1, keepdims=True)
    return np.where(out[..., 3:4] < 0, -out, out)


def quat_ned_frd_to_world_body(q: np.ndarray) -> np.ndarray:
    """Inverse of quat_world_body_to_ned_frd (the same conjugation)."""
    return quat_world_body_to_ned_frd(q)


def rotation_world_body_to_ned_frd(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) body FLU -> world matrix  ->  body FRD -> NED matrix (F R F)."""
    return FLU_FRD @ np.asarray(R, dtype=np.float64) @ FLU_FRD


def euler_ned_frd(q_world_flu: np.ndarray) -> np.ndarray:
    """(..., 4) xyzw body FLU -> world  ->  (..., 3) roll, pitch, yaw (rad) of FRD in NED
    (aerospace ZYX), as an autopilot reports them."""
    q = quat_world_body_to_ned_frd(q_world_flu)
    R = Rotation.from_quat(q.reshape(-1, 4)).as_matrix()
    return euler_zyx_from_matrix(R).reshape(q.shape[:-1] + (3,))


def yaw_matrix_ned(yaw_offset_rad: float) -> np.ndarray:
    """(3, 3) rotation about NED down by yaw_offset (clockwise seen from above)."""
    c, s = np.cos(yaw_offset_rad), np.sin(yaw_offset_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
