"""`visionpos sitl --autopilot px4`: PX4 SITL (SIH) started with its EKF2 set for vision only, the demo's cameras
following SIH's true state, the bridge feeding PX4's Onboard link, and the flight: EKF2 fusing the vision, Position
mode, arm, Offboard take-off, hold (cut, yaw swing), square, circle, AUTO.LAND, disarm; the summary against SIH's truth.
With plan.link_delay_ms, a DelayRelay sits between the bridge and the Onboard port.

EKF2_EV_DELAY is sitl.viso_delay_ms when given, for the whole flight. Else PX4 boots with FIRST_EV_DELAY_MS plus
the link delay (its horizon, EKF2_DELAY_MAX, is sized from it at start), and the flight sets the bridge's advice
(PX4 in SITL stamps the poses on arrival: the mean stamp-to-arrival delay, bridge/estimator_delay.py) once
airborne, again before the circle and each time the advice is renewed while circling (set_advised_ev_delay).
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any, Callable, TextIO

import numpy as np

from visionpos.app.linkdelay import DelayRelay
from visionpos.app.sitl.flight import CIRCLE_RADIUS_M, FlightPlan, fly_circle
from visionpos.app.sitl.px4 import (
    AUTO,
    AUTO_LAND,
    OFFBOARD,
    POSCTL,
    Px4Gcs,
    Px4Process,
    free_px4_instance,
    px4_parameters,
    px4_ports,
)
from visionpos.app.sitl.report import flight_summary, say_to
from visionpos.app.sitl.settings import SITL, SitlError
from visionpos.app.sitl.truth import LiveArena, TruthTrack, until_settled
from visionpos.config.arena import ArenaConfig
from visionpos.geometry.frames import ned_to_world

FIRST_EV_DELAY_MS = 15.0  # the bridge's stamp -> send median on the reference VM (issue 31: 16 ms)
# EKF2's horizon is sized at start: room for an advice this much over the first value (issue 31: 16-23 ms advised
# on this 2-core host after 15)
ADVICE_HEADROOM_MS = 10.0
ADVICE_EVERY_S = 5.0  # the back-channel renews its advice this often (backchannel.DELAY_EVERY_NS)
OUR_MODES = {POSCTL << 16, OFFBOARD << 16, (AUTO << 16) | (AUTO_LAND << 24)}
# SIH's vibrating IMU keeps its hover wandering a few cm even on an exact vision (visionpos/app/sitl/px4_floor.py:
# EKF horizontal p99 33 mm): a waypoint counts as reached within 8 cm (ArduPilot's flight: 5 cm)
SETTLE_RADIUS_M = 0.08


def px4_arena(arena: ArenaConfig, instance: int, onboard_port: int | None = None) -> ArenaConfig:
    """The arena with its first vehicle only, as PX4's instance: sysid instance+1, the Onboard link (udpout,
    unsigned: PX4 does not sign with our key; onboard_port: a relay's in its place), `autopilot: px4`, PX4's
    TIMESYNC requests not answered, no origin (EKF2 flies the local frame)."""
    from visionpos.config.arena import ConfigError, parse_arena

    data = arena.to_dict()
    vehicles = data.get("vehicles") or []
    if not vehicles:
        raise ConfigError(arena.source, "vehicles", "SITL flies the first vehicle: add one (docs/autopilot-setup.md)")
    v = dict(vehicles[0])
    for k in ("signing", "origin", "autopilot_address"):
        v.pop(k, None)
    port = onboard_port if onboard_port is not None else px4_ports(instance)["onboard"]
    # answer_timesync off: SIH's clock runs about 1 % slow of ours and unevenly with the host's load, so PX4's
    # TIMESYNC, converged after about 50 s, then mapped time_usec up to tens of ms off (its timesync_status, issue
    # 31). Unanswered, PX4 stamps every pose on arrival for the whole flight, which EKF2_EV_DELAY is advised for.
    v.update(sysid=instance + 1, endpoint=f"udpout:127.0.0.1:{port}", autopilot="px4", answer_timesync=False)
    data["vehicles"] = [v]
    return parse_arena(data, arena.source)


def run_px4(arena: ArenaConfig, build: Path, plan: FlightPlan, out: TextIO | None) -> dict[str, Any]:
    """Start PX4 SIH with the vision-only EKF2, fly the plan on the live arena, the summary dict. With
    plan.link_delay_ms, the bridge talks to PX4's Onboard link through a DelayRelay holding each direction that
    long (the relay's 'autopilot side' is the bridge here: it sends first; its target is PX4's fixed port)."""
    sec = SITL.check(arena.section("sitl"))
    instance = SITL.read(sec, "instance") or free_px4_instance()
    if plan.link_delay_ms is None:
        return _run_px4(arena, sec, build, plan, out, instance, None)
    with DelayRelay(("127.0.0.1", px4_ports(instance)["onboard"]), plan.link_delay_ms,
                    lifetime_s=plan.timeout_s + 180.0) as relay:
        return _run_px4(arena, sec, build, plan, out, instance, relay)


def _run_px4(arena: ArenaConfig, sec: Any, build: Path, plan: FlightPlan, out: TextIO | None, instance: int,
             relay: DelayRelay | None) -> dict[str, Any]:
    from bridge.config import parse_vehicles

    home = tuple(float(x) for x in SITL.read(sec, "home"))
    arena = px4_arena(arena, instance, relay.port if relay is not None else None)
    veh = parse_vehicles(arena)[0]
    given = SITL.read(sec, "viso_delay_ms")
    ev_delay = given if given is not None else FIRST_EV_DELAY_MS + (plan.link_delay_ms or 0.0)
    params = px4_parameters(veh.message, round(ev_delay), SITL.read(sec, "viso_pos_m_nse"),
                            SITL.read(sec, "viso_yaw_m_nse"), veh.sysid,
                            headroom_ms=ADVICE_HEADROOM_MS if given is None else 0.0)
    say = say_to(out)
    truth = TruthTrack(home[:3])
    live = LiveArena(veh.body, truth)
    record: dict[str, Any] = {"viso_delay_ms": round(ev_delay), "first_viso_delay_ms": round(ev_delay),
                              "delay_param": "EKF2_EV_DELAY"}
    t0 = time.monotonic()
    with Px4Process(build, instance, params, home) as proc:
        gcs = Px4Gcs(px4_ports(instance), truth, on_text=lambda text: say(f"  PX4: {text}"))
        try:
            say(f"PX4 SIH instance {instance} in {proc.folder}: GCS udp 127.0.0.1:{gcs.port}, the bridge on its "
                f"Onboard link {veh.endpoint}"
                + ("" if relay is None else f" (a relay holding each direction {plan.link_delay_ms:g} ms -> "
                   f"udp 127.0.0.1:{px4_ports(instance)['onboard']})")
                + f"; EKF2 set at start ({len(params)} parameters)")
            gcs.connect(30.0, proc)
            gcs.check_params(params)
            say(f"parameters read back; cameras start (EKF2_EV_DELAY {round(ev_delay)} ms)")
            demo = _fly_live(arena, gcs, live, plan, veh.body, record, say, follow_advice=given is None)
        finally:
            gcs.close()
    summary = flight_summary(gcs, truth, demo, record, plan, time.monotonic() - t0, our_modes=OUR_MODES)
    made = max(live.frames_made, 1)
    summary["real_time"] = {"frames_made": live.frames_made, "frames_late_fraction": live.frames_late / made,
                            "frames_not_fused_fraction": (summary["vision"]["frames_not_fused"] or 0) / made}
    summary["delay_param"] = "EKF2_EV_DELAY"
    summary["px4_log"] = proc.log_timing
    summary["px4_clock_rate"] = clock_rate_summary(gcs)
    summary["delay_advised_ms"] = record.get("advised_ms")
    summary["circle_stamp_to_arrival_ms"] = record.get("circle_stamp_to_arrival_ms")
    summary["circle_ev_delays_ms"] = record.get("circle_ev_delays_ms")
    summary["first_viso_delay_ms"] = record["first_viso_delay_ms"]
    summary["delay_measured_ms"] = record.get("measured_ms")
    summary["send_minus_stamp_ms_p50"] = record.get("send_minus_stamp_ms_p50")
    if relay is not None:
        summary["link_relay"] = {"added_ms": plan.link_delay_ms,
                                 "hold_ms_p50": relay.hold_ms_median("to_autopilot")}
    return summary


def clock_rate_summary(gcs: Px4Gcs) -> dict[str, Any]:
    """PX4's clock's seconds per ours over the flight (Px4Gcs.clock_rates): p1, median, p99 and the estimates."""
    r = np.array([x for _, x in gcs.clock_rates])
    if not len(r):
        return {"estimates": 0}
    return {"estimates": len(r), "p1": float(np.percentile(r, 1)), "p50": float(np.median(r)),
            "p99": float(np.percentile(r, 99))}


def stamp_to_arrival_mean_ms(bc: Any, start_ns: int, end_ns: int) -> float | None:
    """The mean stamp-to-arrival delay (ms) of the poses sent from start_ns to end_ns (server clock): each one's
    send less stamp, plus half the link's fastest TIMESYNC round trip: what the advice would read over that span."""
    rows = _send_minus_stamp_ns(bc, start_ns, end_ns)
    rtt = bc.timesync_rtt_ns(fastest=True)
    return float(rows.mean() + 0.5 * (rtt or 0.0)) * 1e-6 if len(rows) else None


