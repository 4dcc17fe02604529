"""`visionpos replay`: re-run the fusion pipeline on a recording, deterministically.

The recording holds every station datagram the live server accepted, with
its receive time on the server clock. Replay feeds them in order through the
server's own Ingest into a fresh FusionPipeline; the sequence and time rules
are checked again, but registrations are trusted (the HELLO cookie cannot be
re-checked: the live server's secret is gone) and tags are not verified, so a
recording replays without the key. Recordings of protocol version 1 (before
sessions and counters) are upgraded packet by packet (`V1Upgrade`). Output
ticks fall on a fixed grid of the recording's clock
(first receive time + k / output rate) and run before any packet received
after them. The vehicles' IMU samples the live pipeline took (topic /fusion/imu) are handed over again at the same
point of its input order: those a frame's push took just before that frame, those a tick took after the
replay's ticks up to that tick's time. Nothing reads the wall clock, so the same log and settings give
the same outputs, byte for byte (--speed only sleeps between steps).

Writes trajectories.csv; where the log carries ground truth also
metrics.json, a printed table and PNG plots (plots need matplotlib).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from visionpos import protocol as P
from visionpos.analysis import metrics as M
from visionpos.config.arena import (
    ArenaConfig,
    ConfigError,
    apply_overrides,
    load_yaml,
    parse_arena,
    resolve_config_path,
)
from visionpos.messages import BlobFrame, BodyState

# ---------------------------------------------------------------- results


@dataclass
class BodyTrack:
    """One body's outputs as arrays, one row per output tick (N rows).

    tick_ns: (N,) when the pipeline produced the state (recording clock);
    time_ns: (N,) the instant the state is valid for; capture_ns: (N,) newest
    contributing capture; position (N, 3) m; quaternion (N, 4) xyzw;
    velocity (N, 3) m/s; tracked (N,) bool; n_markers, n_cameras (N,) int;
    residual_mm (N,); update_kind (N,) str: "pose", "views" (single-camera updates through
    occlusion) or "" (BodyState.update_kind); position_sigma_mm (N,): root of the trace of the
    reported position covariance (NaN when not tracked).
    """

    name: str
    tick_ns: np.ndarray
    time_ns: np.ndarray
    capture_ns: np.ndarray
    position: np.ndarray
    quaternion: np.ndarray
    velocity: np.ndarray
    tracked: np.ndarray
    n_markers: np.ndarray
    n_cameras: np.ndarray
    residual_mm: np.ndarray
    update_kind: np.ndarray
    position_sigma_mm: np.ndarray

    @property
    def latency_ns(self) -> np.ndarray:
        """(N,) capture -> output time inside the pipeline."""
        return self.tick_ns - self.capture_ns

    @classmethod
    def from_states(cls, name: str, ticks: list[int], states: list[BodyState]) -> "BodyTrack":
        n = len(states)
        f = lambda attr, shape: np.array([getattr(s, attr) for s in states], dtype=np.float64).reshape((n, *shape))  # noqa: E731
        return cls(
            name=name,
            tick_ns=np.asarray(ticks, dtype=np.int64),
            time_ns=np.array([s.time_ns for s in states], dtype=np.int64),
            capture_ns=np.array([s.capture_ns for s in states], dtype=np.int64),
            position=f("position", (3,)),
            quaternion=f("quaternion", (4,)),
            velocity=f("velocity", (3,)),
            tracked=np.array([bool(s.tracked) for s in states], dtype=bool),
            n_markers=np.array([int(s.n_markers) for s in states], dtype=np.int64),
            n_cameras=np.array([int(s.n_cameras) for s in states], dtype=np.int64),
            residual_mm=np.array([float(s.residual_mm) for s in states], dtype=np.float64),
            update_kind=np.array([s.update_kind for s in states], dtype=str).reshape(n),
            position_sigma_mm=np.array([math.sqrt(s.covariance[0, 0] + s.covariance[1, 1] + s.covariance[2, 2]) * 1e3
                                        for s in states], dtype=np.float64),
        )


@dataclass
class ReplayResult:
    """Everything one replay produced. truth: name -> (times (T,), positions (T, 3), quats (T, 4))."""

    arena: ArenaConfig
    ticks_ns: np.ndarray
    bodies: dict[str, BodyTrack]
    truth: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
    n_packets: int = 0
    n_frames: int = 0
    n_bad: int = 0
    bad_reasons: dict[str, int] = field(default_factory=dict)
    span_ns: int = 0
    first_frame_ns: int | None = None
    wall_s: float = 0.0
    cpu_s: float = 0.0
    pipeline_stats: dict[str, Any] = field(default_factory=dict)

    @property
    def speed_x(self) -> float:
        """Recording time replayed per wall-clock second."""
        return self.span_ns * 1e-9 / self.wall_s if self.wall_s > 0 else float("inf")

    @property
    def speed_x_cpu(self) -> float:
        """Recording time replayed per CPU second of this process (robust to a busy machine)."""
        return self.span_ns * 1e-9 / self.cpu_s if self.cpu_s > 0 else float("inf")

    def metrics(self) -> list[M.BodyMetrics]:
        """Per-body metrics; error columns are nan for bodies without truth.

        tracked_fraction and rate_hz count the ticks from the first accepted
        frame on (registration and clock sync before it are not tracking time).
        """
        first = self.first_frame_ns if self.first_frame_ns is not None else (
            int(self.ticks_ns[0]) if len(self.ticks_ns) else 0)
        n_ticks = int(np.count_nonzero(self.ticks_ns >= first))
        span = int(self.ticks_ns[-1] - first) if len(self.ticks_ns) and self.ticks_ns[-1] > first else self.span_ns
        out = []
        for name, b in self.bodies.items():
            out.append(
                M.body_metrics(
                    name,
                    b.time_ns,
                    b.tracked,
                    b.position,
                    b.quaternion,
                    latencies_ns=b.latency_ns,
                    truth=self.truth.get(name),
                    n_ticks=n_ticks,
                    span_ns=span,
                )
            )
        return out


# ---------------------------------------------------------------- core


def load_settings(
    recorded_config: dict[str, Any] | None, config_path: str | None = None, overrides: Iterable[str] = ()
) -> ArenaConfig:
    """Arena for a replay: the recording's config (or --config), then --set overrides."""
    if config_path is not None:
        p = resolve_config_path(config_path)
        data, source = load_yaml(p), str(p)
    elif recorded_config:
        data, source = recorded_config, "recording config"
    else:
        raise ConfigError("recording", "config", "the log carries no arena config; pass --config arena.yaml")
    data = apply_overrides(data, list(overrides))
    return parse_arena(data, source)


