"""What the Foxglove channels show, as pure functions: geometry on numpy arrays and message dicts.

Frames: "world" (the arena's, z up) and one per camera, "camera_<id>", an optical frame as OpenCV
and Foxglove's CameraCalibration have it (x right, y down, z forward), placed by the calibration.
Message dicts are the protobuf field names of visionpos/foxglove/protobuf.py; times are int ns on
the server's monotonic clock (the capture clock).
"""

from __future__ import annotations

import math
import struct
from functools import lru_cache
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos.camera.model import Camera
from visionpos.foxglove.protobuf import encode, len_field, time_msg, varint

WORLD_FRAME = "world"
FRUSTUM_DEPTH_M = 0.4  # drawn frustum length: visible at arena scale, short enough not to clutter
AXES_LENGTH_M = 0.15  # a body's axes
MARKER_DIAMETER_M = 0.02
GRID_STEP_M = 1.0
MIN_BLOB_DIAMETER_PX = 6.0  # a one-pixel blob still shows as a ring

RED = {"r": 0.9, "g": 0.15, "b": 0.15, "a": 1.0}
GREEN = {"r": 0.15, "g": 0.8, "b": 0.15, "a": 1.0}
BLUE = {"r": 0.2, "g": 0.35, "b": 1.0, "a": 1.0}
GREY = {"r": 0.55, "g": 0.55, "b": 0.55, "a": 0.6}
CAMERA_COLOR = {"r": 1.0, "g": 0.75, "b": 0.1, "a": 1.0}
MARKER_COLOR = {"r": 1.0, "g": 1.0, "b": 1.0, "a": 0.9}
LABEL_COLOR = {"r": 1.0, "g": 1.0, "b": 1.0, "a": 1.0}
BLOB_COLOR = {"r": 0.1, "g": 1.0, "b": 0.3, "a": 1.0}
BLOB_THICKNESS_PX = 2.0
_IDENTITY = encode("foxglove.Pose", {"position": {}, "orientation": {"w": 1.0}})
_NO_ROTATION = encode("foxglove.Quaternion", {"w": 1.0})
_AXES_COLORS = [encode("foxglove.Color", c) for c in (RED, RED, GREEN, GREEN, BLUE, BLUE)]
_MARKER_COLOR = encode("foxglove.Color", MARKER_COLOR)
_MARKER_SIZE = encode("foxglove.Vector3", {"x": MARKER_DIAMETER_M, "y": MARKER_DIAMETER_M, "z": MARKER_DIAMETER_M})
_LABEL_COLOR = encode("foxglove.Color", LABEL_COLOR)
_BLOB_COLOR = encode("foxglove.Color", BLOB_COLOR)

LOG_INFO, LOG_WARNING = 2, 3  # foxglove.Log.Level
_LINE_LIST = 2  # foxglove.LinePrimitive.Type


def camera_frame_id(camera_id: int) -> str:
    return f"camera_{int(camera_id)}"


# ---------------------------------------------------------------- geometry


