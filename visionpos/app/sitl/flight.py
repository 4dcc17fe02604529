"""The scripted flight on the live arena: EKF on vision, VISO_DELAY_MS, GUIDED, arm, take off, hold (a
vision cut, a yaw swing), the square, land.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import time
from typing import Any, Callable

import numpy as np

from bridge.estimator_delay import JITTER_WINDOW, advised_delay, ardupilot_transfer_ms
from visionpos.app.sitl.delay import delay_record, fmt_ms
from visionpos.app.sitl.gcs import (
    COPTER_MODES,
    EXTNAV_TEXT,
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_NAV_TAKEOFF,
    Gcs,
)
from visionpos.app.sitl.preflight import SERIAL1_BAUD_BPS
from visionpos.app.sitl.settings import SitlError, SitlSettings
from visionpos.app.sitl.truth import LATE_NS, LiveArena, truth_now, until_settled
from visionpos.geometry.frames import ned_to_world


@dataclasses.dataclass
class FlightPlan:
    altitude_m: float = 1.0
    side_m: float = 1.0
    hold_s: float = 4.0
    square: bool = True
    cut_s: float = 0.0  # vision hidden this long mid-hover (0: no cut)
    timeout_s: float = 240.0
    # the vision link through a DelayRelay holding each direction this long (None: SERIAL1 straight to the bridge)
    link_delay_ms: float | None = None
    # yaw rate swung sinusoidally (rad/s amplitude, YAW_SWING_PERIOD_S) during the hold: the rotation the
    # back-channel's gyro/optical correlation needs to measure the delay (0: hold still)
    yaw_swing_rad_s: float = 0.0
    # a horizontal circle (CIRCLE_RADIUS_M, CIRCLE_PERIOD_S) flown this long after the square, about the square's
    # centre: a steady speed turning through every direction, what the EKF's lead is fitted on (0: none)
    circle_s: float = 0.0

    def yaw_rate_at(self, t_s: float) -> float:
        """The swing's yaw rate (rad/s) t_s into the hold."""
        return self.yaw_swing_rad_s * math.sin(2 * math.pi * t_s / YAW_SWING_PERIOD_S)


def circle_at(t_s: float) -> tuple[float, float, float, float]:
    """The circle's setpoint t_s after its start: north and east from its centre (m), and their rates (m/s).
    It starts CIRCLE_RADIUS_M north of the centre, turning towards the east."""
    w = 2 * math.pi / CIRCLE_PERIOD_S
    r = CIRCLE_RADIUS_M
    return r * math.cos(w * t_s), r * math.sin(w * t_s), -r * w * math.sin(w * t_s), r * w * math.cos(w * t_s)