def run_pipeline(
    arena: ArenaConfig,
    packets: Iterable[tuple[int, bytes] | tuple[int, bytes, Any]],
    rate_hz: float | None = None,
    speed: float | None = None,
    realtime_minus_monotonic_ns: int | None = None,
) -> ReplayResult:
    """Feed recorded datagrams through the server's own ingest into a fresh pipeline.

    packets: (recv_ns, datagram) or (recv_ns, datagram, (host, port)) in
    receive order. The server's Ingest does what it does live (registration,
    sequence and clock checks, HMAC when the arena names a key_file, cameras that
    vanish), on a clock that is the recording's receive time, so the only
    input is the log (packets may come with recorded IMU samples between them:
    RecordingReader.inputs). Ticks: t0 + k * period for k >= 1, t0 the first receive
    time; every tick at or before a packet's receive time runs before that
    packet (and the vanish check runs every 20 ms of recording time before a
    tick, as in the server), ticks continue to the last receive time.
    speed: None = as fast as possible, else sleep so recording time runs at
    speed x wall time. realtime_minus_monotonic_ns: the recording host's
    CLOCK_REALTIME - monotonic difference (from the recording's meta), used
    for stations that stamp in Timebase.REALTIME instead of this host's clocks.
    """
    from visionpos.recording.codec import ImuRecord

    loop = _ReplayLoop(arena, rate_hz, speed, realtime_minus_monotonic_ns)
    held = None  # the last packet: the IMU samples its frame's push took follow it in the recording
    for item in packets:
        if isinstance(item, ImuRecord):
            if item.at == "frame" and held is not None and item.log_ns == held[0][0]:
                held[1].append(item)
                continue
            if held is not None:
                loop.feed(*held)
                held = None
            loop.feed_imu(item)
        else:
            if held is not None:
                loop.feed(*held)
            held = (item, [])
    if held is not None:
        loop.feed(*held)
    return loop.result()


