"""`visionpos serve`: the fusion service for live stations (visionpos.app.serve)."""

from __future__ import annotations

import argparse
import asyncio
import logging

from visionpos.app.serve import serve
from visionpos.errors import UsageError
from visionpos.server.service import load_config_with_overrides, loopback_note, status_log
from visionpos.server.settings import ServerSettings


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, help="arena YAML (path or built-in name: thesis, arena8)")
    p.add_argument("--record", metavar="FILE", help="record every station packet, the config and outputs (MCAP)")
    p.add_argument("--port", type=int, default=None, help="UDP port for stations (default server.port, 5600)")
    p.add_argument("--host", default=None, metavar="ADDRESS",
                   help="address to listen on (default: server.bind from the config, 127.0.0.1)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: Ctrl-C)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key, e.g. server.output_rate_hz=50 (repeatable)")


def run(args: argparse.Namespace) -> int:
    if status_log.level == logging.NOTSET:
        status_log.setLevel(logging.INFO)
    arena = load_config_with_overrides(args.config, args.set)
    settings = ServerSettings.from_arena(arena)
    if args.port is not None:
        settings = settings.with_port(args.port)
    if args.host is not None:
        settings = settings.with_bind(args.host)

    listening_on: list[int] = []

    def listening(server) -> None:
        listening_on.append(server.port)
        print(f"visionpos serve: listening on udp {settings.bind}:{server.port}"
              + (f", recording to {args.record}" if args.record else "") + "; Ctrl-C to stop", flush=True)
        note = loopback_note(settings.bind)
        if note is not None:
            print(f"visionpos serve: {note}", flush=True)

    try:
        h = asyncio.run(serve(arena, settings, None, args.record, args.duration, listening))
    except OSError as e:
        if listening_on:
            raise
        # port in use, bad address: the user's environment, not a bug
        raise UsageError(e.strerror or str(e)) from None
    print(f"visionpos serve: stopped after {h['packets']} packets ({h['frames_accepted']} frames accepted, "
          f"{h['frames_shed']} shed as backlog, {h['malformed']} malformed, {h['auth_failed']} failed auth, "
          f"{h['unknown']} unknown), {h['ticks']} output ticks", flush=True)
    return 0
