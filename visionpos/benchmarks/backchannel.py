"""The back-channel (issue 19): the capture-to-autopilot delay measured from the autopilot's gyro, and what
reading the autopilot costs the sender thread.

    visionpos bench --only backchannel [--quick]

Delay: three vehicles on loopback, each with a fake autopilot (bridge.fake_autopilot) whose sensors follow
the simulator's `aggressive` trajectory and which delays every packet it receives by 0, 20 or 50 ms (the
added link delay). The bridge is fed that trajectory's poses at 100 Hz in real time (rate noise 0.02 rad/s)
and measures each vehicle's delay from the autopilot's gyro and TIMESYNC answers; the error is against the
fake autopilot's own record (median stamp-to-arrival of the poses over the same 20 s window, including its
added delay). Goal: within 2 ms.

Cost: CPU time per pose of what the back-channel adds to the send path (recording the optical sample and the
send), and per run of the identity check (every 0.25 s) and of the delay measurement (every 5 s, right after a
send), on 20 s of 50 Hz telemetry.
"""

from __future__ import annotations

import time

import numpy as np

from visionpos.benchmarks import BenchResult

DELAYS_MS = (0.0, 20.0, 50.0)


def bench_delay(duration_s: float) -> list[dict]:
    from bridge import Bridge
    from bridge.backchannel import DELAY_WINDOW_NS
    from bridge.fake_autopilot import FakeAutopilot, trajectory_truth
    from visionpos.benchmarks.factories import arena_with_vehicles, body_state
    from visionpos.sim.trajectories import Aggressive

    traj = Aggressive(np.array([0.0, 0.0, 1.5]))
    t0 = time.monotonic_ns()
    aps = [FakeAutopilot("udpin:127.0.0.1:0", sysid=i + 1, truth=trajectory_truth(traj, t0), delay_ms=d,
                         boot_ns=t0 - int((i + 1) * 3.7e9)).start() for i, d in enumerate(DELAYS_MS)]
    arena = arena_with_vehicles([{"body": f"body{i + 1}", "sysid": i + 1, "endpoint": f"udpout:127.0.0.1:{ap.port}"}
                                 for i, ap in enumerate(aps)])
    bridge = Bridge(arena, {"report_interval_s": 0})
    bridge.start()
    rng = np.random.default_rng(0)
    try:
        period = 10_000_000
        t_next = time.monotonic_ns()
        t_end = t_next + int(duration_s * 1e9)
        while t_next < t_end:
            now = time.monotonic_ns()
            if now < t_next:
                time.sleep((t_next - now) * 1e-9)
            now = time.monotonic_ns()
            m = traj(np.array([(now - t0) * 1e-9]))
            bridge.publish([body_state(f"body{i + 1}", i + 1, capture_ns=now, position=m.positions[0],
                                       quaternion=m.quaternions[0], velocity=m.velocities[0],
                                       angular_velocity=m.angular_velocities[0] + rng.normal(0, 0.02, 3))
                            for i in range(len(aps))])
            t_next += period
        rows = []
        for ap, v, d in zip(aps, bridge.vehicles, DELAYS_MS):
            bc = v.bc
            true = ap.true_delay_ms(window_s=DELAY_WINDOW_NS * 1e-9)
            rows.append({"added_ms": d, "true_ms": true, "measured_ms": bc.delay_ms,
                         "error_ms": (bc.delay_ms - true) if bc.delay_ms is not None else float("nan"),
                         "correlation": bc.delay_correlation, "source": bc.gyro_source, "detail": bc.delay_reason})
        return rows
    finally:
        bridge.close()
        for ap in aps:
            ap.close()


