"""The one interface of the fusion server's outputs: `Sink`.

FusionServer (service.py) calls every sink at each output tick and on the server's rarer
news. Everything has a no-op default, so an output overrides only what it does: the MAVLink
bridge takes poses and markers, the Foxglove server also packets, health and events, the
demo's collector only poses. The core defines the interface and never imports an
implementation (bridge/ and console/ subclass it; visionpos/app/outputs.py builds them from
the arena).

Timing contract (all calls on the server's event loop, one thread):
- publish(states) once per output tick; publish_markers(points) at a tick after the pipeline
  triangulated a new set of loose markers. Neither may block: queue internally.
- packet_taps() is asked once, at construction of the server; each tap is called by Ingest
  with every accepted packet (recv_ns, data) and must cost about a dictionary store.
- publish_health(time_ns, health) every status period; publish_event(time_ns, info) on a
  camera registered, vanished, a clock jump, a camera pose corrected ...
- start() before the server listens (an OSError, such as a port in use, stops the start);
  close() after the server stopped. stats() is read by health() (an empty dict: nothing to say).
- status_line() is appended to the server's status line when not empty.
A sink that raises is counted in health()['sink_errors'] under its `name` and keeps being called.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from visionpos.errors import UsageError
from visionpos.messages import BodyState, LoosePoints

# tap(recv_ns, data): a station packet Ingest accepted
PacketTap = Callable[[int, bytes], None]


class Sink:
    """An output of the fusion server (see the module docstring); every method is a no-op here."""

    @property
    def name(self) -> str:
        """The key of this sink in health()['sinks'] and ['sink_errors']."""
        return type(self).__name__

    def opens(self) -> dict[str, Any]:
        """The arena keys and values of what start() opens ({'vrpn.host': '0.0.0.0', 'vrpn.port': 3883}),
        named by the error when it cannot; empty: nothing configured."""
        return {}

    def start(self) -> None:
        """Open sockets and threads (before the server listens); an OSError when an address cannot be
        opened (start_sink turns it into a SinkStartError naming opens())."""

    def use_identity(self, book: Any) -> None:
        """The pipeline's IdentityBook (fusion/identity.py), once, before any publish: read it on the loop."""

    def imu_sources(self) -> list[Any]:
        """Callables drain(push_imu) that hand the pipeline IMU samples (FusionPipeline.add_imu_source)."""
        return []

    def publish(self, states: list[BodyState]) -> None:
        """The tick's states, one per configured body (never blocks)."""

    def publish_markers(self, points: LoosePoints) -> None:
        """A new set of loose markers (points of no body)."""

    def packet_taps(self) -> list[PacketTap]:
        """Callables Ingest calls with every accepted packet."""
        return []

    def publish_health(self, time_ns: int, health: dict[str, Any]) -> None:
        """FusionServer.health() every status period."""

    def publish_event(self, time_ns: int, info: dict[str, Any]) -> None:
        """A server event: {'kind': ..., ...}."""

    def stats(self) -> dict[str, Any]:
        """Counters for health()['sinks'][name]; empty: the sink is left out."""
        return {}

    def status_line(self) -> str:
        """This sink's part of the server's status line ('' for none)."""
        return ""

    def close(self) -> None:
        """Stop threads and close sockets. Idempotent."""


class SinkStartError(UsageError):
    """A sink could not open what its config asks for (a port taken, a bad address): the user's environment,
    one line naming the keys."""

    def __init__(self, sink: Sink, error: OSError):
        keys = sink.opens()
        what = ", ".join(f"{k}={v}" for k, v in keys.items()) or sink.name
        sections = sorted({k.split(".")[0] for k in keys})
        fix = (f"change {' or '.join(keys)}, or remove the {' and '.join(sections)} section" if keys
               else "check its addresses in the config")
        super().__init__(f"cannot open {what}: {error.strerror or error}; {fix}")
        self.sink, self.error = sink, error


def start_sink(sink: Sink) -> None:
    """sink.start(); an OSError (also one a RuntimeError was raised from: an SDK's) becomes a SinkStartError."""
    try:
        sink.start()
    except OSError as e:
        raise SinkStartError(sink, e) from None
    except RuntimeError as e:
        if not isinstance(e.__cause__, OSError):
            raise
        raise SinkStartError(sink, e.__cause__) from None
