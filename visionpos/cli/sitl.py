"""`visionpos sitl`: fly ArduPilot SITL on visionpos alone, closed loop (visionpos.app.sitl)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from visionpos.app.sitl import FlightPlan, find_sitl_binary, format_flight, run_sitl, sitl_arena
from visionpos.app.sitl.flight import CIRCLE_PERIOD_S, CIRCLE_RADIUS_M
from visionpos.app.sitl.px4 import PX4_MESSAGE, check_build_kind, find_px4_dir
from visionpos.app.sitl.px4_run import run_px4
from visionpos.app.sitl.settings import SitlError
from visionpos.errors import UsageError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--autopilot", choices=("ardupilot", "px4"), default="ardupilot",
                   help="ArduPilot's SITL (default) or PX4's SITL with SIH")
    p.add_argument("--sitl", metavar="PATH", help="ArduPilot's arducopter SITL binary (default: the arena's "
                   "sitl.binary, $VISIONPOS_SITL, or ../shared/sitl/arducopter beside the checkout); with --autopilot "
                   "px4, PX4's build folder holding bin/px4 and etc/ (default: sitl.px4_dir, $VISIONPOS_PX4_SITL)")
    p.add_argument("--defaults", metavar="PATH", help="ArduPilot's SITL defaults file, copter.parm (default: the "
                   "arena's sitl.defaults, else copter.parm beside the binary, in its ArduPilot tree, ../shared/sitl)")
    p.add_argument("--scenario", default=None,
                   help="arena: thesis (default), pair (default with --vehicles 2), arena8 or a YAML path")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    p.add_argument("--message", choices=("vision_position_estimate", "odometry"), default=None,
                   help="the pose message to the autopilot (default: odometry with --autopilot px4, which EKF2 "
                        "fuses with its velocity; else the arena's vehicles[0].message, vision_position_estimate); "
                        "the same as --set vehicles.0.message=...")
    p.add_argument("--altitude", type=float, default=1.0, help="take-off height (m; default 1)")
    p.add_argument("--side", type=float, default=1.0, help="side of the square flown (m; default 1)")
    p.add_argument("--no-square", action="store_true", help="take off, hold and land only")
    p.add_argument("--hold", type=float, default=4.0, help="hover before the square (s; default 4)")
    p.add_argument("--cut", type=float, default=0.0, metavar="S",
                   help="hide the vehicle from every camera for S seconds mid-hover (e.g. 1)")
    p.add_argument("--link-delay-ms", type=float, default=None, metavar="D",
                   help="put a relay in the vision link (ArduPilot: SITL's SERIAL1 <-> the bridge; PX4: the bridge "
                        "-> its Onboard port) holding each direction D ms; with ArduPilot, compare the back-channel's "
                        "measured capture-to-autopilot delay with the true one")
    p.add_argument("--yaw-swing", type=float, default=None, metavar="RAD_S",
                   help="swing the yaw rate +-RAD_S (2 s period) during the hold: the rotation the delay measurement "
                        "correlates (default 1 with --link-delay-ms, else 0)")
    p.add_argument("--circle", type=float, default=0.0, metavar="S",
                   help=f"after the square, fly S seconds round a {CIRCLE_RADIUS_M:g} m circle ({CIRCLE_PERIOD_S:g} s "
                        "a turn) and fit the EKF's lead on it alone: the precise check of the delay setting (e.g. 30)")
    p.add_argument("--vehicles", type=int, default=1, metavar="N",
                   help="fly the arena's first N vehicles together, one ArduPilot SITL each, from a row on the floor: "
                        "take-off, a hover, a crossing and back, land (bodies of distinct layouts: the pair scenario)")
    p.add_argument("--same-layout", action="store_true",
                   help="with --vehicles: every flown body gets the first one's markers (identical drones): each is "
                        "bound on its parking pad before take-off and checked by its motion")
    p.add_argument("--swap-pads", action="store_true",
                   help="with --same-layout: the first two vehicles parked on each other's pads (the operator's "
                        "mistake): the pads bind them wrongly, their first motion must stop and re-bind them")
    p.add_argument("--swap-at", type=float, default=None, metavar="S",
                   help="with --vehicles: S s into the hover, exchange the first two vehicles' links (two radios "
                        "swapped) for --swap-for s, then put them back; the bridge must stop both at once")
    p.add_argument("--swap-for", type=float, default=2.0, metavar="S",
                   help="how long the links stay swapped (default 2)")
    p.add_argument("--timeout", type=float, default=240.0, help="give up after this many seconds (default 240)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def run(args: argparse.Namespace) -> int:
    if not 0.3 <= args.altitude <= 3.0:
        raise UsageError(f"--altitude {args.altitude}: give 0.3 to 3 m (the arena's cameras look at 0-2 m)")
    if not 0.1 <= args.side <= 2.0:
        raise UsageError(f"--side {args.side}: give 0.1 to 2 m")
    if not 0 <= args.cut <= 5:
        raise UsageError(f"--cut {args.cut}: give 0 to 5 s")
    if args.link_delay_ms is not None and not 0 <= args.link_delay_ms <= 200:
        raise UsageError(f"--link-delay-ms {args.link_delay_ms}: give 0 to 200 ms")
    swing = args.yaw_swing if args.yaw_swing is not None else (1.0 if args.link_delay_ms is not None else 0.0)
    if not 0 <= swing <= 3:
        raise UsageError(f"--yaw-swing {swing}: give 0 to 3 rad/s")
    if not 0 <= args.circle <= 120:
        raise UsageError(f"--circle {args.circle}: give 0 to 120 s")
    if args.circle > 0 and args.vehicles != 1:
        raise UsageError("--circle: one vehicle only (the fleet flight has its own crossing)")
    plan = FlightPlan(args.altitude, args.side, args.hold, not args.no_square, args.cut, args.timeout,
                      args.link_delay_ms, swing, args.circle)
    sets = list(args.set) + ([f"vehicles.0.message={args.message}"] if args.message else [])
    if args.autopilot == "px4" and not any(s.split("=", 1)[0].strip() == "vehicles.0.message" for s in sets):
        sets.append(f"vehicles.0.message={PX4_MESSAGE}")
    if args.defaults:  # the flag is the arena key, relative to here
        sets.append(f"sitl.defaults={Path(args.defaults).resolve()}")
    scenario = args.scenario or ("pair" if args.vehicles > 1 else "thesis")
    arena = sitl_arena(scenario, sets, args.timeout + 60.0)
    out = sys.stderr if args.json else sys.stdout
    if args.sitl:  # the wrong build for --autopilot: one line
        check_build_kind(Path(args.sitl), args.autopilot)
    if args.vehicles != 1 and args.autopilot == "px4":
        raise UsageError("--vehicles: ArduPilot SITL only (PX4 flies one vehicle here)")
    if args.same_layout and args.vehicles < 2:
        raise UsageError("--same-layout gives several vehicles one layout: give --vehicles 2 or more")
    if args.swap_at is not None and args.vehicles < 2:
        raise UsageError("--swap-at swaps two vehicles' links: give --vehicles 2 or more")
    if args.autopilot == "px4":
        build = find_px4_dir(args.sitl, arena)
        out.write(f"visionpos sitl: PX4 {build} with {len(arena.cameras)} simulated cameras on 127.0.0.1\n")
        try:
            summary = run_px4(arena, build, plan, out)
        except SitlError as e:  # PX4 refused the set-up (a parameter, its HEARTBEAT): which and why, status 1
            print(f"visionpos sitl: {e}", file=sys.stderr)
            return 1
    elif args.vehicles > 1:
        from visionpos.app.sitl.fleet import Swap, format_fleet, run_fleet

        if args.link_delay_ms is not None or args.cut:
            raise UsageError("--vehicles: --link-delay-ms and --cut fly one vehicle; leave them out")
        swap = None
        if args.swap_at is not None:
            if not (0 <= args.swap_at and 0.5 <= args.swap_for <= 5 and args.swap_at + args.swap_for <= args.hold):
                raise UsageError(f"--swap-at {args.swap_at} --swap-for {args.swap_for}: the swap (0.5 to 5 s) must "
                                 f"end within the hover (--hold {args.hold:g})")
            swap = Swap(args.swap_at, args.swap_for)
        binary = find_sitl_binary(args.sitl, arena)
        out.write(f"visionpos sitl: {args.vehicles} x {binary} with {len(arena.cameras)} simulated cameras on "
                  "127.0.0.1\n")
        summary = run_fleet(arena, binary, plan, args.vehicles, swap, out, args.same_layout, args.swap_pads)
        print(json.dumps(summary, indent=2) if args.json else format_fleet(summary))
        return 0 if summary["ok"] else 1
    else:
        binary = find_sitl_binary(args.sitl, arena)
        out.write(f"visionpos sitl: {binary} with {len(arena.cameras)} simulated cameras on 127.0.0.1\n")
        summary = run_sitl(arena, binary, plan, out)
    print(json.dumps(summary, indent=2) if args.json else format_flight(summary))
    return 0 if summary["ok"] else 1