def measured_floor(bc: Any) -> dict[str, Any]:
    """The back-channel's measured capture-to-PX4 delay (ms) and, over the poses of its window, the median of
    their send less stamp: with the relay's hold, a floor the measured delay cannot physically be under (PX4
    cannot take a pose in before the relay passes it on)."""
    win = getattr(bc, "delay_window_ns", None) or (None, None)
    rows = _send_minus_stamp_ns(bc, *win)
    return {"measured_ms": bc.delay_ms,
            "send_minus_stamp_ms_p50": float(np.median(rows)) * 1e-6 if len(rows) else None}


def _send_minus_stamp_ns(bc: Any, start_ns: int | None, end_ns: int | None) -> np.ndarray:
    """The send less stamp (ns) of the poses the back-channel saw sent from start_ns to end_ns (None: all)."""
    return np.array([r[1] for r in list(bc.sends.d)
                     if start_ns is None or start_ns <= r[0] <= end_ns], dtype=np.float64)


def _fly_live(arena: ArenaConfig, gcs: Px4Gcs, live: LiveArena, plan: FlightPlan, body: str,
              record: dict[str, Any], say: Callable[[str], None], follow_advice: bool) -> dict[str, Any]:
    from visionpos.app.demo import run_demo

    async def during(ctx: Any) -> None:
        try:
            link = ctx.bridge.vehicle(body)
            await fly_px4(gcs, plan, record, say, live, lambda: link.sending_state() == "sending",
                          lambda: link.bc.advice, follow_advice)
            record.update(measured_floor(link.bc))
            if "circle" in record:
                record["circle_stamp_to_arrival_ms"] = stamp_to_arrival_mean_ms(link.bc, *record["circle"])
        except SitlError as e:
            record["error"] = str(e)
            say(f"flight failed: {e}")
        finally:
            live.stop()

    return asyncio.run(run_demo(arena, plan.timeout_s + 60.0, None, during=during, live=live))


