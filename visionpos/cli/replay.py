"""`visionpos replay`: re-run the pipeline on a recording (visionpos.analysis.replay)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from visionpos.analysis import metrics as M
from visionpos.analysis.replay import METRIC_COLUMNS, metrics_rows, replay_log, summary, write_outputs
from visionpos.app.console import add_calibrate_out_argument, add_console_arguments, announce_console
from visionpos.errors import UsageError


def parse_speed(s: str) -> float | None:
    if s == "max":
        return None
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--speed takes a number (1 = real time) or 'max', got {s!r}") from None
    if v <= 0:
        raise argparse.ArgumentTypeError(f"--speed must be > 0, got {s}")
    return v


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", help="recording (.mcap) from `visionpos sim --out` or `visionpos record`")
    p.add_argument("--config", help="arena YAML replacing the one stored in the recording")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a setting, e.g. fusion.time_alignment=naive (repeatable)")
    p.add_argument("--speed", type=parse_speed, default=None, metavar="1|max",
                   help="1 = real time, N = N x real time, max = as fast as possible (default)")
    p.add_argument("--rate", type=float, default=None, metavar="HZ",
                   help="output tick rate (default: server.output_rate_hz or 100)")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="output folder (default ./replay_out); with --foxglove the copy (default LOG.foxglove.mcap)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots (faster; no matplotlib needed)")
    p.add_argument("--foxglove", action="store_true",
                   help="instead of replaying, write a copy of LOG (to --out) with the Foxglove channels (3-D scene, "
                        "blobs, health) built from what it recorded, for Foxglove or Lichtblick (docs/interop.md)")
    p.add_argument("--force", action="store_true", help="with --foxglove: overwrite the copy if it exists")
    p.add_argument("--view", action="store_true",
                   help="serve the web console for the recording, with play, pause, seek and speed (until Ctrl-C); "
                        "writes no outputs")
    p.add_argument("--duration", type=float, default=None, help="--view: stop after this many seconds")
    add_console_arguments(p)
    add_calibrate_out_argument(p)


def run(args: argparse.Namespace) -> int:
    if args.view:
        return view(args)
    if args.foxglove:
        return foxglove(args)
    if args.force:
        raise UsageError("--force is for --foxglove (a replay's --out folder is always written into)")
    res = replay_log(args.log, args.config, args.set, speed=args.speed, rate_hz=args.rate)
    written, note = write_outputs(res, args.out or "replay_out", plots=not args.no_plots)
    summ = summary(res)
    if args.json:
        print(json.dumps(summ, indent=2, sort_keys=True))
    else:
        print(
            f"replayed {summ['duration_s']:.2f} s of recording ({res.n_packets} packets, {res.n_frames} frames, "
            f"{res.n_bad} bad) in {res.wall_s:.2f} s = {res.speed_x:.1f}x real time, {len(res.ticks_ns)} ticks"
        )
        cols = METRIC_COLUMNS if res.truth else [c for c in METRIC_COLUMNS if "rmse" not in c[0] and "max" not in c[0]]
        print(M.format_table(metrics_rows(res), cols))
        if not res.truth:
            print("(the recording carries no ground truth: no error metrics; jitter and latency only)")
    if note:
        print(f"note: {note}", file=sys.stderr)
    print("wrote " + ", ".join(str(w) for w in written), file=sys.stderr)
    return 0


def foxglove(args: argparse.Namespace) -> int:
    from visionpos.recording import TOPIC_STATES, foxglove_copy

    if args.config or args.set or args.rate is not None or args.speed is not None or args.no_plots:
        raise UsageError("--foxglove copies what LOG recorded; it takes no --config, --set, --rate, --speed or "
                         "--no-plots")
    log = Path(args.log)
    out = Path(args.out) if args.out is not None else log.with_name(log.name.removesuffix(".mcap") + ".foxglove.mcap")
    if out.exists() and not args.force:
        raise UsageError(f"{out} exists; pass --force to overwrite it or --out to write elsewhere")
    rep = foxglove_copy(log, out)
    if args.json:
        print(json.dumps(rep, indent=2, sort_keys=True))
    else:
        print(f"wrote {out}: {rep['messages']} messages of {log} and {rep['foxglove_messages']} "
              "Foxglove messages (open it in Foxglove or Lichtblick)")
    if rep["damage"]:
        print(f"note: {args.log} is damaged ({rep['damage']}); copied everything before it", file=sys.stderr)
    if not rep["messages_by_topic"].get(TOPIC_STATES):
        print(f"note: {args.log} recorded no poses (a `visionpos record` file?): the copy shows cameras and blobs; "
              "the bodies appear in recordings of `visionpos serve --record` or `visionpos demo --record`",
              file=sys.stderr)


def view(args: argparse.Namespace) -> int:
    """`replay LOG --view`: the console for the recording until Ctrl-C."""
    import asyncio

    from console.settings import parse_console
    from visionpos.app.console import replay_view

    if args.no_console:
        raise UsageError("--view serves the console: leave out --no-console")
    # the console's own section comes from --config or the recording's arena, with --set applied there
    from visionpos.analysis.replay import load_settings
    from visionpos.recording import RecordingReader

    try:
        arena = load_settings(RecordingReader(args.log).config, args.config, args.set)
    except FileNotFoundError:
        raise UsageError(f"{args.log}: no such recording") from None
    settings = parse_console(arena).with_address(args.console_bind, args.console_port)
    try:
        asyncio.run(replay_view(args.log, args.config, args.set, args.rate, settings,
                                lambda v: announce_console("replay", v), args.duration,
                                calibrate_out=args.calibrate_out))
    except OSError as e:
        raise UsageError(f"{e.strerror or e}; pick another --console-port") from None
    return 0
