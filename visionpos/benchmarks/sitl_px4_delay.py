"""Benchmark group `sitl_px4_delay`: PX4 SIH with its vision link slowed by a relay (D = 20 and 50 ms each way,
`visionpos sitl --autopilot px4 --link-delay-ms D`), EKF2_EV_DELAY as the back-channel advises.

EKF2_EV_DELAY needs a restart, so each D takes two flights: the first boots with 15 ms + D and yields the
back-channel's advice (the median stamp-to-arrival delay: PX4 in SITL stamps the poses on arrival), the second
boots with that advice. Each flight: Offboard take-off to 1 m, an 8 s hold turning about the vertical at +-1 rad/s
(the rotation the delay measurement correlates), a 1 m square, AUTO.LAND. The goal: with the advised value, the
EKF runs within 2 ms of SIH's truth (visionpos.app.sitl.report.ekf_lead_ms). D = 0 is in `sitl_px4`.
Skipped, with the reason in the notes, where no PX4 build is found.
"""

from __future__ import annotations

import math

from visionpos.benchmarks import BenchResult
from visionpos.benchmarks.sitl_px4 import log_cell

DELAYS_MS = (20.0, 50.0)


def run(quick: bool = False) -> BenchResult:
    from visionpos.app.sitl import FlightPlan, sitl_arena
    from visionpos.app.sitl.px4 import PX4_ENV, default_px4_dir
    from visionpos.app.sitl.px4_run import run_px4

    build = default_px4_dir()
    if build is None:
        return BenchResult(notes=[f"skipped: no PX4 SITL build (set {PX4_ENV}=DIR holding bin/px4 and etc/, or put "
                                  "it in ../shared/sitl-px4/build beside the checkout)"])
    res = BenchResult(notes=[f"PX4 build: {build}"])
    fmt = (lambda x, spec=".1f": "-" if x is None else format(x, spec))  # noqa: E731
    rows = ["| added link delay ms (each way) | EKF2_EV_DELAY ms | EKF ahead of truth ms (+- standard error) | "
            "the same from PX4's log | advised ms | EKF horizontal p99 mm | flight |",
            "|---|---|---|---|---|---|---|"]
    leads = []
    for d in DELAYS_MS:
        plan = FlightPlan(altitude_m=1.0, side_m=1.0, hold_s=8.0, square=True, cut_s=0.0, timeout_s=200.0,
                          link_delay_ms=d, yaw_swing_rad_s=1.0)
        first = run_px4(sitl_arena("thesis", [], plan.timeout_s + 60.0), build, plan, None)
        advised = first.get("delay_advised_ms")
        second = run_px4(sitl_arena("thesis", [f"sitl.viso_delay_ms={advised}"], plan.timeout_s + 60.0), build,
                         plan, None) if advised is not None else None
        tag = f"added_{d:.0f}"
        for s in (first, second):
            if s is None:
                continue
            rows.append(f"| {d:.0f} | {fmt(s.get('viso_delay_ms'), '.0f')} | {fmt(s.get('ekf_lead_ms'))} +- "
                        f"{fmt(s.get('ekf_lead_se_ms'))} | {log_cell(s)} | "
                        f"{fmt(s.get('delay_advised_ms'), '.0f')} | "
                        f"{fmt((s.get('ekf_horizontal_error_mm') or {}).get('p99'))} | "
                        f"{'completed' if s['completed'] else 'NOT completed'} |")
            if s.get("error"):
                res.notes.append(f"D = {d:g} ms, EKF2_EV_DELAY {s.get('viso_delay_ms')}: {s['error']}")
        res.metrics[f"sitl_px4_delay_first_ekf_lead_ms_{tag}"] = float(first.get("ekf_lead_ms") or math.nan)
        if second is None:
            res.notes.append(f"D = {d:g} ms: the first flight gave no delay advice")
            leads.append(math.nan)
            continue
        lead = second.get("ekf_lead_ms")
        leads.append(abs(lead) if lead is not None else math.nan)
        res.metrics[f"sitl_px4_delay_ev_delay_ms_{tag}"] = float(second.get("viso_delay_ms") or math.nan)
        res.metrics[f"sitl_px4_delay_ekf_lead_ms_{tag}"] = float(lead) if lead is not None else math.nan
        if second.get("ekf_lead_se_ms") is not None:
            res.metrics[f"sitl_px4_delay_ekf_lead_se_ms_{tag}"] = float(second["ekf_lead_se_ms"])
        for k in ("output_lead_ms", "output_lead_se_ms"):
            if (second.get("px4_log") or {}).get(k) is not None:
                res.metrics[f"sitl_px4_delay_ekf2_{k}_{tag}"] = float(second["px4_log"][k])
        res.metrics[f"sitl_px4_delay_flight_completed_{tag}"] = 1.0 if second["completed"] else 0.0
    res.metrics["sitl_px4_delay_ekf_lead_ms_abs_max"] = max(leads) if not any(math.isnan(x) for x in leads) \
        else math.nan
    res.tables["PX4 SIH through a slowed link: EKF2_EV_DELAY first 15 ms + D, then as advised"] = "\n".join(rows)
    return res
