"""Benchmark group `sitl`: ArduPilot SITL flown closed loop on the simulated thesis arena (`visionpos sitl`).

The full scripted flight (take off to 1 m, hold with a 1 s vision cut, 1 m square, land), about
70 s of real time. Skipped, with the reason in the notes, where no SITL binary is found
($VISIONPOS_SITL or ../shared/sitl/arducopter beside the checkout).
"""

from __future__ import annotations

from pathlib import Path

from visionpos.benchmarks import BenchResult


def sitl_binary() -> tuple[Path | None, BenchResult | None]:
    """(ArduPilot's SITL binary, None), or (None, the skipped group's result saying why) where none is found."""
    from visionpos.app.sitl import SITL_ENV, default_sitl_binary

    binary = default_sitl_binary()
    if binary is None:
        return None, BenchResult(notes=[f"skipped: no ArduPilot SITL binary (set {SITL_ENV}=PATH or put it in "
                                        "../shared/sitl/arducopter beside the checkout)"])
    return binary, None


def full_flight():
    """The full scripted flight: take off to 1 m, hold 4 s with a 1 s vision cut, 1 m square, land."""
    from visionpos.app.sitl import FlightPlan

    return FlightPlan(altitude_m=1.0, side_m=1.0, hold_s=4.0, square=True, cut_s=1.0, timeout_s=200.0)


def run(quick: bool = False) -> BenchResult:
    from visionpos.app.sitl import run_sitl, sitl_arena

    binary, skipped = sitl_binary()
    if skipped is not None:
        return skipped
    plan = full_flight()
    s = run_sitl(sitl_arena("thesis", [], plan.timeout_s + 60.0), binary, plan, None)
    h = s.get("ekf_horizontal_error_mm") or {}
    y = s.get("ekf_yaw_error_deg") or {}
    ratios = s.get("ekf_test_ratios") or {}
    cut = s.get("cut") or {}
    metrics = {
        "sitl_flight_completed": 1.0 if s["completed"] else 0.0,
        "sitl_ekf_horizontal_error_p50_mm": h.get("p50"),
        "sitl_ekf_horizontal_error_p99_mm": h.get("p99"),
        "sitl_ekf_horizontal_error_max_mm": h.get("max"),
        "sitl_ekf_vertical_error_p99_mm": (s.get("ekf_vertical_error_mm") or {}).get("p99"),
        "sitl_ekf_yaw_error_p99_deg": y.get("p99"),
        "sitl_ekf_lead_ms": s.get("ekf_lead_ms"),
        "sitl_ekf_pos_test_ratio_max": (ratios.get("position_horizontal") or {}).get("max"),
        "sitl_vision_position_rmse_mm": s["vision"].get("position_rmse_mm"),
        "sitl_failsafe_messages": float(len(s["failsafe_or_lane_switch"]) + len(s["mode_changes_not_ours"])),
        "sitl_cut_1s_max_drift_mm": cut.get("max_drift_from_hold_mm"),
        "sitl_viso_delay_ms": s.get("viso_delay_ms"),
        "sitl_frames_late_fraction": s["real_time"]["frames_late_fraction"],
        "sitl_frames_not_fused_fraction": s["real_time"]["frames_not_fused_fraction"],
    }
    metrics = {k: float(v) for k, v in metrics.items() if v is not None}
    notes = [f"SITL binary: {binary}", "STATUSTEXT during the run: " + " | ".join(s["statustext"])]
    if s["real_time"]["frames_late_fraction"] > 0.02 or s["real_time"]["frames_not_fused_fraction"] > 0.05:
        notes.append("this host did not keep real time during the flight (camera frames late or not fused): the "
                     "EKF figures measure the host's load, not the EKF")
    return BenchResult(metrics=metrics, notes=notes)