class _ReplayLoop:
    """run_pipeline's state: the server's Ingest and a fresh pipeline on the recording's clock, the tick grid,
    and each body's outputs at its ticks."""

    def __init__(self, arena: ArenaConfig, rate_hz: float | None, speed: float | None,
                 realtime_minus_monotonic_ns: int | None) -> None:
        from visionpos.fusion.pipeline import FusionPipeline
        from visionpos.server.ingest import Ingest
        from visionpos.server.service import VANISH_CHECK_S
        from visionpos.server.settings import ServerSettings

        self.arena = arena
        settings = ServerSettings.for_replay(arena)  # recordings are trusted: no key file needed
        self.period_ns = int(round(1e9 / float(rate_hz or settings.output_rate_hz)))
        self.check_ns = int(VANISH_CHECK_S * 1e9)
        self.speed = speed
        self.pipe = FusionPipeline(arena)
        self.now_ns = 0
        # the recording holds only what a live server accepted: trust its registrations, need no key
        self.ingest = Ingest(arena, settings, self.pipe, None, clock=lambda: self.now_ns, verify_cookies=False,
                             authenticate=False)
        self.upgrade = V1Upgrade()
        # the recording holds only what stations sent after their trigger: accept all of it
        self.ingest.set_start(-(1 << 62))
        if realtime_minus_monotonic_ns is not None:
            # live, Ingest converts realtime-stamped frames with this host's clocks; a replay must use
            # the recording host's difference
            self.ingest.realtime_minus_monotonic_ns = int(realtime_minus_monotonic_ns)
        self.imu_queue: list = []  # the recorded IMU samples the next frame's push takes (ImuRecord)
        self.pipe.add_imu_source(self._drain_imu)
        self.per_body: dict[str, tuple[list[int], list[BodyState]]] = {}
        self.ticks: list[int] = []
        self.t0 = self.next_tick = self.last = self.first_frame = None
        self.next_check = 0
        self.wall0 = time.perf_counter()
        self.cpu0 = time.process_time()

    def _drain_imu(self, push) -> None:
        q, self.imu_queue = self.imu_queue, []
        for r in q:
            push(r.body, r.t_ns, r.accel, r.gyro, r.lever_arm)

    def _ticks_to(self, t_ns: int, before: bool = False) -> None:
        """The ticks due up to t_ns (before: strictly before it)."""
        while self.next_tick < t_ns + (not before):
            self._pace(self.next_tick)
            self._tick(self.next_tick)
            self.next_tick += self.period_ns

    def feed_imu(self, r) -> None:
        """One recorded IMU sample (ImuRecord) a tick took (or one without its frame): the ticks due before its
        log time, then the sample into the pipeline (a tick at that time takes it, as the tick that did live)."""
        if self.t0 is not None:
            self._ticks_to(r.log_ns, before=True)
        self.pipe.push_imu(r.body, r.t_ns, r.accel, r.gyro, r.lever_arm)

    def feed(self, item: tuple, imu: list | None = None) -> None:
        """One recorded datagram: the ticks due before it, then the datagram through Ingest; imu: the recorded
        IMU samples its frame's push took (ImuRecord), handed over by that push."""
        recv_ns, data = int(item[0]), item[1]
        if len(data) > 4 and data[4] == 1 and data[:4] == P.MAGIC:
            data = self.upgrade(data)
        addr = item[2] if len(item) > 2 and item[2] is not None else ("replay", 0)
        if self.t0 is None:
            self.t0 = recv_ns
            self.next_tick = recv_ns + self.period_ns
        self._ticks_to(recv_ns)
        self.last = recv_ns
        self.now_ns = recv_ns
        if imu:
            self.imu_queue.extend(imu)
        self.ingest.handle(data, addr, recv_ns)
        if self.first_frame is None and self.ingest.counters.frames_accepted:
            self.first_frame = recv_ns

    def _tick(self, t: int) -> None:
        self.now_ns = t
        if t >= self.next_check:
            self.next_check = t + self.check_ns
            self.ingest.check_vanished(t)
        self.ticks.append(t)
        for s in self.pipe.tick(t):
            tk, st = self.per_body.setdefault(s.name, ([], []))
            tk.append(t)
            st.append(s)

    def _pace(self, t: int) -> None:
        if self.speed:
            ahead = (t - self.t0) * 1e-9 / self.speed - (time.perf_counter() - self.wall0)
            if ahead > 0:
                time.sleep(ahead)

    def result(self) -> ReplayResult:
        """The replay's outputs and counters (the recording must have held station packets)."""
        wall = time.perf_counter() - self.wall0
        cpu = time.process_time() - self.cpu0
        if self.t0 is None:
            raise ValueError("the recording holds no station packets; record with stations streaming")
        names = [b.name for b in self.arena.bodies]
        order = names + sorted(set(self.per_body) - set(names))
        bodies = {n: BodyTrack.from_states(n, *self.per_body[n]) for n in order if n in self.per_body}
        try:
            stats = dict(self.pipe.stats())
        except Exception as e:  # stats are informative only; never fail a replay on them
            stats = {"error": str(e)}
        c = self.ingest.counters
        reasons = dict(c.malformed_reasons)
        for k in ("auth_failed", "unknown", "pipeline_errors"):
            if getattr(c, k):
                reasons[k] = getattr(c, k)
        return ReplayResult(
            arena=self.arena,
            ticks_ns=np.asarray(self.ticks, dtype=np.int64),
            bodies=bodies,
            truth={},
            n_packets=c.packets,
            n_frames=c.frames_accepted,
            n_bad=c.malformed + c.auth_failed,
            bad_reasons=reasons,
            span_ns=int(self.last - self.t0),
            first_frame_ns=self.first_frame,
            wall_s=wall,
            cpu_s=cpu,
            pipeline_stats=stats,
        )


