"""The operator console composed with `serve`, `demo`, `record` and `replay --view` (console/, docs/console.md).

console_settings() applies the command line to the arena's `console:` section; open_console()
starts the console for a source on the running loop. For `record`, which fuses nothing,
RecordSource stands in for the server: the cameras' newest blobs and their health, no bodies.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from console.server import ConsoleServer
from console.settings import ConsoleSettings
from visionpos.config.arena import ArenaConfig
from visionpos.messages import BlobFrame


def add_console_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--console-port", type=int, default=None, metavar="PORT",
                   help="TCP port of the web console (default console.port, 8080; 0 = any free port)")
    p.add_argument("--console-bind", default=None, metavar="ADDRESS",
                   help="address of the web console (default console.bind, 127.0.0.1; another needs the token)")
    p.add_argument("--no-console", action="store_true", help="no web console")


def console_settings(arena: ArenaConfig, args: argparse.Namespace) -> ConsoleSettings | None:
    """The arena's console settings with --console-bind/--console-port; None when turned off."""
    s = ConsoleSettings.from_arena(arena)
    if getattr(args, "no_console", False) or not s.enabled:
        return None
    return s.with_address(getattr(args, "console_bind", None), getattr(args, "console_port", None))


def announce_console(command: str, console: ConsoleServer) -> None:
    s = console.settings
    print(f"visionpos {command}: console at {console.url}", flush=True)
    if s.token_generated:
        print(f"visionpos {command}: the console listens on {s.bind}, so it needs this token (set console.token "
              f"to keep one): {s.token}", flush=True)


async def open_console(settings: ConsoleSettings, source: Any, **kw: Any) -> ConsoleServer:
    """A started ConsoleServer for source (an OSError, such as the port in use, propagates)."""
    console = ConsoleServer(settings, source, **kw)
    await console.start()
    return console


@dataclass
class _Seen:
    """One camera's newest frame as the console's view reads a pipeline's observation."""

    capture_ns: int
    xn: np.ndarray
    label: np.ndarray


class RecordSource:
    """`visionpos record`'s stand-in for the fusion server: its Ingest's pipeline (push, remove_camera)
    keeps each camera's newest blobs, undistorted for the rays; no body is tracked."""

    def __init__(self, arena: ArenaConfig):
        self.arena = arena
        self.pipeline = self  # what Ingest pushes frames into, and what the console reads
        self.ingest: Any = None  # set once record_traffic made it
        self.obs: dict[int, _Seen] = {}
        self.last_px: dict[int, np.ndarray] = {}
        self.tracks: list = []
        self.untracked_why: dict[int, str] = {i: "not fused: `visionpos record` only records"
                                              for i in range(len(arena.bodies))}
        self.loose_points = None
        self.last_states: list = []
        self._cams = {c.id: c for c in arena.cameras}

    def push(self, frame: BlobFrame) -> None:
        cam = self._cams.get(frame.camera_id)
        blobs = np.asarray(frame.blobs, dtype=float)
        if cam is None or blobs.ndim != 2 or blobs.shape[1] < 2:
            return
        px = blobs[:, :2]
        self.last_px[cam.id] = px
        self.obs[cam.id] = _Seen(int(frame.capture_ns), cam.model.undistort(px), np.full(len(px), -1))

    def remove_camera(self, camera_id: int) -> None:
        self.obs.pop(camera_id, None)
        self.last_px.pop(camera_id, None)

    def clock(self) -> int:
        return time.monotonic_ns()

    def health(self) -> dict[str, Any]:
        return self.ingest.health() if self.ingest is not None else {}


async def replay_view(log: str, config: str | None, overrides: list[str], rate_hz: float | None,
                      settings: ConsoleSettings, on_console: Any = None, duration_s: float | None = None,
                      paused: bool = False) -> Any:
    """Serve the console for a recording (`visionpos replay LOG --view`) until a signal (or duration_s); returns
    the ReplaySession."""
    import asyncio
    from pathlib import Path

    from console.replay import ReplaySession
    from visionpos.analysis.replay import load_settings
    from visionpos.config.arena import ConfigError
    from visionpos.recording import RecordingReader
    from visionpos.server.service import run_until_signal

    if not Path(log).exists():
        raise ConfigError(str(log), "(file)", "no such recording; make one with `visionpos demo --record`, "
                                              "`visionpos sim --out` or `visionpos record`")
    reader = RecordingReader(Path(log))
    arena = load_settings(reader.config, config, overrides)
    meta = reader.meta or {}
    rt = None
    if isinstance(meta.get("wall_start_unix_ns"), int) and isinstance(meta.get("monotonic_start_ns"), int):
        rt = meta["wall_start_unix_ns"] - meta["monotonic_start_ns"]
    session = ReplaySession(arena, list(reader.packets_with_source()), rate_hz, rt)
    session.playing = not paused
    view = await open_console(settings, session, clock=session.clock, controls=session.command,
                              extra=session.position)
    player = asyncio.get_running_loop().create_task(session.run(), name="visionpos-replay")
    try:
        if on_console is not None:
            on_console(view)
        await run_until_signal(duration_s)
    finally:
        player.cancel()
        try:
            await player
        except asyncio.CancelledError:
            pass
        await view.stop()
    return session
