"""EKF2's output against SIH's truth from PX4's own flight log (ULog), both on PX4's clock: `vehicle_local_position`
(what PX4 flies on and sends as LOCAL_POSITION_NED) against `vehicle_local_position_groundtruth`, as
report.ekf_lead_ms does on the host, here without the telemetry's transport in either. A check on the host's
figure, which compares two MAVLink streams as they arrive.

A vision gap (no pose fused, `estimator_aid_src_ev_pos`, for over GAP_NS: a cut) and the second after it are left
out of the fit. EKF2's vision innovations are not used to time the vision: EKF2's state follows the vision it
fuses, so a pose placed late moves the state with it, and the innovations against the true velocity read
1.5-2.8 ms whether EKF2_EV_DELAY was 35 or 43 ms (issue 31). Reading the log needs pyulog (PX4's ULog parser; the
`px4log` extra); without it, and without a log, the figure is missing and `error` says why.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from visionpos.app.sitl.flight import CIRCLE_PERIOD_S, CIRCLE_SPEED_M_S
from visionpos.app.sitl.report import CUT_SETTLE_NS, time_shift_fit

GAP_NS = 500_000_000


def _shift_against_truth(t_ns: np.ndarray, xy: np.ndarray, keep: np.ndarray, truth_t_ns: np.ndarray,
                         truth_xy: np.ndarray, truth_vel: np.ndarray, detrend_ns: int | None = None
                         ) -> tuple[float, float | None, int] | None:
    """time_shift_fit of the kept rows of xy (N, 2) m at t_ns (N,) against the truth interpolated there."""
    t = t_ns[keep]
    at = [np.column_stack([np.interp(t, truth_t_ns, y[:, j]) for j in range(2)]) for y in (truth_xy, truth_vel)]
    return time_shift_fit(t, np.asarray(xy)[keep] - at[0], at[1], detrend_ns=detrend_ns)


def output_lead(ev_t_us: np.ndarray, ev_fused: np.ndarray, out_t_us: np.ndarray, out_xy: np.ndarray,
                truth_t_us: np.ndarray, truth_xy: np.ndarray, truth_vel: np.ndarray) -> dict[str, Any]:
    """EKF2's output lead (time_shift_fit: ms, its standard error, samples) from the log's arrays, times in us on
    PX4's clock: the vision samples (N,) and whether each was fused (N,); the output (M,) and its NE position
    (M, 2) m; the truth (K,), its NE position (K, 2) m and velocity (K, 2) m/s. {} with too little motion."""
    ev_t, out_t, tt = (np.asarray(x, dtype=np.int64) * 1000 for x in (ev_t_us, out_t_us, truth_t_us))
    ft = ev_t[np.asarray(ev_fused, dtype=bool)]
    keep = (out_t >= max(tt[0], ft[0] if len(ft) else tt[-1])) & (out_t <= tt[-1])
    for a, b in zip(ft[:-1], ft[1:]):
        if b - a > GAP_NS:
            keep &= ~((out_t > a) & (out_t < b + CUT_SETTLE_NS))
    fit = _shift_against_truth(out_t, out_xy, keep, tt, truth_xy, truth_vel)
    return {} if fit is None else dict(zip(("output_lead_ms", "output_lead_se_ms", "output_samples"), fit))


def circle_span(t_ns: np.ndarray, vel: np.ndarray) -> tuple[int, int] | None:
    """The flight's circle (flight.py) on the truth's clock: the longest stretch of t_ns (N,) with the speed of
    vel (N, 2) m/s over half the circle's (dips shorter than half a turn bridged: PX4 tracks the circle
    unevenly), less its first turn; None under two turns."""
    period_ns = int(CIRCLE_PERIOD_S * 1e9)
    fast = np.flatnonzero(np.hypot(vel[:, 0], vel[:, 1]) > 0.5 * CIRCLE_SPEED_M_S)
    if not len(fast):
        return None
    runs = np.split(fast, np.flatnonzero(np.diff(t_ns[fast]) > period_ns // 2) + 1)
    run = max(runs, key=lambda r: t_ns[r[-1]] - t_ns[r[0]])
    a, b = int(t_ns[run[0]]) + period_ns, int(t_ns[run[-1]])
    return (a, b) if b - a >= period_ns else None


def circle_leads(ev_t_us: np.ndarray, ev_xy: np.ndarray, out_t_us: np.ndarray, out_xy: np.ndarray,
                 truth_t_us: np.ndarray, truth_xy: np.ndarray, truth_vel: np.ndarray) -> dict[str, Any]:
    """On the circle (circle_span), each turn's drift taken out (time_shift_fit's detrend): how far EKF2's output
    runs ahead of SIH's truth (ms, standard error, samples), and how old the vision samples are on arrival: the
    shift of their position against the truth at their arrival stamp, negated (ms, standard error), on PX4's clock.
    Arrays as output_lead's, ev_xy (N, 2) the samples' NE position; {} without a circle."""
    tt = np.asarray(truth_t_us, dtype=np.int64) * 1000
    span = circle_span(tt, np.asarray(truth_vel))
    if span is None:
        return {}

    def fit(t_us: np.ndarray, xy: np.ndarray) -> tuple[float, float | None, int] | None:
        t = np.asarray(t_us, dtype=np.int64) * 1000
        return _shift_against_truth(t, xy, (t >= span[0]) & (t <= span[1]), tt, truth_xy, truth_vel,
                                    detrend_ns=int(CIRCLE_PERIOD_S * 1e9))

    out: dict[str, Any] = {"circle_s": (span[1] - span[0]) * 1e-9}
    lead, age = fit(out_t_us, out_xy), fit(ev_t_us, ev_xy)
    if lead is not None:
        out["output_lead_circle_ms"], out["output_lead_circle_se_ms"], out["output_circle_samples"] = lead
    if age is not None:
        out["vision_delay_circle_ms"], out["vision_delay_circle_se_ms"] = -age[0], age[1]
    return out


def read_px4_log(folder: str | Path) -> dict[str, Any]:
    """output_lead and circle_leads from the newest ULog under a PX4 working folder (log/<date>/*.ulg), or
    {'error': why}."""
    logs = sorted(Path(folder).glob("log/*/*.ulg"), key=lambda p: p.stat().st_mtime)
    if not logs:
        return {"error": f"no ULog under {folder}/log"}
    try:
        from pyulog import ULog
    except ImportError:
        return {"error": "pyulog is not installed (the px4log extra): PX4's log not read"}
    names = ["estimator_aid_src_ev_pos", "vehicle_local_position", "vehicle_local_position_groundtruth",
             "vehicle_visual_odometry"]
    try:
        u = ULog(str(logs[-1]), names)
        d = {x.name: x.data for x in u.data_list if x.multi_id == 0}
        ev, lp, gt, vo = (d[n] for n in names)
    except Exception as e:  # a log cut short (PX4 killed while writing) or without those topics
        return {"error": f"{logs[-1].name}: {type(e).__name__}: {e}"}
    out_xy, truth = np.column_stack([lp["x"], lp["y"]]), (gt["timestamp_sample"], np.column_stack([gt["x"], gt["y"]]),
                                                          np.column_stack([gt["vx"], gt["vy"]]))
    return {**output_lead(ev["timestamp_sample"], ev["fused"], lp["timestamp_sample"], out_xy, *truth),
            **circle_leads(vo["timestamp_sample"], np.column_stack([vo["position[0]"], vo["position[1]"]]),
                           lp["timestamp_sample"], out_xy, *truth)}
