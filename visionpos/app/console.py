"""The operator console composed with `serve`, `demo`, `record` and `replay --view` (console/, docs/console.md).

console_settings() applies the command line to the arena's `console:` section; open_console()
starts the console for a source on the running loop. For `record`, which fuses nothing,
RecordSource stands in for the server: the cameras' newest blobs and their health, no bodies. `record` and
`replay --view` feed every accepted frame to the calibration assistant (console/calibration.py); the console of
a running fusion server (serve, demo) gets the live one (console/live_calibration.py).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from console.server import ConsoleServer
from console.settings import ConsoleSettings, parse_console
from visionpos.config.arena import ArenaConfig
from visionpos.fusion.snapshot import CameraFrame, FusionSnapshot
from visionpos.messages import BlobFrame


def add_console_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--console-port", type=int, default=None, metavar="PORT",
                   help="TCP port of the web console (default console.port, 8080; 0 = any free port)")
    p.add_argument("--console-bind", default=None, metavar="ADDRESS",
                   help="address of the web console (default console.bind, 127.0.0.1; another needs the token)")
    p.add_argument("--no-console", action="store_true", help="no web console")


def add_calibrate_out_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--calibrate-out", default=None, metavar="YAML",
                   help="where the console's wand solve (Solve in its Calibration panel) writes the calibrated arena "
                        "(default: beside the recording, WAVE.mcap -> WAVE.calibrated.yaml)")


def console_settings(arena: ArenaConfig, args: argparse.Namespace) -> ConsoleSettings | None:
    """The arena's console settings with --console-bind/--console-port; None when turned off."""
    s = parse_console(arena)
    if getattr(args, "no_console", False) or not s.enabled:
        return None
    return s.with_address(getattr(args, "console_bind", None), getattr(args, "console_port", None))


MASK_VIEW_WIDTH_PX = 320  # the mask travels to the page at about the camera view's size


def station_masks(arena: ArenaConfig, paths: tuple[str, ...]) -> dict[int, dict[str, Any]]:
    """Camera id -> {"rois": [[x0, y0, x1, y1], ...], "ignore": [...], "mask_png": data URL or None} from the
    station files' `detector` sections (console.stations): what each station searches for blobs."""
    import base64

    import cv2

    from stations.config import build_mask
    from visionpos.config.arena import ConfigError, Section, load_yaml

    cams = {c.id: c for c in arena.cameras}
    out: dict[int, dict[str, Any]] = {}
    for path in paths:
        try:
            data = load_yaml(Path(path))
        except (OSError, ConfigError) as e:
            raise ConfigError(arena.source, "console.stations", f"cannot read {path}: {e}") from None
        cid = data.get("camera_id") if isinstance(data, dict) else None
        if cid not in cams:
            raise ConfigError(path, "camera_id", f"{cid!r} is none of the arena's cameras {sorted(cams)} "
                                                 "(console.stations lists this file)")
        det = Section(data.get("detector") or {}, path, "detector")
        rects = {k: ([[int(v) for v in r] for r in det.array(k, (None, 4))] if det.has(k) else [])
                 for k in ("rois", "ignore")}
        mask_file = det.data.get("mask") or ""
        if mask_file and not Path(mask_file).is_absolute():
            mask_file = str(Path(path).parent / mask_file)
        m = cams[cid].model
        spec = SimpleNamespace(mask_path=mask_file, rois=tuple(map(tuple, rects["rois"])),
                               ignore=tuple(map(tuple, rects["ignore"])), source_file=path)
        mask = build_mask(spec, m.width, m.height)
        png = None
        if mask is not None:
            scale = min(1.0, MASK_VIEW_WIDTH_PX / m.width)
            small = cv2.resize(mask, (max(1, round(m.width * scale)), max(1, round(m.height * scale))),
                               interpolation=cv2.INTER_AREA)
            ok, buf = cv2.imencode(".png", small)
            png = "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode() if ok else None
        out[cid] = {**rects, "mask_png": png}
    return out