async def wait_ev_fused(gcs: Px4Gcs, timeout_s: float, sending: Callable[[], bool]) -> None:
    """Until EKF2 has a relative position from the vision; else SitlError saying why (bridge/px4_status.py)."""
    from bridge.px4_status import ev_fusion_state

    end = time.monotonic() + timeout_s
    while not gcs.ev_fused():
        if time.monotonic() > end:
            m = gcs.estimator
            why = ("PX4 sent no ESTIMATOR_STATUS" if m is None else
                   ev_fusion_state(m.flags, m.pos_horiz_ratio, m.pos_vert_ratio, m.vel_ratio, sending())[1])
            raise SitlError(f"PX4's EKF2 never fused the vision in {timeout_s:g} s: {why}; last messages: "
                            + "; ".join(t for _, _, t in gcs.texts[-5:]))
        await asyncio.sleep(0.1)


async def arm_in_position_mode(gcs: Px4Gcs, timeout_s: float) -> None:
    """GCS heartbeat (always) and MANUAL_CONTROL, Position mode (MAV_CMD_DO_SET_MODE 1, 3), then arm, asked again
    until PX4 lets it (its preflight checks settle on the vision); SitlError with its last words otherwise."""
    gcs.manual = True
    await asyncio.sleep(0.5)  # a few MANUAL_CONTROL first: Position mode wants them
    await gcs.command_async(176, 1, POSCTL, what="Position mode")
    end = time.monotonic() + timeout_s
    while True:
        gcs.command(400, 1)
        try:
            await gcs.until(lambda: gcs.armed, 1.5, "arming")
            return
        except SitlError:
            if time.monotonic() > end:
                raise SitlError("PX4 would not arm in Position mode; last messages: "
                                + "; ".join(t for _, _, t in gcs.texts[-5:])) from None


