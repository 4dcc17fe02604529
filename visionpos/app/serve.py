"""The fusion service with its outputs: FusionServer composed with the arena's outputs
(visionpos.app.outputs.build_outputs: MAVLink, pose stream, VRPN, NatNet, Foxglove)."""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from visionpos.app.outputs import build_outputs
from visionpos.config.arena import ArenaConfig
from visionpos.server.service import FusionServer, run_until_signal
from visionpos.server.settings import ServerSettings


@contextlib.contextmanager
def startup_heap_frozen() -> Iterator[None]:
    """While it is open, what the start allocated (modules, the arena, compiled kernels, the outputs) is out of
    the garbage collector's reach (gc.freeze), so a full collection walks only what the run allocates: on the
    live demo one held the server's loop for 115 ms, 14-24 ms with the start-up heap frozen. Unfrozen at the
    end, so a process that runs again (tests, benchmarks) can collect it."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


async def serve(arena: ArenaConfig, settings: ServerSettings, host: str | None = None, record: str | Path | None = None,
                duration_s: float | None = None,
                on_listening: Callable[[FusionServer], None] | None = None, console: Any = None,
                on_console: Callable[[Any], None] | None = None) -> dict[str, Any]:
    """Run the fusion server with the arena's outputs until a signal (or duration_s); returns its health.

    host: the address to listen on (None: settings.bind). record: MCAP path; every station
    packet, the config and the outputs are recorded.
    on_listening(server) is called once the socket is open; an OSError (port in use, bad
    address) propagates, with the recording closed. console: ConsoleSettings of the web console
    (None: none), served on the same loop; on_console(ConsoleServer) once it listens.
    """
    sinks = build_outputs(arena)
    recorder = None
    if record is not None:
        from visionpos.recording import RecordingWriter

        recorder = RecordingWriter(record, arena.to_dict(), {"command": "serve", "config_path": arena.source})
    server = FusionServer(arena, settings, sinks, host=host, port=settings.port, recorder=recorder)
    try:
        await server.start()
    except BaseException:
        if recorder is not None:
            recorder.close()
        raise
    if on_listening is not None:
        on_listening(server)
    view = None
    try:
        if console is not None:
            from visionpos.app.console import open_console

            view = await open_console(console, server)
            if on_console is not None:
                on_console(view)
        with startup_heap_frozen():
            await run_until_signal(duration_s)
    finally:
        if view is not None:
            await view.stop()
        await server.stop()
    return server.health()