def bench_cost() -> dict[str, float]:
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    from bridge.backchannel import Backchannel
    from bridge.config import parse_vehicles
    from visionpos.benchmarks.factories import arena_with_vehicles
    from visionpos.geometry.frames import euler_ned_frd, flu_to_frd, quat_world_body_to_ned_frd
    from visionpos.sim.trajectories import Aggressive

    cfg = parse_vehicles(arena_with_vehicles([{"body": "body1", "sysid": 1, "endpoint": "udpout:127.0.0.1:9"}]))[0]
    now = [0]
    bc = Backchannel(cfg, lambda: now[0], mavlink2.MAVLink(None, 1, 197), lambda m: True, lambda *a: None)
    traj = Aggressive(np.array([0.0, 0.0, 1.5]))
    ts = np.arange(0, 20_000_000_000, 20_000_000)
    m = traj(ts * 1e-9)
    e, g, q = euler_ned_frd(m.quaternions), flu_to_frd(m.angular_velocities), quat_world_body_to_ned_frd(m.quaternions)
    off = 5_000_000_000
    per_pose = []
    for i, t in enumerate(ts):
        t = int(t)
        now[0] = t
        c0 = time.process_time_ns()
        bc.on_optical(t, e[i, 0], e[i, 1], g[i], q[i])
        bc.sends.add(t + 1_000_000, (1_000_000,))  # on_sent without triggering the measurement
        per_pose.append(time.process_time_ns() - c0)
        bc.handle(mavlink2.MAVLink_attitude_message((t + off) // 1_000_000, *e[i], *g[i]), 1, t + 1_000_000)
        bc.handle(mavlink2.MAVLink_raw_imu_message((t + off) // 1000, 0, 0, -1000, *(np.round(g[i] * 1000)), 0, 0, 0),
                  1, t + 1_000_000)
        if i % 25 == 0:
            bc._ts_pending[t] = t
            bc.on_timesync_reply(t, t + off + 2_000_000, t + 3_000_000)
    bc.autopilot = "ardupilot"

    def cpu_ms(fn, n: int) -> float:
        fn()
        c0 = time.process_time_ns()
        for _ in range(n):
            fn()
        return (time.process_time_ns() - c0) / n * 1e-6

    t_last = int(ts[-1]) + 1_000_000
    return {
        "backchannel_per_pose_us_p50": float(np.percentile(per_pose, 50)) * 1e-3,
        "backchannel_identity_check_ms": cpu_ms(lambda: bc.check_identity(t_last), 50),
        "backchannel_delay_measurement_ms": cpu_ms(bc.measure_delay, 5),
    }


def run(quick: bool = False) -> BenchResult:
    res = BenchResult()
    rows = bench_delay(14.0 if quick else 30.0)
    errs = [abs(r["error_ms"]) for r in rows]
    res.metrics["backchannel_delay_error_ms_max"] = float(max(errs)) if all(np.isfinite(errs)) else float("nan")
    for r in rows:
        res.metrics[f"backchannel_delay_error_ms_added_{r['added_ms']:.0f}"] = float(r["error_ms"])
    res.metrics.update(bench_cost())
    lines = ["| added link delay ms | true capture->autopilot ms | measured ms | error ms | gyro/optical correlation "
             "| gyro message |", "|---|---|---|---|---|---|"]
    for r in rows:
        fmt = (lambda x: f"{x:.2f}" if x is not None and np.isfinite(x) else "-")  # noqa: E731
        lines.append(f"| {r['added_ms']:.0f} | {fmt(r['true_ms'])} | {fmt(r['measured_ms'])} | {fmt(r['error_ms'])} "
                     f"| {fmt(r['correlation'])} | {r['source'] or r['detail']} |")
    res.tables["Measured capture-to-autopilot delay (fake autopilot, aggressive flight, loopback)"] = "\n".join(lines)
    m = res.metrics
    res.tables["Back-channel cost on the sender thread (one core, CPU time)"] = "\n".join([
        "| step | cost |", "|---|---|",
        f"| per sent pose: optical sample + send record | {m['backchannel_per_pose_us_p50']:.1f} µs |",
        f"| identity check (every 0.25 s, 1 s window) | {m['backchannel_identity_check_ms']:.2f} ms |",
        f"| delay measurement (every 5 s, 20 s window) | {m['backchannel_delay_measurement_ms']:.1f} ms |",
    ])
    res.notes.append("Against ArduPilot SITL with added link delays of 0, 20 and 50 ms: `bench --only sitl_delay`.")
    return res