async def fly(ctx: Any, gcs: Gcs, live: LiveArena, plan: FlightPlan, cfg: SitlSettings, body: str,
              record: dict[str, Any], say: Callable[[str], None], relay: Any = None) -> None:
    """The scripted flight: EKF on vision, VISO_DELAY_MS, GUIDED, arm, take off, hold (cut, yaw swing),
    square, land. With a relay, record["link_delay"] gets delay_record at the end of the hold."""
    end = time.monotonic() + plan.timeout_s
    left = lambda: max(1.0, end - time.monotonic())  # noqa: E731
    await Gcs.until(gcs.ekf_using_vision, min(60.0, left()), f"STATUSTEXT '{EXTNAV_TEXT}'")
    record["extnav_ns"] = time.monotonic_ns()
    link = ctx.bridge.vehicle(body)
    if cfg.viso_delay_ms is None:
        await set_advised_delay(gcs, link, plan, say, relay)
    record["viso_delay_ms"] = gcs.params.get("VISO_DELAY_MS")
    record["stamp_age_ms"] = [_stamp_age_ms(link)]  # the bridge's stamp age when the delay was set, then landed
    await arm_in_guided(gcs, live, left())
    record["armed_ns"] = time.monotonic_ns()
    say("armed in GUIDED")
    await gcs.command_async(MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, plan.altitude_m, what="takeoff")

    def height() -> float:
        t, x = truth_now(gcs.truth)
        return x[2] if t else 0.0

    await Gcs.until(lambda: height() >= plan.altitude_m - 0.05, min(30.0, left()), f"climb to {plan.altitude_m} m")
    record["airborne_ns"] = time.monotonic_ns()
    x0, y0, z0 = gcs.local[-1][1:4]
    say(f"at {height():.2f} m; holding" + (f", yaw swinging +-{plan.yaw_swing_rad_s:g} rad/s"
                                             if plan.yaw_swing_rad_s > 0 else ""))
    await _hold(gcs, plan, x0, y0, plan.hold_s / 2)
    if plan.cut_s > 0:
        now = time.monotonic_ns()
        live.cut(now, now + int(plan.cut_s * 1e9))
        record["cut"] = (now, now + int(plan.cut_s * 1e9), (x0, y0, z0))
        say(f"vision cut for {plan.cut_s:g} s (the body hidden from every camera)")
        await asyncio.sleep(plan.cut_s)
    await _hold(gcs, plan, x0, y0, plan.hold_s / 2)
    if relay is not None:
        record["link_delay"] = delay_record(link.bc, relay, plan.link_delay_ms or 0.0, gcs.truth, clock=gcs.clock)
        d = record["link_delay"]
        say(f"link delay {d['added_ms']:g} ms: back-channel measured {fmt_ms(d['measured_ms'])} ms, true "
            f"{fmt_ms(d['true_ms'])} ms ({d['detail']})")
    if plan.square:
        s = plan.side_m
        for dx, dy in ((s, 0.0), (s, s), (0.0, s), (0.0, 0.0)):
            await goto(gcs, x0 + dx, y0 + dy, -plan.altitude_m, min(20.0, left()))
            say(f"  corner N {dx:+.1f} E {dy:+.1f} m reached")
            await asyncio.sleep(1.0)
    if plan.circle_s > 0:
        c = (x0 + plan.side_m / 2, y0 + plan.side_m / 2)
        await goto(gcs, c[0] + CIRCLE_RADIUS_M, c[1], -plan.altitude_m, min(20.0, left()))
        await fly_circle(lambda n, e, vn, ve: gcs.conn.mav.set_position_target_local_ned_send(
            0, gcs.target, 1, 1, 0b0000_1111_1100_0000, n, e, -plan.altitude_m, vn, ve, 0, 0, 0, 0, 0, 0),
            c, plan.circle_s, record, say)
    record["land_ns"] = time.monotonic_ns()
    record["stamp_age_ms"].append(_stamp_age_ms(link))
    await gcs.command_async(MAV_CMD_DO_SET_MODE, 1, COPTER_MODES["LAND"], what="LAND mode")
    await Gcs.until(lambda: not gcs.armed, min(40.0, left()), "landing and disarm")
    record["disarmed_ns"] = time.monotonic_ns()
    record["completed"] = True
    say("landed and disarmed")


def _stamp_age_ms(link: Any) -> float | None:
    age = link.stamps.age_ns
    return None if age is None else age * 1e-6


YAW_SWING_PERIOD_S = 2.0
# 0.5 m at 3 s a turn: 1.05 m/s, 2.2 m/s^2 inward; a 2 ms lead is then 2.1 mm across the track. The first turn
# (the vehicle catching up with the setpoint) is left out of the fit.
CIRCLE_RADIUS_M, CIRCLE_PERIOD_S = 0.5, 3.0
CIRCLE_SPEED_M_S = 2 * math.pi * CIRCLE_RADIUS_M / CIRCLE_PERIOD_S
ADVICE_POSES = 2 * JITTER_WINDOW  # the newest poses the advice is taken from: two of ArduPilot's jitter windows
ADVICE_HOLD_NS = 4_000_000_000  # the relay's hold: its median over this long


async def set_advised_delay(gcs: Gcs, link: Any, plan: FlightPlan, say: Callable[[str], None],
                            relay: Any = None) -> None:
    """VISO_DELAY_MS set to the bridge's advice (bridge/estimator_delay.py) from the newest ADVICE_POSES poses, once
    the bridge's stamp age has settled (bridge/stamp_grid.py) and that many went out at it: each pose's stamp ->
    arrival, its stamp -> send plus the relay's measured hold (loopback adds nothing), less the time SITL takes
    off each arrival for its bytes at SERIAL1_BAUD."""
    await Gcs.until(lambda: link.stamps.settled, 30.0, "the bridge's stamp age (its first 5 s of tracking)")
    await asyncio.sleep(ADVICE_POSES / link.cfg.rate_hz)  # poses sent at the settled age only
    cfg = link.cfg
    transfer = ardupilot_transfer_ms(cfg.message, cfg.signing_key is not None,
                                     cfg.autopilot_baud or SERIAL1_BAUD_BPS)
    recent = link.lat_stamp.values()[-ADVICE_POSES:]  # the stamp age the bridge settled on, not its first guess
    held = relay.hold_ms_median("to_autopilot", time.monotonic_ns() - ADVICE_HOLD_NS) if relay is not None else None
    added = held if held is not None else (plan.link_delay_ms or 0.0)  # the relay's hold as measured
    advice = advised_delay("ardupilot", recent * 1e-6 + added, transfer_ms=transfer)
    delay_ms = advice.value_ms if advice is not None else 10
    await gcs.set_params_async({"VISO_DELAY_MS": delay_ms})
    say(f"EKF3 uses the vision; VISO_DELAY_MS = {delay_ms}: "
        + (advice.why if advice is not None else "no pose timed yet")
        + (f", with the relay's {added:.2f} ms" if plan.link_delay_ms else ""))
    if advice is not None and advice.horizon_param is not None:
        booted = gcs.params.get(advice.horizon_param)
        say(f"  the poses need {advice.horizon_param}={advice.horizon_ms} ({advice.horizon_why}); SITL booted with "
            + (f"{booted:g}" if booted is not None else "its default")
            + ("" if booted is not None and booted >= advice.horizon_ms else ": short, the EKF will trail the truth"))


