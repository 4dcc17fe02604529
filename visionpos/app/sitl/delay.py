"""The back-channel's measured capture-to-autopilot delay against the true one on SITL's clock, for a
vision link through a DelayRelay (`visionpos sitl --link-delay-ms`, the sitl_delay benchmark).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from visionpos.app.sitl.clock import SitlClock
from visionpos.app.sitl.truth import TruthTrack


def fmt_ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def delay_record(bc: Any, relay: Any, added_ms: float, truth: TruthTrack | None = None,
                 window_ns: int | None = None, clock: SitlClock | None = None) -> dict[str, Any]:
    """The back-channel's measured capture-to-autopilot delay against the true one, for a link through relay.

    True delay, on SITL's clock (the one VISO_DELAY_MS is on): the SITL time at which SITL takes in a pose,
    less the SITL time of the physics the pose shows. Its parts, each the median over the back-channel's
    measurement window (the optical span of its last figure, bc.delay_window_ns; else the newest window_ns,
    DELAY_WINDOW_NS):
    - the bridge's write to its socket less the pose's stamp (our clock);
    - the relay's hold of the datagrams towards SITL (our clock; loopback adds microseconds);
    - with clock (SitlClock): SIM_STATE's age, our arrival time less its SITL time (the cameras render the
      truth as of its arrival, so a pose stamped t shows SITL's physics of that much earlier), plus how late
      SITL takes in a datagram the relay sends on the vision link (its receive time in TIMESYNC's tc1 less the
      relay's send time; IntakeProbe): their sum cancels both clocks' offsets.
    Without clock (or too few records) the last part is missing and true_ms is None. Not in it: the
    bridge's write to the relay's read (loopback and the relay thread's wake-up, a median under 0.1 ms), and
    the poses' own lag behind the motion they render (the fusion's), which the back-channel counts.
    true_motion_ms counts it: the SITL time of the intake less the SITL time of the motion the poses show
    (their body rates correlated with SIM_STATE's at the SITL times of its buckets), so error_motion_ms is
    the back-channel's own error (its gyro filter model and TIMESYNC).
    Left out: RAW_IMU's own timing (stamped when sent, at the step of its loop, which is the instant its gyro
    describes, bar the gyro filter's lag that the back-channel removes). optical_lag_ms, for diagnosis: how far
    the poses' body rates trail SIM_STATE's as stamped here (the fusion's lag; a bias of the optics, which the
    measurement sees and the true delay does not)."""
    from bridge.backchannel import DELAY_WINDOW_NS
    from visionpos.analysis.autopilot import theil_sen_at

    now = time.monotonic_ns()
    since = now - (window_ns if window_ns is not None else DELAY_WINDOW_NS)
    until = now
    win = getattr(bc, "delay_window_ns", None)
    if window_ns is None and win is not None:  # the span the measurement used: the link's figures drift
        since, until = win
    sends = np.array([r[1] for r in list(bc.sends.d) if since <= r[0] <= until], dtype=float)  # list(): a copy
    hold_ms = relay.hold_ms_median("to_autopilot", since, until)
    lag_ms = _optical_lag_ms(bc, truth, since) if truth is not None else None
    sitl = clock.summary(since, until) if clock is not None else {}
    sitl_ms = sitl.get("sitl_term_ms")
    true_ms = (float(np.median(sends)) * 1e-6 + hold_ms + sitl_ms
               if len(sends) and hold_ms is not None and sitl_ms is not None else None)
    measured = bc.delay_ms
    shown = _shown_lag_ms(bc, truth, clock, since) if truth is not None and clock is not None else None
    intake = np.array([r for r in list(clock.intake) if r[0] >= since], dtype=np.int64).reshape(-1, 2) \
        if clock is not None else np.zeros((0, 2), np.int64)
    motion_ms = None
    if true_ms is not None and shown is not None and len(intake) >= SitlClock.MIN_TIMESYNCS:
        # the intake at the instant the correlation stands for: SITL's clock drifts from ours
        fwd_ms = theil_sen_at(intake[:, 0], (intake[:, 1] - intake[:, 0]).astype(float), shown[1]) * 1e-6
        motion_ms = true_ms - sitl_ms + fwd_ms - shown[0]
    shown_ms = shown[0] if shown is not None else None
    return {"added_ms": float(added_ms), "measured_ms": measured, "true_ms": true_ms,
            "true_motion_ms": motion_ms, "shown_lag_ms": shown_ms,
            "error_motion_ms": measured - motion_ms if measured is not None and motion_ms is not None else None,
            "error_ms": measured - true_ms if measured is not None and true_ms is not None else None,
            "send_minus_stamp_ms_p50": float(np.median(sends)) * 1e-6 if len(sends) else None,
            "relay_hold_ms_p50": hold_ms, "relay_hold_back_ms_p50": relay.hold_ms_median("to_bridge", since),
            "sitl_clock_ms": sitl_ms, "sitl_clock_serial0_ms": sitl.get("sitl_term_serial0_ms"),
            "sitl_clock_records": (sitl.get("truth_pairs"), sitl.get("intake_timesyncs"), sitl.get("gcs_timesyncs")),
            "sitl_bucket_mismatch_fraction": sitl.get("bucket_mismatch_fraction"),
            "optical_lag_ms": lag_ms,
            "correlation": float(bc.delay_correlation) if np.isfinite(bc.delay_correlation) else None,
            "gyro_source": bc.gyro_source or None, "detail": bc.delay_reason}


def _shown_lag_ms(bc: Any, truth: TruthTrack, clock: SitlClock, since_ns: int) -> tuple[float, float] | None:
    """The SITL time of the motion a pose shows less the pose's stamp (ms, offset-laden like SitlClock's
    records), and the instant (server clock, ns) it stands for: the poses' body rates (from their attitudes)
    correlated with SIM_STATE's body rates at the SITL times of their buckets; None without enough rotation
    or records."""
    from visionpos.analysis.autopilot import body_rates_from_attitudes, estimate_lag, weighted_time_ns
    from visionpos.geometry.frames import flu_to_frd

    pairs = np.array([r for r in list(clock.truth) if r[0] >= since_ns], dtype=np.int64).reshape(-1, 2)
    rows = [r for r in list(bc.opt.d) if r[0] >= since_ns]
    t_true, x = truth.snapshot()
    keep = t_true >= since_ns
    if len(rows) < 50 or len(pairs) < 50 or keep.sum() < 50:
        return None
    off = pairs[:, 1] - pairs[:, 0]  # SITL time less arrival, per SIM_STATE: interpolated onto the track's
    t_sitl = t_true[keep] + np.round(np.interp(t_true[keep], pairs[:, 0], off)).astype(np.int64)
    to, rates = body_rates_from_attitudes(np.array([r[0] for r in rows], dtype=np.int64),
                                          np.array([r[6:10] for r in rows], dtype=float))
    est = estimate_lag(to, rates, t_sitl, flu_to_frd(x[keep, 10:13]), float(np.median(off)), 60e6, step_ns=1e6)
    if est is None or est.correlation <= 0.8:
        return None
    return est.lag_ns * 1e-6, weighted_time_ns(to, rates)


def _optical_lag_ms(bc: Any, truth: TruthTrack, since_ns: int) -> float | None:
    """How far the bridge's poses trail SITL's truth (ms, server clock): the lag of the body rates from the
    poses' attitudes (as the back-channel derives them) behind SIM_STATE's body rates, since since_ns;
    None without enough rotation to correlate."""
    from visionpos.analysis.autopilot import body_rates_from_attitudes, estimate_lag
    from visionpos.geometry.frames import flu_to_frd

    rows = [r for r in list(bc.opt.d) if r[0] >= since_ns]
    t_true, x = truth.snapshot()
    keep = t_true >= since_ns
    if len(rows) < 50 or keep.sum() < 50:
        return None
    to, rates = body_rates_from_attitudes(np.array([r[0] for r in rows], dtype=np.int64),
                                          np.array([r[6:10] for r in rows], dtype=float))
    est = estimate_lag(t_true[keep], flu_to_frd(x[keep, 10:13]), to, rates, 0.0, 50e6, step_ns=1e6)
    return est.lag_ns * 1e-6 if est is not None and est.correlation > 0.8 else None