class V1Upgrade:
    """Protocol-1 datagrams of an old recording -> the unsigned version-2 datagrams they stand for.

    Version 1 has no frame sessions and no control counters: a frame gets the session of its camera's
    latest HELLO (none: 0, so a camera that never registered stays unregistered, as live), and control
    messages get a counter that increases per camera. Packets that do not decode as v1 pass unchanged
    (ingest counts them as malformed).
    """

    def __init__(self) -> None:
        self.sessions: dict[int, int] = {}
        self.counters: dict[int, int] = {}

    def __call__(self, data: bytes) -> bytes:
        try:
            msg = P.decode_v1(data)
        except P.ProtocolError:
            return data
        cid = msg.camera_id
        if isinstance(msg, BlobFrame):
            return P.encode_frame(replace(msg, session=self.sessions.get(cid, 0)))
        if isinstance(msg, P.Hello) and self.sessions.get(cid) != msg.session:
            self.sessions[cid] = msg.session
            self.counters[cid] = 0
        self.counters[cid] = counter = self.counters.get(cid, 0) + 1
        if isinstance(msg, (P.Hello, P.Heartbeat, P.Bye)):
            return P.encode(replace(msg, counter=counter))
        return P.encode(replace(msg, counter=counter, session=self.sessions.get(cid, 0)))  # SyncRequest


def replay_log(
    log: str | Path,
    config: str | None = None,
    overrides: Iterable[str] = (),
    speed: float | None = None,
    rate_hz: float | None = None,
) -> ReplayResult:
    """Replay a recording file with optional config replacement and overrides."""
    from visionpos.recording import RecordingReader

    p = Path(log)
    if not p.exists():
        raise ConfigError(
            str(p), "(file)", "no such recording; make one with `visionpos sim --out` or `visionpos record`"
        )
    reader = RecordingReader(p)
    arena = load_settings(reader.config, config, overrides)
    meta = reader.meta or {}
    rt = None
    if isinstance(meta.get("wall_start_unix_ns"), int) and isinstance(meta.get("monotonic_start_ns"), int):
        rt = meta["wall_start_unix_ns"] - meta["monotonic_start_ns"]
    res = run_pipeline(arena, reader.inputs(), rate_hz=rate_hz, speed=speed,
                       realtime_minus_monotonic_ns=rt)
    res.truth = dict(reader.truth() or {})
    return res


# ---------------------------------------------------------------- outputs

CSV_HEADER = (
    "body,tick_ns,time_ns,capture_ns,x,y,z,qx,qy,qz,qw,vx,vy,vz,tracked,n_markers,n_cameras,residual_mm,"
    "update_kind,position_sigma_mm\n"
)


def _csv_rows(b: BodyTrack) -> Iterator[str]:
    for i in range(len(b.tick_ns)):
        p, q, v = b.position[i], b.quaternion[i], b.velocity[i]
        yield (
            f"{b.name},{b.tick_ns[i]},{b.time_ns[i]},{b.capture_ns[i]},"
            f"{p[0]:.6f},{p[1]:.6f},{p[2]:.6f},{q[0]:.8f},{q[1]:.8f},{q[2]:.8f},{q[3]:.8f},"
            f"{v[0]:.5f},{v[1]:.5f},{v[2]:.5f},{int(b.tracked[i])},{b.n_markers[i]},{b.n_cameras[i]},"
            f"{b.residual_mm[i]:.4f},{b.update_kind[i]},{b.position_sigma_mm[i]:.4f}\n"
        )


