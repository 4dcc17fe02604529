"""The autopilot's IMU into the fusion's prediction (fusion/imu.py, issue 29).

The back-channel (bridge/backchannel.py) already asks the autopilot for its IMU stream with
MAV_CMD_SET_MESSAGE_INTERVAL (RAW_IMU from ArduPilot, HIGHRES_IMU from PX4, at the vehicle's
telemetry_rate_hz) and measures the vehicle's clock against the server's (Backchannel.clock_lag_ns:
autopilot time less the capture-clock stamp of one physical instant). This module turns each IMU
message into a sample the core takes (FusionPipeline.push_imu): its time on the capture clock, its
specific force and rate in the tracked body's frame (FLU: the vehicle's FRD with y and z turned over,
as bridge/convert.py maps the body), SI units.

imu_sample (pure) reads one message; ImuFeed is the mailbox between the vehicle link's sender thread,
which offers the messages, and the server's loop, which drains the samples into the pipeline before
each fusion step (a deque: appends and pops are atomic under the GIL; bounded, the oldest dropped).
"""

from __future__ import annotations

import collections

import numpy as np

from visionpos.fusion.imu import GRAVITY_M_S2

FRD_TO_FLU = np.array([1.0, -1.0, -1.0])  # the vehicle's FRD axes as the body's FLU ones (and back)
_MAX_QUEUED = 4096


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
        ta, acc_scale, gyro_scale = int(m.time_usec) * 1000, GRAVITY_M_S2 * 1e-3, 1e-3
    elif t == "SCALED_IMU":
        ta, acc_scale, gyro_scale = int(m.time_boot_ms) * 1_000_000, GRAVITY_M_S2 * 1e-3, 1e-3
    else:
        return None
    acc = np.array([m.xacc, m.yacc, m.zacc], dtype=np.float64) * acc_scale
    gyro = np.array([m.xgyro, m.ygyro, m.zgyro], dtype=np.float64) * gyro_scale
    if not (np.isfinite(acc).all() and np.isfinite(gyro).all()):
        return None
    return ta, acc, gyro


def to_fusion(t_ap_ns: int, accel_frd: np.ndarray, gyro_frd: np.ndarray,
              clock_lag_ns: float) -> tuple[int, np.ndarray, np.ndarray]:
    """A sample on the autopilot's clock as the core takes it: (capture-clock ns, specific force (3,) m/s^2
    and rate (3,) rad/s in the body's FLU frame); clock_lag_ns: autopilot time less capture-clock time."""
    return int(round(t_ap_ns - clock_lag_ns)), accel_frd * FRD_TO_FLU, gyro_frd * FRD_TO_FLU


class ImuFeed:
    """The IMU samples of the vehicle bound to one body, from the link's thread to the server's loop."""

    def __init__(self, body: str):
        self.body = body
        self.queue: collections.deque[tuple[int, np.ndarray, np.ndarray]] = collections.deque(maxlen=_MAX_QUEUED)
        self.offered = 0
        self.unmapped = 0  # messages before the vehicle's clock was measured: not usable

    def offer(self, m, autopilot: str | None, clock_lag_ns: float | None) -> bool:
        """On the link's thread: one message from the autopilot; True if it was an IMU sample queued."""
        s = imu_sample(m, autopilot)
        if s is None:
            return False
        if clock_lag_ns is None:
            self.unmapped += 1
            return False
        self.queue.append(to_fusion(s[0], s[1], s[2], clock_lag_ns))
        self.offered += 1
        return True

    def drain(self, push, until_ns: int | None = None) -> int:
        """On the server's loop: hand the queued samples (up to until_ns, if given) to push(body, t_ns, accel,
        gyro), e.g. FusionPipeline.push_imu; returns how many the core took."""
        taken = 0
        q = self.queue
        while q and (until_ns is None or q[0][0] <= until_ns):
            t, a, w = q.popleft()
            taken += bool(push(self.body, t, a, w))
        return taken
