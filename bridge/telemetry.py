"""The autopilot's telemetry as the bridge keeps it: rings of timed samples, their pairing on common instants,
and what its messages carry, in SI units (pure functions and small containers; the back-channel,
bridge/backchannel.py, and the IMU's readers, bridge/imu_samples.py and bridge/imu_feed.py, use them).
"""

from __future__ import annotations

import collections
import math

import numpy as np

from visionpos.geometry.frames import GRAVITY_M_S2

EARTH_RADIUS_M = 6_378_137.0  # WGS-84 equatorial: metres per radian of latitude, near enough for centimetres
IMU_MESSAGES = ("HIGHRES_IMU", "RAW_IMU", "SCALED_IMU")
MILLI_G_M_S2 = GRAVITY_M_S2 * 1e-3  # MAVLink's "mG"


def imu_sample(m, autopilot: str | None) -> tuple[int, np.ndarray, np.ndarray] | None:
    """One IMU message (pymavlink HIGHRES_IMU, RAW_IMU or SCALED_IMU) as (time on the autopilot's boot clock
    ns, specific force (3,) m/s^2 FRD, rate (3,) rad/s FRD); None for another message, for RAW_IMU from an
    autopilot other than ArduPilot (raw sensor units), and for non-finite values.

    HIGHRES_IMU: m/s^2, rad/s, time_usec; RAW_IMU (ArduPilot's): mG and mrad/s, time_usec; SCALED_IMU:
    mG and mrad/s, time_boot_ms."""
    t = m.get_type()
    if t == "HIGHRES_IMU":
        ta, acc_scale, gyro_scale = int(m.time_usec) * 1000, 1.0, 1.0
    elif t == "RAW_IMU" and autopilot == "ardupilot":
        ta, acc_scale, gyro_scale = int(m.time_usec) * 1000, MILLI_G_M_S2, 1e-3
    elif t == "SCALED_IMU":
        ta, acc_scale, gyro_scale = int(m.time_boot_ms) * 1_000_000, MILLI_G_M_S2, 1e-3
    else:
        return None
    acc = np.array([m.xacc, m.yacc, m.zacc], dtype=np.float64) * acc_scale
    gyro = np.array([m.xgyro, m.ygyro, m.zgyro], dtype=np.float64) * gyro_scale
    if not (np.isfinite(acc).all() and np.isfinite(gyro).all()):
        return None
    return ta, acc, gyro


def geodetic_offset_m(lat_deg: float, lon_deg: float, ref_lat_deg: float, ref_lon_deg: float) -> tuple[float, float]:
    """(north, east) m of a point from a reference a few km away at most (equirectangular; under 1 mm error at
    100 m)."""
    north = math.radians(lat_deg - ref_lat_deg) * EARTH_RADIUS_M
    east = math.radians(lon_deg - ref_lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(ref_lat_deg))
    return north, east


def gyro_filter_lag_ns(cutoff_hz: float) -> float:
    """Group delay (ns) of a 2-pole Butterworth low-pass at cutoff_hz for motion well below it (ArduPilot's
    LowPassFilter2p; its sample rate moves it by under 0.1 ms at 400 Hz and up): sqrt(2) / (2 pi fc). 0 for a
    filter turned off (cutoff 0)."""
    return math.sqrt(2.0) / (2.0 * math.pi * cutoff_hz) * 1e9 if cutoff_hz > 0 else 0.0


class Ring:
    """The last n samples (time ns, k values), read back oldest first as arrays. A deque of tuples:
    appending is what runs per pose and per telemetry message, so it is the cheap side."""

    __slots__ = ("d", "k", "n")

    def __init__(self, n: int, k: int):
        self.d: collections.deque[tuple] = collections.deque(maxlen=n)
        self.k = k
        self.n = 0  # samples ever added (since the last clear)

    def add(self, t: int, values) -> None:
        self.d.append((t, *values))
        self.n += 1

    def clear(self) -> None:
        self.d.clear()
        self.n = 0

    def __len__(self) -> int:
        return len(self.d)

    def last_t(self) -> int | None:
        return self.d[-1][0] if self.d else None

    def since(self, t0: int) -> tuple[np.ndarray, np.ndarray]:
        """Times (m,) int64 and values (m, k) of the samples at or after t0."""
        rows = []
        for r in reversed(self.d):
            if r[0] < t0:
                break
            rows.append(r)
        if not rows:
            return np.zeros(0, np.int64), np.zeros((0, self.k))
        rows.reverse()
        return np.array([r[0] for r in rows], dtype=np.int64), np.array([r[1:] for r in rows], dtype=np.float64)


def sample_at(t_query: np.ndarray, t: np.ndarray, v: np.ndarray, max_gap_ns: float) -> tuple[np.ndarray, np.ndarray]:
    """v (N, k) at times t (N,) ns, linearly interpolated at t_query (M,) ns: (ok (M,) bool, values (M, k));
    ok only inside the samples' span with neighbours at most max_gap_ns apart (the values elsewhere are NaN
    with fewer than two samples, else clamped)."""
    out = np.full((len(t_query), v.shape[1]), np.nan)
    if len(t) < 2:
        return np.zeros(len(t_query), bool), out
    j = np.clip(np.searchsorted(t, t_query), 1, len(t) - 1)
    ok = (t_query >= t[0]) & (t_query <= t[-1]) & ((t[j] - t[j - 1]) <= max_gap_ns)
    for c in range(v.shape[1]):
        out[:, c] = np.interp(t_query, t, v[:, c])
    return ok, out
