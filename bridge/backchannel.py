"""What the autopilot sends back on a vehicle link, and what the bridge concludes from it.

A Backchannel belongs to one VehicleLink and runs on its sender thread; it has no socket of its own (it sends through
the link's encoder). The link hands it only packets that passed the link's checks (the vehicle's sysid, a verified
signature on a signed link, the configured or learned peer), and it keeps only those from the autopilot component (1).

From them it keeps:
- the autopilot's type (HEARTBEAT) and reboots (its boot clock going back);
- its attitude and body rates (ATTITUDE / ATTITUDE_QUATERNION) and its gyro (HIGHRES_IMU, RAW_IMU or SCALED_IMU),
  asked for with SET_MESSAGE_INTERVAL;
- the EKF's view (EKF_STATUS_REPORT flags and test ratios, STATUSTEXT);
- GPS_GLOBAL_ORIGIN (the origin confirmed), COMMAND_ACK, PARAM_VALUE;
- TIMESYNC answers to its own requests (the autopilot's receive time).

And it decides (pure math in visionpos.analysis.autopilot):
- identity: roll, pitch and body rates against the optical body's, over a 1 s window; a mismatch latches (the poses
  are someone else's until restarted);
- the measured capture-to-autopilot delay (gyro against optical rate). ArduPilot's reported gyro (RAW_IMU, ATTITUDE's
  rates) has been through its INS_GYRO_FILTER low-pass (a 2-pole Butterworth, 20 Hz on a copter): it trails the motion
  by the filter's group delay, sqrt(2) / (2 pi fc), 11.3 ms at 20 Hz, while its EKF runs on the unfiltered IMU. The
  correlation's lag is corrected by it, so the delay is measured against the motion itself; INS_GYRO_FILTER is read
  from the autopilot (PARAM_REQUEST_READ) and the delay stays unknown until it has answered. TIMESYNC's forward
  latency is taken at the instant the correlation stands for (where the vehicle turned most), on a line through the
  answers: the two clocks drift apart. A delay under the poses' age when sent is a clock map gone wrong: not reported.

Every check is "unknown" while its data is missing: nothing here ever holds a pose back for want of telemetry. Only a
positive finding does (a mismatch, or an autopilot that is talking but has not yet confirmed the origin).
"""

from __future__ import annotations

import collections
import logging
import math
from typing import Callable

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from bridge.config import VehicleConfig
from bridge.estimator_delay import DelayAdvice, advice_text, advised_delay, ardupilot_transfer_ms
from bridge.imu_clock import ImuClockMap
from bridge.imu_samples import AccelSamples
from bridge.px4_status import ev_fusion_state
from bridge.px4_timesync import Px4TimesyncTracker, fastest_round_trip_ns, median_round_trip_ns, px4_link_advice
from bridge.telemetry import IMU_MESSAGES, Ring, geodetic_offset_m, gyro_filter_lag_ns, imu_sample, sample_at
from visionpos.analysis.autopilot import (
    body_rates_from_attitudes,
    estimate_lag,
    identity_residuals,
    identity_statistic,
    vision_delay_ns,
    weighted_time_ns,
)
from visionpos.geometry.frames import GRAVITY_M_S2

log = logging.getLogger("visionpos.bridge")

MAV_COMP_ID_AUTOPILOT1 = 1
REBOOT_STEP_NS = 1_000_000_000  # the autopilot's clock going back this far: it rebooted
IDENTITY_WINDOW_NS = 1_000_000_000
IDENTITY_EVERY_NS = 250_000_000
IDENTITY_MIN_PAIRS = 20
IDENTITY_THRESHOLD = 9.0  # mean squared normalised residual: RMS 3 sigma over the window
IDENTITY_RATE_NOISE_RAD_S = 0.1
IDENTITY_RATE_REL = 0.1
MAX_PAIR_GAP_NS = 100_000_000  # optical samples further apart than this are not interpolated between
OPTICAL_ONLY_HOLD_NS = 500_000_000  # no optical-only pose (optical_only) this long: the filter's poses again
DELAY_WINDOW_NS = 20_000_000_000  # the lag's noise falls as the root of the window
DELAY_MIN_SPAN_NS = 4_000_000_000
DELAY_EVERY_NS = 5_000_000_000
DELAY_SEARCH_NS = 250e6  # around the coarse clock offset (covers the return link's latency)
DELAY_MIN_CORRELATION = 0.8
DELAY_MIN_RATE_STD = 0.05  # rad/s of optical rate: less, and there is nothing to correlate
DELAY_FLOOR_SLACK_NS = 2e6  # a delay this far under the poses' age when sent is a wrong clock map, not a link
TIMESYNC_EVERY_NS = 500_000_000
STREAM_RETRY_NS = 3_000_000_000
SILENT_WARN_NS = 10_000_000_000
TELEMETRY_STALE_NS = 2_000_000_000
MOTION_SAMPLES = 5  # Backchannel.moving: the newest IMU / ATTITUDE samples looked at ...
MOTION_ACCEL_M_S2 = 1.0  # ... a specific force this far off 1 g ...
MOTION_RATE_RAD_S = 0.2  # ... or a body rate over this: the vehicle moves (a take-off)
EKF_STATUS_STALE_NS = 5_000_000_000
PARAM_RETRY_NS = 2_000_000_000
ORIGIN_SILENT_GRACE_NS = 2_000_000_000  # with an origin to confirm, wait this long for a silent autopilot
DELAY_RESET_MS = 5.0  # re-set the parameter when the measurement moves this far ...
PX4_DELAY_RESET_MS = 0.1  # ... PX4's when its advice does: EKF2 reads it per sample and leads 1.1-1.8 ms per ms off

# EKF_STATUS_REPORT flags (ArduPilot's EKF_STATUS_FLAGS)
EKF_ATTITUDE = 1
EKF_POS_HORIZ_REL = 8
EKF_CONST_POS_MODE = 128
EKF_UNINITIALIZED = 1024

