"""`visionpos demo`: the whole chain on a simulated arena over loopback (visionpos.app.demo)."""

from __future__ import annotations

import argparse
import asyncio
import errno
import json
import sys

from visionpos.app.console import add_console_arguments, announce_console, console_settings, port_in_use
from visionpos.app.demo import demo_arena, run_demo
from visionpos.app.demo_summary import format_summary
from visionpos.errors import UsageError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default="thesis",
                   help="arena: thesis (default), arena8, fleet (10 identical quads), fleet20 or a YAML path "
                        "with a sim section")
    p.add_argument("--duration", type=float, default=10.0, help="seconds of streaming (real time; default 10)")
    p.add_argument("--seed", type=int, default=None, help="simulation seed (default: the scenario's sim.seed)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key (repeatable)")
    p.add_argument("--json", action="store_true",
                   help="print the summary as JSON on stdout (live status goes to stderr)")
    p.add_argument("--quiet", action="store_true", help="no live status")
    p.add_argument("--record", metavar="FILE",
                   help="also record the session (packets, outputs, truth) to an MCAP file for replay/tune")
    add_console_arguments(p)


def run(args: argparse.Namespace) -> int:
    if not 0.5 <= args.duration <= 3600:
        raise UsageError(f"--duration {args.duration}: give 0.5 to 3600 seconds")
    arena = demo_arena(args.scenario, args.duration, args.seed, args.set)
    status_out = None if args.quiet else (sys.stderr if args.json else sys.stdout)
    if status_out is not None:
        n_cams, n_bodies = len(arena.cameras), len(arena.bodies)
        status_out.write(f"visionpos demo: {n_cams} simulated station{'s' * (n_cams != 1)}, "
                         f"{n_bodies} bod{'y' if n_bodies == 1 else 'ies'}, {args.duration:g} s on 127.0.0.1 ...\n")
        status_out.flush()
    console = console_settings(arena, args)
    notes = sys.stderr if args.json else sys.stdout
    if console is not None and args.console_port is None and port_in_use(console):
        # a demo is for trying things: another program on the default port must not stop it
        print(f"visionpos demo: port {console.port} is in use; the console takes a free port", file=notes)
        console = console.with_address(port=0)
    try:
        summary = asyncio.run(run_demo(arena, args.duration, status_out, args.record, console=console,
                                       on_console=lambda view: announce_console("demo", view, notes)))
    except OSError as e:
        if e.errno not in (errno.EADDRINUSE, errno.EADDRNOTAVAIL):
            raise
        raise UsageError(f"console: {e.strerror or e}; pick another --console-port or pass --no-console") from None
    if args.record:
        summary["recording"] = args.record
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(format_summary(summary))
        if args.record:
            print(f"recorded to {args.record}; try: visionpos replay {args.record}")
    ok = all(b["tracked_fraction"] and b["tracked_fraction"] > 0 for b in summary["bodies"])
    if not ok:
        print("visionpos demo: a body was never tracked; see the log above", file=sys.stderr)
    return 0 if ok else 1
