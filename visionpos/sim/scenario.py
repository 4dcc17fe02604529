"""Simulation scenario: an arena config plus its `sim` section, validated.

A Scenario is everything `capture.simulate` needs, fully resolved and
deterministic from `seed`: which bodies move how, each camera's frame timing,
each station's clock, the noise and nuisance models.

The `sim` section (all keys optional; defaults in brackets):

  duration: s of simulated capture [30]
  seed: integer seed of every random draw [0]
  start_time: s, server-clock time of the scenario start [1000]
  session: which entry of `sessions` runs [first one]
  sessions: {name: {body_name: {trajectory: KIND, ...}}}; body names come
      from `bodies` or `props` (see trajectories.from_config for the keys).
      Without sessions every body hovers at 1 m, spread along x.
  props: list of simulated-only bodies fusion does not track (calibration
      wand, L-frame): {name, markers, marker_diameter, occlusion}
  truth_rate: Hz of the fine ground-truth samples in SimResult [200]
  phase: random | zero: each camera's first exposure offset within a frame [random]
  timing_jitter_us: std of exposure instants around the frame grid
      (clipped at 4 std) [20]
  stamp_noise_us: std of white noise on reported capture stamps [0]
  clock_offset_ms: std of raw station clock offsets before sync [200]
  clock_drift_ppm: std of station crystal drift (frame periods stretch) [20]
  sync_residual_us: std of the offset error left after clock sync, per
      station: a constant part plus slow (0.01-0.2 Hz) wander [50]
  centroid_noise_px: std of blob centroid noise per axis [0.2]
  drop_probability: chance each frame is lost (its seq is skipped) [0.002]
  latency_ms: {mean [4], std [0.5], max [15]}: exposure -> server receive,
      gamma distributed, clipped at max
  spurious: {static_per_camera [2]: fixed floor reflections of the IR ring
      seen every frame, random_per_frame [0.02]: mean one-frame glints,
      floor_mirror [0]: brightness ratio of the markers' mirror images in a
      glossy floor (0 = matte floor; 0.3 = polished concrete)}
  occlusion: {enabled [true], disc_radius [0.05] m: a disc in the body's
      x-y plane at its origin (hub, battery) that hides markers of any body
      behind it, normal_cutoff_deg [105]: a marker is seen only from
      directions within this angle of its normal (body z tilted ~27 deg
      outward)}; bodies and props may override it
      with their own `occlusion` mapping
  brightness: {peak_at_1m [1000]: blob peak (0-255 scale, clipped) of a
      marker 1 m away, falling with range^2, min_peak [20]}
  merge_blobs: markers whose images overlap become one blob [true]
  max_blobs: a station sends at most this many blobs (FLAG_TRUNCATED) [64];
      at most visionpos.protocol.MAX_BLOBS_PER_PACKET (one datagram)
  rolling_shutter_ms: readout time from the first to the last row; 0 is a
      global shutter [0]. Pi camera modules are rolling-shutter (~10-30 ms
      full-frame readout); capture_ns then stamps the first row
  cameras: {camera_id: {fps, phase_ms, drop_probability, rolling_shutter_ms,
      enabled}} per-camera overrides
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from visionpos.camera.model import Camera
from visionpos.protocol import MAX_BLOBS_PER_PACKET
from visionpos.config.arena import (
    ArenaConfig,
    BodyConfig,
    Section,
    apply_overrides,
    load_yaml,
    parse_arena,
    resolve_config_path,
)
from visionpos.sim import trajectories as trj
from visionpos.sim.trajectories import Motion, Trajectory

_SIM_KEYS = {
    "duration", "seed", "start_time", "session", "sessions", "props", "truth_rate", "phase",
    "timing_jitter_us", "stamp_noise_us", "clock_offset_ms", "clock_drift_ppm", "sync_residual_us",
    "centroid_noise_px", "drop_probability", "latency_ms", "spurious", "occlusion", "brightness",
    "merge_blobs", "max_blobs", "cameras", "rolling_shutter_ms",
}  # fmt: skip

# stream tags for per-purpose random generators: rng([seed, TAG, ...])
TAG_TRAJ, TAG_CLOCK, TAG_PHASE, TAG_FRAMES, TAG_STATIC = 1, 2, 3, 4, 5


def rng_for(seed: int, *keys: int) -> np.random.Generator:
    """An independent generator for (seed, keys): same keys, same stream, any call order."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, *[int(k) & 0xFFFFFFFF for k in keys]])