MSG_ATTITUDE = 30
MSG_RAW_IMU = 27
MSG_HIGHRES_IMU = 105
MSG_LOCAL_POSITION_NED = 32
MSG_EKF_STATUS_REPORT = 193
MSG_ESTIMATOR_STATUS = 230  # PX4's (EKF2): bridge/px4_status.py
MSG_GPS_GLOBAL_ORIGIN = 49
MSG_HOME_POSITION = 242
HOME_TOLERANCE_M = 0.01  # home read back further than this from the origin: said (a float32 COMMAND_LONG's error)
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_REQUEST_MESSAGE = 512
MAV_CMD_DO_SET_HOME = 179
GYRO_FILTER_PARAM = "INS_GYRO_FILTER"  # ArduPilot: the cutoff (Hz) of the low-pass on the gyro it reports


def _newest(d: collections.deque, n: int) -> list:
    """The newest n entries of a deque another thread appends to, by index (each read atomic under the GIL;
    iterating it could meet an append), none where it was emptied meanwhile."""
    try:
        return [d[-k] for k in range(1, min(n, len(d)) + 1)]
    except IndexError:
        return []


class Backchannel:
    """The autopilot's telemetry for one vehicle link and the checks on it; see the module docstring.

    send(msg) -> bool sends a MAVLink message on the link (signed as the link signs);
    mav: the link's pymavlink encoder; warn(kind, msg, *args): the link's rate-limited log.
    """

    def __init__(self, cfg: VehicleConfig, clock_ns: Callable[[], int], mav, send: Callable[[object], bool],
                 warn: Callable[..., None], base_offset_ns: int = 0, write_ns: Callable[[], int] | None = None):
        self.cfg = cfg
        self.clock_ns = clock_ns
        self.mav = mav
        self.send = send
        self.warn = warn
        self.base_offset_ns = base_offset_ns
        # when the last send reached the socket (the link's clock read just before its write): the TIMESYNC
        # request's s1, so neither packing nor a wait for the GIL after the write counts as link latency
        self.write_ns = write_ns if write_ns is not None else clock_ns
        self.autopilot: str | None = None  # 'ardupilot', 'px4' or 'other' (from HEARTBEAT)
        self.armed = False  # its HEARTBEAT's MAV_MODE_FLAG_SAFETY_ARMED
        self.first_heard_ns = 0
        self.last_heard_ns = 0
        self.reboots = 0
        self.messages = 0  # accepted from the autopilot component
        self._t_ap_newest: int | None = None
        self.att = Ring(512, 5)  # autopilot clock: roll, pitch, p, q, r (FRD)
        self.gyro = Ring(8192, 3)  # autopilot clock: p, q, r (FRD)
        self.gyro_source = ""
        self.accel = AccelSamples()  # autopilot clock: the IMU's specific force, for a fleet's binding
        self.opt = Ring(8192, 9)  # server clock (pose stamp): roll, pitch, p, q, r (FRD), quaternion NED<-FRD xyzw
        self.sends = Ring(8192, 1)  # server clock (send time): send - stamp ns
        self.clock_offsets = Ring(256, 1)  # server receive time: autopilot time - receive time
        self.timesync = Ring(64, 2)  # server send time s1: tc1 - s1, round trip
        self._ts_pending: collections.OrderedDict[int, int] = collections.OrderedDict()
        self.local_position: tuple[float, float, float] | None = None
        self.local_position_ns = 0  # its receive time, server clock
        # identity
        self.identity = "unknown"
        self.identity_reason = "no attitude from the autopilot yet"
        self.identity_statistic = float("nan")
        self.identity_tripped = False
        self.identity_tripped_after_s: float | None = None  # from the first optical pose to the mismatch
        self._first_opt_ns = 0
        self._next_identity = 0
        # the optical body feeding this vehicle changed (a fleet's binding, bridge/fleet_binding.py): written by the
        # bridge on the server's loop, read here on the sender thread, which then starts the optical side afresh
        self.optical_epoch = 0
        self._opt_epoch_seen = 0
        # delay
        self.clock_lag_ns: float | None = None  # autopilot time less server stamp of one physical instant
        self.imu_clock = ImuClockMap()  # clock_lag_ns carried by TIMESYNC, for the IMU's samples
        self.delay_ms: float | None = None  # the median pose-instant-to-arrival delay (ms)
        self.advice: DelayAdvice | None = None  # what the autopilot's estimator wants set (bridge/estimator_delay.py)
        self.delay_correlation = float("nan")
        self.delay_window_ns: tuple[int, int] | None = None  # server clock: the optical span of the last figure
        self.delay_reason = "no gyro from the autopilot yet"
        self._delays: collections.deque[float] = collections.deque(maxlen=5)
        self.px4_timesync = Px4TimesyncTracker()  # PX4's TIMESYNC requests we answered, as PX4 would use them
        self._delay_said: float | None = None  # the delay last logged
        self._next_delay = 0
        self.gyro_filter_hz: float | None = None  # ArduPilot's INS_GYRO_FILTER, once it has answered
        self._next_filter_request = 0
        self._delay_param_value: float | None = None
        self.delay_param_confirmed: float | None = None
        self._next_param = 0
        # EKF
        self.ekf_flags: int | None = None
        self.ekf_ratios: dict[str, float] = {}
        self._ekf_ns = 0
        self.estimator_status: tuple[int, int, float, float, float] | None = None  # PX4: recv ns, flags, 3 ratios
        self._ev_said = ""  # the PX4 EV state last logged
        self.ext_nav_text = ""  # the last STATUSTEXT about external navigation
        self.statustexts: collections.deque[tuple[int, str]] = collections.deque(maxlen=20)
        self._ekf_bad_reports = 0
        # origin and home
        self.origin_confirmed = False
        self.origin_reported: tuple[float, float, float] | None = None
        self.home_acked = False
        self.home_reported: tuple[float, float, float] | None = None  # HOME_POSITION: lat, lon (deg), alt (m)
        self.home_error_m: float | None = None  # its horizontal distance from the configured origin
        # what we asked for
        self._streams_due = 0
        self.link_up_ns = 0
        self._origin_release_said = False
        self._att_recv_ns = self._gyro_recv_ns = 0
        self._next_timesync = 0
        self._silent_warned = False
        self._first_send_ns = 0
        self.imu_feed = None  # bridge/imu_feed.py's ImuFeed: the IMU samples on to the fusion (offer)
        # optical-only poses (bridge/imu_feed.py BridgeImu.optical_pose, from the loop) while this vehicle's IMU is in
        # the filter: they stand in for the filter's (on_optical), which carry the gyro they are compared with
        self.optical_only: collections.deque[tuple] = collections.deque(maxlen=1024)
        self._optical_only_ns = -(1 << 62)  # stamp of the newest taken

    # ------------------------------------------------------------ receive
    def handle(self, m, compid: int, recv_ns: int) -> None:
        """One message from the vehicle's sysid that passed the link's checks."""
        if compid != MAV_COMP_ID_AUTOPILOT1:
            return
        t = m.get_type()
        self.messages += 1
        self.last_heard_ns = recv_ns
        if t == "HEARTBEAT":
            if m.autopilot == mavlink2.MAV_AUTOPILOT_INVALID:
                return
            kind = {mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot", mavlink2.MAV_AUTOPILOT_PX4: "px4"}.get(
                m.autopilot, "other")
            if self.autopilot is None:
                self.first_heard_ns = recv_ns
                self._streams_due = recv_ns
                log.info("vehicle %s: autopilot heard (%s)", self.cfg.name, kind)
            self.autopilot = kind
            self.armed = bool(m.base_mode & mavlink2.MAV_MODE_FLAG_SAFETY_ARMED)
        elif t == "ATTITUDE":
            if self._stamp(m.time_boot_ms * 1_000_000, recv_ns):
                self.att.add(m.time_boot_ms * 1_000_000, (m.roll, m.pitch, m.rollspeed, m.pitchspeed, m.yawspeed))
                self._att_recv_ns = recv_ns
        elif t == "ATTITUDE_QUATERNION":
            ta = m.time_boot_ms * 1_000_000
            if self._stamp(ta, recv_ns):
                w, x, y, z = m.q1, m.q2, m.q3, m.q4
                roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
                pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
                self.att.add(ta, (roll, pitch, m.rollspeed, m.pitchspeed, m.yawspeed))
                self._att_recv_ns = recv_ns
        elif t in IMU_MESSAGES:
            s = imu_sample(m, self.autopilot)  # None: another autopilot's raw RAW_IMU units, values not finite
            if s is not None and self._stamp(s[0], recv_ns):
                self.gyro.add(s[0], s[2])
                self.accel.add(s[0], s[1])
                self.gyro_source = t
                self._gyro_recv_ns = recv_ns
                if self.imu_feed is not None:
                    self.imu_feed.offer(*s, self)
        elif t == "LOCAL_POSITION_NED":
            self.local_position, self.local_position_ns = (m.x, m.y, m.z), recv_ns
        elif t == "EKF_STATUS_REPORT":
            self._on_ekf_status(m, recv_ns)
        elif t == "ESTIMATOR_STATUS":
            self.estimator_status = (recv_ns, int(m.flags), float(m.pos_horiz_ratio), float(m.pos_vert_ratio),
                                     float(m.vel_ratio))
            state, why = self.ekf_state(recv_ns)
            if state != self._ev_said:  # said in words when it changes
                self._ev_said = state
                log.log(logging.INFO if state == "using vision" else logging.WARNING, "vehicle %s: %s",
                        self.cfg.name, why)
        elif t == "STATUSTEXT":
            self._on_statustext(m)
        elif t == "GPS_GLOBAL_ORIGIN":
            self._on_origin(m)
        elif t == "HOME_POSITION":
            self._on_home(m)
        elif t == "COMMAND_ACK":
            if m.command == MAV_CMD_DO_SET_HOME:
                if m.result == mavlink2.MAV_RESULT_ACCEPTED:
                    if not self.home_acked:
                        log.info("vehicle %s: the autopilot accepted its home", self.cfg.name)
                    self.home_acked = True
                else:
                    self.warn("home", "vehicle %s: the autopilot refused MAV_CMD_DO_SET_HOME (result %d); "
                              "retrying", self.cfg.name, m.result)
        elif t == "PARAM_VALUE":
            pid = m.param_id.rstrip("\0") if isinstance(m.param_id, str) else ""
            if pid == GYRO_FILTER_PARAM and self.autopilot == "ardupilot" and 0.0 <= m.param_value < 1e4:
                self.gyro_filter_hz = float(m.param_value)
            if pid == self._delay_param_name() and self._delay_param_value is not None \
                    and abs(m.param_value - self._delay_param_value) < 0.5:
                if self.delay_param_confirmed != self._delay_param_value:
                    log.warning("vehicle %s: set %s = %g on the autopilot (measured)", self.cfg.name, pid,
                                m.param_value)
                self.delay_param_confirmed = self._delay_param_value

    def on_timesync_request(self) -> None:
        """We answered one of the autopilot's TIMESYNC requests (bridge/px4_timesync.py)."""
        self.px4_timesync.answered(self.timesync_rtt_ns())

    def timesync_rtt_ns(self, fastest: bool = False) -> float | None:
        """The median (or fastest) round trip of our 20 newest TIMESYNC requests (ns); None before 3 answers."""
        rtts = [r[2] for r in list(self.timesync.d)[-20:]]  # list() copies under the GIL
        return fastest_round_trip_ns(rtts) if fastest else median_round_trip_ns(rtts)

    def on_timesync_reply(self, ts1: int, tc1: int, recv_ns: int) -> bool:
        """An answer to one of our TIMESYNC requests (ts1 as we sent it); False if it is not one of ours."""
        s1 = self._ts_pending.pop(ts1, None)
        if s1 is None:
            return False
        newest = self._t_ap_newest
        if newest is not None and tc1 < newest - REBOOT_STEP_NS:
            self._on_reboot(newest, tc1)
            self._t_ap_newest = tc1
            return True
        if newest is None or tc1 > newest:
            self._t_ap_newest = tc1
        self.timesync.add(s1, (float(tc1 - s1), float(recv_ns - s1)))
        self.imu_clock.fit(self.timesync)
        return True

    def imu_clock_lag_ns(self, t_ap_ns: int) -> float | None:
        """The clock lag that moves an IMU sample stamped t_ap_ns onto the capture clock (bridge/imu_clock.py)."""
        return self.imu_clock.lag_ns(t_ap_ns, self.clock_lag_ns)

    def _stamp(self, t_ap: int, recv_ns: int) -> bool:
        """Note a timestamped sample; detects a reboot. False for a stamp too old to use."""
        newest = self._t_ap_newest
        if newest is not None and t_ap < newest - REBOOT_STEP_NS:
            self._on_reboot(newest, t_ap)
            newest = None
        if newest is None or t_ap > newest:
            self._t_ap_newest = t_ap
        elif t_ap < newest - DELAY_WINDOW_NS:
            return False
        self.clock_offsets.add(recv_ns, (t_ap - recv_ns,))
        return True

    def _on_reboot(self, was_ns: int, now_ap_ns: int) -> None:
        self.reboots += 1
        self.warn("reboot", "vehicle %s: the autopilot rebooted (its clock went back from %.1f s to %.1f s); "
                  "poses go on; resending the origin and the telemetry requests, and the checks start again",
                  self.cfg.name, was_ns * 1e-9, now_ap_ns * 1e-9)
        for r in (self.att, self.gyro, self.clock_offsets, self.timesync, self.sends):
            r.clear()
        self._ts_pending.clear()
        self._delays.clear()
        self.px4_timesync.reset()
        self.clock_lag_ns = None
        self.imu_clock.reset()
        self.delay_ms = None
        self.advice = None
        self.delay_reason = "the autopilot rebooted; measuring again"
        if not self.identity_tripped:
            self.identity, self.identity_reason = "unknown", "the autopilot rebooted; checking again"
        self.origin_confirmed = False
        self._origin_release_said = False
        self.home_acked = False
        self.home_reported = self.home_error_m = None
        self.delay_param_confirmed = None
        self.gyro_filter_hz = None  # read again: it may have been changed for this boot
        self.ekf_flags = None
        self.estimator_status = None
        self.ekf_ratios = {}
        self.ext_nav_text = ""
        self._streams_due = self.clock_ns()

    def _on_ekf_status(self, m, recv_ns: int) -> None:
        self.ekf_flags = int(m.flags)
        self.ekf_ratios = {"velocity": float(m.velocity_variance), "pos_horiz": float(m.pos_horiz_variance),
                           "pos_vert": float(m.pos_vert_variance), "compass": float(m.compass_variance)}
        self._ekf_ns = recv_ns
        if self.sends.n and max(m.pos_horiz_variance, m.velocity_variance) > 1.0:
            self._ekf_bad_reports += 1
            if self._ekf_bad_reports >= 3:
                self.warn("ekf_reject", "vehicle %s: the autopilot's EKF rejects the vision (position test ratio "
                          "%.2f, velocity %.2f; over 1 fails its gate): it disagrees with its own IMU; check "
                          "yaw_offset_deg and the frame alignment, the measured delay, and VISO_POS_M_NSE "
                          "(docs/autopilot-setup.md)", self.cfg.name, m.pos_horiz_variance, m.velocity_variance)
        else:
            self._ekf_bad_reports = 0

    def _on_statustext(self, m) -> None:
        text = m.text.rstrip("\0") if isinstance(m.text, str) else str(m.text)
        self.statustexts.append((int(m.severity), text))
        low = text.lower()
        if "external nav" in low or "visodom" in low or "ext nav" in low:
            self.ext_nav_text = text
        if m.severity <= mavlink2.MAV_SEVERITY_WARNING:
            log.warning("vehicle %s: autopilot says: %s", self.cfg.name, text)
        else:
            log.info("vehicle %s: autopilot says: %s", self.cfg.name, text)

    def _on_origin(self, m) -> None:
        got = (m.latitude * 1e-7, m.longitude * 1e-7, m.altitude * 1e-3)
        self.origin_reported = got
        o = self.cfg.origin
        if o is not None and not self.origin_confirmed:
            if abs(got[0] - o.lat) > 2e-7 or abs(got[1] - o.lon) > 2e-7 or abs(got[2] - o.alt) > 0.01:
                self.warn("origin_differs", "vehicle %s: the autopilot reports its origin at %.7f, %.7f, %.2f m, "
                          "not the configured %.7f, %.7f, %.2f m (it kept an older one); poses go out in its "
                          "frame; reboot the autopilot to take the configured origin",
                          self.cfg.name, *got, o.lat, o.lon, o.alt)
            else:
                log.info("vehicle %s: the autopilot confirmed its origin", self.cfg.name)
        self.origin_confirmed = True

    def _on_home(self, m) -> None:
        """HOME_POSITION: where the autopilot put home, against the configured origin (1 cm: the float32
        degrees of a COMMAND_LONG put it up to a metre off, which is why home goes as COMMAND_INT)."""
        self.home_reported = (m.latitude * 1e-7, m.longitude * 1e-7, m.altitude * 1e-3)
        o = self.cfg.origin
        if o is None:
            return
        north, east = geodetic_offset_m(self.home_reported[0], self.home_reported[1], o.lat, o.lon)
        self.home_error_m = math.hypot(north, east)
        if self.home_error_m > HOME_TOLERANCE_M and self.home_acked:
            self.warn("home_off", "vehicle %s: the autopilot's home is %.3f m N, %.3f m E of the configured origin "
                      "(it kept another home?)", self.cfg.name, north, east)

    # ------------------------------------------------------------ optical side (sender thread, per pose)
    def on_optical(self, stamp_ns: int, roll: float, pitch: float, rate_frd, quat_ned_frd) -> None:
        """One optical pose at its stamp: roll, pitch (rad), the filter's body rate (3,) rad/s FRD and the
        attitude (4,) xyzw; while optical-only poses come (optical_only, the IMU in the filter), those instead."""
        q = self.optical_only
        if q or stamp_ns - self._optical_only_ns < OPTICAL_ONLY_HOLD_NS:
            while q:
                t, *rest = q.popleft()
                if t > (self.opt.last_t() or 0) or self.optical_epoch != self._opt_epoch_seen:
                    self._optical_only_ns = t
                    self._on_optical(t, *rest)
            return
        self._on_optical(stamp_ns, roll, pitch, rate_frd, quat_ned_frd)

    def _on_optical(self, stamp_ns: int, roll: float, pitch: float, rate_frd, quat_ned_frd) -> None:
        if self.optical_epoch != self._opt_epoch_seen:  # another body now: its samples are not the last one's
            self._opt_epoch_seen = self.optical_epoch
            self.opt.clear()
            self._first_opt_ns = 0
            if self.identity_tripped:  # the mismatch was against the body this vehicle no longer gets
                self.identity_tripped, self.identity_tripped_after_s = False, None
                self.identity, self.identity_reason = "unknown", "bound to another optical body; checking again"
        self.opt.add(stamp_ns, (roll, pitch, rate_frd[0], rate_frd[1], rate_frd[2], *quat_ned_frd))
        if not self._first_opt_ns:
            self._first_opt_ns = stamp_ns

    def on_sent(self, send_ns: int, stamp_ns: int) -> None:
        """A pose went out; the delay measurement (milliseconds of numpy every DELAY_EVERY_NS) runs right
        after a send, when the next pose is a whole period away."""
        self.sends.add(send_ns, (send_ns - stamp_ns,))
        if not self._first_send_ns:
            self._first_send_ns = send_ns
        if send_ns >= self._next_delay:
            self._delay_due(send_ns)

    def _delay_due(self, now: int) -> None:
        self._next_delay = now + DELAY_EVERY_NS
        self.measure_delay()
        self._maybe_set_delay(now)

    # ------------------------------------------------------------ periodic (sender thread)
    def service(self, now: int) -> None:
        """Requests to send and checks to run; cheap when nothing is due."""
        if self.autopilot is not None and self.cfg.telemetry_rate_hz > 0 and now >= self._streams_due:
            # asked again while the attitude or the gyro does not come (a lost request, a reboot)
            self._streams_due = now + STREAM_RETRY_NS
            if now - self._att_recv_ns > TELEMETRY_STALE_NS or now - self._gyro_recv_ns > TELEMETRY_STALE_NS:
                self._request_streams()
        if self.autopilot == "ardupilot" and self.gyro_filter_hz is None and now >= self._next_filter_request:
            self._next_filter_request = now + PARAM_RETRY_NS
            self.send(self.mav.param_request_read_encode(self.cfg.sysid, MAV_COMP_ID_AUTOPILOT1,
                                                         GYRO_FILTER_PARAM.encode(), -1))
        if self.cfg.timesync and now >= self._next_timesync:
            self._next_timesync = now + TIMESYNC_EVERY_NS
            ts1 = self.clock_ns() + self.base_offset_ns  # an identifier; the send time is taken at the write
            if self.send(self.mav.timesync_encode(0, ts1)):
                self._ts_pending[ts1] = self.write_ns()
                while len(self._ts_pending) > 16:
                    self._ts_pending.popitem(last=False)
        if now >= self._next_identity:
            self._next_identity = now + IDENTITY_EVERY_NS
            self.check_identity(now)
        if now >= self._next_delay and (not self.sends.d or now - self.sends.last_t() > DELAY_EVERY_NS):
            self._delay_due(now)  # nothing sent lately: after_send will not run it
        if not self._silent_warned and self._first_send_ns and not self.messages:
            if now - self._first_send_ns > SILENT_WARN_NS:
                self._silent_warned = True
                log.warning("vehicle %s: the autopilot has sent nothing back in %.0f s of poses: the identity "
                            "check, the delay measurement and the EKF state stay unknown (poses go on); "
                            "check that the autopilot's port sends MAVLink (SERIALn_PROTOCOL=2, stream rates) "
                            "and, on a signed link, that it signs with the vehicle's key", self.cfg.name,
                            SILENT_WARN_NS * 1e-9)

    def _request_streams(self) -> None:
        imu = MSG_RAW_IMU if self.autopilot == "ardupilot" else MSG_HIGHRES_IMU
        ekf = MSG_ESTIMATOR_STATUS if self.autopilot == "px4" else MSG_EKF_STATUS_REPORT
        imu_hz = self.cfg.imu_rate_hz or self.cfg.telemetry_rate_hz  # its own rate (the filter's input)
        for msg_id, us in ((MSG_ATTITUDE, 1e6 / self.cfg.telemetry_rate_hz), (imu, 1e6 / imu_hz),
                           (MSG_LOCAL_POSITION_NED, 1e5), (ekf, 5e5)):
            self.send(self.mav.command_long_encode(self.cfg.sysid, MAV_COMP_ID_AUTOPILOT1,
                                                   MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, us, 0, 0, 0, 0, 0))

    def request_origin(self) -> None:
        self.send(self.mav.command_long_encode(self.cfg.sysid, MAV_COMP_ID_AUTOPILOT1, MAV_CMD_REQUEST_MESSAGE, 0,
                                               MSG_GPS_GLOBAL_ORIGIN, 0, 0, 0, 0, 0, 0))

    def request_home(self) -> None:
        """MAV_CMD_REQUEST_MESSAGE for HOME_POSITION (no coordinates in it: COMMAND_LONG is fine)."""
        self.send(self.mav.command_long_encode(self.cfg.sysid, MAV_COMP_ID_AUTOPILOT1, MAV_CMD_REQUEST_MESSAGE, 0,
                                               MSG_HOME_POSITION, 0, 0, 0, 0, 0, 0))

    def coarse_offset_ns(self) -> float | None:
        """Autopilot clock less server clock, from the fastest recent message back (the return latency
        biases it by its minimum); safe from another thread."""
        offsets = list(self.clock_offsets.d)  # list() copies under the GIL while the link's thread appends
        return float(max(r[1] for r in offsets)) if offsets else None

    def attitude_on_server_clock(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The autopilot's recent attitude samples on the server clock, safe to call from another thread: times
        (N,) int64 ns and (N, 5) roll, pitch rad, p, q, r rad/s FRD; None before the clocks can be mapped."""
        rows = list(self.att.d)  # list() copies under the GIL while the sender thread appends
        a = np.array(rows, dtype=np.float64).reshape(-1, 6)
        t = self.ap_to_server_ns(a[:, 0])
        return None if t is None else (t, a[:, 1:])

    def ap_to_server_ns(self, t_ap_ns: np.ndarray) -> np.ndarray | None:
        """Times (N,) ns on the autopilot's clock on the server clock, (N,) int64, from any thread: less the delay
        measurement's lag carried by the clocks' drift (bridge/imu_clock.py), or until it is measured the fastest
        recent message's offset (coarse_offset_ns); None while neither is known."""
        t, lag = np.asarray(t_ap_ns, dtype=np.float64), self.clock_lag_ns
        lags = self.imu_clock.lags_ns(t, lag) if lag is not None else self.coarse_offset_ns()
        return None if lags is None else np.rint(t - lags).astype(np.int64)

    def check_identity(self, now: int) -> str:
        """Run the identity test on the newest window; returns the state ('unknown', 'consistent',
        'mismatch', 'off')."""
        if self.cfg.identity_check == "off":
            self.identity, self.identity_reason = "off", "identity_check: off"
            return self.identity
        if self.identity_tripped:
            return self.identity
        newest = self.att.last_t()
        ta, va = self.att.since(newest - IDENTITY_WINDOW_NS) if newest is not None else (None, None)
        t_srv = self.ap_to_server_ns(ta) if newest is not None else None
        if t_srv is None or now - t_srv[-1] > TELEMETRY_STALE_NS:
            self.identity = "unknown"
            self.identity_reason = "no attitude from the autopilot" + (" lately" if newest is not None else " yet")
            return self.identity
        to, vo = self.opt.since(int(t_srv[0]) - MAX_PAIR_GAP_NS)
        ok, vi = sample_at(t_srv, to, vo[:, :5], MAX_PAIR_GAP_NS)
        vi = vi[ok]
        if ok.sum() < IDENTITY_MIN_PAIRS:
            self.identity = "unknown"
            self.identity_reason = "no optical pose at the autopilot's times"
            return self.identity
        sig_att = math.radians(self.cfg.identity_tolerance_deg)
        r = identity_residuals(va[ok, :2], va[ok, 2:], vi[:, :2], vi[:, 2:], sig_att, IDENTITY_RATE_NOISE_RAD_S,
                               IDENTITY_RATE_REL)
        stat = identity_statistic(r)
        self.identity_statistic = stat
        if stat > IDENTITY_THRESHOLD:
            att_rms = math.degrees(float(np.sqrt(np.mean((r[:, :2] * sig_att) ** 2))))
            rate_rms = float(np.sqrt(np.mean((va[ok, 2:] - vi[:, 2:]) ** 2)))
            self.identity = "mismatch"
            self.identity_reason = (
                f"the autopilot's roll/pitch differ from the optical body's by {att_rms:.1f} deg RMS and its body "
                f"rates by {rate_rms:.2f} rad/s RMS over the last second: these poses are not this vehicle's "
                "(swapped sysid or endpoint, another drone's autopilot, or a mirrored marker layout?)")
            self.identity_tripped = True
            self.identity_tripped_after_s = (now - self._first_opt_ns) * 1e-9
            stop = self.cfg.identity_check == "stop"
            log.error("vehicle %s (sysid %d): identity check failed: %s%s", self.cfg.name, self.cfg.sysid,
                      self.identity_reason,
                      "; poses to this vehicle stopped (fix the vehicles section and restart)" if stop else
                      " (identity_check: warn: poses go on)")
        else:
            self.identity, self.identity_reason = "consistent", f"statistic {stat:.2f} (mismatch above " \
                                                                f"{IDENTITY_THRESHOLD:.0f})"
        return self.identity

    def moving(self) -> bool:
        """Whether the vehicle's own newest IMU samples (the last MOTION_SAMPLES) or ATTITUDE show it moving: a
        specific force off 1 g by over MOTION_ACCEL_M_S2, or a body rate over MOTION_RATE_RAD_S."""
        acc = _newest(self.accel.d, MOTION_SAMPLES)  # (runs every output tick while armed on a pad: no copies)
        if any(abs(math.sqrt(a * a + b * b + c * c) - GRAVITY_M_S2) > MOTION_ACCEL_M_S2 for _, a, b, c in acc):
            return True
        att = _newest(self.att.d, MOTION_SAMPLES)
        return any(max(abs(p), abs(q), abs(r)) > MOTION_RATE_RAD_S for _, _, _, p, q, r in att)

    @property
    def blocks(self) -> bool:
        """True when the identity check has stopped the poses to this vehicle."""
        return self.identity_tripped and self.cfg.identity_check == "stop"

    def measure_delay(self) -> float | None:
        """Update the measured delay (ms) from the newest DELAY_WINDOW_NS of gyro and optical rate (and, for PX4,
        the advice from the link's timing alone: bridge/px4_timesync.py)."""
        est = self.cfg.autopilot if self.cfg.autopilot != "auto" else self.autopilot
        if est == "px4" and self.sends.n:
            _, sends = self.sends.since(self.sends.last_t() - DELAY_WINDOW_NS)
            rtt = self.timesync_rtt_ns(fastest=True)
            self.advice = px4_link_advice(sends[:, 0], rtt, self.px4_timesync.converged, self.cfg.message) \
                or self.advice
        gyro_t, gyro_v = (self.gyro.since(self.gyro.last_t() - DELAY_WINDOW_NS) if self.gyro.n
                          else (np.zeros(0, np.int64), np.zeros((0, 3))))
        if len(gyro_t) < 4 or gyro_t[-1] - gyro_t[0] < DELAY_MIN_SPAN_NS:
            # no gyro message: ATTITUDE's rates (the autopilot's filtered gyro) are the next best
            at, av = self.att.since(self.att.last_t() - DELAY_WINDOW_NS) if self.att.n else (gyro_t, gyro_v)
            gyro_t, gyro_v = at, (av[:, 2:] if av.shape[1] == 5 else av)
        off = self.coarse_offset_ns()
        if len(gyro_t) < 4 or gyro_t[-1] - gyro_t[0] < DELAY_MIN_SPAN_NS or off is None:
            self.delay_reason = "not enough gyro from the autopilot yet"
            return self.delay_ms
        to, vo = self.opt.since(int(gyro_t[0] - off) - int(DELAY_SEARCH_NS))
        if len(to) < 20:
            self.delay_reason = "no optical rates yet"
            return self.delay_ms
        # rates from the attitudes, not the filter's rate: that one trails the motion by milliseconds
        to, rates = body_rates_from_attitudes(to, vo[:, 5:9])
        if len(to) < 20 or float(np.std(rates, axis=0).max()) < DELAY_MIN_RATE_STD:
            self.delay_reason = "the vehicle turns too little to correlate its rates (needs some rotation)"
            return self.delay_ms
        # the instant the correlation stands for (where the vehicle turned most); the clocks drift apart
        at_ns = weighted_time_ns(to, rates)
        gyro_t, off = self.imu_clock.stamps_at(self.timesync, gyro_t, off, self.clock_offsets.last_t(), at_ns)
        fine = estimate_lag(to, rates, gyro_t, gyro_v, off, DELAY_SEARCH_NS, step_ns=4e6)
        if fine is None or fine.correlation < DELAY_MIN_CORRELATION:
            self.delay_reason = ("the autopilot's gyro and the optical rates do not correlate"
                                 + ("" if fine is None else f" (peak {fine.correlation:.2f})")
                                 + ": the vehicle turns too little, or they are not the same vehicle")
            return self.delay_ms
        gyro_lag_ns = self.gyro_lag_ns()
        if gyro_lag_ns is None:
            self.delay_reason = (f"waiting for {GYRO_FILTER_PARAM} from the autopilot (its gyro filter delays the "
                                 "rates it reports)")
            return self.delay_ms
        self.clock_lag_ns = fine.lag_ns - gyro_lag_ns  # the motion's instant, not the filtered gyro's
        self.imu_clock.mark_lag(at_ns)
        self.delay_correlation = fine.correlation
        ts_t, ts = self.timesync.since(int(to[0]) - DELAY_WINDOW_NS)
        _, sends = self.sends.since(int(to[0]))
        if len(ts) < 3 or len(sends) < 10:
            self.delay_reason = "waiting for TIMESYNC answers from the autopilot" if len(ts) < 3 else \
                "waiting for poses to be sent"
            return self.delay_ms
        d_ns = vision_delay_ns(sends[:, 0], ts_t, ts_t + ts[:, 0], self.clock_lag_ns, at_ns=at_ns)
        sent_ns = float(np.median(sends[:, 0]))  # no pose arrives younger than it left
        if d_ns < sent_ns - DELAY_FLOOR_SLACK_NS:
            self.delay_ms, self.delay_reason = None, (
                f"the gyro correlation and TIMESYNC gave {d_ns * 1e-6:.1f} ms, under the poses' age when sent "
                f"({sent_ns * 1e-6:.1f} ms): the clock map is off (a clock drifting unevenly); no delay reported")
            return None
        self.delay_window_ns = (int(to[0]), int(to[-1]))
        self._delays.append(d_ns * 1e-6)
        self.delay_ms = d_ns * 1e-6  # each estimate spans DELAY_WINDOW_NS already; the newest follows changes
        # each pose's delay: its own stamp -> send, plus the link's share of the median (the same for all)
        link_ns = d_ns - sent_ns
        cfg = self.cfg
        if est != "px4":
            self.advice = advised_delay(est, (sends[:, 0] + link_ns) * 1e-6, transfer_ms=ardupilot_transfer_ms(
                cfg.message, cfg.signing_key is not None, cfg.autopilot_baud))
        if self._delay_said is None or abs(self.delay_ms - self._delay_said) >= DELAY_RESET_MS:
            self._delay_said = self.delay_ms
            log.warning("vehicle %s: %s", self.cfg.name, self.delay_advice())
        source = self.gyro_source or "ATTITUDE"
        self.delay_reason = f"gyro/optical rate correlation {fine.correlation:.3f} ({source}" + (
            f"; its {self.gyro_filter_hz:g} Hz filter's {gyro_lag_ns * 1e-6:.1f} ms lag removed)" if gyro_lag_ns
            else ")")
        return self.delay_ms

    def gyro_lag_ns(self) -> float | None:
        """How far the reported gyro trails the motion (ns): ArduPilot's INS_GYRO_FILTER group delay, None until
        it has answered; 0 for others (PX4's HIGHRES_IMU carries the unfiltered, integrated gyro)."""
        if self.autopilot != "ardupilot":
            return 0.0
        return None if self.gyro_filter_hz is None else gyro_filter_lag_ns(self.gyro_filter_hz)

    def _delay_param_name(self) -> str:
        return self.advice.param if self.advice is not None else (
            "EKF2_EV_DELAY" if self.autopilot == "px4" else "VISO_DELAY_MS")

    def _maybe_set_delay(self, now: int) -> None:
        advice = self.advice
        if not self.cfg.set_delay or advice is None or self.autopilot is None:
            return
        px4 = advice.param == "EKF2_EV_DELAY"  # PX4's from the link's timing; ArduPilot's needs 3 measurements
        if not px4 and (self.delay_ms is None or len(self._delays) < 3):
            return
        value = float(advice.value_ms)
        if self._delay_param_value is None or \
                abs(value - self._delay_param_value) >= (PX4_DELAY_RESET_MS if px4 else DELAY_RESET_MS):
            self._delay_param_value = value
            self.delay_param_confirmed = None
            self._next_param = now
        if self.delay_param_confirmed == self._delay_param_value or now < self._next_param:
            return
        self._next_param = now + PARAM_RETRY_NS
        ptype = mavlink2.MAV_PARAM_TYPE_REAL32 if px4 else mavlink2.MAV_PARAM_TYPE_INT16
        self.send(self.mav.param_set_encode(self.cfg.sysid, MAV_COMP_ID_AUTOPILOT1, advice.param.encode(), value,
                                            ptype))

    # ------------------------------------------------------------ reporting
    def ekf_state(self, now: int) -> tuple[str, str]:
        """('using vision' | 'rejecting vision' | 'not using vision' | 'unknown', plain-language detail)."""
        es = self.estimator_status
        if es is not None and now - es[0] <= EKF_STATUS_STALE_NS:  # PX4's EKF2
            sending = bool(self.sends.d) and now - self.sends.last_t() < TELEMETRY_STALE_NS
            return ev_fusion_state(es[1], es[2], es[3], es[4], sending)
        if self.ekf_flags is None or now - self._ekf_ns > EKF_STATUS_STALE_NS:
            if self.ext_nav_text:
                return "using vision", self.ext_nav_text
            return "unknown", "no EKF_STATUS_REPORT from the autopilot"
        r = self.ekf_ratios
        ratios = f"test ratios position {r['pos_horiz']:.2f}, velocity {r['velocity']:.2f}"
        if self._ekf_bad_reports >= 3:
            return "rejecting vision", f"{ratios}: the EKF refuses the vision (over 1 fails its gate)"
        f = self.ekf_flags
        if f & EKF_UNINITIALIZED or not f & EKF_ATTITUDE:
            return "not using vision", "the EKF has not started"
        if f & EKF_POS_HORIZ_REL and not f & EKF_CONST_POS_MODE:
            return "using vision", ratios
        return "not using vision", (f"{ratios}; the EKF has no relative position (flags 0x{f:x}): check "
                                    "EK3_SRC1_POSXY=6 and VISO_TYPE (docs/autopilot-setup.md)")

    def origin_state(self, now: int) -> str:
        """'not set' (no origin configured), 'confirmed', 'waiting' (held), 'unconfirmed' (timed out or
        the autopilot is silent: poses go anyway)."""
        if self.cfg.origin is None:
            return "not set"
        if self.origin_confirmed:
            return "confirmed"
        if self.holds_for_origin(now):
            return "waiting"
        return "unconfirmed"

    def on_link_up(self, now: int) -> None:
        self.link_up_ns = now

    def holds_for_origin(self, now: int) -> bool:
        """True while poses are held until the autopilot confirms its origin: an origin is configured,
        hold_until_origin, the autopilot is talking (heard recently; or not yet, for the first
        ORIGIN_SILENT_GRACE_NS after the link came up: its first heartbeat may be a second away, and
        vision that reaches a running EKF before its origin is what this hold is for), and
        origin_confirm_timeout_s has not passed. A silent autopilot never holds the poses longer."""
        cfg = self.cfg
        if cfg.origin is None or not cfg.hold_until_origin or self.origin_confirmed:
            return False
        if self.autopilot is None:
            if now - self.link_up_ns < ORIGIN_SILENT_GRACE_NS:
                return True
            return self._origin_released("the autopilot has said nothing")
        if now - self.last_heard_ns > TELEMETRY_STALE_NS:
            return self._origin_released("the autopilot has gone quiet")
        if cfg.origin_confirm_timeout_s > 0 and now - self.first_heard_ns > cfg.origin_confirm_timeout_s * 1e9:
            return self._origin_released(f"it did not report it in {cfg.origin_confirm_timeout_s:g} s "
                                         "(origin_confirm_timeout_s)")
        return True

    def _origin_released(self, why: str) -> bool:
        """Poses go without a confirmed origin: say so once (False, for holds_for_origin)."""
        if not self._origin_release_said:
            self._origin_release_said = True
            log.warning("vehicle %s: sending poses although the autopilot has not confirmed its origin: %s. If its "
                        "EKF took vision before the origin, its height can stay centimetres off: then reboot the "
                        "autopilot (the origin is resent until it is confirmed)", self.cfg.name, why)
        return False

    def delay_advice(self) -> str:
        return advice_text(self.advice, self.delay_ms, self.delay_reason, self.cfg.answers_timesync,
                           self.delay_param_confirmed is not None)

    def snapshot(self, now: int) -> dict:
        ekf, ekf_detail = self.ekf_state(now)
        rtts = [r[2] for r in list(self.timesync.d)]  # list() copies under the GIL: health() runs on other threads
        return {
            "autopilot": self.autopilot,
            "autopilot_heard_s_ago": (now - self.last_heard_ns) * 1e-9 if self.last_heard_ns else None,
            "autopilot_messages": self.messages,
            "reboots": self.reboots,
            "timesync_rtt_ms": float(np.median(rtts)) * 1e-6 if rtts else None,
            "ekf": ekf,
            "ekf_detail": ekf_detail,
            "ekf_flags": self.ekf_flags,
            "ekf_test_ratios": dict(self.ekf_ratios),
            "ext_nav_statustext": self.ext_nav_text or None,
            "statustexts": [t for _, t in list(self.statustexts)],
            "identity": self.identity,
            "identity_detail": self.identity_reason,
            "identity_statistic": self.identity_statistic if np.isfinite(self.identity_statistic) else None,
            "identity_tripped_after_s": self.identity_tripped_after_s,
            "delay_ms": self.delay_ms,
            "delay_detail": self.delay_reason,
            "delay_advice": self.delay_advice(),
            "delay_param": self.advice.param if self.advice else None,
            "delay_advised_ms": self.advice.value_ms if self.advice else None,
            "delay_param_set": self.delay_param_confirmed,
            "delay_horizon_param": self.advice.horizon_param if self.advice else None,
            "delay_horizon_ms": self.advice.horizon_ms if self.advice else None,
            "origin": self.origin_state(now),
            "home_acked": self.home_acked,
            "home_reported": list(self.home_reported) if self.home_reported else None,
            "home_error_m": self.home_error_m,
            "gyro_source": self.gyro_source or None,
            "gyro_filter_hz": self.gyro_filter_hz,
            "local_position_ned": list(self.local_position) if self.local_position else None,
        }
