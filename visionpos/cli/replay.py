"""`visionpos replay`: re-run the pipeline on a recording (visionpos.analysis.replay)."""

from __future__ import annotations

import argparse
import json
import sys

from visionpos.analysis import metrics as M
from visionpos.analysis.replay import METRIC_COLUMNS, metrics_rows, replay_log, summary, write_outputs
from visionpos.app.console import add_console_arguments, announce_console


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
    p.add_argument("--out", default="replay_out", metavar="DIR", help="output folder (default ./replay_out)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots (faster; no matplotlib needed)")
    p.add_argument("--view", action="store_true",
                   help="serve the web console for the recording, with play, pause, seek and speed (until Ctrl-C); "
                        "writes no outputs")
    p.add_argument("--duration", type=float, default=None, help="--view: stop after this many seconds")
    add_console_arguments(p)


def run(args: argparse.Namespace) -> int:
    if args.view:
        return view(args)
    res = replay_log(args.log, args.config, args.set, speed=args.speed, rate_hz=args.rate)
    written, note = write_outputs(res, args.out, plots=not args.no_plots)
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


def view(args: argparse.Namespace) -> int:
    """`replay LOG --view`: the console for the recording until Ctrl-C."""
    import asyncio

    from console.settings import ConsoleSettings
    from visionpos.app.console import replay_view
    from visionpos.errors import UsageError

    if args.no_console:
        raise UsageError("--view serves the console: leave out --no-console")
    # the console's own section comes from --config or the recording's arena, with --set applied there
    from visionpos.analysis.replay import load_settings
    from visionpos.recording import RecordingReader

    try:
        arena = load_settings(RecordingReader(args.log).config, args.config, args.set)
    except FileNotFoundError:
        raise UsageError(f"{args.log}: no such recording") from None
    settings = ConsoleSettings.from_arena(arena).with_address(args.console_bind, args.console_port)
    try:
        asyncio.run(replay_view(args.log, args.config, args.set, args.rate, settings,
                                lambda v: announce_console("replay", v), args.duration))
    except OSError as e:
        raise UsageError(f"{e.strerror or e}; pick another --console-port") from None
    return 0
