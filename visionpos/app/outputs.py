"""Every output an arena asks for, built in one place: `build_outputs(arena) -> list[Sink]`.

`serve`, `record` (with the console), `demo` and the benchmarks all assemble their outputs here, so
a section honoured by one is honoured by all: `vehicles` (the MAVLink bridge, on the server's loop),
`pose_stream`, `vrpn`, `natnet` and `foxglove` (behind one off-loop dispatcher, bridge/outputs.py).
Nothing is opened here; FusionServer.start() starts them (a port taken: SinkStartError, one line
naming the keys). The server core knows sinks only by visionpos.server.sinks.Sink, so it never
imports the bridge.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from visionpos.config.arena import ArenaConfig, ConfigError
from visionpos.server.sinks import Sink

if TYPE_CHECKING:
    from bridge import Bridge

# the bridge's MAVLink latency report (to stderr) every this many seconds; 0: none
REPORT_INTERVAL_S = 30.0


# each network output: its arena section, and where its Sink class lives (imported only when the section is given,
# so an arena without it never loads that library); each class has from_arena(arena) -> Sink | None
NETWORK_OUTPUTS = (("pose_stream", "bridge.pose_stream", "PoseStream"),
                   ("vrpn", "bridge.vrpn", "VrpnServer"),
                   ("natnet", "bridge.natnet", "NatNetServer"),
                   ("foxglove", "bridge.foxglove_live", "FoxgloveServer"))


def network_outputs(arena: ArenaConfig) -> list[Sink]:
    """The pose stream, VRPN, NatNet and Foxglove servers the arena's sections ask for (none opened)."""
    out: list[Sink] = []
    for key, module, cls_name in NETWORK_OUTPUTS:
        if arena.given(key):
            sink = getattr(importlib.import_module(module), cls_name).from_arena(arena)
            if sink is not None:
                out.append(sink)
    return out


def build_outputs(arena: ArenaConfig, report_interval_s: float = REPORT_INTERVAL_S) -> list[Sink]:
    """The arena's outputs as sinks: the MAVLink bridge (one sender thread per vehicle) on the loop when it
    has `vehicles`, and the network outputs behind one off-loop dispatcher (bridge/outputs.py).
    report_interval_s: how often the bridge prints its latency advice (0: never)."""
    sinks: list[Sink] = []
    if arena.items("vehicles"):
        try:
            from bridge import Bridge
        except ImportError as e:
            raise ConfigError(arena.source, "vehicles",
                              f"the config asks for vehicle outputs but the bridge package cannot be imported ({e}); "
                              "install visionpos completely or remove the vehicles section") from None
        # the pose stream goes off the loop with the others
        sinks.append(Bridge(arena, {"pose_stream": False, "report_interval_s": report_interval_s}))
    network = network_outputs(arena)
    if network:
        from bridge.outputs import OffLoopOutputs

        sinks.append(OffLoopOutputs(network))
    return sinks


def bridge_of(outputs: list[Sink]) -> Bridge | None:
    """The MAVLink bridge among build_outputs' sinks (None without vehicles)."""
    from bridge import Bridge

    return next((s for s in outputs if isinstance(s, Bridge)), None)


def network_of(outputs: list[Sink]) -> list[Sink]:
    """The network outputs among build_outputs' sinks (those behind the off-loop dispatcher)."""
    from bridge.outputs import OffLoopOutputs

    return [o for s in outputs if isinstance(s, OffLoopOutputs) for o in s.outputs]
