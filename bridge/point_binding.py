"""The binding costs of single-marker (point) bodies: accelerations only, without yaw. Pure numpy, no I/O.

A point body has no optical attitude and no body rates, so the fleet binding (fleet_binding.py) cannot compare
them with the autopilots'. What it can compare is the acceleration: the optical track's (the second difference
of its positions) against the IMU's specific force. The IMU's is in the body frame, and the optical one in the
world; the vehicle's own roll and pitch (its ATTITUDE, in the back-channel) turn the IMU's into the level frame,
and without a yaw shared by both (the autopilot's heading comes from its compass or GSF, not from us) two
quantities are free of the heading: the vertical specific force and the horizontal acceleration's magnitude.
Both sides are sampled on the same grid and low-passed alike (the fleet binding's ACCEL_LOWPASS_S), compared
every ACCEL_EVERY instants with the same noise model and bias prior (accel_residuals: 2 residuals per instant
instead of 3).
"""

from __future__ import annotations

import numpy as np

from bridge.telemetry import sample_at
from visionpos.analysis.autopilot import accel_residuals, gaussian_kernel, lowpass
from visionpos.geometry.frames import GRAVITY_M_S2


def level_from_imu(f_frd: np.ndarray, roll_rad: np.ndarray, pitch_rad: np.ndarray) -> np.ndarray:
    """(N, 2): the vertical specific force (m/s^2, down positive: -g at rest) and the horizontal one's magnitude,
    from the IMU's specific force f_frd (N, 3) m/s^2 FRD and the vehicle's roll, pitch (N,) rad (ZYX Euler, NED)."""
    f = np.asarray(f_frd, float)
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    # body -> level: R_y(pitch) R_x(roll) applied to f
    y = cr * f[:, 1] - sr * f[:, 2]
    z1 = sr * f[:, 1] + cr * f[:, 2]
    x = cp * f[:, 0] + sp * z1
    z = -sp * f[:, 0] + cp * z1
    return np.column_stack([z, np.hypot(x, y)])


def level_from_optical(accel_world: np.ndarray) -> np.ndarray:
    """(N, 2) as level_from_imu, from the optical acceleration (N, 3) m/s^2 world z-up (gravity not included):
    an accelerometer reads -(a_z + g) down and |a_xy| across."""
    a = np.asarray(accel_world, float)
    return np.column_stack([-(a[:, 2] + GRAVITY_M_S2), np.hypot(a[:, 0], a[:, 1])])


def point_accel_costs(grid_ns: np.ndarray, positions: list[tuple[np.ndarray, np.ndarray]],
                      attitude: list[tuple[np.ndarray, np.ndarray]], imu: list[tuple[np.ndarray, np.ndarray]],
                      max_gap_ns: float, lowpass_s: float, every: int, noise_m_s2: float, rel: float,
                      bias_m_s2: float, min_instants: int) -> tuple[np.ndarray, int, float] | None:
    """The cost (B, V) of every (point body, vehicle) pair, its degrees of freedom and the largest low-passed
    optical acceleration m/s^2; None where fewer than min_instants instants are shared.

    grid_ns (G,) uniform; positions: per body (times (N,) ns, (N, 3) m world); attitude: per vehicle (times (M,)
    ns, (M, >= 2) roll, pitch rad, ...); imu: per vehicle (times (K,) ns, (K, 3) specific force m/s^2 FRD).
    The low-pass is gaussian_kernel(lowpass_s); every `every`-th instant where all are known is compared
    (accel_residuals with noise_m_s2 + rel * |a|, a bias prior of bias_m_s2).
    """
    dt_s = float(grid_ns[1] - grid_ns[0]) * 1e-9 if len(grid_ns) > 1 else 0.0
    if dt_s <= 0:
        return None
    kernel = gaussian_kernel(lowpass_s, dt_s)
    opt, mag = [], []
    for t, p in positions:
        good, val = sample_at(grid_ns, np.asarray(t, np.float64), np.asarray(p, np.float64), max_gap_ns)
        val[~good] = np.nan
        a = np.full(val.shape, np.nan)
        a[1:-1] = (val[2:] - 2.0 * val[1:-1] + val[:-2]) / (dt_s * dt_s)
        a = lowpass(a, kernel)
        opt.append(level_from_optical(a))
        mag.append(np.linalg.norm(a, axis=1))
    ap = []
    for (ta, att), (ti, f) in zip(attitude, imu):
        ga, rp = sample_at(grid_ns, np.asarray(ta, np.float64), np.asarray(att, np.float64)[:, :2], max_gap_ns)
        gi, fi = sample_at(grid_ns, np.asarray(ti, np.float64), np.asarray(f, np.float64), max_gap_ns)
        fi[~(ga & gi)] = np.nan
        ap.append(level_from_imu(lowpass(fi, kernel), rp[:, 0], rp[:, 1]))
    known = np.all([np.isfinite(x).all(axis=1) for x in opt + ap], axis=0)
    at = np.nonzero(known)[0][::-1][::every][::-1]
    if len(at) < min_instants:
        return None
    fo, m, fa = np.array(opt)[:, at], np.array(mag)[:, at], np.array(ap)[:, at]  # (B, n, 2), (B, n), (V, n, 2)
    r = accel_residuals(fa[None], fo[:, None], m[:, None], noise_m_s2, rel, bias_m_s2)
    return (r * r).sum(axis=(2, 3)), 2 * len(at), float(m.max())
