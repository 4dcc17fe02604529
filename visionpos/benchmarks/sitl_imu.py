"""Benchmark group `sitl_imu`: the autopilot's IMU in the filter against ArduPilot SITL, whose IMU is its physics
(`visionpos sitl --cut 1`, then the same with `--set fusion.imu.enabled=true`).

Two full scripted flights (take off to 1 m, hold with a 1 s vision cut, 1 m square, land), about 70 s of real time
each: the fusion's output against SITL's truth with the IMU off and on (RAW_IMU at 200 Hz, in the filter from
before take-off through TIMESYNC's clock offset, bridge/imu_feed.py). Skipped, with the reason in the notes, where
no SITL binary is found.
"""

from __future__ import annotations

from visionpos.benchmarks import BenchResult

_CASES = (("off", []), ("on", ["fusion.imu.enabled=true"]))


def run(quick: bool = False) -> BenchResult:
    from visionpos.app.sitl import run_sitl, sitl_arena
    from visionpos.benchmarks.sitl import full_flight, sitl_binary

    binary, skipped = sitl_binary()
    if skipped is not None:
        return skipped
    plan = full_flight()
    res = BenchResult(notes=[f"SITL binary: {binary}"])
    rows = []
    for tag, overrides in _CASES:
        s = run_sitl(sitl_arena("thesis", overrides, plan.timeout_s + 60.0), binary, plan, None)
        v = s["vision"]
        m = {
            "vision_position_rmse_mm": v.get("position_rmse_mm"),
            "vision_position_max_mm": v.get("position_max_mm"),
            "vision_rotation_rmse_deg": v.get("rotation_rmse_deg"),
            "vision_latency_p50_ms": (v.get("latency_ms") or {}).get("p50"),
            "ekf_horizontal_error_p99_mm": (s.get("ekf_horizontal_error_mm") or {}).get("p99"),
            "frames_not_fused_fraction": s["real_time"]["frames_not_fused_fraction"],
            "flight_completed": 1.0 if s["completed"] else 0.0,
        }
        res.metrics.update({f"sitl_imu_{tag}_{k}": float(x) for k, x in m.items() if x is not None})
        rows.append((tag, m))
        if s["real_time"]["frames_not_fused_fraction"] > 0.05:
            res.notes.append(f"IMU {tag}: this host did not keep real time (frames not fused): the figures measure "
                             "its load too")

    def f(x, fmt):
        return "-" if x is None else format(x, fmt)

    lines = ["| IMU | position RMSE mm | largest mm | rotation RMSE deg | capture->tick p50 ms | EKF horizontal p99 mm "
             "| frames not fused |", "|---|---|---|---|---|---|---|"]
    for tag, m in rows:
        lines.append(f"| {tag} | {f(m['vision_position_rmse_mm'], '.2f')} | {f(m['vision_position_max_mm'], '.1f')} "
                     f"| {f(m['vision_rotation_rmse_deg'], '.3f')} | {f(m['vision_latency_p50_ms'], '.1f')} "
                     f"| {f(m['ekf_horizontal_error_p99_mm'], '.1f')} | {m['frames_not_fused_fraction']:.1%} |")
    res.tables["ArduPilot SITL: the fusion's output against the truth, IMU off and on (one flight each)"] = \
        "\n".join(lines)
    return res
