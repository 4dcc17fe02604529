"""Which delay each autopilot's estimator wants for the vision, from the poses' stamp-to-arrival delays.

The two estimators use the pose's stamp differently, so the same measured delays call for different settings:

- ArduPilot (EKF3). The stamp goes through GCS_MAVLINK::correct_offboard_timestamp_usec_to_ms, i.e.
  JitterCorrection::correct_offboard_timestamp_usec (libraries/AP_RTC/JitterCorrection.cpp): it tracks the
  smallest (arrival - stamp) seen and maps every stamp with it, so each pose is taken as if it had arrived with
  the smallest delay seen; the jitter is gone, and what is left is that smallest delay, which
  NavEKF3_core::writeExtNavData (libraries/AP_NavEKF3/AP_NavEKF3_Measurements.cpp) removes as its `delay_ms`
  argument, VISO_DELAY_MS. Its smallest is taken afresh every JITTER_WINDOW (100) messages (the minimum of
  the last window replaces it), so the advice is that: the median, over consecutive windows of 100 poses in
  arrival order, of each window's smallest delay (a single early outlier moves one window, not the advice).
  Two more terms from the source: the arrival GCS_MAVLINK takes is UARTDriver::receive_time_constraint_us,
  the read time less the message's bytes (PAYLOAD_SIZE: its length, 12 framing bytes, 13 of signature when
  signing) at 10 bits each at the port's baud, which SITL applies to its UDP ports as well (so the advice
  takes that transfer time off: ardupilot_transfer_ms); and the corrected time is floored to whole ms (half
  a ms early on average) while a pose is fused at the first EKF step (12.5 ms at a 400 Hz loop) at or after
  its time less half of 12 ms (a quarter ms late on average): EKF3_STAMP_MS. Against SITL, before these
  terms, the EKF wanted 0.9-3.9 ms (mean 2.2, 6 flights) less than the smallest stamp-to-arrival delay.
  The median delay over-delays every pose by (median - minimum): against SITL 16 ms instead of 7 ms put the EKF
  11-13 ms ahead of the truth (issue 31); so did a low percentile (p2) where the host's load spread the
  delays: p2 9-14 ms put the EKF 4-6 ms ahead in 3 flights, 5-8 ms 0.3-1.4 ms in 3.
- PX4 (EKF2). mavlink_receiver stamps the sample with the synchronised `time_usec` only while its TIMESYNC estimate
  has converged, else with the arrival time (../shared/sitl-px4/README.md); EKF2 then moves every sample back by
  EKF2_EV_DELAY (EstimatorInterface::setExtVisionData, src/modules/ekf2/EKF/estimator_interface.cpp: time_us -
  ev_delay_ms * 1000 - half an EKF step), no jitter correction. Stamped on arrival, each sample's error is its own
  delay less the setting, and EKF2's state, linear in what it fuses, follows their mean. Against PX4 SIH (issue 31, a
  26 s circle at 1.05 m/s, EKF2's lead read from PX4's own log), over 15 flights (13 direct, 2 through 20 and 50 ms
  added each way), EKF2's output led SIH's truth by 1.81 (+-0.25) times the setting less the mean of the poses'
  stamp-to-arrival delays on the bridge's side, less 2.44 (+-0.67) ms, with 2.1 ms of scatter from flight to flight:
  at the mean it trails, and it is on the truth 1.35 ms over the mean (EKF2_ARRIVAL_TRAIL_MS), which the advice adds.
  On ODOMETRY, whose velocity EKF2 fuses too (29 flights: 7 direct at means of 10-16 ms, 10 through 20 ms and 12
  through 50 ms added, circles of 26-86 s), EKF2's output was on the truth at 0.05 ms over the mean on the direct link
  (+-0.38 ms, the flights' standard error) and 1.93 ms over it through either relay (+-0.23): the advice takes the
  first up to a 14 ms mean, the second from 34 ms, a line between. Each flight scatters about 1 ms about that (EKF2's
  lead wanders over tens of seconds: two 86 s circles through 20 ms, set 0.5 and 1.2 ms over their mean, read -1.9 and
  +1.7 ms), and the delays are right: each flight's mean delay on PX4's clock (its fused samples' positions against
  SIH's truth, in its log) matched the bridge's within 0.6 ms. What moves it from the direct link to the relay is not
  found: not the delays' spread (alike) and not clearly the horizon (two direct flights with EKF2_DELAY_MAX 120, as
  through 50 ms: +2.7 and +0.7). EKF2_EV_DELAY is a float of one decimal, and the advice is given to 0.1 ms: rounded
  to whole ms it would be up to 0.5 ms off, 0.6-0.9 ms of lead. Why it trails on position alone is not found: EKF2's
  rate limit (a sample under an EKF step after the last one kept is dropped) keeps the poses that follow late ones
  less often, but moves the mean by under 1.5 ms; and with SIH's truth as the vision, its delays steady, EKF2 did not
  trail (+1.0 ms at 0.2 ms over). The mean on the bridge's side, which holds every pose: PX4's log keeps
  vehicle_visual_odometry at about 33 Hz, a subset of 50 Hz poses, and where the delays follow a pattern (the output
  ticks against the cameras' capture grid: two modes 8 ms apart) the subset can miss one mode (in one flight the log's
  70th percentile read 10.6 ms against the bridge's 20.3). Fitted on the log's subsets
  (34 flights) the 70th percentile had looked right; flown, it put EKF2 up to 8 ms ahead. Stamped with a converged
  TIMESYNC, the stamp is the pose's instant: 0.

Each estimator also keeps only so much IMU history (its delayed horizon), and a pose older than that is fused
as if it were as old as the horizon, i.e. newer than it is: the EKF then trails the truth whatever the delay
setting. So the advice also names the horizon the poses need (DelayAdvice.horizon_*):
- EKF3 sizes its buffer once, at boot (NavEKF3_core::setup_core): floor(M / 12 ms) + 1 samples of at least one
  EKF step (12 ms; 12.5 at a 400 Hz loop) each, M being the largest of its sensor delays (EK3_HGT_DELAY, 60 ms
  by default, EK3_FLOW_DELAY, EK3_BCN_DELAY, VISO_DELAY_MS), and writeExtNavData clamps an older pose to the
  buffer's oldest sample. Its jitter correction gives a pose the smallest delay plus its own lateness, so the
  poses reach back to about the p99 of the delays, plus half a step. Through a relay adding 50 ms each way
  (SITL, issue 31) the default buffer (62.5 ms) was short of that (about 80 ms): the EKF trailed the truth by
  15-20 ms with VISO_DELAY_MS as advised, 2 ms once the buffer was sized for it. EK3_BCN_DELAY, a delay EKF3
  uses only for range beacons, sizes the buffer without moving any sensor in time (reboot to apply).
- EKF2 keeps ceil(EKF2_DELAY_MAX / EKF2_PREDICT_US) IMU steps (EstimatorInterface::initialise_interface; read
  at start, raised to its largest sensor delay), and a step is the whole IMU samples nearest EKF2_PREDICT_US:
  8 ms from PX4 SIH's 250 Hz IMU. So the history reaches back (steps - 1) x 8 ms, not EKF2_DELAY_MAX: 24 ms
  for 40. A sample older than that is fused at the oldest step (newer than it is; past 100 ms, dropped).
  ekf2_horizon_ms: the setting for a sample stamped on arrival (the delay setting and half a step back), or,
  with a converged TIMESYNC, the delays' p99, plus one step of margin.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from bridge.signing import SIGNATURE_BLOCK_LEN

JITTER_WINDOW = 100  # JitterCorrection's convergence_loops (libraries/AP_RTC/JitterCorrection.h default)
PARAMS = {"ardupilot": "VISO_DELAY_MS", "px4": "EKF2_EV_DELAY"}
HORIZON_PERCENTILE = 99.0  # the poses' horizon covers this share of their delays


class Ekf2Trail(NamedTuple):
    """What EKF2 on the mean trails by (ms): ms_at_zero + per_ms x the mean delay, held within [least_ms, most_ms]."""
    ms_at_zero: float
    per_ms: float
    least_ms: float
    most_ms: float


# EKF2 on the mean trails as if the poses were this much older, by the message it fuses. PX4 SIH, fitted on the lead
# against the setting less the mean: VISION_POSITION_ESTIMATE 15 flights; ODOMETRY, whose velocity it fuses too,
# 29 flights: +0.05 ms on a direct link (means of 10-16 ms), +1.93 through 20 or 50 ms added, a line between the two
# clusters' means (14 and 34 ms)
EKF2_ARRIVAL_TRAIL_MS = {"vision_position_estimate": Ekf2Trail(1.35, 0.0, 1.35, 1.35),
                         "odometry": Ekf2Trail(-1.26, 0.094, 0.05, 1.93)}
EKF3_SLOT_MS = 12  # EKF_TARGET_DT_MS: one buffer sample per this much of the largest delay, each at least this long
EKF3_HALF_STEP_MS = 6.0  # writeExtNavData also moves each pose back by half an EKF step
EKF3_DEFAULT_LARGEST_DELAY_MS = 60  # EK3_HGT_DELAY's default, the largest of EKF3's delays unless one is raised
EKF3_MAX_DELAY_MS = 250  # the delay parameters' range, and what EKF3 takes of VISO_DELAY_MS for its buffer
EKF3_HORIZON_PARAM = "EK3_BCN_DELAY"  # used only for range beacons: it sizes the buffer and moves no sensor
MAVLINK2_FRAMING_BYTES = mavlink2.HEADER_LEN_V2 + 2  # MAVLINK_NUM_NON_PAYLOAD_BYTES: header and checksum
# MAVLINK_MSG_ID_*_LEN: the full payload, as PAYLOAD_SIZE counts it (MAVLink2's trailing-zero cut left aside)
MESSAGE_PAYLOAD_BYTES = {"vision_position_estimate": mavlink2.MAVLink_vision_position_estimate_message.unpacker.size,
                         "odometry": mavlink2.MAVLink_odometry_message.unpacker.size}
EKF3_STAMP_MS = -0.25  # the corrected stamp floored to whole ms (-0.5) and fused at the first 12.5 ms EKF step
# at or after it less half of 12 (+0.25): on average
EKF2_PREDICT_MS = 10.0  # EKF2_PREDICT_US's default: EKF2 keeps ceil(EKF2_DELAY_MAX / this) IMU steps
EKF2_STEP_MIN_MS = 8.0  # the shortest such step of common IMU rates: two 4 ms samples (PX4 SIH's 250 Hz IMU)


@dataclasses.dataclass(frozen=True)
class DelayAdvice:
    param: str  # the autopilot parameter (VISO_DELAY_MS, EKF2_EV_DELAY)
    value_ms: float  # what to set it to (VISO_DELAY_MS whole ms, an INT16; EKF2_EV_DELAY to 0.1 ms, a float)
    why: str  # one phrase: which statistic of the delays, and why
    # the estimator's horizon the poses need, where its default falls short (ArduPilot: None when
    # EK3_HGT_DELAY's default buffer holds them; PX4: always, EKF2_DELAY_MAX's default being far too long)
    horizon_param: str | None = None  # EK3_BCN_DELAY, EKF2_DELAY_MAX; both need a reboot
    horizon_ms: int | None = None
    horizon_why: str = ""


def ardupilot_transfer_ms(message: str, signed: bool, baud: int | None) -> float:
    """How far ArduPilot moves a pose's arrival back (ms): its bytes (payload, framing, signature) at 10 bits
    each at the port's baud; 0 when the baud is not known."""
    if not baud:
        return 0.0
    n = MESSAGE_PAYLOAD_BYTES[message] + MAVLINK2_FRAMING_BYTES + (SIGNATURE_BLOCK_LEN if signed else 0)
    return n * 10.0 / baud * 1e3


