"""`visionpos sitl` end to end: SITL started, set up for vision-only flight, the plan flown on the demo's
live arena, the summary.
"""

from __future__ import annotations

import asyncio
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, TextIO

from visionpos.app.sitl.clock import IntakeProbe
from visionpos.app.sitl.flight import FlightPlan, fly
from visionpos.app.sitl.gcs import Gcs
from visionpos.app.sitl.preflight import prepare_vehicle
from visionpos.app.sitl.process import SitlProcess, free_instance
from visionpos.app.sitl.report import flight_summary, say_to
from visionpos.app.sitl.settings import SitlError, SitlSettings, parse_sitl
from visionpos.app.sitl.truth import LiveArena, TruthTrack
from visionpos.config.arena import ArenaConfig, ConfigError
from visionpos.errors import UsageError

if TYPE_CHECKING:
    from bridge.config import VehicleConfig


def sitl_arena(scenario: str, overrides: list[str], max_duration_s: float) -> ArenaConfig:
    """The demo's arena for the flight (`vehicles.*` overrides apply to the vehicles the demo makes)."""
    from visionpos.app.demo import demo_arena

    arena = demo_arena(scenario, max_duration_s, None, overrides)
    if len(arena.bodies) < 1:
        raise UsageError(f"{arena.source}: the arena has no body to fly")
    return arena


def _vehicle_cfg(arena: ArenaConfig) -> VehicleConfig:
    """The arena's first vehicle, signed: SITL flies over a signed link."""
    from bridge.config import parse_vehicles

    vehicles = parse_vehicles(arena)
    if vehicles[0].signing_key is None:
        raise ConfigError(arena.source, "vehicles[0].signing", "SITL flies over a signed link: give "
                          "signing: {key_file: ...}")
    return vehicles[0]


def run_sitl(arena: ArenaConfig, binary: Path, plan: FlightPlan, out: TextIO | None) -> dict[str, Any]:
    """Start SITL, set it up for vision-only flight, fly the plan on the live arena; the summary dict.

    With plan.link_delay_ms, SITL's SERIAL1 talks to a DelayRelay (visionpos/app/linkdelay.py) that holds
    each datagram that long each way on its way to and from the bridge, and the summary's "link_delay"
    compares the back-channel's measured capture-to-autopilot delay with the true one (delay_record)."""
    from visionpos.app.linkdelay import DelayRelay

    if plan.link_delay_ms is None:
        return _run_sitl(arena, binary, plan, out, None)
    vision_port = _vehicle_cfg(_one_vehicle(arena)).endpoint.port
    with DelayRelay(("127.0.0.1", vision_port), plan.link_delay_ms, lifetime_s=plan.timeout_s + 180.0) as relay:
        return _run_sitl(arena, binary, plan, out, relay)


def _run_sitl(arena: ArenaConfig, binary: Path, plan: FlightPlan, out: TextIO | None,
              relay: Any) -> dict[str, Any]:
    """SITL started, set up (preflight.py), the plan flown on the demo's live arena, the summary."""
    cfg = parse_sitl(arena, binary)
    instance = cfg.instance if cfg.instance is not None else free_instance()
    arena = _one_vehicle(arena)
    veh = _vehicle_cfg(arena)
    key, vision_port = veh.signing_key, veh.endpoint.port
    say = say_to(out)
    truth = TruthTrack(cfg.home[:3])
    live = LiveArena(veh.body, truth)
    record: dict[str, Any] = {}
    t0 = time.monotonic()
    old_switch = sys.getswitchinterval()
    sys.setswitchinterval(0.001)  # the GCS reader stamps truth on arrival: let it run promptly
    serial1_port = vision_port if relay is None else relay.port
    with SitlProcess(cfg, instance, f"udpclient:127.0.0.1:{serial1_port}") as proc:
        gcs = Gcs(proc.gcs_port, truth, on_text=lambda text: say(f"  SITL: {text}"))
        probe: IntakeProbe | None = None
        try:
            say(f"SITL instance {proc.instance} in {proc.folder}: GCS on SERIAL0 tcp:127.0.0.1:{proc.gcs_port}, "
                f"SERIAL1 udpclient:127.0.0.1:{serial1_port} -> "
                + ("" if relay is None else f"a relay holding each direction {plan.link_delay_ms:g} ms -> ")
                + f"the bridge ({veh.endpoint}, signed)")
            prepare_vehicle(gcs, proc, cfg, veh, key, say, plan.link_delay_ms)
            if relay is not None:  # SITL's intake of the vision link's datagrams, for the true delay
                probe = IntakeProbe(relay, key, gcs.clock).__enter__()
            say(f"set-up done in {time.monotonic() - t0:.1f} s; cameras start")
            demo = _fly_live(arena, gcs, live, plan, cfg, veh.body, record, say, relay)
        finally:
            if probe is not None:
                probe.__exit__()
            gcs.close()
            sys.setswitchinterval(old_switch)
    return _summary(gcs, truth, live, demo, record, plan, time.monotonic() - t0)


def _fly_live(arena: ArenaConfig, gcs: Gcs, live: LiveArena, plan: FlightPlan, cfg: SitlSettings, body: str,
              record: dict[str, Any], say: Callable[[str], None], relay: Any) -> dict[str, Any]:
    """The demo (simulated stations, the server, the bridge and its outputs) on the live arena, with the flight
    as its `during`; the demo's summary. A failed flight is recorded (record["error"]), not raised."""
    from visionpos.app.demo import run_demo

    async def during(ctx: Any) -> None:
        try:
            await fly(ctx, gcs, live, plan, cfg, body, record, say, relay)
        except SitlError as e:  # the flight failed: still summarise what happened (and why)
            record["error"] = str(e)
            say(f"flight failed: {e}")
        finally:
            live.stop()

    return asyncio.run(run_demo(arena, plan.timeout_s + 60.0, None, during=during, live=live))


def _summary(gcs: Gcs, truth: TruthTrack, live: LiveArena, demo: dict[str, Any], record: dict[str, Any],
             plan: FlightPlan, wall_s: float) -> dict[str, Any]:
    """flight_summary plus the link delay (when measured) and how well this host kept real time."""
    summary = flight_summary(gcs, truth, demo, record, plan, wall_s)
    if "link_delay" in record:
        summary["link_delay"] = record["link_delay"]
    made = max(live.frames_made, 1)
    summary["real_time"] = {"frames_made": live.frames_made, "frames_late_fraction": live.frames_late / made,
                            "frames_not_fused_fraction": (summary["vision"]["frames_not_fused"] or 0) / made}
    return summary


def _one_vehicle(arena: ArenaConfig) -> ArenaConfig:
    """The arena with its first vehicle only (SITL is one copter, system 1)."""
    from visionpos.config.arena import parse_arena

    data = arena.to_dict()
    vehicles = data.get("vehicles") or []
    if not vehicles:
        raise ConfigError(arena.source, "vehicles", "SITL flies the first vehicle: add one (docs/autopilot-setup.md)")
    if int(vehicles[0].get("sysid", 1)) != 1:
        raise UsageError(f"vehicles[0].sysid {vehicles[0].get('sysid')}: SITL is system 1; fly a body with sysid 1")
    data["vehicles"] = vehicles[:1]
    return parse_arena(data, arena.source)
