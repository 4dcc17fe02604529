"""Foxglove WebSocket server: the recordings' Foxglove channels live, for Foxglove and Lichtblick.

Off unless the arena has a `foxglove:` section; needs the optional extra (`pip install
visionpos[foxglove]`: foxglove-sdk, Foxglove's maintained server). The channels and their
messages are the recordings' (visionpos/foxglove/channels.py): the transforms, the arena scene
(frusta, floor, world axes) and the camera calibrations, the tracked bodies and the loose markers.
The cameras' blobs and the health log are in recordings only (sinks get poses and markers, not
packets or health).

publish() and publish_markers() (on the server's loop) only put the newest states or markers in
a one-slot mailbox; a sender thread encodes them and hands them to the SDK, whose server queues
at most `backlog` messages per client and drops the oldest for a client that does not keep up.
Nothing a client does reaches fusion.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from visionpos.config.arena import ArenaConfig, ConfigError
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, section
from visionpos.foxglove.channels import FoxgloveChannels
from visionpos.foxglove.protobuf import file_descriptor_set
from visionpos.messages import BodyState, LoosePoints

log = logging.getLogger(__name__)

FOXGLOVE = section(
    "foxglove",
    "Foxglove WebSocket server: the 3-D scene live in Foxglove or Lichtblick (docs/interop.md). Needs "
    "`pip install visionpos[foxglove]`.",
    Setting("enabled", "boolean", True, "false: the section is ignored"),
    Setting("host", "text", "127.0.0.1", "address to listen on (0.0.0.0: every interface; the server has no "
            "authentication, docs/security.md)"),
    Setting("port", "integer", 8765, "TCP port of the WebSocket server (Foxglove's default)", min=1, max=65535),
    Setting("rate_hz", "number", 30.0, "scene updates per second (bodies, markers)", min=1.0, max=200.0),
    Setting("backlog", "integer", 256, "messages queued per client; a client that falls further behind loses "
            "the oldest", min=16, max=100000),
)
register_section("foxglove", FOXGLOVE)


@dataclass(frozen=True)
class FoxgloveConfig:
    """The `foxglove:` section, checked (see FOXGLOVE for each key)."""

    host: str = FOXGLOVE["host"].field_default
    port: int = FOXGLOVE["port"].field_default
    rate_hz: float = FOXGLOVE["rate_hz"].field_default
    backlog: int = FOXGLOVE["backlog"].field_default


def parse_foxglove(arena: ArenaConfig) -> FoxgloveConfig | None:
    """Validate `foxglove:`; None when absent or `enabled: false`."""
    if "foxglove" not in arena.raw:
        return None
    s = FOXGLOVE.check(arena.section("foxglove"))
    F = FOXGLOVE
    if not F.read(s, "enabled"):
        return None
    return FoxgloveConfig(host=F.read(s, "host"), port=F.read(s, "port"), rate_hz=F.read(s, "rate_hz"),
                          backlog=F.read(s, "backlog"))


def _sdk(source: str) -> Any:
    try:
        import foxglove
    except ImportError:
        raise ConfigError(source, "foxglove", "the Foxglove server needs the foxglove-sdk package: "
                          "`pip install visionpos[foxglove]`, or remove the foxglove section") from None
    return foxglove


class FoxgloveServer:
    """Sink: FoxgloveServer(cfg, cameras) or FoxgloveServer.from_arena(arena); start(), publish(states),
    publish_markers(lp), stats(), close()."""

    def __init__(self, cfg: FoxgloveConfig, cameras: Any, source: str = "<arena>"):
        self.cfg = cfg
        self._sdk = _sdk(source)
        self._fox = FoxgloveChannels(cameras, cfg.rate_hz)
        self._lock = threading.Lock()  # the mailbox
        self._states: list[BodyState] | None = None
        self._markers: LoosePoints | None = None
        self._wake = threading.Event()
        self._running = False
        self._thread: threading.Thread | None = None
        self._server: Any = None
        self._context: Any = None
        self._channels: dict[str, Any] = {}
        self.port = 0
        self.counters = {"updates": 0, "messages": 0, "replaced": 0, "errors": 0}

    @classmethod
    def from_arena(cls, arena: ArenaConfig) -> "FoxgloveServer | None":
        cfg = parse_foxglove(arena)
        return None if cfg is None else cls(cfg, arena.cameras, arena.source)

    def start(self) -> None:
        """Listen (RuntimeError from the SDK when the port is taken) and start the sender thread."""
        fg = self._sdk
        self._context = fg.Context()  # our channels only, not the SDK's global ones
        self._server = fg.start_server(name="visionpos", host=self.cfg.host, port=self.cfg.port,
                                       context=self._context, message_backlog_size=self.cfg.backlog)
        self.port = self._server.port
        self._running = True
        self._thread = threading.Thread(target=self._send_loop, name="foxglove-sender", daemon=True)
        self._thread.start()
        log.info("Foxglove WebSocket server on ws://%s:%d", self.cfg.host, self.port)

    def close(self) -> None:
        self._running = False
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._server is not None:
            self._server.stop()
            self._server = None

    # ---- sink interface (server loop): never blocks ----------------------------------------------

    def publish(self, states: list[BodyState]) -> None:
        if not self._running:
            return
        with self._lock:
            if self._states is not None:
                self.counters["replaced"] += 1
            self._states = list(states)
        self._wake.set()

    def publish_markers(self, lp: LoosePoints) -> None:
        if not self._running:
            return
        with self._lock:
            self._markers = lp
        self._wake.set()

    def stats(self) -> dict[str, Any]:
        return dict(self.counters, port=self.port)

    # ---- sender thread ---------------------------------------------------------------------------

    def _channel(self, topic: str, schema: str) -> Any:
        ch = self._channels.get(topic)
        if ch is None:
            fg = self._sdk
            ch = self._channels[topic] = fg.Channel(
                topic, schema=fg.Schema(name=schema, encoding="protobuf", data=file_descriptor_set(schema)),
                message_encoding="protobuf", context=self._context)
        return ch

    def _send_loop(self) -> None:
        while self._running:
            self._wake.wait(0.5)
            self._wake.clear()
            with self._lock:
                states, self._states = self._states, None
                markers, self._markers = self._markers, None
            out = []
            if states is not None:
                out += self._fox.states(states)
            if markers is not None:
                pts = np.asarray(markers.points, dtype=np.float64).reshape(-1, 3)
                out += self._fox.markers(int(markers.time_ns), pts)
            if out:
                self.counters["updates"] += 1
            for topic, schema, t, data in out:
                try:
                    self._channel(topic, schema).log(data, log_time=t)
                    self.counters["messages"] += 1
                except Exception:  # the SDK failing must not end the thread: count, log once per burst
                    self.counters["errors"] += 1
                    if self.counters["errors"] == 1:
                        log.exception("Foxglove server: logging on %s failed", topic)
