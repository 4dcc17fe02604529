"""The flight's summary: the EKF and the vision against SITL's truth, test ratios, texts, failsafes;
format_flight prints it.
"""

from __future__ import annotations

import time
from typing import Any, Callable, TextIO

import numpy as np

from visionpos.app.sitl.delay import fmt_ms
from visionpos.app.sitl.flight import CIRCLE_PERIOD_S, FlightPlan
from visionpos.app.sitl.gcs import COPTER_MODES, MODE_NAMES, Gcs
from visionpos.app.sitl.truth import LATE_NS, TruthTrack
from visionpos.geometry.frames import euler_ned_frd, ned_to_world, world_to_ned


def _pcts(v: np.ndarray) -> dict[str, float | None]:
    if len(v) == 0:
        return {"p50": None, "p99": None, "max": None}
    return {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99)), "max": float(v.max())}


def say_to(out: TextIO | None) -> Callable[[str], None]:
    """The flight's running commentary: each line written and flushed to out, or dropped (None)."""
    if out is None:
        return lambda text: None
    return lambda text: (out.write(text + "\n"), out.flush(), None)[-1]


LEAD_MIN_SPEED_M_S = 0.1  # samples slower than this carry no timing information
LEAD_MIN_SAMPLES = 50
LEAD_SE_BLOCK_NS = 1_000_000_000
CUT_SETTLE_NS = 1_000_000_000  # after a vision cut, the EKF's pull back to the vision: left out with the cut
YAW_LEAD_MIN_RATE_RAD_S = 0.2
YAW_RATE_STEP_NS = 5_000_000  # the true yaw rate: central difference over twice this