@dataclass(frozen=True)
class StationClock:
    """One station's clock against the server clock (true time).

    raw reading = true + offset_ns + drift_ppm * 1e-6 * (true - start_ns);
    after clock sync the station's converted stamps are true + residual(true),
    residual = bias_ns + sum_k amp_ns[k] sin(2 pi freq_hz[k] t + phase[k]).
    """

    station_id: int
    offset_ns: int
    drift_ppm: float
    bias_ns: float
    amp_ns: np.ndarray
    freq_hz: np.ndarray
    phase: np.ndarray
    start_ns: int

    def raw_ns(self, true_ns: np.ndarray) -> np.ndarray:
        """Station's own clock reading (T,) int64 at true times (T,) int64."""
        dt = (np.asarray(true_ns, np.int64) - self.start_ns).astype(np.float64)
        return np.asarray(true_ns, np.int64) + self.offset_ns + np.round(dt * self.drift_ppm * 1e-6).astype(np.int64)

    def residual_ns(self, true_ns: np.ndarray) -> np.ndarray:
        """Sync error (T,) float ns of converted stamps at true times (T,) int64."""
        t = (np.asarray(true_ns, np.int64) - self.start_ns).astype(np.float64) * 1e-9
        arg = 2 * np.pi * t[:, None] * self.freq_hz[None] + self.phase[None]
        return self.bias_ns + (self.amp_ns[None] * np.sin(arg)).sum(axis=1)

    @property
    def residual_bound_ns(self) -> float:
        return abs(self.bias_ns) + float(np.abs(self.amp_ns).sum())


@dataclass(frozen=True)
class CameraTiming:
    """When a camera exposes: true time of frame k is
    start_ns + phase_ns + k * period_ns + jitter_k (|jitter_k| <= 4 jitter_ns)."""

    camera_id: int
    station_id: int
    fps: float
    phase_ns: float
    period_ns: float  # true-time period: nominal 1/fps on the station's drifting crystal
    jitter_ns: float
    stamp_noise_ns: float
    drop_probability: float
    readout_ns: float = 0.0  # rolling-shutter readout time, first row to last (0 = global shutter)


@dataclass(frozen=True)
class SimBody:
    """A simulated rigid body. markers (M, 3) body frame m; normals (M, 3) unit
    outward directions (body frame) a marker is seen from; tracked: listed in
    the arena's `bodies` (props are not)."""

    name: str
    id: int
    markers: np.ndarray
    marker_diameter: float
    trajectory: Trajectory
    normals: np.ndarray
    normal_cutoff_cos: float
    disc_radius: float
    tracked: bool


@dataclass(frozen=True)
class Scenario:
    """Everything the capture simulation needs; see the module docstring for the keys."""

    arena: ArenaConfig
    cameras: tuple[Camera, ...]
    timings: tuple[CameraTiming, ...]
    clocks: dict[int, StationClock]
    bodies: tuple[SimBody, ...]
    session: str
    duration_s: float
    seed: int
    start_ns: int
    truth_rate_hz: float
    centroid_noise_px: float
    latency_mean_ns: float
    latency_std_ns: float
    latency_max_ns: float
    static_spurious_per_camera: int
    random_spurious_per_frame: float
    floor_mirror: float
    occlusion: bool
    peak_at_1m: float
    min_peak: float
    merge_blobs: bool
    max_blobs: int
    raw: dict[str, Any] = field(default_factory=dict)

    @property
    def end_ns(self) -> int:
        return self.start_ns + int(round(self.duration_s * 1e9))

    def body(self, name: str) -> SimBody:
        for b in self.bodies:
            if b.name == name:
                return b
        raise KeyError(f"no simulated body '{name}'; bodies in session '{self.session}': {[b.name for b in self.bodies]}")

    def motion_at(self, body_name: str, times_ns: Any) -> Motion:
        """Full true motion of a body at server-clock times (T,) int64 ns."""
        return self.body(body_name).trajectory.sample_ns(times_ns, self.start_ns)

    def truth_at(self, body_name: str, times_ns: Any) -> tuple[np.ndarray, np.ndarray]:
        """True positions (T, 3) m and quaternions (T, 4) xyzw of a body at times (T,) int64 ns."""
        m = self.motion_at(body_name, times_ns)
        return m.positions, m.quaternions

    def with_changes(self, **changes: Any) -> "Scenario":
        """A copy with fields replaced (e.g. centroid_noise_px=0 for exact tests)."""
        return replace(self, **changes)


