"""`visionpos record`: record live station traffic to an MCAP log, no fusion and no outputs."""

from __future__ import annotations

import argparse
import sys

from visionpos.app.console import (
    add_calibrate_out_argument,
    add_console_arguments,
    announce_console,
    console_settings,
)
from visionpos.cli.serve import announce_listening, live_settings, run_listening
from visionpos.errors import UsageError
from visionpos.server.service import record_traffic


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", metavar="FILE", help="MCAP file to write")
    # the form before --out, `visionpos record FILE --config ...`, still works (with a warning)
    p.add_argument("output", nargs="?", default=None, help=argparse.SUPPRESS)
    p.add_argument("--config", required=True, help="arena YAML (path or built-in name: thesis, arena8)")
    p.add_argument("--port", type=int, default=None, help="UDP port (default: server.port from the config, 5600)")
    p.add_argument("--host", default=None, metavar="ADDRESS",
                   help="address to listen on (default: server.bind from the config, 127.0.0.1)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: until Ctrl-C)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    add_console_arguments(p)
    add_calibrate_out_argument(p)


def output_path(args: argparse.Namespace) -> str:
    """--out, or the deprecated positional FILE."""
    if args.out is not None and args.output is not None:
        raise UsageError(f"give the output once: --out {args.out} (not also {args.output})")
    if args.out is None and args.output is None:
        raise UsageError("say where to write the recording: --out FILE.mcap")
    if args.output is not None:
        print(f"visionpos record: warning: `visionpos record {args.output}` is deprecated; "
              f"use `visionpos record --out {args.output}`", file=sys.stderr)
        return args.output
    return args.out


def run(args: argparse.Namespace) -> int:
    out = output_path(args)
    arena, settings = live_settings(args)
    listening_on: list[int] = []

    def listening(port: int) -> None:
        listening_on.append(port)
        announce_listening("record", settings, port, f", recording to {out}")

    console = console_settings(arena, args)
    if console is None and args.calibrate_out is not None:
        raise UsageError("--calibrate-out says where the console's Solve writes; it needs the console (leave out "
                         "--no-console and keep console.enabled)")
    source = None
    on_ingest = None
    if console is not None:
        from console.calibration import CalibrationAssistant, default_out
        from visionpos.app.console import RecordSource, open_console

        source = RecordSource(arena, CalibrationAssistant(arena, args.calibrate_out or default_out(out)))

        async def on_ingest(ingest):
            source.ingest = ingest
            view = await open_console(console, source)
            announce_console("record", view)
            return view.stop

    n = run_listening(record_traffic(arena, settings, out, None, args.duration, listening, source, on_ingest),
                      listening_on)
    print(f"visionpos record: {n} packets written to {out}", flush=True)
    return 0
