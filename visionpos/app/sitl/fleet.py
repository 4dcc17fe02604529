"""`visionpos sitl --vehicles N`: N ArduPilot SITL instances flown together on the demo's live arena.

Vehicle i (the arena's first N): its own SITL (a free instance, `--sysid` its vehicle's sysid, home where it
stands: a row along the arena's y axis, ROW_SPACING_M apart), its own GCS link and truth, its body following
that truth. Every SITL's SERIAL1 goes through one CrossRelay (visionpos/app/linkswap.py) to its vehicle's
endpoint; with swap_at_s the relay exchanges the first two vehicles' links that long into the hover, as two
radios swapped at the ground station, and puts them back swap_for_s later. The bridge must stop the poses on both
crossed links before either autopilot flies on the other's (bridge/crossed_link.py); the relay counts every pose
that reached the wrong autopilot.

The flight, all vehicles together: EKF on vision, VISO_DELAY_MS as advised, GUIDED, arm and take off (one after
the other), hover (the swap), a crossing (the first and the last vehicle exchange places, passing CROSS_GAP_M
apart at the same height on parallel lines: their markers merge in some cameras' images; with three or more,
CROSS_OFFSET_M out of the row, clear of the others: crossing_legs), the crossing back, land.

Vehicles whose bodies share a marker layout (--same-layout: identical drones) are bound before take-off by their
parking pads (vehicles[].pad, set where each stands): ArduPilot on vision alone cannot arm before its body is bound
("Arm: VisOdom: not healthy"), so it cannot be bound by a take-off, and a SITL vehicle cannot be turned by hand
on the floor (docs/autopilot-setup.md, "A fleet"). The motion checks each pad binding from the first one on.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
import sys
import time
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from visionpos.app.sitl.flight import FlightPlan, arm_in_guided, goto, set_advised_delay
from visionpos.app.sitl.gcs import COPTER_MODES, EXTNAV_TEXT, MAV_CMD_DO_SET_MODE, MAV_CMD_NAV_TAKEOFF, Gcs
from visionpos.app.sitl.preflight import prepare_vehicle
from visionpos.app.sitl.process import SitlProcess, free_instances
from visionpos.app.sitl.report import FAILSAFE_WORDS, flight_summary, horizontal_error_mm, say_to
from visionpos.app.sitl.settings import SitlError, parse_sitl
from visionpos.app.sitl.truth import LATLON_TO_M, LiveArena, TruthTrack, truth_now
from visionpos.config.arena import ArenaConfig
from visionpos.errors import UsageError
from visionpos.geometry.frames import world_to_ned

ROW_SPACING_M = 1.2  # the vehicles stand in a row along y this far apart, centred on the origin
CROSS_GAP_M = 0.3  # the crossing vehicles pass this far apart (north-south), at the same height
CROSS_OFFSET_M = 0.8  # with 3 or more vehicles the crossing is flown this far north of the row (clear of the others)
RESUME_TIMEOUT_S = 10.0  # after the links are put back, the poses must flow again within this
SWAP_SLACK_NS = 60_000_000  # a pose already on its way when the bridge read the other autopilot's packet
_AFTER_SWAP_NS = 5_000_000_000  # the EKF is judged again this long after the poses resumed


@dataclasses.dataclass(frozen=True)
class Swap:
    at_s: float  # into the hover
    for_s: float = 2.0


@dataclasses.dataclass
class _Vehicle:
    name: str  # the vehicle's (and its body's) name
    sysid: int
    start_world: np.ndarray  # (3,) m where it stands
    truth: TruthTrack
    gcs: Gcs | None = None
    record: dict = dataclasses.field(default_factory=dict)


def fleet_arena(arena: ArenaConfig, n: int, same_layout: bool = False, swap_pads: bool = False) -> ArenaConfig:
    """The arena with its first n vehicles only (its other bodies fly their scenario's paths). same_layout: their
    bodies all get the first one's markers (identical drones). Vehicles whose bodies share a layout get a pad where
    they stand (start_positions; swap_pads: the first two exchanged, drones parked on each other's pads), unless
    the file gives one: the bridge binds each still body to the vehicle on
    whose pad it stands, and checks it by motion (bridge/fleet_binding.py); ArduPilot on vision alone cannot arm
    before its body is bound ('Arm: VisOdom: not healthy'), so it could not take off to be bound by its motion."""
    from visionpos.config.arena import parse_arena

    data = arena.to_dict()
    vehicles = [dict(v) for v in (data.get("vehicles") or [])[:n]]
    if len(vehicles) < n:
        raise UsageError(f"{arena.source}: --vehicles {n}, but the arena has {len(vehicles)} vehicle(s) "
                         "(the demo makes one per body): take a scenario with more bodies (pair, arena8)")
    names = [v["body"] for v in vehicles]
    bodies = {b["name"]: b for b in data["bodies"]}
    if same_layout:
        first = bodies[names[0]]
        for name in names[1:]:
            bodies[name].update(markers=[list(m) for m in first["markers"]],
                                marker_diameter=first.get("marker_diameter", bodies[name].get("marker_diameter")))
    layouts = [np.asarray(bodies[name]["markers"], np.float64).round(6).tobytes() for name in names]
    if len(set(layouts)) < len(layouts):
        pads = [[float(at[0]), float(at[1])] for at in start_positions(n)]
        if swap_pads:  # the first two parked on each other's pads: the pads bind them wrongly until they move
            pads[0], pads[1] = pads[1], pads[0]
        for v, pad in zip(vehicles, pads):
            v.setdefault("pad", pad)
    elif swap_pads:
        raise UsageError("--swap-pads: the pads bind vehicles of one layout; give --same-layout")
    data["vehicles"] = vehicles
    return parse_arena(data, arena.source)


def start_positions(n: int) -> np.ndarray:
    """(n, 3) m world positions of the row the vehicles stand in (y from -, on the floor)."""
    y = (np.arange(n) - (n - 1) / 2.0) * ROW_SPACING_M
    return np.column_stack([np.zeros(n), y, np.zeros(n)])


def crossing_legs(start_a_ned: np.ndarray, start_b_ned: np.ndarray, n: int
                  ) -> list[tuple[tuple[float, float], tuple[float, float], str]]:
    """The crossing of the first (a) and last (b) vehicle of n standing in the row: legs [((north, east) m of a,
    (north, east) m of b, what they did)], local NED, each leg flown by both at once. They first step apart
    north-south (CROSS_GAP_M), exchange places on parallel lines, come back the same way and return over their
    pads: flown straight from the row to the other's place they would pass at half the gap. With more than two,
    the others hover in the row between them, so a and b step out CROSS_OFFSET_M north of it first."""
    ea, eb = float(start_a_ned[1]), float(start_b_ned[1])
    x = 0.0 if n <= 2 else CROSS_OFFSET_M
    na, nb = x + CROSS_GAP_M / 2, x - CROSS_GAP_M / 2
    passed = f"({CROSS_GAP_M:g} m apart as they passed)"
    out = f"stepped {CROSS_GAP_M:g} m apart" + (f", {x:g} m out of the row" if x else "")
    return [((na, ea), (nb, eb), out), ((na, eb), (nb, ea), f"crossed {passed}"),
            ((na, ea), (nb, eb), f"crossed back {passed}"), ((0.0, ea), (0.0, eb), "are back over their pads")]


def home_at(origin: tuple[float, float, float, float], world: np.ndarray) -> tuple[float, float, float, float]:
    """SITL's --home (lat, lon deg, alt m, heading deg) for a vehicle standing at world (3,) m from the origin."""
    north, east, _ = world_to_ned(np.asarray(world, float))
    lat, lon, alt, hdg = origin
    return (lat + north / LATLON_TO_M * 1e-7, lon + east / (LATLON_TO_M * math.cos(math.radians(lat))) * 1e-7,
            alt, hdg)


def run_fleet(arena: ArenaConfig, binary: Path, plan: FlightPlan, n: int, swap: Swap | None,
              out: TextIO | None, same_layout: bool = False, swap_pads: bool = False) -> dict[str, Any]:
    """Start n SITLs, set each up for vision-only flight, fly them together on the live arena; the summary dict."""
    from bridge.config import parse_vehicles
    from visionpos.app.linkswap import CrossRelay

    if n < 2:
        raise UsageError(f"--vehicles {n}: give 2 or more (one vehicle: leave --vehicles out)")
    if swap is not None and swap.at_s + swap.for_s > plan.hold_s:
        raise UsageError("--swap-at: the swap must end within the hover (--hold)")
    arena = fleet_arena(arena, n, same_layout, swap_pads)
    cfg = parse_sitl(arena, binary)
    vcfgs = parse_vehicles(arena)
    if any(v.signing_key is None for v in vcfgs):
        raise UsageError("SITL flies over signed links: give each vehicle signing: {key_file: ...}")
    say = say_to(out)
    starts = start_positions(n)
    fleet = [_Vehicle(v.body, v.sysid, starts[i], TruthTrack(cfg.home[:3])) for i, v in enumerate(vcfgs)]
    live = LiveArena(fleet[0].name, fleet[0].truth, {v.name: v.truth for v in fleet[1:]})
    t0 = time.monotonic()
    old_switch = sys.getswitchinterval()
    sys.setswitchinterval(0.001)  # the GCS readers stamp truth on arrival: let them run promptly
    relay = CrossRelay([("127.0.0.1", v.endpoint.port) for v in vcfgs], lifetime_s=plan.timeout_s + 300,
                       keep_data=swap is not None).start()
    demo: dict[str, Any] = {}
    try:
        with contextlib.ExitStack() as stack:
            for i, (v, inst) in enumerate(zip(fleet, free_instances(n))):
                vcfg = dataclasses.replace(cfg, home=home_at(cfg.home, v.start_world))
                proc = stack.enter_context(SitlProcess(vcfg, inst, f"udpclient:127.0.0.1:{relay.autopilot_port(i)}",
                                                       sysid=v.sysid))
                v.gcs = Gcs(proc.gcs_port, v.truth, on_text=lambda text, name=v.name: say(f"  {name}: {text}"))
                v.gcs.target = v.sysid
                stack.callback(v.gcs.close)
                at = v.start_world[:2].round(2).tolist()
                say(f"{v.name}: SITL instance {inst}, sysid {v.sysid}, standing at {at} m; "
                    f"SERIAL1 -> relay leg {i} -> the bridge ({vcfgs[i].endpoint}, signed)")
                prepare_vehicle(v.gcs, proc, cfg, vcfgs[i], vcfgs[i].signing_key, say, None,
                                home=vcfg.home[:3])
            say(f"set-up of {n} vehicles done in {time.monotonic() - t0:.1f} s; cameras start")
            demo = _fly_live(arena, fleet, live, plan, swap, relay, say)
    finally:
        relay.stop()
        sys.setswitchinterval(old_switch)
    return _summary(fleet, live, demo, plan, relay, time.monotonic() - t0)


def _fly_live(arena: ArenaConfig, fleet: list[_Vehicle], live: LiveArena, plan: FlightPlan, swap: Swap | None,
              relay: Any, say: Any) -> dict[str, Any]:
    from visionpos.app.demo import run_demo

    async def during(ctx: Any) -> None:
        try:
            await _fly(ctx, fleet, live, plan, swap, relay, say)
        except SitlError as e:
            fleet[0].record["error"] = str(e)
            say(f"flight failed: {e}")
        finally:  # the bindings as they ended (a failed flight too)
            fleet[0].record["fleet_binding"] = ctx.bridge.stats().get("fleet_binding") or {}
            for v in fleet:
                h = ctx.bridge.health().get(v.name) or {}
                v.record["binding_at_end"] = {k: h.get(k) for k in ("identity_binding", "identity_reason",
                                                                     "bound_body")}
            live.stop()

    return asyncio.run(run_demo(arena, plan.timeout_s + 60.0, None, during=during, live=live))


async def _fly(ctx: Any, fleet: list[_Vehicle], live: LiveArena, plan: FlightPlan, swap: Swap | None, relay: Any,
               say: Any) -> None:
    """All vehicles: vision, delay, GUIDED and arm, take off, hover (the swap), cross, cross back, land."""
    end = time.monotonic() + plan.timeout_s
    left = lambda: max(1.0, end - time.monotonic())  # noqa: E731
    for v in fleet:
        try:
            await Gcs.until(v.gcs.ekf_using_vision, min(60.0, left()), f"STATUSTEXT '{EXTNAV_TEXT}' from {v.name}")
        except SitlError as e:  # nothing went to it: say why (a fleet vehicle's binding)
            h = ctx.bridge.health().get(v.name) or {}
            raise SitlError(f"{e}; the bridge: {h.get('sending')}" + (
                f", identity {h['identity_binding']}: {h.get('identity_reason')}" if "identity_binding" in h
                else "")) from None
    await asyncio.gather(*(set_advised_delay(v.gcs, ctx.bridge.vehicle(v.name), plan, say) for v in fleet))
    for v in fleet:  # each takes off as soon as it is armed (an armed copter left on the ground disarms itself)
        v.record["viso_delay_ms"] = v.gcs.params.get("VISO_DELAY_MS")
        await arm_in_guided(v.gcs, live, left())
        v.record["armed_ns"] = time.monotonic_ns()
        # how it was bound when it takes off (a fleet of one layout: on its pad); read here, not after the
        # others armed: by then a loss in its flight may have had it bound again by its motion
        h = ctx.bridge.health().get(v.name) or {}
        v.record["binding"] = {k: h.get(k) for k in ("identity_binding", "identity_reason", "bound_body")}
        await v.gcs.command_async(MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, plan.altitude_m, what="takeoff")
        say(f"{v.name} armed in GUIDED, taking off")
    alt = plan.altitude_m - 0.05
    await Gcs.until(lambda: all(truth_now(v.truth)[1][2] >= alt for v in fleet), min(30.0, left()),
                    f"every vehicle at {plan.altitude_m} m")
    say(f"all at {plan.altitude_m:g} m; hovering {plan.hold_s:g} s")
    hover_end = time.monotonic() + plan.hold_s
    if swap is not None:
        await asyncio.sleep(swap.at_s)
        fleet[0].record["swap"] = await _swap(ctx, fleet, relay, swap, say)
    await asyncio.sleep(max(0.0, hover_end - time.monotonic()))
    a, b = fleet[0], fleet[-1]
    down = -plan.altitude_m
    for pa, pb, what in crossing_legs(world_to_ned(a.start_world), world_to_ned(b.start_world), len(fleet)):
        await asyncio.gather(goto(a.gcs, pa[0], pa[1], down, min(25.0, left())),
                             goto(b.gcs, pb[0], pb[1], down, min(25.0, left())))
        say(f"  {a.name} and {b.name} {what}")
        await asyncio.sleep(1.0)
    for v in fleet:
        v.record["land_ns"] = time.monotonic_ns()
        await v.gcs.command_async(MAV_CMD_DO_SET_MODE, 1, COPTER_MODES["LAND"], what="LAND mode")
    await Gcs.until(lambda: not any(v.gcs.armed for v in fleet), min(40.0, left()), "every vehicle landed")
    for v in fleet:
        v.record["disarmed_ns"] = time.monotonic_ns()
        v.record["completed"] = True
    say("all landed and disarmed")


async def _swap(ctx: Any, fleet: list[_Vehicle], relay: Any, swap: Swap, say: Any) -> dict[str, Any]:
    """Exchange the first two vehicles' links for swap.for_s, put them back, wait for the poses to flow again."""
    links = [ctx.bridge.vehicle(v.name) for v in fleet[:2]]
    t_swap = relay.swap(0, 1)
    say(f"  links of {fleet[0].name} and {fleet[1].name} swapped (the relay exchanged their autopilots)")
    await asyncio.sleep(swap.for_s)
    stopped = [link.sending_state() for link in links]
    t_back = relay.swap(0, 1)
    say(f"  links put back after {swap.for_s:g} s; while swapped the bridge said: " + "; ".join(stopped))
    deadline = time.monotonic() + RESUME_TIMEOUT_S
    while any(link.sending_state() != "sending" for link in links):
        if time.monotonic() > deadline:
            raise SitlError("the poses did not resume within "
                            f"{RESUME_TIMEOUT_S:g} s after the links were put back: "
                            + "; ".join(link.sending_state() for link in links))
        await asyncio.sleep(0.05)
    t_resumed = time.monotonic_ns()
    say(f"  poses flow again {(t_resumed - t_back) * 1e-9:.2f} s after the links were put back")
    return {"t_swap": t_swap, "t_back": t_back, "t_resumed": t_resumed, "said": stopped}


POSE_MSGIDS = (102, 103, 331)  # VISION_POSITION_ESTIMATE, VISION_SPEED_ESTIMATE, ODOMETRY


def carries_pose(datagram: bytes) -> bool:
    """Whether a datagram of MAVLink2 packets holds a pose message (its packets walked by their headers)."""
    i = 0
    while i + 10 <= len(datagram) and datagram[i] == 0xFD:
        if int.from_bytes(datagram[i + 7:i + 10], "little") in POSE_MSGIDS:
            return True
        i += 12 + datagram[i + 1] + (13 if datagram[i + 2] & 1 else 0)
    return False


def swap_record(relay: Any, swap: dict[str, Any]) -> dict[str, Any]:
    """What crossed during the swap: for each of the two autopilots, when the bridge first heard it on the other
    link (ms after the swap) and the poses of the bridge's other link that reached it, with the last one's time
    after that detection (ms); those after it (SWAP_SLACK_NS allowed for a pose already on its way) must be none."""
    t_swap, t_back = swap["t_swap"], swap["t_back"]
    out = {}
    for ap in (0, 1):
        heard = [r[0] for r in relay.to_bridge if r[2] == ap and r[1] != ap and t_swap <= r[0] <= t_back]
        first = min(heard) if heard else None
        wrong = [r[0] for r in relay.to_autopilot if r[2] == ap and r[1] != ap and carries_pose(r[3])]
        out[f"autopilot{ap}"] = {
            "detected_after_ms": None if first is None else (first - t_swap) * 1e-6,
            "wrong_poses": len(wrong),
            "wrong_poses_after_detection": None if first is None else sum(t > first + SWAP_SLACK_NS for t in wrong),
            "last_wrong_after_detection_ms": None if not wrong or first is None else (max(wrong) - first) * 1e-6,
        }
    out["ok"] = all(v["detected_after_ms"] is not None and v["wrong_poses_after_detection"] == 0
                    for k, v in out.items() if k.startswith("autopilot"))
    out["resumed_after_s"] = (swap["t_resumed"] - t_back) * 1e-9
    out["said"] = swap["said"]
    return out


def _summary(fleet: list[_Vehicle], live: LiveArena, demo: dict[str, Any], plan: FlightPlan, relay: Any,
             wall_s: float) -> dict[str, Any]:
    swap = fleet[0].record.get("swap")
    vehicles = {}
    for v in fleet:
        s = flight_summary(v.gcs, v.truth, demo, v.record, plan, wall_s, body=v.name)
        s["binding_at_take_off"] = v.record.get("binding")
        s["binding_at_end"] = v.record.get("binding_at_end")
        if swap is not None:  # the target is judged outside the swap: the EKF is on its IMU alone during it
            o = s["ekf_horizontal_error_outside_swap_mm"] = _outside(v, swap)
            # and so are the failsafes: a lane switch while the vision is cut is the EKF's answer to the cut
            s["failsafe_or_lane_switch"], s["failsafe_during_swap"] = alarms_outside_and_during(v.gcs.texts, swap)
            s["ok"] = bool(s["completed"] and o["p99"] is not None and o["p99"] <= 20.0
                           and not s["failsafe_or_lane_switch"] and not s["mode_changes_not_ours"])
        vehicles[v.name] = s
    out: dict[str, Any] = {"vehicles": vehicles, "error": fleet[0].record.get("error"), "wall_s": wall_s}
    if swap is not None:
        out["swap"] = swap_record(relay, swap)
    if "fleet_binding" in fleet[0].record:
        out["fleet_binding"] = fleet[0].record["fleet_binding"]
    made = max(live.frames_made, 1)
    out["real_time"] = {"frames_made": live.frames_made, "frames_late_fraction": live.frames_late / made}
    out["ok"] = bool(all(s["ok"] for s in vehicles.values()) and (swap is None or out["swap"]["ok"]))
    return out


def alarms_outside_and_during(texts: list[tuple[int, int, str]], swap: dict[str, Any]) -> tuple[list[str], list[str]]:
    """The failsafe and lane-switch STATUSTEXTs ((ns, severity, text), report.FAILSAFE_WORDS) outside the swap's
    vision cut (from the swap to _AFTER_SWAP_NS after the poses resumed) and during it."""
    lo, hi = swap["t_swap"], swap["t_resumed"] + _AFTER_SWAP_NS
    alarms = [(lo <= when <= hi, t) for when, _, t in texts if any(w in t.lower() for w in FAILSAFE_WORDS)]
    return [t for during, t in alarms if not during], [t for during, t in alarms if during]


def _outside(v: _Vehicle, swap: dict[str, Any]) -> dict[str, float | None]:
    """The EKF's horizontal error p99/max (mm) armed to disarmed, leaving out the swap and 5 s after the poses
    resumed (the EKF on its IMU alone meanwhile, then pulled back)."""
    a, b = v.record.get("armed_ns"), v.record.get("disarmed_ns") or time.monotonic_ns()
    if a is None:
        return {"p99": None, "max": None}
    lo, hi = swap["t_swap"], swap["t_resumed"] + _AFTER_SWAP_NS
    loc = np.array([r for r in v.gcs.local if a <= r[0] <= b and not lo <= r[0] <= hi], dtype=float).reshape(-1, 4)
    if not len(loc):
        return {"p99": None, "max": None}
    e = horizontal_error_mm(loc, v.truth)
    return {"p99": float(np.percentile(e, 99)), "max": float(e.max())}


def format_fleet(s: dict[str, Any]) -> str:
    from visionpos.app.sitl.report import format_flight

    lines = [f"visionpos sitl --vehicles {len(s['vehicles'])}: " + ("all flights completed" if all(
        v["completed"] for v in s["vehicles"].values()) else "NOT all completed") + f" ({s['wall_s']:.0f} s wall)"
        + (f": {s['error']}" if s.get("error") else "")]
    for name, v in s["vehicles"].items():
        lines.append(f"{name}:")
        text = format_flight(v)
        b = v.get("binding_at_take_off") or {}
        if b.get("identity_binding"):
            text += f"\n  binding at take-off: {b['identity_binding']}, {b.get('identity_reason')}"
        e = v.get("binding_at_end") or {}
        if e.get("identity_binding"):
            text += f"\n  binding at the end: {e['identity_binding']}, {e.get('identity_reason')}"
        o = v.get("ekf_horizontal_error_outside_swap_mm")
        if o is not None:  # judged outside the swap: the EKF is on its IMU alone during it
            text = text.replace("target (EKF horizontal p99 <= 20 mm", "target (EKF horizontal p99 outside the swap "
                                "<= 20 mm").replace("failsafe / lane switch messages:", "failsafe / lane switch "
                                                    "messages outside the swap (and 5 s after):")
            text += (f"\n  EKF horizontal error outside the swap (and 5 s after): p99 "
                     f"{'-' if o['p99'] is None else format(o['p99'], '.1f')} mm; failsafe / lane switch messages "
                     f"during it: {v.get('failsafe_during_swap') or 'none'}")
        lines += ["  " + x for x in text.splitlines()]
    sw = s.get("swap")
    if sw is not None:
        for k in ("autopilot0", "autopilot1"):
            a = sw[k]
            heard = "never" if a["detected_after_ms"] is None else f"{a['detected_after_ms']:.0f} ms"
            lines.append(f"  swap, {k}: the bridge heard it on the other link {heard} after the swap; "
                         f"{a['wrong_poses']} pose(s) of the other vehicle reached it, the last "
                         + ("-" if a["last_wrong_after_detection_ms"] is None
                            else f"{a['last_wrong_after_detection_ms']:.0f} ms") + " after that")
        lines.append(f"  poses flowed again {sw['resumed_after_s']:.2f} s after the links were put back; "
                     f"swap caught: {'yes' if sw['ok'] else 'NO'}")
    fb = s.get("fleet_binding")
    if fb:
        lines.append(f"  fleet binding: {fb.get('binds')} bindings made, {fb.get('drops')} dropped, "
                     f"{fb.get('disagreements')} disagreed with the motion; at the end {fb.get('bound')}")
    rt = s["real_time"]
    lines.append(f"  real time: {rt['frames_made']} camera frames made, {100 * rt['frames_late_fraction']:.1f}% more "
                 "than 50 ms late")
    lines.append(f"  target (each EKF horizontal p99 <= 20 mm, no failsafe, the swap caught): "
                 f"{'met' if s['ok'] else 'NOT met'}")
    return "\n".join(lines)
