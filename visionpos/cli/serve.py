"""`visionpos serve`: the fusion service for live stations (visionpos.app.serve)."""

from __future__ import annotations

import argparse
import asyncio
import logging
from typing import Any, Coroutine, TypeVar

from visionpos.app.console import add_console_arguments, announce_console, console_settings
from visionpos.app.serve import serve
from visionpos.config.arena import ArenaConfig
from visionpos.errors import UsageError
from visionpos.server.service import load_config_with_overrides, loopback_note, status_log
from visionpos.server.settings import ServerSettings, parse_server

T = TypeVar("T")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, help="arena YAML (path or built-in name: thesis, arena8)")
    p.add_argument("--record", metavar="FILE", help="record every station packet, the config and outputs (MCAP)")
    p.add_argument("--port", type=int, default=None, help="UDP port for stations (default server.port, 5600)")
    p.add_argument("--host", default=None, metavar="ADDRESS",
                   help="address to listen on (default: server.bind from the config, 127.0.0.1)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: Ctrl-C)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key, e.g. server.output_rate_hz=50 (repeatable)")
    add_console_arguments(p)


def live_settings(args: argparse.Namespace) -> tuple[ArenaConfig, ServerSettings]:
    """The arena with --set applied, and its server settings with --port and --host applied (serve, record)."""
    if status_log.level == logging.NOTSET:
        status_log.setLevel(logging.INFO)
    arena = load_config_with_overrides(args.config, args.set)
    settings = parse_server(arena)
    if args.port is not None:
        settings = settings.with_port(args.port)
    if args.host is not None:
        settings = settings.with_bind(args.host)
    return arena, settings


def announce_listening(command: str, settings: ServerSettings, port: int, doing: str) -> None:
    """The start-up line of a live command, and the loopback hint when it listens on loopback only."""
    print(f"visionpos {command}: listening on udp {settings.bind}:{port}{doing}; Ctrl-C to stop", flush=True)
    note = loopback_note(settings.bind)
    if note is not None:
        print(f"visionpos {command}: {note}", flush=True)


def run_listening(main: Coroutine[Any, Any, T], listening_on: list[int]) -> T:
    """asyncio.run(main); an OSError before the socket listened (port in use, bad address) is the user's
    environment, not a bug: a one-line UsageError."""
    try:
        return asyncio.run(main)
    except OSError as e:
        if listening_on:
            raise
        raise UsageError(e.strerror or str(e)) from None


def run(args: argparse.Namespace) -> int:
    arena, settings = live_settings(args)
    listening_on: list[int] = []

    def listening(server) -> None:
        listening_on.append(server.port)
        announce_listening("serve", settings, server.port, f", recording to {args.record}" if args.record else "")

    console = console_settings(arena, args)
    h = run_listening(serve(arena, settings, None, args.record, args.duration, listening, console,
                            lambda view: announce_console("serve", view)), listening_on)
    print(f"visionpos serve: stopped after {h['packets']} packets ({h['frames_accepted']} frames accepted, "
          f"{h['frames_shed']} shed as backlog, {h['malformed']} malformed, {h['auth_failed']} failed auth, "
          f"{h['unknown']} unknown), {h['ticks']} output ticks", flush=True)
    return 0
