"""The fusion service with its outputs: FusionServer composed with the bridge (MAVLink, pose stream).

The server core knows sinks only as objects with `publish(states)`; which sinks an arena asks
for (its `vehicles:`, `pose_stream:` and `vrpn:` sections) is decided here, so the core never imports
the bridge.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from visionpos.config.arena import ArenaConfig, ConfigError
from visionpos.server.service import FusionServer, run_until_signal
from visionpos.server.settings import ServerSettings


def bridge_sinks(arena: ArenaConfig) -> list[Any]:
    """The arena's outputs as sinks: the MAVLink bridge (one sender thread per vehicle) on the loop, and the
    pose stream, VRPN, NatNet and Foxglove servers behind one off-loop dispatcher (bridge/outputs.py)."""
    network: list[Any] = []
    # each bridge module is imported only for an output the arena asks for
    if arena.given("pose_stream"):
        from bridge.config import parse_pose_stream
        from bridge.pose_stream import PoseStream

        ps = parse_pose_stream(arena)
        if ps is not None:
            network.append(PoseStream(ps))
    if arena.given("vrpn"):
        from bridge.vrpn import VrpnServer, parse_vrpn

        vrpn = parse_vrpn(arena)
        if vrpn is not None:
            network.append(VrpnServer(vrpn))
    if arena.given("natnet"):
        from bridge.natnet import NatNetServer

        natnet = NatNetServer.from_arena(arena)
        if natnet is not None:
            network.append(natnet)
    if arena.given("foxglove"):
        from bridge.foxglove_live import FoxgloveServer

        fox = FoxgloveServer.from_arena(arena)
        if fox is not None:
            network.append(fox)
    sinks: list[Any] = []
    if arena.items("vehicles"):
        try:
            from bridge import Bridge
        except ImportError as e:
            raise ConfigError(arena.source, "vehicles",
                              f"the config asks for vehicle outputs but the bridge package cannot be imported ({e}); "
                              "install visionpos completely or remove the vehicles section") from None
        sinks.append(Bridge(arena, {"pose_stream": False}))  # the pose stream goes off the loop with the others
    if network:
        from bridge.outputs import OffLoopOutputs

        sinks.append(OffLoopOutputs(network))
    return sinks


async def serve(arena: ArenaConfig, settings: ServerSettings, host: str | None = None, record: str | Path | None = None,
                duration_s: float | None = None,
                on_listening: Callable[[FusionServer], None] | None = None, console: Any = None,
                on_console: Callable[[Any], None] | None = None) -> dict[str, Any]:
    """Run the fusion server with the arena's bridge sinks until a signal (or duration_s); returns its health.

    host: the address to listen on (None: settings.bind). record: MCAP path; every station
    packet, the config and the outputs are recorded.
    on_listening(server) is called once the socket is open; an OSError (port in use, bad
    address) propagates, with the recording closed. console: ConsoleSettings of the web console
    (None: none), served on the same loop; on_console(ConsoleServer) once it listens.
    """
    sinks = bridge_sinks(arena)
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
        await run_until_signal(duration_s)
    finally:
        if view is not None:
            await view.stop()
        await server.stop()
    return server.health()
