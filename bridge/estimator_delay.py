"""Which delay each autopilot's estimator wants for the vision, from the poses' stamp-to-arrival delays.

The two estimators use the pose's stamp differently, so the same measured delays call for different settings:

- ArduPilot (EKF3). The stamp goes through GCS_MAVLINK::correct_offboard_timestamp_usec_to_ms, i.e.
  JitterCorrection::correct_offboard_timestamp_usec (libraries/AP_RTC/JitterCorrection.cpp): it tracks the
  smallest (arrival - stamp) seen and maps every stamp with it, so each pose is taken as if it had arrived with
  the smallest delay seen; the jitter is gone, and what is left is that smallest delay, which
  NavEKF3_core::writeExtNavData (libraries/AP_NavEKF3/AP_NavEKF3_Measurements.cpp) removes as its `delay_ms`
  argument, VISO_DELAY_MS. So VISO_DELAY_MS wants about the smallest stamp-to-arrival delay: a low percentile
  (ARDUPILOT_PERCENTILE; a single early outlier sets ArduPilot's own minimum too, but not the advice). The median
  over-delays every pose by (median - minimum): against SITL 16 ms instead of 7 ms put the EKF 11-13 ms ahead
  of the truth (issue 31).
- PX4 (EKF2). mavlink_receiver stamps the sample with the synchronised `time_usec` only while its TIMESYNC
  estimate has converged, else with the arrival time (../shared/sitl-px4/README.md); EKF2 then moves every
  sample back by EKF2_EV_DELAY (EstimatorInterface::setExtVisionData, src/modules/ekf2/EKF/
  estimator_interface.cpp: time_us - ev_delay_ms * 1000 - half an EKF step), no jitter correction. Stamped on
  arrival, each sample's error is its own delay less the setting: the median of the delays makes the errors
  balance (PX4_PERCENTILE). Stamped with a converged TIMESYNC, the stamp is the pose's instant: 0.
"""

from __future__ import annotations

import dataclasses

import numpy as np

ARDUPILOT_PERCENTILE = 2.0  # about the smallest delay, robust to a stray early sample
PX4_PERCENTILE = 50.0
PARAMS = {"ardupilot": "VISO_DELAY_MS", "px4": "EKF2_EV_DELAY"}


@dataclasses.dataclass(frozen=True)
class DelayAdvice:
    param: str  # the autopilot parameter (VISO_DELAY_MS, EKF2_EV_DELAY)
    value_ms: int  # what to set it to (whole ms: both parameters are)
    why: str  # one phrase: which statistic of the delays, and why


def advised_delay(autopilot: str | None, stamp_to_arrival_ms: np.ndarray, px4_timesync_converged: bool = False,
                  ) -> DelayAdvice | None:
    """The delay parameter to set for `autopilot` ('ardupilot', 'px4'; any other is taken as ArduPilot, the
    estimator that reads the stamps as ArduPilot does) from the poses' stamp-to-arrival delays (N,) ms on the
    autopilot's side; None without delays. px4_timesync_converged: PX4 maps time_usec with a converged TIMESYNC
    (its samples then carry their own instant)."""
    d = np.asarray(stamp_to_arrival_ms, dtype=np.float64)
    d = d[np.isfinite(d)]
    if not len(d):
        return None
    if autopilot == "px4":
        if px4_timesync_converged:
            return DelayAdvice("EKF2_EV_DELAY", 0, "PX4 stamps the poses with their own time (TIMESYNC converged)")
        v = float(np.percentile(d, PX4_PERCENTILE))
        return DelayAdvice("EKF2_EV_DELAY", int(round(max(0.0, v))),
                           "the median stamp-to-arrival delay (PX4 stamps each pose on arrival)")
    v = float(np.percentile(d, ARDUPILOT_PERCENTILE))
    return DelayAdvice("VISO_DELAY_MS", int(round(max(0.0, v))),
                       f"the smallest stamp-to-arrival delay (p{ARDUPILOT_PERCENTILE:g}: ArduPilot's jitter "
                       "correction gives every pose the smallest delay it has seen)")
