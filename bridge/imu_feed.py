"""The autopilot's IMU into the fusion's prediction (fusion/imu.py, issue 29).

The back-channel (bridge/backchannel.py) already asks the autopilot for its IMU stream with
MAV_CMD_SET_MESSAGE_INTERVAL (RAW_IMU from ArduPilot, HIGHRES_IMU from PX4, at the vehicle's
imu_rate_hz: 200 Hz with fusion.imu.enabled) and measures the vehicle's clock against the server's
(Backchannel.clock_lag_ns: autopilot time less the capture-clock stamp of one physical instant).
This module turns each IMU message into a sample the core takes (FusionPipeline.push_imu):
its time on the capture clock, its specific force and rate in the tracked body's frame
(FLU: the vehicle's FRD with y and z turned over, as bridge/convert.py maps the body), SI units.

to_fusion (pure) maps one sample (bridge/telemetry.py imu_sample reads the message); ImuFeed is the mailbox
between the vehicle link's sender thread, which offers the samples (Backchannel.handle), and the server's loop,
which drains the
samples into the pipeline before each frame and tick (a deque: appends and pops are atomic under the
GIL; bounded, the oldest dropped); BridgeImu drains every vehicle of a Bridge into the body bound to it
(Bridge.imu_sources -> FusionPipeline.add_imu_source, composed by server/service.py).
"""

from __future__ import annotations

import collections

import numpy as np

FRD_TO_FLU = np.array([1.0, -1.0, -1.0])  # the vehicle's FRD axes as the body's FLU ones (and back)
_MAX_QUEUED = 4096


def to_fusion(t_ap_ns: int, accel_frd: np.ndarray, gyro_frd: np.ndarray,
              clock_lag_ns: float) -> tuple[int, np.ndarray, np.ndarray]:
    """A sample on the autopilot's clock as the core takes it: (capture-clock ns, specific force (3,) m/s^2
    and rate (3,) rad/s in the body's FLU frame); clock_lag_ns: autopilot time less capture-clock time."""
    return int(round(t_ap_ns - clock_lag_ns)), accel_frd * FRD_TO_FLU, gyro_frd * FRD_TO_FLU


class ImuFeed:
    """The IMU samples of one vehicle, from its link's thread to the server's loop."""

    def __init__(self):
        self.queue: collections.deque[tuple[int, np.ndarray, np.ndarray]] = collections.deque(maxlen=_MAX_QUEUED)
        self.offered = 0
        self.unmapped = 0  # messages before the vehicle's clock (and its gyro filter's lag) was known: not usable

    def offer(self, t_ap_ns: int, accel_frd: np.ndarray, gyro_frd: np.ndarray, bc) -> bool:
        """On the link's thread: one IMU sample (bridge/telemetry.py imu_sample) from the autopilot of Backchannel
        `bc`; True if it is queued. Its time: the autopilot's, less bc.clock_lag_ns (the clocks, measured against
        the optical motion) and bc.gyro_lag_ns() (ArduPilot's INS_GYRO_FILTER: its samples trail the motion by
        that)."""
        lag, filter_lag = bc.clock_lag_ns, bc.gyro_lag_ns()
        if lag is None or filter_lag is None:
            self.unmapped += 1
            return False
        self.queue.append(to_fusion(t_ap_ns, accel_frd, gyro_frd, lag + filter_lag))
        self.offered += 1
        return True

    def drain(self, push, body: str | None, lever_arm_m: np.ndarray) -> int:
        """On the server's loop: hand the queued samples to push(body, t_ns, accel, gyro, lever_arm_m), e.g.
        FusionPipeline.push_imu (body None: the vehicle is bound to none, the samples are dropped); returns how
        many the core took."""
        taken = 0
        q = self.queue
        while q:
            t, a, w = q.popleft()
            if body is not None:
                taken += bool(push(body, t, a, w, lever_arm_m))
        return taken


class BridgeImu:
    """Every vehicle's ImuFeed on a Bridge (bridge/mavlink.py), drained into the bodies bound to them: a fleet
    vehicle's bound body (bridge/fleet_binding.py), else its configured one. The IMU is taken to sit at the
    vehicle's reference point (pivot_offset from the body's origin)."""

    def __init__(self, bridge):
        self.bridge = bridge
        self.feeds = []
        for v in bridge.vehicles:
            v.bc.imu_feed = ImuFeed()
            self.feeds.append((v, v.bc.imu_feed, np.asarray(v.cfg.pivot_offset, dtype=np.float64)))

    def drain(self, push) -> int:
        """Hand every vehicle's queued samples to push (FusionPipeline.push_imu)."""
        taken = 0
        for v, feed, arm in self.feeds:
            if feed.queue:
                bound = self.bridge.identity(v.cfg.name)
                body = bound.get("bound_body") if bound else v.cfg.body
                taken += feed.drain(push, body, arm)
        return taken