def minus_moving_mean(t_ns: np.ndarray, y: np.ndarray, window_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """y (T, k) less its mean over the samples within window_ns / 2 either side of each (t_ns (T,) ascending),
    and the mask (T,) of the samples whose whole window lies inside the record (the others' means are one-sided).
    Over one period of a periodic motion this takes out what drifts slower than the motion and keeps the motion."""
    t = np.asarray(t_ns, dtype=np.int64)
    c = np.vstack([np.zeros((1, y.shape[1])), np.cumsum(y, axis=0)])
    lo = np.searchsorted(t, t - window_ns // 2, "left")
    hi = np.searchsorted(t, t + window_ns // 2, "right")
    whole = (t - window_ns // 2 >= t[0]) & (t + window_ns // 2 <= t[-1]) if len(t) else np.zeros(0, bool)
    return y - (c[hi] - c[lo]) / (hi - lo)[:, None], whole


def time_shift_fit(t_ns: np.ndarray, err: np.ndarray, vel: np.ndarray, min_speed_m_s: float = LEAD_MIN_SPEED_M_S,
                   block_ns: int = LEAD_SE_BLOCK_NS, detrend_ns: int | None = None
                   ) -> tuple[float, float | None, int] | None:
    """The time shift tau (ms) with err = vel * tau + c, fitted by least squares over both horizontal axes on the
    samples moving faster than min_speed_m_s; its standard error (ms) by the jackknife over blocks of block_ns (an
    EKF's error wanders over about a second, so neighbouring samples are not independent and the blocks are;
    None under 3 blocks); and the samples used. t_ns (T,); err, vel (T, 2) m and m/s. With detrend_ns (one period
    of a periodic flight), err and vel each less their moving mean over it first (minus_moving_mean): c then
    drifts, and the samples within half a period of either end are left out. None under LEAD_MIN_SAMPLES moving
    samples."""
    t_ns, err, vel = np.asarray(t_ns, dtype=np.int64), np.asarray(err, dtype=float), np.asarray(vel, dtype=float)
    if detrend_ns is not None and len(t_ns):
        (err, whole), (vel, _) = (minus_moving_mean(t_ns, x, detrend_ns) for x in (err, vel))
        t_ns, err, vel = t_ns[whole], err[whole], vel[whole]
    moving = np.hypot(vel[:, 0], vel[:, 1]) > min_speed_m_s
    n = int(moving.sum())
    if n < LEAD_MIN_SAMPLES:
        return None
    t, e, v = t_ns[moving], err[moving], vel[moving]

    def fit(keep: np.ndarray) -> float | None:
        if keep.sum() < LEAD_MIN_SAMPLES:
            return None
        ek, vk = e[keep] - e[keep].mean(axis=0), v[keep] - v[keep].mean(axis=0)
        return float((ek * vk).sum() / (vk * vk).sum() * 1e3)

    block = (t - t[0]) // block_ns
    leads = [x for b in np.unique(block) if (x := fit(block != b)) is not None]
    se = None
    if len(leads) >= 3:
        a = np.array(leads)
        se = float(np.sqrt((len(a) - 1) / len(a) * ((a - a.mean()) ** 2).sum()))
    return fit(np.ones(n, dtype=bool)), se, n


def _ekf_error_and_velocity(t_ns: np.ndarray, ekf_ned: np.ndarray, truth: TruthTrack) -> tuple[np.ndarray, ...]:
    p, v, _, _ = truth.sample(np.asarray(t_ns).astype(np.int64))
    return (ekf_ned - world_to_ned(p))[:, :2], world_to_ned(v)[:, :2]


def ekf_lead_fit(t_ns: np.ndarray, ekf_ned: np.ndarray, truth: TruthTrack, detrend_ns: int | None = None
                 ) -> tuple[float, float | None, int] | None:
    """How far ahead of the truth the EKF's horizontal position runs (ms; negative: behind), its standard error
    and the samples the fit used: the shift tau with ekf(t) = truth(t + tau) (time_shift_fit, detrend_ns passed
    on). t_ns (T,): arrival times on the server clock, as the truth's own (both cross loopback, so the transport
    cancels); ekf_ned (T, 3) m. None with too little motion."""
    return time_shift_fit(t_ns, *_ekf_error_and_velocity(t_ns, ekf_ned, truth), detrend_ns=detrend_ns)


def outside_cut(rows: np.ndarray, record: dict[str, Any]) -> np.ndarray:
    """The rows (T, ...; server ns in column 0) outside the flight's vision cut and the CUT_SETTLE_NS after it
    (all of them without a cut)."""
    if "cut" not in record or not len(rows):
        return rows
    c0, c1, _ = record["cut"]
    return rows[(rows[:, 0] < c0) | (rows[:, 0] > c1 + CUT_SETTLE_NS)]


def ekf_yaw_lead_ms(att: np.ndarray, truth: TruthTrack) -> tuple[float, int] | None:
    """How far ahead of the truth the autopilot's reported yaw runs (ms), and the samples the fit used: as
    ekf_lead_ms, on ATTITUDE rows att (T, 4: arrival ns, roll, pitch, yaw rad) against the true yaw while it
    turns faster than YAW_LEAD_MIN_RATE_RAD_S (a yaw swing). The attitude is the IMU's, carried forward without
    the vision's delay, so this is mostly how much sooner or later ATTITUDE arrives here than the truth does:
    the share of ekf_lead_ms that is transport, not the EKF. None with too little turning."""
    t = att[:, 0].astype(np.int64)
    h = YAW_RATE_STEP_NS
    yaws = [euler_ned_frd(truth.sample(t + k)[3].as_quat())[:, 2] for k in (-h, 0, h)]
    rate = np.angle(np.exp(1j * (yaws[2] - yaws[0]))) / (2 * h * 1e-9)
    e = np.angle(np.exp(1j * (att[:, 3] - yaws[1])))
    turning = np.abs(rate) > YAW_LEAD_MIN_RATE_RAD_S
    n = int(turning.sum())
    if n < LEAD_MIN_SAMPLES:
        return None
    e, rate = e[turning] - e[turning].mean(), rate[turning] - rate[turning].mean()
    return float((e * rate).sum() / (rate * rate).sum() * 1e3), n


def horizontal_error_mm(loc: np.ndarray, truth: TruthTrack) -> np.ndarray:
    """The EKF's horizontal distance (T,) mm from the truth at each LOCAL_POSITION_NED row of loc (T, 4): arrival
    ns, N, E, D m."""
    p, _, _, _ = truth.sample(loc[:, 0].astype(np.int64))
    return np.hypot(*(loc[:, 1:3] - world_to_ned(p)[:, :2]).T) * 1e3


FAILSAFE_WORDS = ("failsafe", "ekf variance", "lane switch", "ekf primary changed", "position lost", "crash")


def flight_summary(gcs: Gcs, truth: TruthTrack, demo: dict[str, Any], record: dict[str, Any], plan: FlightPlan,
                   wall_s: float, our_modes: set[int] | None = None, body: str | None = None) -> dict[str, Any]:
    """EKF and vision against SITL's truth, EKF test ratios, every STATUSTEXT, failsafes. our_modes: the
    HEARTBEAT custom_modes the flight commands (default ArduCopter's GUIDED and LAND); body: whose vision figures
    (default the demo's first body)."""
    a = record.get("armed_ns")
    b = record.get("disarmed_ns") or time.monotonic_ns()
    out: dict[str, Any] = {"completed": bool(record.get("completed")), "error": record.get("error"), "wall_s": wall_s,
                           "viso_delay_ms": record.get("viso_delay_ms"), "stamp_age_ms": record.get("stamp_age_ms")}
    if a is not None:
        loc = np.array([r for r in gcs.local if a <= r[0] <= b], dtype=float).reshape(-1, 4)
        if len(loc):
            p, _, _, _ = truth.sample(loc[:, 0].astype(np.int64))
            out["ekf_horizontal_error_mm"] = _pcts(horizontal_error_mm(loc, truth))
            out["ekf_vertical_error_mm"] = _pcts(np.abs(loc[:, 3] - world_to_ned(p)[:, 2]) * 1e3)
            # the lead is the vision's timing: fitted where the EKF has it (a cut's dead reckoning, and the second
            # after it, left out: the drift's error follows the drift's velocity, whatever the delay)
            seen = outside_cut(loc, record)
            lead = ekf_lead_fit(seen[:, 0], seen[:, 1:4], truth)
            if "cut" in record and len(seen):  # the tracking alone: its error without the cut's dead reckoning
                out["ekf_horizontal_error_outside_cut_mm"] = _pcts(horizontal_error_mm(seen, truth))
            if lead is not None:
                out["ekf_lead_ms"], out["ekf_lead_se_ms"], out["ekf_lead_samples"] = lead
            if "circle" in record:  # the steady circle alone, each turn's slow drift taken out
                c0, c1 = record["circle"]
                on = loc[(loc[:, 0] >= c0) & (loc[:, 0] <= c1)]
                lead = ekf_lead_fit(on[:, 0], on[:, 1:4], truth, detrend_ns=int(CIRCLE_PERIOD_S * 1e9))
                if lead is not None:
                    out["ekf_lead_circle_ms"], out["ekf_lead_circle_se_ms"], out["ekf_lead_circle_samples"] = lead
        att = np.array([r for r in gcs.attitude if a <= r[0] <= b], dtype=float).reshape(-1, 4)
        if len(att):
            _, _, _, rot = truth.sample(att[:, 0].astype(np.int64))
            yaw_true = euler_ned_frd(rot.as_quat())[:, 2]
            dyaw = np.angle(np.exp(1j * (att[:, 3] - yaw_true)))
            out["ekf_yaw_error_deg"] = _pcts(np.degrees(np.abs(dyaw)))
            yaw_lead = ekf_yaw_lead_ms(att, truth)
            if yaw_lead is not None:
                out["ekf_yaw_lead_ms"], out["ekf_yaw_lead_samples"] = yaw_lead
        ekf = np.array([r for r in gcs.ekf if a <= r[0] <= b], dtype=float).reshape(-1, 6)
        if len(ekf):
            out["ekf_test_ratios"] = {name: {"max": float(ekf[:, k].max()), "p99": float(np.percentile(ekf[:, k], 99))}
                                      for k, name in ((2, "velocity"), (3, "position_horizontal"),
                                                      (4, "position_vertical"), (5, "compass"))}
        if "cut" in record:
            c0, c1, hold = record["cut"]
            t, x = truth.snapshot()
            sel = (t >= c0) & (t <= c1 + 2_000_000_000)
            hold_world = ned_to_world(np.array(hold))
            dev = np.linalg.norm(x[sel, :2] - hold_world[:2], axis=1) * 1e3 if sel.any() else np.zeros(0)
            out["cut"] = {"seconds": plan.cut_s, "max_drift_from_hold_mm": float(dev.max()) if len(dev) else None}
            after = loc[(loc[:, 0] >= c1 + 1_000_000_000) & (loc[:, 0] <= c1 + 3_000_000_000)] if len(loc) else loc
            if len(after):
                out["cut"]["ekf_horizontal_error_1_to_3_s_after_mm"] = _pcts(horizontal_error_mm(after, truth))
    texts = [t for _, _, t in gcs.texts]
    out["statustext"] = texts
    out["failsafe_or_lane_switch"] = [t for t in texts if any(w in t.lower() for w in FAILSAFE_WORDS)]
    ours = our_modes if our_modes is not None else {COPTER_MODES["GUIDED"], COPTER_MODES["LAND"]}
    out["mode_changes_not_ours"] = [MODE_NAMES.get(m, m) for t, m in gcs.modes
                                    if a is not None and a <= t <= b and m not in ours]
    vb = next((x for x in demo.get("bodies", []) if body is None or x.get("name") == body), {})
    out["vision"] = {k: vb.get(k) for k in ("position_rmse_mm", "position_max_mm", "rotation_rmse_deg",
                                            "tracked_fraction", "latency_ms")}
    sent = (vb.get("bridge") or {}).get("sent") or 0
    out["vision"]["poses_sent"] = sent
    out["vision"]["poses_per_s"] = sent / demo["duration_s"] if demo.get("duration_s") else None
    out["vision"]["frames_not_fused"] = (demo.get("server") or {}).get("frames_shed")
    out["truth_samples"] = truth.n
    h = out.get("ekf_horizontal_error_mm", {})
    out["ok"] = bool(out["completed"] and h.get("p99") is not None and h["p99"] <= 20.0
                     and not out["failsafe_or_lane_switch"] and not out["mode_changes_not_ours"])
    return out


def format_flight(s: dict[str, Any]) -> str:
    f = lambda v, spec=".1f": "-" if v is None else format(v, spec)  # noqa: E731
    h = s.get("ekf_horizontal_error_mm", {})
    v = s.get("ekf_vertical_error_mm", {})
    y = s.get("ekf_yaw_error_deg", {})
    vis = s["vision"]
    lines = [
        f"visionpos sitl: flight {'completed' if s['completed'] else 'NOT completed'} "
        f"({s['wall_s']:.0f} s wall, {s.get('delay_param', 'VISO_DELAY_MS')} {f(s.get('viso_delay_ms'), '.0f')}"
        + (f"; the bridge advises {s['delay_advised_ms']}" if s.get("delay_advised_ms") is not None else "") + ")"
        + (f": {s['error']}" if s.get("error") else ""),
        f"  EKF position vs SITL truth (armed to disarmed): horizontal p50 {f(h.get('p50'))} mm, p99 {f(h.get('p99'))}"
        f" mm, max {f(h.get('max'))} mm; vertical p99 {f(v.get('p99'))} mm",
        f"  EKF ahead of the truth by {f(s.get('ekf_lead_ms'))} ms"
        + ("" if s.get("ekf_lead_se_ms") is None else f" +- {s['ekf_lead_se_ms']:.1f} (standard error)")
        + f" (fitted on the {s.get('ekf_lead_samples') or 0} samples moving faster than {LEAD_MIN_SPEED_M_S:g} m/s"
        f"{', the cut and its second after left out' if 'cut' in s else ''}; negative: behind)"
        + ("" if s.get("ekf_yaw_lead_ms") is None else
           f"; its reported yaw {s['ekf_yaw_lead_ms']:.1f} ms ahead of the true yaw while turning (how much sooner its "
           "telemetry arrives than the truth: the transport's share)"),
        *([] if s.get("ekf_lead_circle_ms") is None else [
            f"  on the circle: EKF ahead of the truth by {s['ekf_lead_circle_ms']:.1f} ms"
            + ("" if s.get("ekf_lead_circle_se_ms") is None else f" +- {s['ekf_lead_circle_se_ms']:.1f}")
            + f" ({s['ekf_lead_circle_samples']} samples after the first turn, each turn's drift taken out)"]),
        f"  EKF yaw vs truth: p50 {f(y.get('p50'), '.2f')} deg, p99 {f(y.get('p99'), '.2f')} deg, "
        f"max {f(y.get('max'), '.2f')} deg",
        f"  vision (fusion output) vs truth: RMS {f(vis.get('position_rmse_mm'), '.2f')} mm, max "
        f"{f(vis.get('position_max_mm'), '.2f')} mm, rotation RMS {f(vis.get('rotation_rmse_deg'), '.3f')} deg; "
        f"{vis['poses_sent']} poses sent to SITL ({f(vis.get('poses_per_s'))} per s); "
        f"{vis.get('frames_not_fused') or 0} camera frames queued too long to fuse",
    ]
    for name, r in (s.get("ekf_test_ratios") or {}).items():
        lines.append(f"  EKF test ratio {name}: max {r['max']:.2f}, p99 {r['p99']:.2f}")
    if "cut" in s:
        c = s["cut"]
        e = c.get("ekf_horizontal_error_1_to_3_s_after_mm") or {}
        lines.append(f"  vision cut {c['seconds']:g} s: true drift from the hold point max "
                     f"{f(c['max_drift_from_hold_mm'])} mm; EKF error 1-3 s after: p99 {f(e.get('p99'))} mm")
    if "px4_log" in s:
        g = s["px4_log"]
        lines.append("  PX4's log: " + (g["error"] if "error" in g else
                     f"EKF2's output {fmt_ms(g.get('output_lead_ms'))} +- {fmt_ms(g.get('output_lead_se_ms'))} ms "
                     "ahead of SIH's truth (both on PX4's clock)"))
    if "link_relay" in s:
        r = s["link_relay"]
        lines.append(f"  link delay {r['added_ms']:g} ms each way (a relay; held {fmt_ms(r['hold_ms_p50'])} ms p50)"
                     + ("" if s.get("send_minus_stamp_ms_p50") is None else
                        f"; capture->autopilot delay measured by the back-channel {fmt_ms(s.get('delay_measured_ms'))}"
                        f" ms, its floor send-stamp {fmt_ms(s['send_minus_stamp_ms_p50'])} + relay "
                        f"{fmt_ms(r['hold_ms_p50'])} ms"))
    if "link_delay" in s:
        d = s["link_delay"]
        lines.append(f"  link delay {d['added_ms']:g} ms each way: capture->autopilot delay measured by the "
                     f"back-channel {fmt_ms(d['measured_ms'])} ms, true {fmt_ms(d['true_ms'])} ms (send-stamp "
                     f"{fmt_ms(d['send_minus_stamp_ms_p50'])} + relay {fmt_ms(d['relay_hold_ms_p50'])} + SITL's truth "
                     f"age and intake {fmt_ms(d.get('sitl_clock_ms'))}), difference "
                     f"{fmt_ms(d['error_ms'])} ms; poses behind SITL's truth {fmt_ms(d['optical_lag_ms'])} ms; "
                     f"{d['detail']}")
    lines.append(f"  failsafe / lane switch messages: {s['failsafe_or_lane_switch'] or 'none'}; "
                 f"mode changes not commanded: {s['mode_changes_not_ours'] or 'none'}")
    lines.append("  STATUSTEXT: " + " | ".join(s["statustext"]))
    rt = s.get("real_time") or {}
    if rt:
        lines.append(f"  real time: {rt['frames_made']} camera frames made, {100 * rt['frames_late_fraction']:.1f}% "
                     f"more than {LATE_NS // 1_000_000} ms late, {100 * rt['frames_not_fused_fraction']:.1f}% not "
                     "fused (queued too long): above a few % this host could not keep up, and the figures above "
                     "measure the host, not the EKF")
    lines.append(f"  target (EKF horizontal p99 <= 20 mm, no failsafe): {'met' if s['ok'] else 'NOT met'}")
    return "\n".join(lines)
