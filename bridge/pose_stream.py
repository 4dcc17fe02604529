"""UDP pose stream: every body's state at the output rate, JSON lines or binary.

Format (docs/pose-stream.md is the reference):
- json: each datagram holds one or more lines, one JSON object per body,
  each ending in '\\n'. Lines are never split across datagrams.
- binary: little-endian; a 24-byte header then one 208-byte record per body
  (HEADER_DTYPE, RECORD_DTYPE below; numpy reads it in one call).
- loose markers (`markers: true`): datagrams of their own, never mixed with
  bodies: one JSON object with a "markers" key, or binary magic VPM1
  (MARKER_HEADER_DTYPE, MARKER_DTYPE).

publish() runs on the server's loop: it encodes and calls sendto() on a
non-blocking socket; a full socket buffer drops the datagram (counted).
"""

from __future__ import annotations

import json
import math
import socket
import time
from typing import Any, Callable

import numpy as np

from bridge.config import PoseStreamConfig, is_multicast, parse_pose_stream
from bridge.transport import RateGrid, pack_datagrams
from visionpos.config.arena import ArenaConfig
from visionpos.messages import BodyState, LoosePoints
from visionpos.server.sinks import Sink

MAGIC = b"VPS1"
VERSION = 1
MAX_DATAGRAM = 8192  # JSON: lines are packed up to this size (fits any LAN's reassembly comfortably)

HEADER_DTYPE = np.dtype([
    ("magic", "S4"),  # b"VPS1"
    ("version", "<u1"),  # 1
    ("n_bodies", "<u1"),
    ("record_size", "<u2"),  # 208: lets a client skip records of a newer, longer layout
    ("seq", "<u4"),  # datagram counter, wraps
    ("reserved", "<u4"),
    ("sent_ns", "<i8"),  # server monotonic clock at send
])
RECORD_DTYPE = np.dtype([
    ("body_id", "<u2"),
    ("flags", "<u1"),  # bit 0: tracked
    ("n_markers", "<u1"),
    ("n_cameras", "<u1"),
    ("reset_counter", "<u1"),
    ("reserved", "<u2"),
    ("time_ns", "<i8"),  # instant the state is valid for (server monotonic ns)
    ("capture_ns", "<i8"),  # capture time of the newest contributing frame
    ("position", "<f8", (3,)),  # m, world z-up
    ("quaternion", "<f4", (4,)),  # x y z w, body FLU -> world
    ("velocity", "<f4", (3,)),  # m/s world
    ("angular_velocity", "<f4", (3,)),  # rad/s body
    ("residual_mm", "<f4"),
    ("covariance", "<f4", (21,)),  # pose 6x6 [x y z rx ry rz] upper triangle, row-major
    ("velocity_covariance", "<f4", (6,)),  # 3x3 upper triangle, row-major
    ("reserved2", "<u8"),
])
assert HEADER_DTYPE.itemsize == 24 and RECORD_DTYPE.itemsize == 208

MARKER_MAGIC = b"VPM1"
MARKER_HEADER_DTYPE = np.dtype([
    ("magic", "S4"),  # b"VPM1"
    ("version", "<u1"),  # 1
    ("reserved", "<u1"),
    ("n_markers", "<u2"),
    ("seq", "<u4"),  # datagram counter, wraps
    ("reserved2", "<u4"),
    ("time_ns", "<i8"),  # capture-clock time of the fusion that triangulated them
    ("sent_ns", "<i8"),
])
MARKER_DTYPE = np.dtype([
    ("position", "<f8", (3,)),  # m, world z-up
    ("residual_px", "<f4"),  # RMS reprojection residual
    ("reserved", "<u4"),
])
assert MARKER_HEADER_DTYPE.itemsize == 32 and MARKER_DTYPE.itemsize == 32
MAX_MARKERS_PER_DATAGRAM = 250

_UT6 = np.triu_indices(6)
_UT3 = np.triu_indices(3)