async def set_advised_ev_delay(gcs: Px4Gcs, advice: Any, record: dict[str, Any], say: Callable[[str], None]) -> None:
    """EKF2_EV_DELAY set in flight to the bridge's advice (record["viso_delay_ms"] follows) where it differs from
    the value now and fits the horizon PX4 booted with (EKF2_DELAY_MAX). PX4 marks the parameter reboot_required,
    yet EKF2 reads it afresh for each vision sample (EstimatorInterface::setExtVisionData); only the horizon is
    sized at start. The flight's own advice then times its own poses: the host's load moves the pipeline's
    latency by several ms from one run to the next."""
    if advice is None or advice.value_ms == record["viso_delay_ms"]:
        return
    horizon = gcs.params.get("EKF2_DELAY_MAX")
    if horizon is not None and advice.horizon_ms is not None and advice.horizon_ms > horizon:
        say(f"the bridge advises EKF2_EV_DELAY={advice.value_ms}, which needs EKF2_DELAY_MAX={advice.horizon_ms}; "
            f"PX4 started with {horizon:g}: EKF2_EV_DELAY kept at {record['viso_delay_ms']}")
        return
    await gcs.set_params_async({"EKF2_EV_DELAY": float(advice.value_ms)})
    say(f"EKF2_EV_DELAY {record['viso_delay_ms']} -> {advice.value_ms} in flight ({advice.why})")
    record["viso_delay_ms"] = advice.value_ms
    record.setdefault("ev_delay_set_ns", []).append(time.monotonic_ns())


async def _follow_advice(gcs: Px4Gcs, advice: Callable[[], Any], record: dict[str, Any],
                         say: Callable[[str], None]) -> None:
    """While circling: EKF2_EV_DELAY set to the advice each time the back-channel renews it (as `set_delay: true`
    does; the circle's load on the host moved the delays by up to 5 ms from the advice set before it, issue 31);
    record["circle_ev_delays_ms"] gets each value."""
    while True:
        await asyncio.sleep(ADVICE_EVERY_S)
        before = record["viso_delay_ms"]
        try:
            await set_advised_ev_delay(gcs, advice(), record, say)
        except SitlError as e:  # PX4 did not echo it: the flight goes on with the value it has
            say(f"EKF2_EV_DELAY not changed in flight: {e}")
        if record["viso_delay_ms"] != before:
            record["circle_ev_delays_ms"].append(record["viso_delay_ms"])


