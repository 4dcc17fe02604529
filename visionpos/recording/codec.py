"""The recording format: its names (profile, topics, metadata), the MCAP framing the writer and the reader
share (the provisional end), and the JSON codec of BodyState and what the recordings hold beside it."""

from __future__ import annotations

import json
import logging
import math
from typing import Any, NamedTuple

import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.records import DataEnd, Footer
from mcap.writer import Writer

from visionpos.config.arena import parse_arena
from visionpos.errors import VisionposError
from visionpos.foxglove.protobuf import file_descriptor_set
from visionpos.messages import BodyState

log = logging.getLogger(__name__)

PROFILE = "visionpos"
FORMAT_VERSION = 1
TOPIC_PACKETS = "/station/packets"
TOPIC_STATES = "/fusion/states"
TOPIC_TRUTH = "/sim/truth"
TOPIC_MARKERS = "/fusion/markers"
TOPIC_HEALTH = "/server/health"
TOPIC_EVENTS = "/server/events"
TOPIC_IMU = "/fusion/imu"  # the vehicles' IMU samples the pipeline took (FusionPipeline.push_imu): an input
PACKET_ENCODING = "visionpos.station"
META_END = "visionpos.end"
MCAP_MAGIC = b"\x89MCAP0\r\n"


def _provisional_end() -> bytes:
    b = RecordBuilder()
    DataEnd(0).write(b)  # crc 0: not computed
    Footer(0, 0, 0).write(b)  # summary_start 0: no summary, readers read the data section linearly
    b.write(MCAP_MAGIC)
    return b.end()


PROVISIONAL_END = _provisional_end()

STATE_SCHEMA = {
    "title": "visionpos.BodyState",
    "type": "object",
    "description": "Filtered rigid-body pose (SI units, world z up, quaternion x,y,z,w body->world).",
    "properties": {
        "name": {"type": "string"},
        "body_id": {"type": "integer"},
        "time_ns": {"type": "integer"},
        "capture_ns": {"type": "integer"},
        "position": {"type": "array", "items": {"type": ["number", "null"]}},
        "quaternion": {"type": "array", "items": {"type": ["number", "null"]}},
        "velocity": {"type": "array", "items": {"type": ["number", "null"]}},
        "angular_velocity": {"type": "array", "items": {"type": ["number", "null"]}},
        "covariance": {"type": "array", "items": {"type": ["number", "null"]}, "description": "6x6 row-major"},
        "velocity_covariance": {"type": "array", "items": {"type": ["number", "null"]},
                                "description": "3x3 row-major"},
        "tracked": {"type": "boolean"},
        "n_markers": {"type": "integer"},
        "n_cameras": {"type": "integer"},
        "residual_mm": {"type": ["number", "null"]},
        "reset_counter": {"type": "integer"},
        "update_kind": {"type": "string", "enum": ["", "pose", "views"],
                        "description": "last measurement that kept the body tracked: triangulated pose or "
                                       "single-camera views"},
    },
}
TRUTH_SCHEMA = {
    "title": "visionpos.Truth",
    "type": "object",
    "description": "Simulator ground truth of one body (m, quaternion x,y,z,w body->world).",
    "properties": {
        "name": {"type": "string"},
        "position": {"type": "array", "items": {"type": "number"}},
        "quaternion": {"type": "array", "items": {"type": "number"}},
    },
}
IMU_SCHEMA = {
    "title": "visionpos.ImuSample",
    "type": "object",
    "description": "One IMU sample handed to FusionPipeline.push_imu, logged at the pipeline's input time: the receive "
                   "time of the frame whose push took it (at 'frame', recorded after that frame's packet) or the "
                   "output tick's time (at 'tick'); a replay hands it over at the same point of the input order.",
    "properties": {
        "body": {"type": "string"},
        "t_ns": {"type": "integer", "description": "sample time, capture clock ns"},
        "accel": {"type": "array", "items": {"type": ["number", "null"]},
                  "description": "specific force, body frame (FLU), m/s^2"},
        "gyro": {"type": "array", "items": {"type": ["number", "null"]}, "description": "rate, body frame, rad/s"},
        "lever_arm": {"type": ["array", "null"], "items": {"type": ["number", "null"]},
                      "description": "body frame, origin to the IMU, m (null: at the origin)"},
        "at": {"type": "string", "enum": ["frame", "tick"]},
    },
}


class ImuRecord(NamedTuple):
    """A recorded IMU sample as RecordingReader.inputs yields it (IMU_SCHEMA); log_ns: the message's log time."""
    log_ns: int
    body: str
    t_ns: int
    accel: np.ndarray  # (3,) m/s^2, body frame
    gyro: np.ndarray  # (3,) rad/s, body frame
    lever_arm: np.ndarray | None  # (3,) m, body frame
    at: str  # "frame" or "tick"


def imu_to_dict(body: str, t_ns: int, accel: Any, gyro: Any, lever_arm: Any, at: str) -> dict[str, Any]:
    """One IMU sample as recorded (IMU_SCHEMA); NaN/inf -> null (read back as NaN: refused alike)."""
    return {"body": str(body), "t_ns": int(t_ns), "accel": _list(accel), "gyro": _list(gyro),
            "lever_arm": None if lever_arm is None else _list(lever_arm), "at": str(at)}