def _num(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None  # JSON has no NaN: null


def _round(a: np.ndarray, nd: int) -> list:
    return [_num(round(float(x), nd)) for x in np.asarray(a, float).ravel()]


def state_to_json(st: BodyState, sent_ns: int) -> dict:
    """One body as a JSON-ready dict (names and units in docs/pose-stream.md)."""
    return {
        "name": st.name,
        "id": int(st.body_id),
        "tracked": bool(st.tracked),
        "time_ns": int(st.time_ns),
        "capture_ns": int(st.capture_ns),
        "sent_ns": int(sent_ns),
        "position": _round(st.position, 6),
        "quaternion": _round(st.quaternion, 7),
        "velocity": _round(st.velocity, 5),
        "angular_velocity": _round(st.angular_velocity, 5),
        "covariance": [_num(float(f"{x:.6g}")) for x in np.asarray(st.covariance, float)[_UT6]],
        "velocity_covariance": [_num(float(f"{x:.6g}")) for x in np.asarray(st.velocity_covariance, float)[_UT3]],
        "n_markers": int(st.n_markers),
        "n_cameras": int(st.n_cameras),
        "residual_mm": _num(round(float(st.residual_mm), 4)),
        "reset_counter": int(st.reset_counter),
    }


# The line of a body whose numbers are all finite, in one %-format: it runs once per body per tick on the
# server's loop, where building the dict of state_to_json and json.dumps cost ~10x more. %.6f and round(x, 6)
# both round the exact binary value correctly, so a parser reads the same numbers from either.
_JSON_LINE = (
    '{"name":%s,"id":%d,"tracked":%s,"time_ns":%d,"capture_ns":%d,"sent_ns":%d,'
    '"position":[%.6f,%.6f,%.6f],"quaternion":[%.7f,%.7f,%.7f,%.7f],'
    '"velocity":[%.5f,%.5f,%.5f],"angular_velocity":[%.5f,%.5f,%.5f],'
    '"covariance":[' + ",".join(["%.6g"] * 21) + '],"velocity_covariance":[' + ",".join(["%.6g"] * 6) + '],'
    '"n_markers":%d,"n_cameras":%d,"residual_mm":%.4f,"reset_counter":%d}\n'
)
_json_names: dict[str, str] = {}


def _json_line(st: BodyState, sent_ns: int) -> bytes:
    """One body as a JSON line: the %-format above when every number is finite, else (NaN -> null)
    json.dumps of state_to_json."""
    numbers = np.concatenate((st.position, st.quaternion, st.velocity, st.angular_velocity,
                              np.asarray(st.covariance, float)[_UT6],
                              np.asarray(st.velocity_covariance, float)[_UT3], (st.residual_mm,)))
    if not np.isfinite(numbers).all():
        return json.dumps(state_to_json(st, sent_ns), separators=(",", ":")).encode() + b"\n"
    name = _json_names.get(st.name)
    if name is None:
        name = _json_names.setdefault(st.name, json.dumps(st.name))
    values = numbers.tolist()
    return (_JSON_LINE % (name, st.body_id, "true" if st.tracked else "false", st.time_ns, st.capture_ns, sent_ns,
                          *values[:-1], st.n_markers, st.n_cameras, values[-1], st.reset_counter)).encode()


def encode_json(states: list[BodyState], sent_ns: int) -> list[bytes]:
    """States -> datagrams of JSON lines (each <= MAX_DATAGRAM unless one line is larger)."""
    return pack_datagrams([_json_line(st, sent_ns) for st in states], MAX_DATAGRAM)


def encode_binary(states: list[BodyState], sent_ns: int, seq: int) -> list[bytes]:
    """States -> binary datagrams (at most 255 bodies each)."""
    out = []
    for i in range(0, max(len(states), 1), 255):
        chunk = states[i:i + 255]
        h = np.zeros(1, HEADER_DTYPE)
        h["magic"], h["version"], h["n_bodies"] = MAGIC, VERSION, len(chunk)
        h["record_size"], h["seq"], h["sent_ns"] = RECORD_DTYPE.itemsize, seq & 0xFFFFFFFF, sent_ns
        r = np.zeros(len(chunk), RECORD_DTYPE)
        if chunk:
            r["body_id"] = [s.body_id for s in chunk]
            r["flags"] = [1 if s.tracked else 0 for s in chunk]
            r["n_markers"] = np.clip([s.n_markers for s in chunk], 0, 255)
            r["n_cameras"] = np.clip([s.n_cameras for s in chunk], 0, 255)
            r["reset_counter"] = [s.reset_counter % 256 for s in chunk]
            r["time_ns"] = [s.time_ns for s in chunk]
            r["capture_ns"] = [s.capture_ns for s in chunk]
            r["position"] = np.stack([s.position for s in chunk])
            r["quaternion"] = np.stack([s.quaternion for s in chunk])
            r["velocity"] = np.stack([s.velocity for s in chunk])
            r["angular_velocity"] = np.stack([s.angular_velocity for s in chunk])
            r["residual_mm"] = [s.residual_mm for s in chunk]
            r["covariance"] = np.stack([s.covariance for s in chunk])[:, _UT6[0], _UT6[1]]
            r["velocity_covariance"] = np.stack([s.velocity_covariance for s in chunk])[:, _UT3[0], _UT3[1]]
        out.append(h.tobytes() + r.tobytes())
    return out


def encode_markers_json(lp: LoosePoints, sent_ns: int) -> list[bytes]:
    """Loose markers -> JSON datagrams: {"markers": [[x, y, z], ...], "residual_px": [...], "time_ns", "sent_ns"}."""
    pts = np.asarray(lp.points, float).reshape(-1, 3)
    res = np.asarray(lp.residual_px, float).ravel()
    out = []
    for i in range(0, max(len(pts), 1), MAX_MARKERS_PER_DATAGRAM):
        sl = slice(i, i + MAX_MARKERS_PER_DATAGRAM)
        obj = {
            "markers": [_round(p, 6) for p in pts[sl]],
            "residual_px": _round(res[sl], 3) if len(res) == len(pts) else [],
            "time_ns": int(lp.time_ns),
            "sent_ns": int(sent_ns),
        }
        out.append(json.dumps(obj, separators=(",", ":")).encode() + b"\n")
    return out


def encode_markers_binary(lp: LoosePoints, sent_ns: int, seq: int) -> list[bytes]:
    """Loose markers -> binary datagrams (VPM1 header + 32-byte records)."""
    pts = np.asarray(lp.points, float).reshape(-1, 3)
    res = np.asarray(lp.residual_px, float).ravel()
    out = []
    for i in range(0, max(len(pts), 1), MAX_MARKERS_PER_DATAGRAM):
        chunk = pts[i:i + MAX_MARKERS_PER_DATAGRAM]
        h = np.zeros(1, MARKER_HEADER_DTYPE)
        h["magic"], h["version"], h["n_markers"] = MARKER_MAGIC, VERSION, len(chunk)
        h["seq"], h["time_ns"], h["sent_ns"] = seq & 0xFFFFFFFF, lp.time_ns, sent_ns
        r = np.zeros(len(chunk), MARKER_DTYPE)
        r["position"] = chunk
        r["residual_px"] = res[i:i + len(chunk)] if len(res) == len(pts) else np.nan
        out.append(h.tobytes() + r.tobytes())
    return out


def _header(buf: bytes, dtype: np.dtype, magic: bytes, what: str) -> np.void:
    """The header record of a datagram, checked for size and magic (ValueError naming `what`)."""
    if len(buf) < dtype.itemsize:
        raise ValueError(f"{what} datagram too short ({len(buf)} bytes)")
    h = np.frombuffer(buf, dtype, count=1)[0]
    if bytes(h["magic"]) != magic:
        raise ValueError(f"not a visionpos {what} datagram (magic {bytes(h['magic'])!r})")
    return h


def decode_markers_binary(buf: bytes) -> tuple[np.void, np.ndarray]:
    """VPM1 datagram -> (header record, (n,) MARKER_DTYPE array). ValueError on a bad datagram."""
    h = _header(buf, MARKER_HEADER_DTYPE, MARKER_MAGIC, "marker")
    n = int(h["n_markers"])
    if len(buf) < MARKER_HEADER_DTYPE.itemsize + n * MARKER_DTYPE.itemsize:
        raise ValueError(f"marker datagram truncated: {n} markers need more than {len(buf)} bytes")
    return h, np.frombuffer(buf, MARKER_DTYPE, count=n, offset=MARKER_HEADER_DTYPE.itemsize).copy()


def decode_binary(buf: bytes) -> tuple[np.void, np.ndarray]:
    """Binary datagram -> (header record, (n,) RECORD_DTYPE array). ValueError on a bad datagram."""
    h = _header(buf, HEADER_DTYPE, MAGIC, "pose stream")
    n, size = int(h["n_bodies"]), int(h["record_size"])
    if size < RECORD_DTYPE.itemsize or len(buf) < HEADER_DTYPE.itemsize + n * size:
        raise ValueError(f"pose stream datagram truncated: {n} records of {size} bytes need more than {len(buf)} bytes")
    body = np.frombuffer(buf, np.uint8, count=n * size, offset=HEADER_DTYPE.itemsize).reshape(n, size)
    recs = body[:, : RECORD_DTYPE.itemsize].copy().view(RECORD_DTYPE).reshape(n)
    return h, recs


def upper_to_full(ut: np.ndarray, n: int) -> np.ndarray:
    """(..., n(n+1)/2) upper triangle, row-major -> (..., n, n) symmetric."""
    ut = np.asarray(ut, float)
    iu = np.triu_indices(n)
    m = np.zeros(ut.shape[:-1] + (n, n))
    m[..., iu[0], iu[1]] = ut
    m[..., iu[1], iu[0]] = ut
    return m


class PoseStream(Sink):
    """Sends every body's state to the configured destinations.

    PoseStream(cfg) with a PoseStreamConfig, or PoseStream.to("127.0.0.1:5005", format="json").
    start() opens the socket; publish(states) sends (rate-limited to
    cfg.rate_hz when set); close(); stats().
    """

    def __init__(self, cfg: PoseStreamConfig, clock_ns: Callable[[], int] = time.monotonic_ns):
        self.cfg = cfg
        self.clock_ns = clock_ns
        self.sock: socket.socket | None = None
        self.seq = 0
        self.counters = {"ticks": 0, "datagrams": 0, "bytes": 0, "send_errors": 0, "skipped_rate": 0,
                         "marker_sets": 0}
        self._grid = RateGrid(cfg.rate_hz)

    @classmethod
    def from_arena(cls, arena: ArenaConfig) -> "PoseStream | None":
        cfg = parse_pose_stream(arena)
        return None if cfg is None else cls(cfg)

    @classmethod
    def to(cls, *destinations: str, format: str = "json", rate_hz: float = 0.0, **kw) -> "PoseStream":
        """Standalone use: PoseStream.to('127.0.0.1:5005')."""
        dests = []
        for d in destinations:
            host, _, port = d.rpartition(":")
            dests.append((host, int(port)))
        clock = kw.pop("clock_ns", time.monotonic_ns)
        return cls(PoseStreamConfig(tuple(dests), format=format, rate_hz=rate_hz, **kw), clock_ns=clock)

    def opens(self) -> dict[str, Any]:
        return {"pose_stream.destinations": ", ".join(f"{h}:{p}" for h, p in self.cfg.destinations)}

    def start(self) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        if any(is_multicast(h) for h, _ in self.cfg.destinations):
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, self.cfg.multicast_ttl)
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1 if self.cfg.multicast_loopback else 0)
            if self.cfg.multicast_interface:
                s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(self.cfg.multicast_interface))
        s.setblocking(False)
        self._dests = [(socket.gethostbyname(h), p) for h, p in self.cfg.destinations]
        self.sock = s

    def publish(self, states: list[BodyState]) -> None:
        if self.sock is None:
            return
        now = self.clock_ns()
        if not self._grid.due(now):
            self.counters["skipped_rate"] += 1
            return
        if not self.cfg.include_untracked:
            states = [s for s in states if s.tracked]
        if not states:
            return
        self.counters["ticks"] += 1
        self.seq += 1
        if self.cfg.format == "binary":
            grams = encode_binary(states, now, self.seq)
        else:
            grams = encode_json(states, now)
        self._send(grams)

    def publish_markers(self, lp: LoosePoints) -> None:
        """Send a new set of loose markers (when `markers: true`), in datagrams of their own."""
        if self.sock is None or not self.cfg.markers:
            return
        now = self.clock_ns()
        self.counters["marker_sets"] += 1
        self.seq += 1
        if self.cfg.format == "binary":
            self._send(encode_markers_binary(lp, now, self.seq))
        else:
            self._send(encode_markers_json(lp, now))

    def _send(self, grams: list[bytes]) -> None:
        for g in grams:
            for d in self._dests:
                try:
                    self.sock.sendto(g, d)
                    self.counters["datagrams"] += 1
                    self.counters["bytes"] += len(g)
                except OSError:  # buffer full, no route, ICMP refused: drop, never block
                    self.counters["send_errors"] += 1

    def stats(self) -> dict:
        return dict(self.counters, destinations=[f"{h}:{p}" for h, p in self.cfg.destinations], format=self.cfg.format)

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None