def write_trajectories_csv(result: ReplayResult, path: str | Path) -> Path:
    """One row per body per tick, bodies in config order then tick order. Deterministic text."""
    path = Path(path)
    with path.open("w", newline="") as f:
        f.write(CSV_HEADER)
        for b in result.bodies.values():
            f.writelines(_csv_rows(b))
    return path


METRIC_COLUMNS = [
    ("name", "body", ""),
    ("tracked_fraction", "tracked", ".3f"),
    ("rate_hz", "rate Hz", ".1f"),
    ("position_rmse_mm", "pos RMSE mm", ".2f"),
    ("position_max_mm", "pos max mm", ".2f"),
    ("rotation_rmse_deg", "rot RMSE deg", ".3f"),
    ("position_jitter_mm", "jitter mm", ".3f"),
    ("latency_p50_ms", "lat p50 ms", ".2f"),
    ("latency_p99_ms", "lat p99 ms", ".2f"),
]


def views_fraction(b: BodyTrack) -> float:
    """Share of a body's tracked outputs kept by single-camera updates (occlusion), 0 when never tracked."""
    n = int(np.count_nonzero(b.tracked))
    return float(np.count_nonzero(b.tracked & (b.update_kind == "views")) / n) if n else 0.0


def metrics_rows(result: ReplayResult) -> list[dict]:
    rows = []
    for m in result.metrics():
        d = m.as_dict()
        d["latency_p50_ms"] = m.latency_ms["p50"]
        d["latency_p99_ms"] = m.latency_ms["p99"]
        b = result.bodies[m.name]
        d["views_fraction"] = views_fraction(b)
        rows.append(d)
    return rows


def write_plots(result: ReplayResult, out: Path) -> list[Path]:
    """trajectory.png, errors.png (truth only), latency.png. Raises PlotsUnavailable without matplotlib."""
    from visionpos.analysis import plots

    t0 = int(result.ticks_ns[0]) if len(result.ticks_ns) else 0
    sec = lambda t: (np.asarray(t, dtype=np.int64) - t0) * 1e-9  # noqa: E731
    traj, errs, lats = {}, {}, {}
    for name, b in result.bodies.items():
        pos = np.where(b.tracked[:, None], b.position, np.nan)
        d = {"t": sec(b.time_ns), "position": pos}
        if name in result.truth:
            tt, tp, tq = result.truth[name]
            inside = (tt >= b.time_ns[0]) & (tt <= b.time_ns[-1]) if len(b.time_ns) else tt == tt
            d["truth_t"], d["truth_position"] = sec(tt[inside]), tp[inside]
            trp, trq, valid = M.interpolate_truth(tt, tp, tq, b.time_ns)
            ok = valid & b.tracked
            errs[name] = {
                "t": sec(b.time_ns),
                "position_error_mm": np.where(ok, M.position_errors(b.position, trp) * 1e3, np.nan),
                "rotation_error_deg": np.where(ok, np.degrees(M.rotation_errors(b.quaternion, trq)), np.nan),
            }
        traj[name] = d
        lats[name] = b.latency_ns[b.tracked] * 1e-6
    paths = [plots.plot_trajectories(out / "trajectory.png", traj)]
    if errs:
        paths.append(plots.plot_errors(out / "errors.png", errs))
    paths.append(plots.plot_latency(out / "latency.png", lats))
    return paths


def _json_safe(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def summary(result: ReplayResult) -> dict[str, Any]:
    """JSON-ready summary: per-body metrics and replay counters."""
    return _json_safe(
        {
            "bodies": metrics_rows(result),
            "has_truth": bool(result.truth),
            "duration_s": result.span_ns * 1e-9,
            "ticks": len(result.ticks_ns),
            "packets": result.n_packets,
            "frames": result.n_frames,
            "bad_packets": result.n_bad,
            "bad_reasons": result.bad_reasons,
            "replay_wall_s": result.wall_s,
            "replay_speed_x": result.speed_x,
            "replay_cpu_s": result.cpu_s,
        }
    )


def write_outputs(result: ReplayResult, out: str | Path, plots: bool = True) -> tuple[list[Path], str | None]:
    """trajectories.csv, metrics.json and (plots=True) the PNGs in folder `out`.

    Returns (files written, note): the note says why the plots are missing when matplotlib
    (the plots extra) is not installed; everything else is written anyway.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = [write_trajectories_csv(result, out / "trajectories.csv")]
    (out / "metrics.json").write_text(json.dumps(summary(result), indent=2, sort_keys=True) + "\n")
    written.append(out / "metrics.json")
    note = None
    if plots:
        try:
            written += write_plots(result, out)
        except ImportError as e:
            note = str(e)
    return written, note
