"""Small frozen messages passed between pipeline stages.

Units are SI; times are int64 nanoseconds on the server's monotonic clock.
Quaternions are scalar-last (x, y, z, w), as scipy's Rotation uses.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntFlag

import numpy as np


class FrameFlag(IntFlag):
    """BlobFrame.flags bits (the frame's u16 flags field on the wire)."""

    TRUNCATED = 1 << 0  # detector hit its blob cap (sunlight, reflections): blobs were dropped
    SATURATED = 1 << 1  # many pixels at full scale: exposure too long
    RESYNC = 1 << 2  # station's clock offset jumped since the previous frame


# Plain ints for per-frame bit tests: `int & IntFlag` builds a new IntFlag, and `~IntFlag` is not the int complement.
FLAG_TRUNCATED = FrameFlag.TRUNCATED.value
FLAG_SATURATED = FrameFlag.SATURATED.value
FLAG_RESYNC = FrameFlag.RESYNC.value

BLOB_COLUMNS = ("x", "y", "area", "peak")


@dataclass(frozen=True, slots=True)
class BlobFrame:
    """One camera frame's detections, exactly what a station sends.

    blobs: (N, 4) float32, columns x_px, y_px (distorted image coordinates,
    pixel centres at integer values), area_px, peak (0..255 scale).
    capture_ns: capture time on the server clock (station converted it).
    session: the station session the frame was sent in (protocol v2; 0 where unknown).
    """

    camera_id: int
    seq: int
    capture_ns: int
    blobs: np.ndarray
    station_id: int = 0
    flags: int = 0
    recv_ns: int = 0
    session: int = 0

    @property
    def xy(self) -> np.ndarray:
        """(N, 2) pixel centroids."""
        return self.blobs[:, :2]


@dataclass(frozen=True, slots=True)
class BodyState:
    """Filtered pose of one rigid body at one output tick.

    position: (3,) m, world frame (z up). quaternion: (4,) x, y, z, w, the
    rotation body->world (body x forward, y left, z up).
    velocity: (3,) m/s world. angular_velocity: (3,) rad/s, body frame.
    covariance: (6, 6) over [x, y, z, rx, ry, rz] (m^2, rad^2); the rotation
    part is of a small world-frame rotation vector error.
    velocity_covariance: (3, 3) m^2/s^2. acceleration: (3,) m/s^2 world, the filter's (NaN where it has
    none: a point body, the default).
    time_ns: the instant the state is valid for (predicted to send time).
    capture_ns: capture time of the newest camera frame that contributed.
    update_kind: which measurement last kept the body tracked: "pose" (triangulated, or the
    identification; in fusion.single_view.mode always the filter took the triangulated frames' views),
    "views" (single-camera reprojection updates through occlusion), "position" (a single-marker point body:
    position and velocity only; its quaternion, angular_velocity and the covariance's rotation rows are NaN),
    "" (none).
    """

    name: str
    body_id: int
    time_ns: int
    capture_ns: int
    position: np.ndarray
    quaternion: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    covariance: np.ndarray
    velocity_covariance: np.ndarray
    tracked: bool
    n_markers: int = 0
    n_cameras: int = 0
    residual_mm: float = float("nan")
    reset_counter: int = 0
    update_kind: str = ""
    acceleration: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))


@dataclass(frozen=True, slots=True)
class LoosePoints:
    """Triangulated markers that belong to no rigid body at one fusion step.

    points: (N, 3) m world; residual_px: (N,) RMS reprojection error.
    """

    time_ns: int
    points: np.ndarray
    residual_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