async def fly_px4(gcs: Px4Gcs, plan: FlightPlan, record: dict[str, Any], say: Callable[[str], None],
                  live: Any, sending: Callable[[], bool], advice: Callable[[], Any], follow_advice: bool = False
                  ) -> None:
    """EKF2 on the vision, arm in Position mode, Offboard take-off, hold (cut), square, circle, AUTO.LAND, disarm.
    live.cut(start_ns, end_ns) hides the vehicle; sending(): poses go; advice(): the bridge's delay advice;
    follow_advice: EKF2_EV_DELAY set to it once airborne, again before the circle and while circling
    (set_advised_ev_delay, _follow_advice)."""
    await wait_ev_fused(gcs, 60.0, sending)
    record["extnav_ns"] = time.monotonic_ns()
    say("EKF2 fuses the vision")
    await arm_in_position_mode(gcs, 45.0)
    record["armed_ns"] = time.monotonic_ns()
    await gcs.until(lambda: bool(gcs.local), 5.0, "LOCAL_POSITION_NED from PX4 (its GCS link streams it)")
    n0, e0, _ = gcs.local[-1][1:4]
    gcs.setpoint = (n0, e0, -plan.altitude_m)  # streamed before and after the switch: Offboard needs it
    await asyncio.sleep(0.5)
    await gcs.command_async(176, 1, OFFBOARD, what="Offboard mode")  # MANUAL_CONTROL goes on: its loss fails safe
    say("armed in Position mode; Offboard take-off")
    await _reach(gcs, n0, e0, -plan.altitude_m, 30.0)
    record["airborne_ns"] = time.monotonic_ns()
    if follow_advice:
        await set_advised_ev_delay(gcs, advice(), record, say)
    await _hold(gcs, plan, plan.hold_s / 2)
    if plan.cut_s > 0:
        now = time.monotonic_ns()
        live.cut(now, now + int(plan.cut_s * 1e9))
        record["cut"] = (now, now + int(plan.cut_s * 1e9), (n0, e0, -plan.altitude_m))
        say(f"vision cut for {plan.cut_s:g} s")
        await asyncio.sleep(plan.cut_s)
    await _hold(gcs, plan, plan.hold_s / 2)
    if plan.square:
        s = plan.side_m
        for dn, de in ((s, 0.0), (s, s), (0.0, s), (0.0, 0.0)):
            await _reach(gcs, n0 + dn, e0 + de, -plan.altitude_m, 20.0)
            say(f"  corner N {dn:+.1f} E {de:+.1f} m reached")
            await asyncio.sleep(1.0)
    if plan.circle_s > 0:
        c = (n0 + plan.side_m / 2, e0 + plan.side_m / 2)
        await _reach(gcs, c[0] + CIRCLE_RADIUS_M, c[1], -plan.altitude_m, 20.0)
        if follow_advice:
            await set_advised_ev_delay(gcs, advice(), record, say)

        def send(n: float, e: float, vn: float, ve: float) -> None:
            gcs.setpoint, gcs.velocity = (n, e, -plan.altitude_m), (vn, ve, 0.0)

        record["circle_ev_delays_ms"] = [record["viso_delay_ms"]]
        follow = asyncio.create_task(_follow_advice(gcs, advice, record, say)) if follow_advice else None
        try:
            await fly_circle(send, c, plan.circle_s, record, say)
        finally:
            gcs.velocity = None
            if follow is not None:
                follow.cancel()
                await asyncio.gather(follow, return_exceptions=True)
        await _reach(gcs, c[0] + CIRCLE_RADIUS_M, c[1], -plan.altitude_m, 20.0)
    adv = advice()
    if adv is not None:
        record["advised_ms"] = adv.value_ms
        say(f"the bridge advises EKF2_EV_DELAY={adv.value_ms} ({adv.why}); this run ended with "
            f"{record['viso_delay_ms']}")
    record["land_ns"] = time.monotonic_ns()
    await gcs.command_async(176, 1, AUTO, AUTO_LAND, what="AUTO.LAND")
    gcs.setpoint = None
    await gcs.until(lambda: not gcs.armed, 40.0, "landing and disarm")
    record["disarmed_ns"] = time.monotonic_ns()
    record["completed"] = True
    say("landed and disarmed")


async def _hold(gcs: Px4Gcs, plan: FlightPlan, duration_s: float) -> None:
    """Hover duration_s: still, or (plan.yaw_swing_rad_s) turning back and forth about the vertical with a
    sinusoidal yaw rate (FlightPlan.yaw_rate_at), the rotation the back-channel's delay measurement
    correlates; SIH's roll and pitch gyros are too noisy for it."""
    t0 = time.monotonic()
    try:
        while (t := time.monotonic() - t0) < duration_s:
            if plan.yaw_swing_rad_s > 0:
                gcs.yaw_rate = plan.yaw_rate_at(t)
            await asyncio.sleep(0.05)
    finally:
        gcs.yaw_rate = None


async def _reach(gcs: Px4Gcs, north: float, east: float, down: float, timeout_s: float) -> None:
    """The offboard setpoint moved there (Px4Gcs streams it), until SIH's true position has settled within
    SETTLE_RADIUS_M of it (truth.until_settled)."""
    gcs.setpoint = (north, east, down)
    x = await until_settled(gcs.truth, ned_to_world(np.array([north, east, down])), timeout_s,
                            radius_m=SETTLE_RADIUS_M)
    if x is not None:
        raise SitlError(f"the vehicle did not reach N {north:.2f} E {east:.2f} D {down:.2f} within {timeout_s:g} s "
                        f"(true position {x.round(3).tolist()} in the world frame)")
