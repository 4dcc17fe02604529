"""`visionpos recover`: rewrite a recording cut short (writer killed, disk full) as a clean MCAP file."""

from __future__ import annotations

import argparse
from pathlib import Path

from visionpos.errors import UsageError
from visionpos.recording import recover


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", metavar="IN", help="the recording to recover (.mcap)")
    p.add_argument("--out", metavar="OUT", default=None,
                   help="where to write the clean recording (default: IN with .recovered.mcap)")
    p.add_argument("--force", action="store_true", help="overwrite OUT if it exists")


def default_output(path: str) -> Path:
    p = Path(path)
    return p.with_name(p.name.removesuffix(".mcap") + ".recovered.mcap")


def run(args: argparse.Namespace) -> int:
    out = Path(args.out) if args.out is not None else default_output(args.input)
    if out.exists() and not args.force:
        raise UsageError(f"{out} exists; pass --force to overwrite it or --out to write elsewhere")
    report = recover(args.input, out)
    topics = ", ".join(f"{t} {n}" for t, n in sorted(report["messages_by_topic"].items())) or "no messages"
    if report["was_complete"]:
        state = "was complete"
    else:
        state = f"ended early ({report['damage']})" if report["damage"] else "ended early"
    print(f"visionpos recover: {args.input} {state}; wrote {out} with {report['messages']} messages ({topics})")
    return 0
