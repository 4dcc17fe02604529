"""FoxgloveChannels: the Foxglove view of what the server sees, at a bounded rate, as encoded messages.

Fed with what a recording gets (accepted station packets, the output ticks' BodyStates, loose
markers, health and events), it returns the messages to write, each (topic, schema name, log time
ns, protobuf bytes); the log time is the message's own timestamp (capture clock). Topics:

    /foxglove/tf                        foxglove.FrameTransforms  world -> camera_<id> (calibration)
    /foxglove/arena                     foxglove.SceneUpdate      world axes, floor grid, camera frusta
    /foxglove/cameras/<id>/calibration  foxglove.CameraCalibration
    /foxglove/cameras/<id>/blobs        foxglove.ImageAnnotations the camera's 2-D blobs (frame_id via calibration)
    /foxglove/bodies                    foxglove.SceneUpdate      tracked bodies (axes + name); lost ones deleted
    /foxglove/markers                   foxglove.SceneUpdate      loose markers as spheres
    /foxglove/log                       foxglove.Log              health snapshots and server events

Rates: bodies, markers and each camera's blobs at most rate_hz (decimated on their own clock, so
the per-packet work is a byte test and a dict look-up); the static channels (tf, arena,
calibration) once at the first data and again every STATIC_PERIOD_S, so seeking into a recording
finds them. A body or marker entity expires after LIFETIME_PERIODS update periods: a killed
writer or a lost body never leaves a stale pose on screen.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from typing import Any

import numpy as np

from visionpos import protocol as P
from visionpos.camera.model import Camera
from visionpos.foxglove import scene
from visionpos.foxglove.protobuf import encode

log = logging.getLogger(__name__)

DEFAULT_RATE_HZ = 30.0
STATIC_PERIOD_S = 1.0
LIFETIME_PERIODS = 3

TOPIC_TF = "/foxglove/tf"
TOPIC_ARENA = "/foxglove/arena"
TOPIC_BODIES = "/foxglove/bodies"
TOPIC_MARKERS = "/foxglove/markers"
TOPIC_LOG = "/foxglove/log"
TOPIC_PREFIX = "/foxglove/"

SCENE_UPDATE = "foxglove.SceneUpdate"
FRAME_TRANSFORMS = "foxglove.FrameTransforms"
IMAGE_ANNOTATIONS = "foxglove.ImageAnnotations"
CAMERA_CALIBRATION = "foxglove.CameraCalibration"
LOG = "foxglove.Log"

Out = list[tuple[str, str, int, bytes]]


def calibration_topic(camera_id: int) -> str:
    return f"/foxglove/cameras/{int(camera_id)}/calibration"


def blobs_topic(camera_id: int) -> str:
    return f"/foxglove/cameras/{int(camera_id)}/blobs"


class FoxgloveChannels:
    """cameras: the arena's calibrated cameras. rate_hz: the most updates per second of each moving
    channel. realtime_minus_monotonic_ns: CLOCK_REALTIME - monotonic of the host that received the
    packets, to put realtime-stamped frames (stations on PTP/chrony) on the capture clock as the
    server does; None: this host's, now.

    Thread-safe; every method returns the messages to write (possibly none).
    """

    def __init__(self, cameras: list[Camera] | tuple[Camera, ...], rate_hz: float = DEFAULT_RATE_HZ,
                 realtime_minus_monotonic_ns: int | None = None):
        if not rate_hz > 0:
            raise ValueError(f"FoxgloveChannels: rate_hz must be > 0, got {rate_hz}")
        self.cameras = {c.id: c for c in cameras}
        self.period_ns = int(round(1e9 / rate_hz))
        self.lifetime_ns = LIFETIME_PERIODS * self.period_ns
        self._static_period_ns = int(STATIC_PERIOD_S * 1e9)
        self._rt = (time.time_ns() - time.monotonic_ns() if realtime_minus_monotonic_ns is None
                    else int(realtime_minus_monotonic_ns))
        self._lock = threading.Lock()
        self._next_static = None  # data time of the next static refresh; None: not written yet
        self._next_bodies = self._next_markers = -(1 << 62)
        self._next_blobs: dict[int, int] = {}  # camera id -> receive time of its next annotated frame
        self._realtime: set[int] = set()  # cameras whose frames are stamped on CLOCK_REALTIME
        self._shown: set[str] = set()  # bodies on screen
        self.messages = 0

    def _static(self, t_ns: int) -> Out:
        """The static channels when they are due (lock held)."""
        if self._next_static is not None and t_ns < self._next_static:
            return []
        self._next_static = t_ns + self._static_period_ns
        cams = list(self.cameras.values())
        out = [(TOPIC_TF, FRAME_TRANSFORMS, t_ns, encode(FRAME_TRANSFORMS, scene.frame_transforms(t_ns, cams))),
               (TOPIC_ARENA, SCENE_UPDATE, t_ns, encode(SCENE_UPDATE, scene.arena_scene(t_ns, cams)))]
        out += [(calibration_topic(c.id), CAMERA_CALIBRATION, t_ns,
                 encode(CAMERA_CALIBRATION, scene.camera_calibration(t_ns, c))) for c in cams]
        return out

    def _done(self, out: Out) -> Out:
        self.messages += len(out)
        return out

    def packet(self, recv_ns: int, data: bytes) -> Out:
        """An accepted station packet: every 1/rate_hz per camera, its frame's blobs as annotations.

        Per packet; anything but a due frame costs a byte test and a look-up.
        """
        if len(data) < P.HEADER_BYTES:
            return []
        mtype = data[5]
        if mtype == P.MsgType.FRAME:
            cid = data[10] | data[11] << 8
            if recv_ns < self._next_blobs.get(cid, -(1 << 62)) or cid not in self.cameras:
                return []
        elif mtype == P.MsgType.HELLO:
            return self._hello(data)
        else:
            return []
        try:
            f = P.decode(data)  # recorded packets were accepted (and authenticated) by the server
        except P.ProtocolError:
            return []
        capture = f.capture_ns - self._rt if cid in self._realtime else f.capture_ns
        if capture < 0:  # before the clock's origin: no time to show it at (MCAP times are unsigned)
            return []
        with self._lock:
            self._next_blobs[cid] = recv_ns + self.period_ns
            out = self._static(capture)
            out.append((blobs_topic(cid), IMAGE_ANNOTATIONS, capture,
                        scene.encode_image_annotations(capture, f.blobs)))
            return self._done(out)

    def _hello(self, data: bytes) -> Out:
        try:
            h = P.decode(data)
        except P.ProtocolError:
            return []
        with self._lock:
            if h.timebase == P.Timebase.REALTIME:
                self._realtime.add(h.camera_id)
            else:
                self._realtime.discard(h.camera_id)
        return []

    def states(self, states: list[Any]) -> Out:
        """One output tick's BodyStates: every 1/rate_hz, the tracked bodies; a body lost since the
        last update is deleted at once."""
        if not states:
            return []
        t = max(s.time_ns for s in states)
        lost = [s.name for s in states if not s.tracked and s.name in self._shown]
        if t < self._next_bodies and not lost:
            return []
        with self._lock:
            self._next_bodies = t + self.period_ns
            tracked = [s for s in states if s.tracked and np.isfinite(s.position).all()
                       and np.isfinite(s.quaternion).all()]
            lost = [n for n in lost if n in self._shown]
            self._shown.difference_update(lost)
            self._shown.update(s.name for s in tracked)
            out = self._static(t)
            out.append((TOPIC_BODIES, SCENE_UPDATE, t,
                        encode(SCENE_UPDATE, scene.bodies_scene(t, tracked, lost, self.lifetime_ns))))
            return self._done(out)

    def markers(self, time_ns: int, points: np.ndarray) -> Out:
        """A new set of loose markers (N, 3): every 1/rate_hz."""
        if time_ns < self._next_markers:
            return []
        with self._lock:
            self._next_markers = int(time_ns) + self.period_ns
            out = self._static(int(time_ns))
            out.append((TOPIC_MARKERS, SCENE_UPDATE, int(time_ns),
                        encode(SCENE_UPDATE, scene.markers_scene(int(time_ns), points, self.lifetime_ns))))
            return self._done(out)

    def health(self, time_ns: int, health: dict[str, Any]) -> Out:
        """A server health snapshot as a log line (at the status period, not rate-limited here)."""
        msg = encode(LOG, scene.health_log(int(time_ns), health))
        with self._lock:
            return self._done([(TOPIC_LOG, LOG, int(time_ns), msg)])

    def event(self, time_ns: int, info: dict[str, Any]) -> Out:
        """A server event (camera registered, vanished, clock jump ...) as a log line."""
        text = json.dumps(info, separators=(", ", ": "), default=str)
        msg = encode(LOG, scene.log_message(int(time_ns), scene.LOG_INFO, "visionpos.events", text))
        with self._lock:
            return self._done([(TOPIC_LOG, LOG, int(time_ns), msg)])
