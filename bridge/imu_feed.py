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

from bridge.convert import convert_state
from visionpos.geometry.rotations import quat_from_matrix, rotvec_from_matrix
from visionpos.messages import BodyState

FRD_TO_FLU = np.array([1.0, -1.0, -1.0])  # the vehicle's FRD axes as the body's FLU ones (and back)
_MAX_QUEUED = 4096
OPTICAL_ONLY_NS = 500_000_000  # a vehicle's IMU sample taken this recently: its identity check goes optical only


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
        self.taken_ns: int | None = None  # capture-clock time of the newest sample the core took

    def offer(self, t_ap_ns: int, accel_frd: np.ndarray, gyro_frd: np.ndarray, bc) -> bool:
        """On the link's thread: one IMU sample (bridge/telemetry.py imu_sample) from the autopilot of Backchannel
        `bc`; True if it is queued. Its time: the autopilot's, less bc.imu_clock_lag_ns (the clocks: measured
        against the optical motion and carried by TIMESYNC, or TIMESYNC alone before the vehicle has turned) and
        bc.gyro_lag_ns() (ArduPilot's INS_GYRO_FILTER: its samples trail the motion by that)."""
        lag, filter_lag = bc.imu_clock_lag_ns(t_ap_ns), bc.gyro_lag_ns()
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
            if body is not None and push(body, t, a, w, lever_arm_m):
                taken += 1
                self.taken_ns = t
        return taken


def optical_rate_body(t_ns: np.ndarray, R: np.ndarray) -> np.ndarray:
    """The body rate (3,) rad/s (body frame) at the middle of three optical rotations R (3, 3, 3) body->world
    at times t_ns (3,): the central difference of the outer two (no lag at the middle one's time)."""
    dR = R[0].T @ R[2]
    return rotvec_from_matrix(dR) / ((int(t_ns[2]) - int(t_ns[0])) * 1e-9)


class BridgeImu:
    """Every vehicle's ImuFeed on a Bridge (bridge/mavlink.py), drained into the bodies bound to them: a fleet
    vehicle's bound body (bridge/fleet_binding.py), else its configured one. The IMU is taken to sit at the
    vehicle's reference point (pivot_offset from the body's origin). Called as drain(push) (an IMU source,
    FusionPipeline.add_imu_source).

    While a vehicle's samples are in the filter (one taken within OPTICAL_ONLY_NS), the filter's attitude and
    rates carry that vehicle's gyro, so its back-channel's identity check and delay measurement would compare
    the gyro with itself: optical_pose gives them, instead, the fusions' triangulated attitudes (the rates by
    optical_rate_body), optical only (Backchannel.optical_only)."""

    def __init__(self, bridge):
        self.bridge = bridge
        self.feeds = []
        self.poses: dict[str, collections.deque] = {}  # vehicle -> its body's last three (t_ns, R)
        for v in bridge.vehicles:
            v.bc.imu_feed = ImuFeed()
            self.feeds.append((v, v.bc.imu_feed, np.asarray(v.cfg.pivot_offset, dtype=np.float64)))
            self.poses[v.cfg.name] = collections.deque(maxlen=3)

    def _body(self, v) -> str | None:
        bound = self.bridge.identity(v.cfg.name)
        return bound.get("bound_body") if bound else v.cfg.body

    def drain(self, push) -> int:
        """Hand every vehicle's queued samples to push (FusionPipeline.push_imu)."""
        taken = 0
        for v, feed, arm in self.feeds:
            if feed.queue:
                taken += feed.drain(push, self._body(v), arm)
        return taken

    __call__ = drain

    def optical_pose(self, body: str, t_ns: int, R: np.ndarray) -> None:
        """One fusion's triangulated rotation R (3, 3) body->world of `body` at t_ns (capture clock), on the
        server's loop: to the back-channel of each vehicle bound to it whose IMU is in the filter, as the pose
        before it with its central-difference rate, in the autopilot's frames (convert_state)."""
        for v, feed, _ in self.feeds:
            if feed.taken_ns is None or abs(t_ns - feed.taken_ns) > OPTICAL_ONLY_NS or self._body(v) != body:
                continue
            poses = self.poses[v.cfg.name]
            if poses and t_ns <= poses[-1][0]:
                continue
            poses.append((int(t_ns), np.array(R, dtype=np.float64)))
            if len(poses) < 3:
                continue
            (t0, R0), (t1, R1), (t2, R2) = poses
            w = optical_rate_body(np.array([t0, t1, t2]), np.stack([R0, R1, R2]))
            st = BodyState(body, 0, t1, t1, np.zeros(3), quat_from_matrix(R1), np.zeros(3), w, np.eye(6),
                           np.eye(3), True)
            conv = convert_state(st, v.pivot, v.yaw_offset_rad, at_ns=t1)
            v.bc.optical_only.append((t1, conv.euler[0], conv.euler[1], conv.angular_velocity_frd,
                                      conv.quaternion_ned_frd))