def imu_from_dict(d: dict[str, Any]) -> tuple[str, int, np.ndarray, np.ndarray, np.ndarray | None, str]:
    """Inverse of imu_to_dict: (body, t_ns, accel (3,), gyro (3,), lever_arm (3,) or None, at). Raises
    KeyError/ValueError/TypeError on a malformed dict."""
    arm = d.get("lever_arm")
    at = str(d.get("at", "tick"))
    if at not in ("frame", "tick"):
        raise ValueError(f"at {at!r}")
    return (str(d["body"]), int(d["t_ns"]), np.asarray(d["accel"], dtype=np.float64).reshape(3),
            np.asarray(d["gyro"], dtype=np.float64).reshape(3),
            None if arm is None else np.asarray(arm, dtype=np.float64).reshape(3), at)


class RecordingError(VisionposError, ValueError):
    """A recording that cannot be read. str() names the file and what is wrong."""


class RecordingDamagedWarning(UserWarning):
    """The recording ends early (writer killed, disk full) or is corrupt part-way; data before it was read."""


# ---------------------------------------------------------------- encoding helpers


def plain(obj: Any) -> Any:
    """numpy scalars/arrays -> plain Python, NaN/inf -> None, so YAML/JSON can hold them."""
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return plain(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None  # strict JSON (Foxglove) has no NaN/inf
    return obj


def _num(x: float) -> float | None:
    return None if not math.isfinite(x) else x


def _list(a: Any) -> list[float | None]:
    """Flat list of floats; NaN/inf -> null (an untracked state's pose is NaN by design)."""
    v = np.asarray(a, dtype=np.float64).ravel()
    if np.isfinite(v).all():
        return v.tolist()
    return [x if math.isfinite(x) else None for x in v.tolist()]


def state_to_dict(s: BodyState) -> dict[str, Any]:
    """BodyState -> JSON-able dict (arrays flattened row-major; NaN -> null)."""
    return {
        "name": s.name,
        "body_id": int(s.body_id),
        "time_ns": int(s.time_ns),
        "capture_ns": int(s.capture_ns),
        "position": _list(s.position),
        "quaternion": _list(s.quaternion),
        "velocity": _list(s.velocity),
        "angular_velocity": _list(s.angular_velocity),
        "covariance": _list(s.covariance),
        "velocity_covariance": _list(s.velocity_covariance),
        "tracked": bool(s.tracked),
        "n_markers": int(s.n_markers),
        "n_cameras": int(s.n_cameras),
        "residual_mm": _num(float(s.residual_mm)),
        "reset_counter": int(s.reset_counter),
        "update_kind": str(s.update_kind),
    }


def state_from_dict(d: dict[str, Any]) -> BodyState:
    """Inverse of state_to_dict. Raises KeyError/ValueError on a malformed dict."""

    def arr(key: str, shape: tuple[int, ...]) -> np.ndarray:
        return np.asarray(d[key], dtype=np.float64).reshape(shape)  # null -> NaN

    res = d.get("residual_mm")
    return BodyState(
        name=str(d["name"]),
        body_id=int(d["body_id"]),
        time_ns=int(d["time_ns"]),
        capture_ns=int(d["capture_ns"]),
        position=arr("position", (3,)),
        quaternion=arr("quaternion", (4,)),
        velocity=arr("velocity", (3,)),
        angular_velocity=arr("angular_velocity", (3,)),
        covariance=arr("covariance", (6, 6)),
        velocity_covariance=arr("velocity_covariance", (3, 3)),
        tracked=bool(d["tracked"]),
        n_markers=int(d.get("n_markers", 0)),
        n_cameras=int(d.get("n_cameras", 0)),
        residual_mm=float("nan") if res is None else float(res),
        reset_counter=int(d.get("reset_counter", 0)),
        update_kind=str(d.get("update_kind", "")),  # recordings before issue 15 have none
    )


def json_bytes(obj: Any) -> bytes:
    # allow_nan=False: a NaN would make the file unreadable for strict JSON tools (Foxglove)
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def realtime_minus_monotonic(meta: dict[str, Any]) -> int | None:
    """The recording host's CLOCK_REALTIME - monotonic difference at the start, from its meta."""
    wall, mono = meta.get("wall_start_unix_ns"), meta.get("monotonic_start_ns")
    return wall - mono if isinstance(wall, int) and isinstance(mono, int) else None


def arena_cameras(config: Any) -> tuple[Any, ...]:
    """The calibrated cameras of a recording's config: an ArenaConfig's, or parsed from the raw mapping
    (a mapping that is no valid arena, as some tools record, has none)."""
    cams = getattr(config, "cameras", None)
    if cams is not None:
        return tuple(cams)
    try:
        return parse_arena(getattr(config, "raw", config)).cameras
    except (VisionposError, TypeError, ValueError) as e:
        log.debug("recording config is no arena (%s): Foxglove channels without cameras", e)
        return ()



def protobuf_schema(w: Writer, registered: dict[str, int], schema: str) -> int:
    """The id of a Foxglove protobuf schema in writer w, registered on first use (registered: name -> id)."""
    sid = registered.get(schema)
    if sid is None:
        sid = registered[schema] = w.register_schema(schema, "protobuf", file_descriptor_set(schema))
    return sid