def jitter_corrected_delay_ms(stamp_to_arrival_ms: np.ndarray) -> float:
    """The delay ArduPilot's jitter correction gives the poses (ms): the median, over consecutive windows of
    JITTER_WINDOW delays (N,) in arrival order, of each window's smallest (the smallest of all for fewer; a last
    partial window counts only if it holds half a window)."""
    d = np.asarray(stamp_to_arrival_ms, dtype=np.float64)
    full = len(d) // JITTER_WINDOW
    if full == 0:
        return float(d.min())
    mins = list(d[: full * JITTER_WINDOW].reshape(full, JITTER_WINDOW).min(axis=1))
    if len(d) - full * JITTER_WINDOW >= JITTER_WINDOW // 2:
        mins.append(float(d[full * JITTER_WINDOW:].min()))
    return float(np.median(mins))


def ekf3_history_ms(largest_delay_ms: float) -> float:
    """The IMU history (ms) EKF3 keeps for a largest sensor delay of largest_delay_ms at boot: floor(M / 12)
    steps of at least 12 ms (NavEKF3_core::setup_core; a lower bound: 12.5 ms steps at a 400 Hz loop)."""
    return (min(largest_delay_ms, EKF3_MAX_DELAY_MS) // EKF3_SLOT_MS) * EKF3_SLOT_MS


def ekf3_history_param_ms(oldest_ms: float, largest_delay_ms: float = EKF3_DEFAULT_LARGEST_DELAY_MS) -> int | None:
    """The EKF3_HORIZON_PARAM value (ms) a pose oldest_ms old needs when EKF3's history for largest_delay_ms
    (ekf3_history_ms) falls short of it; None when it holds the pose. At most EKF3_MAX_DELAY_MS."""
    if ekf3_history_ms(largest_delay_ms) >= oldest_ms:
        return None
    return min(ekf3_largest_delay_for(oldest_ms), EKF3_MAX_DELAY_MS)


def ekf3_largest_delay_for(oldest_ms: float) -> int:
    """The smallest largest-delay setting (ms, whole slots) whose buffer (ekf3_history_ms) holds a pose
    oldest_ms old: may exceed EKF3_MAX_DELAY_MS, which EKF3 cannot hold."""
    return EKF3_SLOT_MS * max(1, math.ceil(oldest_ms / EKF3_SLOT_MS))


def ekf2_horizon_ms(oldest_ms: float) -> int:
    """EKF2_DELAY_MAX (ms) whose IMU history holds a sample oldest_ms old on EKF2's clock: ceil(setting /
    EKF2_PREDICT_MS) steps reach back one fewer steps of as little as EKF2_STEP_MIN_MS; one more step is the
    margin."""
    steps = math.ceil(max(0.0, oldest_ms) / EKF2_STEP_MIN_MS) + 2
    return int(steps * EKF2_PREDICT_MS)


def ekf2_arrival_horizon_ms(ev_delay_ms: float) -> int:
    """ekf2_horizon_ms for a sample stamped on arrival with EKF2_EV_DELAY ev_delay_ms: EKF2 moves it back that
    and half a step."""
    return ekf2_horizon_ms(ev_delay_ms + EKF2_STEP_MIN_MS / 2)


def ekf2_arrival_trail_ms(message: str, mean_delay_ms: float) -> float:
    """What EKF2 trails by (ms) over the mean stamp-to-arrival delay mean_delay_ms of poses sent as message."""
    t = EKF2_ARRIVAL_TRAIL_MS[message]
    return min(t.most_ms, max(t.least_ms, t.ms_at_zero + t.per_ms * mean_delay_ms))


def advised_delay(autopilot: str | None, stamp_to_arrival_ms: np.ndarray, px4_timesync_converged: bool = False,
                  transfer_ms: float = 0.0, message: str = "vision_position_estimate") -> DelayAdvice | None:
    """The delay parameter to set for `autopilot` ('ardupilot', 'px4'; any other is taken as ArduPilot, the
    estimator that reads the stamps as ArduPilot does) from the poses' stamp-to-arrival delays (N,) ms on the
    autopilot's side; None without delays. px4_timesync_converged: PX4 maps time_usec with a converged TIMESYNC
    (its samples then carry their own instant). transfer_ms: ArduPilot's move of each arrival back
    (ardupilot_transfer_ms). message: the pose message sent (PX4's EKF2 trails by its own amount on each)."""
    d = np.asarray(stamp_to_arrival_ms, dtype=np.float64)
    d = d[np.isfinite(d)]
    if not len(d):
        return None
    if autopilot == "px4":
        if px4_timesync_converged:
            late = float(np.percentile(d, HORIZON_PERCENTILE))
            return DelayAdvice("EKF2_EV_DELAY", 0, "PX4 stamps the poses with their own time (TIMESYNC converged)",
                               "EKF2_DELAY_MAX", ekf2_horizon_ms(late),
                               f"the poses reach back {late:.0f} ms (p{HORIZON_PERCENTILE:g}); EKF2's IMU steps "
                               f"can be {EKF2_STEP_MIN_MS:g} ms, and one more is the margin")
        mean = float(d.mean())
        trail = ekf2_arrival_trail_ms(message, mean)
        v = round(max(0.0, mean + trail), 1)  # EKF2_EV_DELAY: a float of one decimal
        return DelayAdvice("EKF2_EV_DELAY", v, f"the mean stamp-to-arrival delay and {trail:+.2f} ms (PX4 stamps "
                           "each pose on arrival, and EKF2 follows the mean of their timing errors, on "
                           f"{message.upper()} by this much more: measured against PX4 SIH)",
                           "EKF2_DELAY_MAX", ekf2_arrival_horizon_ms(v),
                           f"EKF2_EV_DELAY and half a step, in EKF2's IMU steps of as little as "
                           f"{EKF2_STEP_MIN_MS:g} ms, and one more: a shorter horizon carries less IMU noise to the "
                           "output")
    v = int(round(max(0.0, jitter_corrected_delay_ms(d) - transfer_ms + EKF3_STAMP_MS)))
    why = (f"the smallest stamp-to-arrival delay (ArduPilot's jitter correction gives every pose the smallest "
           f"delay of its last {JITTER_WINDOW} messages: the median of such minima)"
           + (f", less the {transfer_ms:.1f} ms its port's baud takes off each arrival" if transfer_ms else ""))
    late = float(np.percentile(d, HORIZON_PERCENTILE))
    oldest = late + EKF3_HALF_STEP_MS
    horizon = ekf3_history_param_ms(oldest, max(EKF3_DEFAULT_LARGEST_DELAY_MS, v))
    if horizon is None:
        return DelayAdvice("VISO_DELAY_MS", v, why)
    return DelayAdvice("VISO_DELAY_MS", v, why, EKF3_HORIZON_PARAM, horizon,
                       f"poses reach EKF3 up to {late:.0f} ms (p{HORIZON_PERCENTILE:g}) after their stamp, older "
                       f"than its IMU history (sized at boot from its largest sensor delay, EK3_HGT_DELAY's "
                       f"{EKF3_DEFAULT_LARGEST_DELAY_MS} ms by default), which takes them as newer than they are; "
                       f"{EKF3_HORIZON_PARAM} (used only for range beacons) sizes it: set it and reboot"
                       + ("" if ekf3_largest_delay_for(oldest) <= EKF3_MAX_DELAY_MS else
                          f"; even its largest, {EKF3_MAX_DELAY_MS} ms, is short: this link is too slow"))


def advice_text(advice: DelayAdvice | None, measured_ms: float | None, reason: str, answers_px4_timesync: bool,
                set_on_autopilot: bool) -> str:
    """The advice in one line, as the log and the health say it: the measured delay (or why there is none), the
    parameter to set and why, for PX4 what its TIMESYNC changes (answers_px4_timesync: the link answers PX4's
    requests), the horizon where it matters."""
    if advice is None:
        return f"delay not measured ({reason})"
    a = advice
    text = (f"measured capture->autopilot delay {measured_ms:.1f} ms (median)" if measured_ms is not None
            else f"delay not measured ({reason})") + f": set {a.param}={a.value_ms}, {a.why}"
    if a.param == "EKF2_EV_DELAY" and a.value_ms > 0:
        text += ("; 0 once PX4's TIMESYNC has converged (about 50 s of our answers at round trips under 10 ms; "
                 "its timesync_status shows it)" if answers_px4_timesync else
                 "; PX4's TIMESYNC requests are not answered on this link (answer_timesync), so it stays so")
    if a.horizon_param is not None:
        text += f"; {a.horizon_param}={a.horizon_ms}: {a.horizon_why}"
    return text + (" (set on the autopilot)" if set_on_autopilot else "")