def camera_in_world(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A camera's frame in the world: R (3, 3), t (3,) map world -> camera (x_cam = R x_world + t).

    Returns (translation (3,), quaternion (4,) x, y, z, w): the camera centre -R^T t and the
    rotation R^T, which takes camera axes to world axes (a FrameTransform's parent <- child).
    """
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    # scipy, not the compiled helper: loading numba's cache on a recorder's first packet would stall it
    return -R.T @ np.asarray(t, dtype=np.float64).reshape(3), Rotation.from_matrix(R.T).as_quat()


def frustum_segments(K: np.ndarray, width: int, height: int, depth_m: float = FRUSTUM_DEPTH_M) -> np.ndarray:
    """(16, 3) camera-frame points, pairs of a line list: the 4 edges from the centre to the image
    corners at z = depth_m and the 4 edges of that far rectangle. K (3, 3) pinhole intrinsics; the
    corners are the outer edges of the corner pixels (pixel centres at integer coordinates)."""
    K = np.asarray(K, dtype=np.float64)
    u = np.array([-0.5, width - 0.5, width - 0.5, -0.5])
    v = np.array([-0.5, -0.5, height - 0.5, height - 0.5])
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    far = np.stack([x, y, np.ones(4)], axis=1) * depth_m
    seg = []
    for i in range(4):
        seg += [np.zeros(3), far[i], far[i], far[(i + 1) % 4]]
    return np.asarray(seg)


def grid_segments(xy_min: np.ndarray, xy_max: np.ndarray, step_m: float = GRID_STEP_M) -> np.ndarray:
    """(2M, 3) points of a line list: a floor grid (z = 0) on whole multiples of step_m covering the box."""
    lo = np.floor(np.asarray(xy_min, dtype=np.float64) / step_m) * step_m
    hi = np.ceil(np.asarray(xy_max, dtype=np.float64) / step_m) * step_m
    xs = np.arange(lo[0], hi[0] + step_m / 2, step_m)
    ys = np.arange(lo[1], hi[1] + step_m / 2, step_m)
    seg = [p for x in xs for p in ((x, lo[1], 0.0), (x, hi[1], 0.0))]
    seg += [p for y in ys for p in ((lo[0], y, 0.0), (hi[0], y, 0.0))]
    return np.asarray(seg, dtype=np.float64)


def blob_circles(blobs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """blobs (N, 4) [x, y, area, peak] -> (centres (N, 2), diameters (N,)) in Foxglove image coordinates.

    visionpos puts pixel centres at integer coordinates; Foxglove's image annotations put the origin
    at the top-left corner of the top-left pixel, so its centre is (0.5, 0.5). The diameter is the
    blob's equivalent circle, at least MIN_BLOB_DIAMETER_PX.
    """
    b = np.asarray(blobs, dtype=np.float64).reshape(-1, 4)
    return b[:, :2] + 0.5, np.maximum(2.0 * np.sqrt(np.maximum(b[:, 2], 0.0) / math.pi), MIN_BLOB_DIAMETER_PX)


# ---------------------------------------------------------------- messages


def _vec(p: np.ndarray) -> dict[str, float]:
    return {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}


def _quat(q: np.ndarray) -> dict[str, float]:
    return {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])}


def _points(p: np.ndarray) -> list[dict[str, float]]:
    return [{"x": x, "y": y, "z": z} for x, y, z in np.asarray(p, dtype=np.float64).tolist()]


def _axes_points(length_m: float) -> list[bytes]:
    axes = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0], [0, 1, 0], [0, 0, 0], [0, 0, 1]], dtype=np.float64) * length_m
    return [encode("foxglove.Point3", p) for p in _points(axes)]


_BODY_AXES = _axes_points(AXES_LENGTH_M)


def _lines(points: np.ndarray | list[bytes], color: dict[str, float] | None = None,
           colors: list[Any] | None = None, thickness_px: float = 2.0) -> dict[str, Any]:
    pts = points if isinstance(points, list) else _points(points)
    line: dict[str, Any] = {"type": _LINE_LIST, "pose": _IDENTITY, "thickness": thickness_px, "scale_invariant": True,
                            "points": pts}
    if colors is not None:
        line["colors"] = colors
    else:
        line["color"] = color
    return line


def _text(text: str, position: np.ndarray, size_px: float = 14.0) -> dict[str, Any]:
    return {"pose": {"position": _vec(position), "orientation": _NO_ROTATION}, "billboard": True,
            "font_size": size_px, "scale_invariant": True, "color": _LABEL_COLOR, "text": text}


@lru_cache(maxsize=64)
def _camera_pose(camera: Camera) -> tuple[bytes, bytes, np.ndarray]:
    """A camera's frame in the world: encoded Vector3 and Quaternion, and its centre (3,)."""
    tr, q = camera_in_world(camera.R, camera.t)
    return encode("foxglove.Vector3", _vec(tr)), encode("foxglove.Quaternion", _quat(q)), tr


def frame_transforms(time_ns: int, cameras: list[Camera]) -> dict[str, Any]:
    """foxglove.FrameTransforms: world -> camera_<id> for every calibrated camera."""
    out = []
    for c in cameras:
        tr, q, _ = _camera_pose(c)
        out.append({"timestamp": time_msg(time_ns), "parent_frame_id": WORLD_FRAME,
                    "child_frame_id": camera_frame_id(c.id), "translation": tr, "rotation": q})
    return {"transforms": out}


@lru_cache(maxsize=8)
def _arena_entities(cameras: tuple[Camera, ...]) -> tuple[dict[str, Any], ...]:
    """The arena's entities without their timestamps, primitives encoded (they never change)."""
    world = {"frame_id": WORLD_FRAME, "id": "world", "frame_locked": True,
             "lines": [encode("foxglove.LinePrimitive", _lines(_axes_points(0.5), colors=_AXES_COLORS,
                                                                thickness_px=3.0))]}
    entities = [world]
    if cameras:
        centres = np.array([_camera_pose(c)[2] for c in cameras])
        lo, hi = centres[:, :2].min(axis=0), centres[:, :2].max(axis=0)
        grid = _lines(grid_segments(lo, hi), color=GREY, thickness_px=1.0)
        entities.append({"frame_id": WORLD_FRAME, "id": "floor", "frame_locked": True,
                         "lines": [encode("foxglove.LinePrimitive", grid)]})
    for c in cameras:
        m = c.model
        frustum = _lines(frustum_segments(m.K, m.width, m.height), color=CAMERA_COLOR)
        entities.append({"frame_id": camera_frame_id(c.id), "id": f"camera/{c.id}", "frame_locked": True,
                         "metadata": [{"key": "name", "value": c.name}, {"key": "model", "value": m.kind}],
                         "lines": [encode("foxglove.LinePrimitive", frustum)],
                         "texts": [encode("foxglove.TextPrimitive", _text(f"{c.id} {c.name}".strip(), np.zeros(3)))]})
    return tuple(entities)


def arena_scene(time_ns: int, cameras: list[Camera]) -> dict[str, Any]:
    """foxglove.SceneUpdate: the world axes, a floor grid under the cameras, each camera's frustum and name."""
    ts = time_msg(time_ns)
    return {"entities": [{"timestamp": ts, **e} for e in _arena_entities(tuple(cameras))]}


def body_entity_id(name: str) -> str:
    return f"body/{name}"


def body_entity(state: Any, lifetime_ns: int) -> dict[str, Any]:
    """SceneEntity of one tracked BodyState: its axes (x red, y green, z blue) at its pose, and its name.

    The entity expires after lifetime_ns unless replaced, so a pose is never shown stale.
    """
    pose = {"position": _vec(state.position), "orientation": _quat(state.quaternion)}
    line = _lines(_BODY_AXES, colors=_AXES_COLORS, thickness_px=4.0)
    line["pose"] = pose
    label = _text(state.name, state.position + np.array([0.0, 0.0, 0.6 * AXES_LENGTH_M]))
    return {"timestamp": time_msg(state.time_ns), "frame_id": WORLD_FRAME, "id": body_entity_id(state.name),
            "lifetime": time_msg(lifetime_ns),
            "metadata": [{"key": "body_id", "value": str(int(state.body_id))},
                         {"key": "n_markers", "value": str(int(state.n_markers))},
                         {"key": "n_cameras", "value": str(int(state.n_cameras))}],
            "lines": [line], "texts": [label]}


def bodies_scene(time_ns: int, tracked: list[Any], lost: list[str], lifetime_ns: int) -> dict[str, Any]:
    """foxglove.SceneUpdate: every tracked body as an entity, a deletion for each body just lost."""
    return {"deletions": [{"timestamp": time_msg(time_ns), "id": body_entity_id(n)} for n in lost],
            "entities": [body_entity(s, lifetime_ns) for s in tracked]}


def markers_scene(time_ns: int, points: np.ndarray, lifetime_ns: int) -> dict[str, Any]:
    """foxglove.SceneUpdate: loose markers (N, 3) as spheres of one entity that expires after lifetime_ns."""
    spheres = [{"pose": encode("foxglove.Pose", {"position": p, "orientation": _NO_ROTATION}), "size": _MARKER_SIZE,
                "color": _MARKER_COLOR} for p in _points(np.asarray(points, dtype=np.float64).reshape(-1, 3))]
    return {"entities": [{"timestamp": time_msg(time_ns), "frame_id": WORLD_FRAME, "id": "markers",
                          "lifetime": time_msg(lifetime_ns), "spheres": spheres}]}


def image_annotations(capture_ns: int, blobs: np.ndarray) -> dict[str, Any]:
    """foxglove.ImageAnnotations: one circle per blob, in the camera's pixel coordinates."""
    ts = time_msg(capture_ns)
    centres, diameters = blob_circles(blobs)
    return {"timestamp": ts, "circles": [
        {"timestamp": ts, "position": {"x": x, "y": y}, "diameter": d, "thickness": BLOB_THICKNESS_PX,
         "outline_color": BLOB_COLOR} for (x, y), d in zip(centres.tolist(), diameters.tolist())]}


_DOUBLE = struct.Struct("<d")


@lru_cache(maxsize=256)
def _circles_struct(n: int, head: int, tail: int) -> struct.Struct:
    return struct.Struct("<" + f"{head}sdBdBd{tail}s" * n)


def encode_image_annotations(capture_ns: int, blobs: np.ndarray) -> bytes:
    """encode("foxglove.ImageAnnotations", image_annotations(capture_ns, blobs)), written directly:
    this runs for every camera at the channel rate. The circles differ only in centre and diameter
    (blob_circles, per blob here: numpy's per-call cost is larger for a few blobs), so they are
    one struct of constant bytes and those three doubles."""
    ts = encode("google.protobuf.Timestamp", time_msg(capture_ns))
    head = len_field(1, ts) + bytes([0x12, 18, 0x09])  # timestamp (1); position (2): Point2 of 18 bytes, x (1)
    tail = b"\x21" + _DOUBLE.pack(BLOB_THICKNESS_PX) + len_field(6, _BLOB_COLOR)  # thickness (4), outline_color (6)
    head = b"\x0a" + varint(len(head) + 26 + len(tail)) + head  # ImageAnnotations.circles (1), all the same length
    args: list[Any] = []
    for x, y, area, _ in blobs.tolist():
        x += 0.5
        y += 0.5
        if not (x and y):  # proto3 leaves a zero coordinate out: the fixed layout would not be canonical
            return encode("foxglove.ImageAnnotations", image_annotations(capture_ns, blobs))
        d = 2.0 * math.sqrt(area / math.pi) if area > 0 else 0.0
        # Point2.y (2), diameter (3): never 0
        args += (head, x, 0x11, y, 0x19, d if d > MIN_BLOB_DIAMETER_PX else MIN_BLOB_DIAMETER_PX, tail)
    body = _circles_struct(len(args) // 7, len(head), len(tail)).pack(*args) if args else b""
    return body + len_field(5, ts)  # ImageAnnotations.timestamp (5)


def camera_calibration(time_ns: int, camera: Camera) -> dict[str, Any]:
    """foxglove.CameraCalibration of a camera (ROS CameraInfo conventions: K row-major, P = [K | 0]).

    distortion_model: "plumb_bob" (k1, k2, p1, p2, k3), "rational_polynomial" (8 coefficients) or
    "kannala_brandt" (fisheye k1..k4), the names Foxglove knows.
    """
    m = camera.model
    K = np.asarray(m.K, dtype=np.float64)
    d = np.asarray(m.dist, dtype=np.float64).ravel()
    if m.kind == "fisheye":  # the model stores k1..k4
        model, D = "kannala_brandt", d[:4]
    elif d[5:].any():  # the model stores 8 pinhole coefficients, k4..k6 zero unless rational
        model, D = "rational_polynomial", d[:8]
    else:
        model, D = "plumb_bob", d[:5]
    P = np.hstack([K, np.zeros((3, 1))])
    return {"timestamp": time_msg(time_ns), "frame_id": camera_frame_id(camera.id), "width": m.width,
            "height": m.height, "distortion_model": model, "D": D.tolist(), "K": K.ravel().tolist(),
            "R": np.eye(3).ravel().tolist(), "P": P.ravel().tolist()}


def log_message(time_ns: int, level: int, name: str, text: str) -> dict[str, Any]:
    """foxglove.Log."""
    return {"timestamp": time_msg(time_ns), "level": level, "message": text, "name": name}


def health_log(time_ns: int, health: dict[str, Any]) -> dict[str, Any]:
    """foxglove.Log of a server health snapshot: one line per camera; WARNING when a camera does not
    stream or packets failed authentication or parsing, else INFO."""
    lines, bad = [], False
    for cid, cam in sorted((health.get("cameras") or {}).items(), key=lambda kv: str(kv[0])):
        if not isinstance(cam, dict):
            continue
        state = cam.get("state", "?")
        bad |= state != "streaming"
        lat = cam.get("latency_ms")
        lat_txt = f", latency {lat:.1f} ms" if isinstance(lat, (int, float)) else ""
        loss = cam.get("loss_recent", 0.0) or 0.0
        lines.append(f"camera {cid} {cam.get('name', '')}: {state}, {cam.get('fps', 0):.0f} fps, "
                     f"loss {100 * loss:.1f} %{lat_txt}")
    problems = {k: health.get(k) for k in ("malformed", "auth_failed", "pipeline_errors") if health.get(k)}
    if problems:
        bad = True
        lines.append(", ".join(f"{k} {v}" for k, v in problems.items()))
    if isinstance(health.get("late_ticks"), int) and health.get("ticks"):
        lines.append(f"ticks {health['ticks']}, late {health['late_ticks']}")
    return log_message(time_ns, LOG_WARNING if bad else LOG_INFO, "visionpos.health",
                       "\n".join(lines) or "no cameras")
