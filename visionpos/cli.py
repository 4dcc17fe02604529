"""`visionpos` command line: one subcommand per module, imported only when used.

Each command module provides `add_arguments(parser)` and `run(args) -> int`.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("visionpos.app.demo", "run the whole chain on a simulated arena over loopback"),
    "serve": ("visionpos.server.service", "start the fusion service for live stations"),
    "record": ("visionpos.recording", "record live station traffic to an MCAP log (no outputs)"),
    "sim": ("visionpos.sim.cli", "simulate a scenario and write a recording"),
    "replay": ("visionpos.analysis.replay", "re-run the pipeline on a recording"),
    "tune": ("visionpos.analysis.tune", "sweep settings over a recording and rank them"),
    "calibrate": ("visionpos.calibration.cli", "intrinsics, wand extrinsics, ground plane"),
    "bench": ("visionpos.benchmarks.cli", "run the benchmark suite"),
}


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="visionpos", description="Optical motion capture for indoor drones.")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == selected:
            importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    selected = next((a for a in argv if a in COMMANDS), None)
    args = build_parser(selected).parse_args(argv)
    logging.basicConfig(
        level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)],
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if args.command is None:
        build_parser().print_help()
        return 2
    module = importlib.import_module(COMMANDS[args.command][0])
    try:
        return int(module.run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except ValueError as e:  # ConfigError and friends: a clear message, no traceback
        if args.verbose >= 2:
            raise
        print(f"visionpos {args.command}: error: {e}", file=sys.stderr)
        return 2