# ------------------------------------------------------------------ building
def _marker_normals(markers: np.ndarray) -> np.ndarray:
    """Mostly-up unit normals (M, 3): body z tilted ~27 deg outward along the
    marker's radial direction (a sphere on a post above the arm is seen from
    the upper hemisphere and a little below); markers on the axis face up."""
    c = markers.mean(axis=0)
    radial = markers[:, :2] - c[:2]
    r = np.linalg.norm(radial, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(r > 0.01, radial / r, 0.0)
    n = np.column_stack([0.5 * u, np.ones(len(markers))])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _occlusion_params(s: Section, default: tuple[float, float]) -> tuple[float, float]:
    if not s.data:
        return default
    extra = sorted(set(s.data) - {"enabled", "disc_radius", "normal_cutoff_deg"})
    if extra:
        raise s.error(extra[0], "unknown occlusion key; use disc_radius, normal_cutoff_deg (and enabled in sim.occlusion)")
    return (
        s.number("disc_radius", default[0], min=0.0, max=2.0),
        s.number("normal_cutoff_deg", default[1], min=0.0, max=180.0),
    )


def _props(sim: Section, arena: ArenaConfig) -> list[tuple[BodyConfig, Section]]:
    """Validate sim.props: simulated-only bodies {name, markers, marker_diameter, occlusion}."""
    out = []
    names = {b.name for b in arena.bodies}
    for p in sim.items("props"):
        extra = sorted(set(p.data) - {"name", "markers", "marker_diameter", "occlusion"})
        if extra:
            raise p.error(extra[0], "unknown prop key; use name, markers, marker_diameter, occlusion")
        name = p.string("name")
        if name in names:
            raise p.error("name", f"'{name}' is already a body or prop name; props need their own names")
        names.add(name)
        markers = p.array("markers", (None, 3))
        if len(markers) < 2:
            raise p.error("markers", f"a prop needs at least 2 markers, got {len(markers)}")
        d = np.linalg.norm(markers[:, None] - markers[None], axis=-1) + np.eye(len(markers)) * 1e9
        if d.min() < 0.01:
            raise p.error("markers", "two markers are closer than 10 mm; cameras cannot separate them")
        body = BodyConfig(name, 0, markers, p.number("marker_diameter", 0.014, min=0.001), p.data)
        out.append((body, p.sub("occlusion")))
    return out


def scenario_from_arena(arena: ArenaConfig, session: str | None = None, **overrides: Any) -> Scenario:
    """Resolve an arena's `sim` section into a Scenario.

    overrides: sim keys to replace (e.g. duration=5, seed=3, centroid_noise_px=0),
    applied before validation so bad values are reported like config errors.
    """
    raw_sim = dict(arena.raw.get("sim") or {})
    raw_sim.update(overrides)
    if session is not None:
        raw_sim["session"] = session
    sim = Section(raw_sim, arena.source, "sim")
    extra = sorted(set(sim.data) - _SIM_KEYS)
    if extra:
        raise sim.error(extra[0], f"unknown sim key; known keys: {sorted(_SIM_KEYS)}")

    seed = sim.integer("seed", 0, min=0)
    duration = sim.number("duration", 30.0, min=0.001)
    start_ns = int(round(sim.number("start_time", 1000.0, min=0.0) * 1e9))

    # ---- bodies: tracked ones and props, selected by the session
    occ = sim.sub("occlusion")
    extra = sorted(set(occ.data) - {"enabled", "disc_radius", "normal_cutoff_deg"})
    if extra:
        raise occ.error(extra[0], "unknown occlusion key; use enabled, disc_radius, normal_cutoff_deg")
    occ_enabled = occ.boolean("enabled", True)
    occ_default = (occ.number("disc_radius", 0.05, min=0.0, max=2.0), occ.number("normal_cutoff_deg", 105.0, min=0.0, max=180.0))
    candidates: dict[str, tuple[BodyConfig, Section, bool]] = {
        b.name: (b, Section(b.raw.get("occlusion"), arena.source, f"bodies[{i}].occlusion"), True)
        for i, b in enumerate(arena.bodies)
    }
    for b, o in _props(sim, arena):
        candidates[b.name] = (b, o, False)

    sessions = sim.sub("sessions")
    if sessions.data:
        names = list(sessions.data)
        session_name = sim.string("session", names[0])
        if session_name not in sessions.data:
            raise sim.error("session", f"'{session_name}' is not one of the sessions {names}")
        entries = sessions.sub(session_name)
    else:
        session_name = sim.string("session", "default")
        # no sessions: every tracked body hovers at 1 m, spread along x
        n = len(arena.bodies)
        entries = Section(
            {
                b.name: {"trajectory": "hover", "center": [0.6 * (i - (n - 1) / 2), 0.0, 1.0]}
                for i, b in enumerate(arena.bodies)
            },
            arena.source,
            "sim.sessions.default",
        )
    bodies: list[SimBody] = []
    used_ids: set[int] = set()
    for name in entries.data:
        spec = entries.sub(str(name))
        if name not in candidates:
            raise entries.error(str(name), f"no body or prop named '{name}'; known: {sorted(candidates)}")
        b, occ_s, tracked = candidates[name]
        traj = trj.from_config(spec, rng_for(seed, TAG_TRAJ, len(bodies)))
        disc, cutoff = _occlusion_params(occ_s, occ_default)
        disc, cutoff = _occlusion_params(spec.sub("occlusion"), (disc, cutoff))
        bid = b.id if tracked else 200 + len(bodies)
        while bid in used_ids:
            bid += 1
        used_ids.add(bid)
        bodies.append(
            SimBody(
                name=b.name,
                id=bid,
                markers=b.markers,
                marker_diameter=b.marker_diameter,
                trajectory=traj,
                normals=_marker_normals(b.markers),
                normal_cutoff_cos=float(np.cos(np.radians(cutoff))),
                disc_radius=disc,
                tracked=tracked,
            )
        )

    # ---- cameras and their stations' clocks
    cam_over = sim.sub("cameras")
    by_id = arena.camera_by_id()
    # keys are camera ids; --set sim.cameras.3.fps=60 makes them strings
    norm = {}
    for k, v in cam_over.data.items():
        kid = int(k) if isinstance(k, str) and k.strip().isdigit() else k
        if not isinstance(kid, int) or kid not in by_id:
            raise cam_over.error(str(k), f"no camera with id {k!r}; camera ids are {sorted(by_id)}")
        norm[kid] = v
    cam_over = Section(norm, cam_over.source, cam_over.path)
    phase_mode = sim.string("phase", "random", choices=("random", "zero"))
    jitter_ns = sim.number("timing_jitter_us", 20.0, min=0.0) * 1e3
    stamp_ns = sim.number("stamp_noise_us", 0.0, min=0.0) * 1e3
    offset_std = sim.number("clock_offset_ms", 200.0, min=0.0) * 1e6
    drift_std = sim.number("clock_drift_ppm", 20.0, min=0.0, max=1000.0)
    resid_std = sim.number("sync_residual_us", 50.0, min=0.0) * 1e3
    drop = sim.number("drop_probability", 0.002, min=0.0, max=1.0)
    readout_ms = sim.number("rolling_shutter_ms", 0.0, min=0.0, max=1000.0)
    cameras, timings = [], []
    clocks: dict[int, StationClock] = {}
    for cam in arena.cameras:
        co = cam_over.sub(cam.id) if cam.id in cam_over.data else Section({}, arena.source, f"sim.cameras.{cam.id}")
        if not co.boolean("enabled", True):
            continue
        fps = co.number("fps", cam.fps, min=0.1, max=10000.0)
        station = cam.id  # one camera per station, as the thesis stations are
        crng = rng_for(seed, TAG_CLOCK, station)
        drift = float(crng.normal(0.0, drift_std)) if drift_std > 0 else 0.0
        clocks[station] = StationClock(
            station_id=station,
            offset_ns=int(round(crng.normal(0.0, offset_std))) if offset_std > 0 else 0,
            drift_ppm=drift,
            bias_ns=float(crng.normal(0.0, resid_std / np.sqrt(2))),
            amp_ns=np.full(3, resid_std / np.sqrt(3)),
            freq_hz=crng.uniform(0.01, 0.2, 3),
            phase=crng.uniform(0, 2 * np.pi, 3),
            start_ns=start_ns,
        )
        period = 1e9 / fps / (1.0 + drift * 1e-6)
        if co.has("phase_ms"):
            phase = co.number("phase_ms", min=0.0) * 1e6
        elif phase_mode == "random":
            phase = float(rng_for(seed, TAG_PHASE, cam.id).uniform(0.0, period))
        else:
            phase = 0.0
        cameras.append(cam)
        timings.append(
            CameraTiming(
                camera_id=cam.id,
                station_id=station,
                fps=fps,
                phase_ns=phase,
                period_ns=period,
                jitter_ns=jitter_ns,
                stamp_noise_ns=stamp_ns,
                drop_probability=co.number("drop_probability", drop, min=0.0, max=1.0),
                readout_ns=co.number("rolling_shutter_ms", readout_ms, min=0.0, max=1e3 / fps) * 1e6,
            )
        )
    if not cameras:
        raise sim.error("cameras", "every camera is disabled; enable at least one")

    lat = sim.sub("latency_ms")
    spur = sim.sub("spurious")
    bright = sim.sub("brightness")
    for sec, keys in ((lat, {"mean", "std", "max"}), (spur, {"static_per_camera", "random_per_frame", "floor_mirror"}), (bright, {"peak_at_1m", "min_peak"})):
        extra = sorted(set(sec.data) - keys)
        if extra:
            raise sec.error(extra[0], f"unknown key; known keys: {sorted(keys)}")
    lat_mean = lat.number("mean", 4.0, min=0.0)
    lat_max = lat.number("max", max(15.0, 4 * lat_mean), min=lat_mean)
    return Scenario(
        arena=arena,
        cameras=tuple(cameras),
        timings=tuple(timings),
        clocks=clocks,
        bodies=tuple(bodies),
        session=session_name,
        duration_s=duration,
        seed=seed,
        start_ns=start_ns,
        truth_rate_hz=sim.number("truth_rate", 200.0, min=1.0, max=100000.0),
        centroid_noise_px=sim.number("centroid_noise_px", 0.2, min=0.0, max=50.0),
        latency_mean_ns=lat_mean * 1e6,
        latency_std_ns=lat.number("std", 0.5, min=0.0) * 1e6,
        latency_max_ns=lat_max * 1e6,
        static_spurious_per_camera=spur.integer("static_per_camera", 2, min=0, max=1000),
        random_spurious_per_frame=spur.number("random_per_frame", 0.02, min=0.0, max=1000.0),
        floor_mirror=spur.number("floor_mirror", 0.0, min=0.0, max=1.0),
        occlusion=occ_enabled,
        peak_at_1m=bright.number("peak_at_1m", 1000.0, min=1.0),
        min_peak=bright.number("min_peak", 20.0, min=0.0, max=255.0),
        merge_blobs=sim.boolean("merge_blobs", True),
        max_blobs=sim.integer("max_blobs", 64, min=1, max=MAX_BLOBS_PER_PACKET),
        raw=raw_sim,
    )


def load_scenario(
    name_or_path: str | Path = "thesis",
    overrides: list[str] | tuple[str, ...] = (),
    session: str | None = None,
    **sim_overrides: Any,
) -> Scenario:
    """Load an arena ('thesis', 'arena8' or a path) and build its Scenario.

    overrides: `--set`-style 'dotted.key=value' strings on the whole file
    (e.g. 'sim.duration=5', 'cameras.0.fps=60'); sim_overrides: sim keys.
    """
    path = resolve_config_path(name_or_path)
    data = load_yaml(path)
    if overrides:
        data = apply_overrides(data, list(overrides))
    arena = parse_arena(data, str(path))
    return scenario_from_arena(arena, session=session, **sim_overrides)