def announce_console(command: str, console: ConsoleServer, out: Any = None) -> None:
    """The console's address (and its fresh token) on out (default stdout)."""
    s = console.settings
    print(f"visionpos {command}: console at {console.url}", file=out, flush=True)
    if s.token_generated:
        print(f"visionpos {command}: the console listens on {s.bind}, so it needs this token (set console.token "
              f"to keep one): {s.token}", file=out, flush=True)


def port_in_use(settings: ConsoleSettings) -> bool:
    """Whether the console's TCP port is taken on its address now (0: never)."""
    import socket

    if settings.port == 0:
        return False
    family = socket.AF_INET6 if ":" in settings.bind else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((settings.bind, settings.port))
        except OSError:
            return True
    return False


async def open_console(settings: ConsoleSettings, source: Any, **kw: Any) -> ConsoleServer:
    """A started ConsoleServer for source, with the stations' masks of console.stations (an OSError, such as
    the port in use, propagates)."""
    calibration = getattr(source, "calibration", None)
    if calibration is None and hasattr(source, "set_cameras"):  # a running fusion server: serve, demo
        from console.live_calibration import LiveCalibration, live_out

        calibration = LiveCalibration(source, live_out(source.arena.source))
    console = ConsoleServer(settings, source, masks=station_masks(source.arena, settings.stations),
                            calibration=calibration, **kw)
    await console.start()
    return console


class RecordSource:
    """`visionpos record`'s stand-in for the fusion server: its Ingest's pipeline (push, remove_camera)
    keeps each camera's newest blobs, undistorted for the rays, and feeds the calibration assistant
    (`calibration`, a console.calibration.CalibrationAssistant, or None); no body is tracked."""

    def __init__(self, arena: ArenaConfig, calibration: Any = None):
        self.arena = arena
        self.calibration = calibration
        self.pipeline = self  # what Ingest pushes frames into, and what the console reads (snapshot())
        self.ingest: Any = None  # set once record_traffic made it
        self.frames: dict[int, CameraFrame] = {}
        self._untracked_why = {i: "not fused: `visionpos record` only records" for i in range(len(arena.bodies))}
        self.last_states: list = []
        self._cams = {c.id: c for c in arena.cameras}

    def push(self, frame: BlobFrame) -> None:
        cam = self._cams.get(frame.camera_id)
        blobs = np.asarray(frame.blobs, dtype=float)
        if cam is None or blobs.ndim != 2 or blobs.shape[1] < 2:
            return
        if self.calibration is not None:
            self.calibration.push(frame)
        px = blobs[:, :2]
        self.frames[cam.id] = CameraFrame(int(frame.capture_ns), px, cam.model.undistort(px), np.full(len(px), -1))

    def remove_camera(self, camera_id: int) -> None:
        self.frames.pop(camera_id, None)

    def pause_view_updates(self, paused: bool) -> bool:
        return False  # nothing is fused: no view updates to pause

    def snapshot(self) -> FusionSnapshot:
        """The console's view of it: each camera's newest blobs, every blob of no body, no body tracked."""
        return FusionSnapshot(dict(self.frames), (False,) * len(self.arena.bodies), self._untracked_why)

    def clock(self) -> int:
        return time.monotonic_ns()

    def health(self) -> dict[str, Any]:
        return self.ingest.health() if self.ingest is not None else {}


async def replay_view(log: str, config: str | None, overrides: list[str], rate_hz: float | None,
                      settings: ConsoleSettings, on_console: Any = None, duration_s: float | None = None,
                      paused: bool = False, calibrate_out: str | None = None) -> Any:
    """Serve the console for a recording (`visionpos replay LOG --view`) until a signal (or duration_s); returns
    the ReplaySession. The calibration assistant counts the recording's wand frames as it plays; its solve writes
    to calibrate_out (default: beside the recording)."""
    import asyncio
    from pathlib import Path

    from console.calibration import CalibrationAssistant, default_out
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
    session = ReplaySession(arena, list(reader.packets_with_source()), rate_hz, rt, name=Path(log).name,
                            calibration=CalibrationAssistant(arena, calibrate_out or default_out(log)),
                            recorded_states=reader.states())
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