async def arm_in_guided(gcs: Gcs, live: LiveArena, timeout_s: float) -> None:
    """GUIDED, then arm, retried while the pre-arm checks wait for the EKF to settle on the vision (at most 45 s)."""
    await gcs.command_async(MAV_CMD_DO_SET_MODE, 1, COPTER_MODES["GUIDED"], what="GUIDED mode")
    arm_end = time.monotonic() + min(45.0, timeout_s)
    while True:
        gcs.command(MAV_CMD_COMPONENT_ARM_DISARM, 1)
        try:
            await Gcs.until(lambda: gcs.armed, 1.5, "arming")
            return
        except SitlError:
            if time.monotonic() > arm_end:
                late = live.frames_late / max(1, live.frames_made)
                raise SitlError("SITL would not arm; last messages: " + "; ".join(t for _, _, t in gcs.texts[-5:])
                                + f". {100 * late:.0f}% of the camera frames so far were made more than "
                                f"{LATE_NS // 1_000_000} ms late" + (": this host is not keeping real time, and "
                                "'VisOdom: not healthy' means gaps of over 300 ms in the vision" if late > 0.02
                                else "")) from None


async def _hold(gcs: Gcs, plan: FlightPlan, north: float, east: float, duration_s: float) -> None:
    """Hold the position for duration_s: still, or (plan.yaw_swing_rad_s) turning back and forth about the
    vertical with a sinusoidal yaw rate (SET_POSITION_TARGET_LOCAL_NED: position and yaw rate)."""
    if plan.yaw_swing_rad_s <= 0:
        await asyncio.sleep(duration_s)
        return
    t0 = time.monotonic()
    while (t := time.monotonic() - t0) < duration_s:
        rate = plan.yaw_rate_at(t)
        gcs.conn.mav.set_position_target_local_ned_send(0, gcs.target, 1, 1, 0b0000_0101_1111_1000, north, east,
                                                        -plan.altitude_m, 0, 0, 0, 0, 0, 0, 0, rate)
        await asyncio.sleep(0.05)


async def fly_circle(send: Callable[[float, float, float, float], None], centre: tuple[float, float],
                     duration_s: float, record: dict[str, Any], say: Callable[[str], None]) -> None:
    """Sweep the setpoint round the circle (circle_at) about centre (N, E m) for duration_s, each 50 ms through
    send(north, east, v_north, v_east): position with the velocity as feed-forward. record["circle"]: the span
    (server ns) after the first turn."""
    say(f"circling: radius {CIRCLE_RADIUS_M:g} m, {CIRCLE_PERIOD_S:g} s a turn, for {duration_s:g} s")
    t0 = time.monotonic_ns()
    while (t := (time.monotonic_ns() - t0) * 1e-9) < duration_s:
        dn, de, vn, ve = circle_at(t)
        send(centre[0] + dn, centre[1] + de, vn, ve)
        await asyncio.sleep(0.05)
    record["circle"] = (t0 + int(CIRCLE_PERIOD_S * 1e9), time.monotonic_ns())


async def goto(gcs: Gcs, north: float, east: float, down: float, timeout_s: float) -> None:
    """SET_POSITION_TARGET_LOCAL_NED (position only, resent every 0.25 s) until the true position has settled
    within 5 cm of it (truth.until_settled)."""
    def setpoint() -> None:
        gcs.conn.mav.set_position_target_local_ned_send(0, gcs.target, 1, 1, 0b0000_1111_1111_1000, north, east, down,
                                                        0, 0, 0, 0, 0, 0, 0, 0)

    x = await until_settled(gcs.truth, ned_to_world(np.array([north, east, down])), timeout_s, setpoint)
    if x is not None:
        raise SitlError(f"the vehicle did not reach N {north:.2f} E {east:.2f} D {down:.2f} within "
                        f"{timeout_s:g} s (true position {x.round(3).tolist()} in the world frame)")


# ---------------------------------------------------------------- the summary
