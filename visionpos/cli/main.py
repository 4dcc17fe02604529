"""`visionpos` command line: the parser, logging and error handling shared by every command.

Each command is a module of this package with `add_arguments(parser)` and `run(args) -> int`,
a thin layer over library functions; a command's module is imported only when it runs, so
`visionpos --help` and each command start fast.

Errors: a `VisionposError` (wrong input or environment) prints as one line and exits 2; any
other exception is a bug and shows its traceback; Ctrl-C exits 130.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from visionpos.errors import VisionposError

COMMANDS: dict[str, str] = {
    "demo": "run the whole chain on a simulated arena over loopback",
    "sitl": "fly ArduPilot SITL closed loop on simulated cameras (the autopilot in the loop)",
    "serve": "start the fusion service for live stations",
    "record": "record live station traffic to an MCAP log (no outputs)",
    "keygen": "make the shared key that server and stations sign packets with",
    "sim": "simulate a scenario and write a recording",
    "replay": "re-run the pipeline on a recording",
    "recover": "rewrite a recording cut short (writer killed, disk full) as a clean MCAP file",
    "tune": "sweep settings over a recording and rank them",
    "calibrate": "intrinsics, wand extrinsics, ground plane",
    "plan": "camera coverage and accuracy bounds over a flight volume; where to add a camera",
    "bench": "run the benchmark suite",
}

# loggers that report progress a user waits for (first-run kernel compilation, live status):
# shown by default, while every other logger stays at WARNING unless -v
PROGRESS_LOGGERS = ("visionpos.progress",)
# commands that start interpreted on a cold kernel cache (fusion/warmup.py): the demo only. serve and sitl
# send poses to autopilots, and an interpreted fusion sheds most frames (a clean install's first demo: 31 poses/s,
# 60 ms latency): they compile first, so no autopilot flies on it
INTERPRET_WHILE_COLD_COMMANDS = ("demo",)


def _version() -> str:
    try:
        from importlib.metadata import PackageNotFoundError, version

        return version("visionpos")
    except PackageNotFoundError:  # running from a source tree that was never installed
        from visionpos import __version__

        return __version__


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="visionpos", description="Optical motion capture for indoor drones.")
    parser.add_argument("--version", action="version", version=f"visionpos {_version()}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_text in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == selected:
            importlib.import_module(f"visionpos.cli.{name}").add_arguments(p)
    return parser


def configure_logging(verbose: int) -> None:
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    for name in PROGRESS_LOGGERS:
        logger = logging.getLogger(name)
        if logger.level == logging.NOTSET:
            logger.setLevel(min(level, logging.INFO))


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    selected = next((a for a in argv if a in COMMANDS), None)
    args = build_parser(selected).parse_args(argv)
    configure_logging(args.verbose)
    if args.command is None:
        build_parser().print_help()
        return 2
    importlib.import_module("visionpos.app.sections")  # every section's keys known to --set
    if args.command in INTERPRET_WHILE_COLD_COMMANDS:  # runs interpreted while its kernels first compile
        importlib.import_module("visionpos.fusion.warmup").interpret_while_cold()
    command = importlib.import_module(f"visionpos.cli.{args.command}")
    try:
        return int(command.run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except VisionposError as e:  # the user's input or environment; anything else is a bug: traceback
        if args.verbose >= 2:
            raise
        command_name = " ".join(filter(None, [args.command, getattr(args, "step", None)]))  # calibrate STEP
        print(f"visionpos {command_name}: error: {e}", file=sys.stderr)
        return 2
