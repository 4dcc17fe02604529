"""Benchmark group `sitl_fleet`: two identical drones (one marker layout), one ArduPilot SITL each, flown
together on the `pair` arena (`visionpos sitl --vehicles 2 --same-layout --swap-at 2 --swap-for 2 --hold 8`).

Each is bound to its optical body on its parking pad before take-off (bridge/fleet_binding.py). Both take off
from a row on the floor, hover, cross 0.3 m apart and back, and land; 2 s into the hover their
vision links are exchanged for 2 s (two radios swapped at the ground station) and put back. Measured: each EKF
against its SITL's truth and its failsafe messages outside the swap (the vision cut and 5 s after: a lane
switch there is the EKF's answer to the cut, counted apart), how soon the bridge saw each autopilot on the
other's link, the poses that reached the wrong autopilot, how soon the poses flowed again. About 65 s of real
time. Skipped, with the reason in the notes, where no SITL binary is found.
"""

from __future__ import annotations

from visionpos.benchmarks import BenchResult


def run(quick: bool = False) -> BenchResult:
    from visionpos.app.sitl import FlightPlan, sitl_arena
    from visionpos.app.sitl.fleet import Swap, run_fleet
    from visionpos.benchmarks.sitl import sitl_binary

    binary, skipped = sitl_binary()
    if skipped is not None:
        return skipped
    plan = FlightPlan(altitude_m=1.0, hold_s=8.0, timeout_s=150.0)
    s = run_fleet(sitl_arena("pair", [], plan.timeout_s + 60.0), binary, plan, 2, Swap(2.0, 2.0), None,
                  same_layout=True)
    vs = list(s["vehicles"].values())
    outside = [(v.get("ekf_horizontal_error_outside_swap_mm") or {}).get("p99") for v in vs]
    whole = [(v.get("ekf_horizontal_error_mm") or {}).get("max") for v in vs]
    sw = s["swap"]
    aps = [sw["autopilot0"], sw["autopilot1"]]
    detected = [a["detected_after_ms"] for a in aps]
    metrics = {
        "sitl_fleet_flights_completed_min": min(1.0 if v["completed"] else 0.0 for v in vs),
        "sitl_fleet_ekf_horizontal_p99_outside_swap_mm_max": max(outside) if None not in outside else None,
        "sitl_fleet_ekf_horizontal_max_during_swap_mm_max": max(whole) if None not in whole else None,
        "sitl_fleet_failsafe_messages": float(sum(len(v["failsafe_or_lane_switch"]) + len(v["mode_changes_not_ours"])
                                                  for v in vs)),
        "sitl_fleet_failsafe_messages_during_swap": float(sum(len(v.get("failsafe_during_swap", [])) for v in vs)),
        "sitl_fleet_swap_detected_after_ms_max": max(detected) if None not in detected else None,
        "sitl_fleet_swap_wrong_poses": float(sum(a["wrong_poses"] for a in aps)),
        "sitl_fleet_swap_wrong_poses_after_detection": (float(sum(a["wrong_poses_after_detection"] for a in aps))
                                                        if None not in detected else None),
        "sitl_fleet_swap_caught": 1.0 if sw["ok"] else 0.0,
        "sitl_fleet_poses_resumed_after_s": sw["resumed_after_s"],
        "sitl_fleet_frames_late_fraction": s["real_time"]["frames_late_fraction"],
    }
    metrics = {k: float(v) for k, v in metrics.items() if v is not None}
    notes = [f"SITL binary: {binary}", f"while swapped the bridge said: {'; '.join(sw['said'])}"]
    for name, v in s["vehicles"].items():
        if v["failsafe_or_lane_switch"] or v["mode_changes_not_ours"] or v.get("failsafe_during_swap"):
            notes.append(f"{name}: failsafe / lane switch messages outside the swap (and 5 s after): "
                         f"{v['failsafe_or_lane_switch']}, during it (the vision cut): "
                         f"{v.get('failsafe_during_swap')}; mode changes not commanded: {v['mode_changes_not_ours']}")
    if s.get("error"):
        notes.append(f"flight error: {s['error']}")
    if s["real_time"]["frames_late_fraction"] > 0.02:
        notes.append("this host did not keep real time during the flight: the EKF figures measure its load")
    return BenchResult(metrics=metrics, notes=notes)
