"""Simulation scenario: an arena config plus its `sim` section, validated.

A Scenario is everything `capture.simulate` needs, fully resolved and
deterministic from `seed`: which bodies move how, each camera's frame timing,
each station's clock, the noise and nuisance models.

The `sim` section (every key optional) is declared in SIM below; its reference table is in
docs/configuration.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from visionpos.camera.model import Camera
from visionpos.config.arena import (
    ArenaConfig,
    BodyConfig,
    Section,
    apply_overrides,
    load_yaml,
    parse_arena,
    resolve_config_path,
)
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, section
from visionpos.protocol import MAX_BLOBS_PER_PACKET
from visionpos.sim import trajectories as trj
from visionpos.sim.trajectories import Motion, Trajectory

SIM_OCCLUSION = section(
    "sim.occlusion",
    "How bodies hide markers; bodies, props and session entries may override it with their own `occlusion`.",
    Setting("enabled", "boolean", True, "simulate occlusion at all"),
    Setting("disc_radius", "number", 0.05, "radius (m) of a disc in each body's x-y plane at its origin (hub, "
            "battery) that hides markers of any body behind it", min=0.0, max=2.0),
    Setting("normal_cutoff_deg", "number", 105.0, "a marker is seen only from directions within this angle of "
            "its normal (body z tilted ~27 deg outward)", min=0.0, max=180.0),
)
PROP_OCCLUSION = section("occlusion", "Self-occlusion of one body, prop or session entry (overrides `sim.occlusion`).",
                         *[st for st in SIM_OCCLUSION.settings if st.key != "enabled"])
PROP = section(
    "sim.props[i]",
    "A simulated-only body fusion does not track (calibration wand, L-frame).",
    Setting("name", "text", doc="unique among bodies and props; sessions refer to it"),
    Setting("markers", "array", doc="marker centres (M, 3) in the body frame (m)", shape=(None, 3)),
    Setting("marker_diameter", "number", 0.014, "marker sphere diameter (m)", min=0.001),
    Setting("occlusion", "section", {}, "self-occlusion", spec=PROP_OCCLUSION),
)
LATENCY = section(
    "sim.latency_ms",
    "Exposure -> server receive latency, gamma distributed, clipped at max.",
    Setting("mean", "number", 4.0, "mean (ms)", min=0.0),
    Setting("std", "number", 0.5, "standard deviation (ms)", min=0.0),
    Setting("max", "number", 15.0, "clip (ms), at least mean", default_doc="max(15, 4 x mean)"),
)
SPURIOUS = section(
    "sim.spurious",
    "Blobs that are not markers.",
    Setting("static_per_camera", "integer", 2, "fixed floor reflections of the IR ring seen every frame",
            min=0, max=1000),
    Setting("random_per_frame", "number", 0.02, "mean one-frame glints per frame", min=0.0, max=1000.0),
    Setting("floor_mirror", "number", 0.0, "brightness ratio of the markers' mirror images in a glossy floor "
            "(0 = matte; 0.3 = polished concrete)", min=0.0, max=1.0),
)
BRIGHTNESS = section(
    "sim.brightness",
    "Blob brightness (0-255 scale, clipped).",
    Setting("peak_at_1m", "number", 1000.0, "blob peak of a marker 1 m away, falling with range^2", min=1.0),
    Setting("min_peak", "number", 20.0, "dimmer blobs are not detected", min=0.0, max=255.0),
)
SIM_CAMERA = section(
    "sim.cameras.ID",
    "Per-camera overrides, keyed by camera id.",
    Setting("enabled", "boolean", True, "false: the camera is not simulated"),
    Setting("fps", "number", None, "frame rate (Hz)", min=0.1, max=10000.0, default_doc="the camera's fps"),
    Setting("phase_ms", "number", None, "first exposure offset within a frame", min=0.0,
            default_doc="from `phase`"),
    Setting("drop_probability", "number", None, "chance each frame is lost", min=0.0, max=1.0,
            default_doc="sim.drop_probability"),
    Setting("rolling_shutter_ms", "number", None, "readout time, at most a frame period", min=0.0,
            default_doc="sim.rolling_shutter_ms"),
    Setting("clock_error_ms", "number", 0.0, "constant error of this camera's synced stamps (a station whose "
            "clock sync is off, e.g. to test the wand calibration's clock-offset estimate)", min=-1000.0,
            max=1000.0),
    Setting("bump_at_s", "number", None, "the camera is knocked at this scenario time (s; from the first "
            "0.5 s generation window that starts at or after it): its true pose turns by bump_rotation_deg "
            "and moves by bump_shift_m, while the arena file keeps the old pose", min=0.0, default_doc="(never)"),
    Setting("bump_rotation_deg", "array", [0.0, 0.0, 0.0], "rotation vector of the bump in the camera frame "
            "(deg; x right, y down, z along the optical axis)", shape=(3,)),
    Setting("bump_shift_m", "array", [0.0, 0.0, 0.0], "move of the camera centre in the world frame (m)", shape=(3,)),
)
VIEW_WINDOW = section(
    "sim.view_schedule[i]",
    "One window of the occlusion schedule: while it lasts, only the listed cameras see the body, and each "
    "only the listed markers (where the geometry and `sim.occlusion` let it see them at all).",
    Setting("body", "text", doc="a body or prop of the session"),
    Setting("start_s", "number", doc="window start, seconds after the scenario start", min=0.0),
    Setting("end_s", "number", doc="window end (s), after start_s", min=0.0),
    Setting("cameras", "any", {}, "{camera id: [marker indices] or 'all'}; cameras not listed see none of the "
            "body's markers during the window"),
)
SIM = section(
    "sim",
    "The simulator's scenario (`visionpos sim`, `visionpos demo`): motion, timing, clocks, noise and nuisances. "
    "Deterministic from `seed`.",
    Setting("duration", "number", 30.0, "simulated capture (s)", min=0.001),
    Setting("seed", "integer", 0, "seed of every random draw", min=0),
    Setting("start_time", "number", 1000.0, "server-clock time of the scenario start (s)", min=0.0),
    Setting("session", "text", None, "which entry of `sessions` runs", default_doc="the first"),
    Setting("sessions", "section", {}, "{name: {body_or_prop_name: {trajectory: KIND, ...}}} (the trajectory "
            "keys: visionpos/sim/trajectories.py from_config); each entry may also hold an `occlusion` mapping. "
            "Without sessions every body hovers at 1 m, spread along x"),
    Setting("props", "list", [], "simulated-only bodies", spec=PROP),
    Setting("truth_rate", "number", 200.0, "rate of the fine ground-truth samples (Hz)", min=1.0, max=100000.0),
    Setting("phase", "text", "random", "each camera's first exposure offset within a frame",
            choices=("random", "zero")),
    Setting("timing_jitter_us", "number", 20.0, "std of exposure instants around the frame grid (clipped at "
            "4 std)", min=0.0),
    Setting("stamp_noise_us", "number", 0.0, "std of white noise on reported capture stamps", min=0.0),
    Setting("clock_offset_ms", "number", 200.0, "std of raw station clock offsets before sync", min=0.0),
    Setting("clock_drift_ppm", "number", 20.0, "std of station crystal drift (frame periods stretch)", min=0.0,
            max=1000.0),
    Setting("sync_residual_us", "number", 50.0, "std of the offset error left after clock sync, per station: a "
            "constant part plus slow (0.01-0.2 Hz) wander", min=0.0),
    Setting("centroid_noise_px", "number", 0.2, "std of blob centroid noise per axis", min=0.0, max=50.0),
    Setting("drop_probability", "number", 0.002, "chance each frame is lost (its seq is skipped)", min=0.0,
            max=1.0),
    Setting("latency_ms", "section", {}, "exposure -> receive latency", spec=LATENCY),
    Setting("spurious", "section", {}, "spurious blobs", spec=SPURIOUS),
    Setting("occlusion", "section", {}, "occlusion model", spec=SIM_OCCLUSION),
    Setting("view_schedule", "list", [], "occlusion schedule: which cameras see which markers of a body, and "
            "when (deterministic)", spec=VIEW_WINDOW),
    Setting("brightness", "section", {}, "blob brightness", spec=BRIGHTNESS),
    Setting("merge_blobs", "boolean", True, "markers whose images overlap become one blob"),
    Setting("max_blobs", "integer", 64, "a station sends at most this many blobs (FLAG_TRUNCATED); at most one "
            "datagram's worth", min=1, max=MAX_BLOBS_PER_PACKET),
    Setting("cameras", "map", {}, "per-camera overrides by camera id", spec=SIM_CAMERA),
    Setting("rolling_shutter_ms", "number", 0.0, "readout time from the first to the last row (0 = global "
            "shutter); capture_ns stamps the first row", min=0.0, max=1000.0),
)

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
class ViewWindow:
    """One window of the occlusion schedule (sim.view_schedule): during [start_ns, end_ns) (server
    clock, true exposure time) body `body` (index into Scenario.bodies) is seen only by the cameras
    in `visible`, each only through the markers it lists (camera id -> marker indices)."""

    body: int
    start_ns: int
    end_ns: int
    visible: dict[int, frozenset[int]]

    def mask(self, camera_id: int, n_markers: int) -> np.ndarray:
        """(n_markers,) bool: which of the body's markers this camera may see during the window."""
        m = np.zeros(n_markers, bool)
        m[list(self.visible.get(camera_id, ()))] = True
        return m


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
    # camera id -> (ns after start from which it renders, the knocked camera): sim.cameras.ID.bump_*
    bumps: dict[int, tuple[int, Camera]] = field(default_factory=dict)
    view_schedule: tuple[ViewWindow, ...] = ()

    @property
    def end_ns(self) -> int:
        return self.start_ns + int(round(self.duration_s * 1e9))

    def body(self, name: str) -> SimBody:
        for b in self.bodies:
            if b.name == name:
                return b
        raise KeyError(
            f"no simulated body '{name}'; bodies in session '{self.session}': {[b.name for b in self.bodies]}"
        )

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
    s = PROP_OCCLUSION.check(s)
    return (
        s.number("disc_radius", default[0], min=0.0, max=2.0),
        s.number("normal_cutoff_deg", default[1], min=0.0, max=180.0),
    )


def _props(sim: Section, arena: ArenaConfig) -> list[tuple[BodyConfig, Section]]:
    """Validate sim.props: simulated-only bodies {name, markers, marker_diameter, occlusion}."""
    out = []
    names = {b.name for b in arena.bodies}
    for p in sim.items("props"):
        p = PROP.check(p)
        name = PROP.read(p, "name")
        if name in names:
            raise p.error("name", f"'{name}' is already a body or prop name; props need their own names")
        names.add(name)
        markers = p.array("markers", (None, 3))
        if len(markers) < 2:
            raise p.error("markers", f"a prop needs at least 2 markers, got {len(markers)}")
        d = np.linalg.norm(markers[:, None] - markers[None], axis=-1) + np.eye(len(markers)) * 1e9
        if d.min() < 0.01:
            raise p.error("markers", "two markers are closer than 10 mm; cameras cannot separate them")
        body = BodyConfig(name, 0, markers, PROP.read(p, "marker_diameter"), p.data)
        out.append((body, p.sub("occlusion")))
    return out


def sim_props(arena: ArenaConfig) -> list[BodyConfig]:
    """The arena's `sim.props`, checked: simulated bodies fusion does not track (calibration tools)."""
    return [b for b, _ in _props(SIM.check(arena.section("sim")), arena)]


def _view_schedule(sim: Section, bodies: list[SimBody], camera_ids: list[int], start_ns: int) -> tuple[ViewWindow, ...]:
    """Validate sim.view_schedule into ViewWindows (body names of the session, camera ids, marker indices)."""
    names = [b.name for b in bodies]
    out = []
    for w in sim.items("view_schedule"):
        w = VIEW_WINDOW.check(w)
        name = VIEW_WINDOW.read(w, "body")
        if name not in names:
            raise w.error("body", f"no body or prop '{name}' in this session; it has {names}")
        start, end = VIEW_WINDOW.read(w, "start_s"), VIEW_WINDOW.read(w, "end_s")
        if not end > start:
            raise w.error("end_s", f"must be after start_s ({start} s), got {end} s")
        cams = w.data.get("cameras") or {}
        if not isinstance(cams, dict):
            raise w.error("cameras", "expected a mapping {camera id: [marker indices] or 'all'}")
        n_markers = len(bodies[names.index(name)].markers)
        visible: dict[int, frozenset[int]] = {}
        for k, v in cams.items():
            kid = int(k) if isinstance(k, str) and k.strip().isdigit() else k
            if not isinstance(kid, int) or kid not in camera_ids:
                raise w.error("cameras", f"no simulated camera with id {k!r}; camera ids are {camera_ids}")
            if v == "all":
                v = list(range(n_markers))
            if not isinstance(v, list) or not all(isinstance(i, int) and 0 <= i < n_markers for i in v):
                raise w.error(f"cameras.{k}", f"expected 'all' or a list of marker indices 0..{n_markers - 1}, "
                              f"got {v!r}")
            visible[kid] = frozenset(v)
        out.append(ViewWindow(names.index(name), start_ns + int(round(start * 1e9)), start_ns + int(round(end * 1e9)),
                              visible))
    return tuple(out)


def parse_sim(arena: ArenaConfig, session: str | None = None, **overrides: Any) -> Scenario:
    """The arena's `sim` section, checked and resolved into a Scenario.

    overrides: sim keys to replace (e.g. duration=5, seed=3, centroid_noise_px=0),
    applied before validation so bad values are reported like config errors.
    Stages: the bodies of the session (_sim_bodies), the cameras with their stations' clocks
    (_sim_cameras), then the occlusion schedule, latency, reflections and brightness.
    """
    arena.require_poses("the simulator")
    raw_sim = dict(arena.section("sim").data)
    raw_sim.update(overrides)
    if session is not None:
        raw_sim["session"] = session
    sim = Section(raw_sim, arena.source, "sim")
    sim = SIM.check(sim)

    seed = SIM.read(sim, "seed")
    duration = SIM.read(sim, "duration")
    start_ns = int(round(SIM.read(sim, "start_time") * 1e9))
    occ = SIM_OCCLUSION.check(sim.sub("occlusion"))
    session_name, bodies = _sim_bodies(arena, sim, occ, seed)
    cameras, timings, clocks, bumps = _sim_cameras(arena, sim, seed, start_ns)

    schedule = _view_schedule(sim, bodies, [c.id for c in cameras], start_ns)
    lat = LATENCY.check(sim.sub("latency_ms"))
    spur = SPURIOUS.check(sim.sub("spurious"))
    bright = BRIGHTNESS.check(sim.sub("brightness"))
    lat_mean = LATENCY.read(lat, "mean")
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
        truth_rate_hz=SIM.read(sim, "truth_rate"),
        centroid_noise_px=SIM.read(sim, "centroid_noise_px"),
        latency_mean_ns=lat_mean * 1e6,
        latency_std_ns=LATENCY.read(lat, "std") * 1e6,
        latency_max_ns=lat_max * 1e6,
        static_spurious_per_camera=SPURIOUS.read(spur, "static_per_camera"),
        random_spurious_per_frame=SPURIOUS.read(spur, "random_per_frame"),
        floor_mirror=SPURIOUS.read(spur, "floor_mirror"),
        occlusion=SIM_OCCLUSION.read(occ, "enabled"),
        peak_at_1m=BRIGHTNESS.read(bright, "peak_at_1m"),
        min_peak=BRIGHTNESS.read(bright, "min_peak"),
        merge_blobs=SIM.read(sim, "merge_blobs"),
        max_blobs=SIM.read(sim, "max_blobs"),
        raw=raw_sim,
        bumps=bumps,
        view_schedule=schedule,
    )


def _session_entries(arena: ArenaConfig, sim: Section) -> tuple[str, Section]:
    """The session's name and its entries (body or prop name -> trajectory); without sessions every tracked
    body hovers at 1 m, spread along x."""
    sessions = sim.sub("sessions")
    if sessions.data:
        names = list(sessions.data)
        session_name = sim.string("session", names[0])
        if session_name not in sessions.data:
            raise sim.error("session", f"'{session_name}' is not one of the sessions {names}")
        return session_name, sessions.sub(session_name)
    n = len(arena.bodies)
    hover = {b.name: {"trajectory": "hover", "center": [0.6 * (i - (n - 1) / 2), 0.0, 1.0]}
             for i, b in enumerate(arena.bodies)}
    return sim.string("session", "default"), Section(hover, arena.source, "sim.sessions.default")


def _sim_bodies(arena: ArenaConfig, sim: Section, occ: Section, seed: int) -> tuple[str, list[SimBody]]:
    """The session's name and its bodies: tracked ones and props, each on its trajectory, with its occluder."""
    occ_default = (SIM_OCCLUSION.read(occ, "disc_radius"), SIM_OCCLUSION.read(occ, "normal_cutoff_deg"))
    candidates: dict[str, tuple[BodyConfig, Section, bool]] = {
        b.name: (b, Section(b.raw.get("occlusion"), arena.source, f"bodies[{i}].occlusion"), True)
        for i, b in enumerate(arena.bodies)
    }
    for b, o in _props(sim, arena):
        candidates[b.name] = (b, o, False)
    session_name, entries = _session_entries(arena, sim)
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
    return session_name, bodies


def _camera_overrides(arena: ArenaConfig, sim: Section) -> Section:
    """sim.cameras keyed by camera id (--set sim.cameras.3.fps=60 gives string keys), unknown ids refused."""
    cam_over = sim.sub("cameras")
    by_id = arena.camera_by_id()
    norm = {}
    for k, v in cam_over.data.items():
        kid = int(k) if isinstance(k, str) and k.strip().isdigit() else k
        if not isinstance(kid, int) or kid not in by_id:
            raise cam_over.error(str(k), f"no camera with id {k!r}; camera ids are {sorted(by_id)}")
        norm[kid] = v
    return Section(norm, cam_over.source, cam_over.path)


def _station_clock(sim: Section, co: Section, seed: int, station: int, start_ns: int) -> StationClock:
    """A station's clock: its offset, drift and sync residual drawn from the seed and the sim's spreads."""
    offset_std = SIM.read(sim, "clock_offset_ms") * 1e6
    drift_std = SIM.read(sim, "clock_drift_ppm")
    resid_std = SIM.read(sim, "sync_residual_us") * 1e3
    crng = rng_for(seed, TAG_CLOCK, station)
    drift = float(crng.normal(0.0, drift_std)) if drift_std > 0 else 0.0
    return StationClock(
        station_id=station,
        offset_ns=int(round(crng.normal(0.0, offset_std))) if offset_std > 0 else 0,
        drift_ppm=drift,
        bias_ns=float(crng.normal(0.0, resid_std / np.sqrt(2))) + co.number("clock_error_ms", 0.0) * 1e6,
        amp_ns=np.full(3, resid_std / np.sqrt(3)),
        freq_hz=crng.uniform(0.01, 0.2, 3),
        phase=crng.uniform(0, 2 * np.pi, 3),
        start_ns=start_ns,
    )


def _bumped_camera(co: Section, cam: Camera) -> tuple[int, Camera]:
    """sim.cameras.N.bump_*: when (ns after start) the camera is knocked, and where it is then (a turn about
    its own axes and a shift of its centre)."""
    from scipy.spatial.transform import Rotation

    dR = Rotation.from_rotvec(np.radians(SIM_CAMERA.read(co, "bump_rotation_deg"))).as_matrix()
    R_new = dR @ cam.R
    C_new = cam.center + SIM_CAMERA.read(co, "bump_shift_m")
    return int(round(SIM_CAMERA.read(co, "bump_at_s") * 1e9)), cam.with_pose(R_new, -R_new @ C_new)


def _sim_cameras(arena: ArenaConfig, sim: Section, seed: int, start_ns: int
                 ) -> tuple[list[Camera], list[CameraTiming], dict[int, StationClock], dict[int, tuple[int, Camera]]]:
    """The enabled cameras, their timing (rate, phase, jitter, drops, rolling shutter), their stations' clocks
    (one camera per station, as the thesis stations are) and the knocks (camera id -> (ns, camera after))."""
    cam_over = _camera_overrides(arena, sim)
    phase_mode = sim.string("phase", "random", choices=("random", "zero"))
    jitter_ns = SIM.read(sim, "timing_jitter_us") * 1e3
    stamp_ns = SIM.read(sim, "stamp_noise_us") * 1e3
    drop = SIM.read(sim, "drop_probability")
    readout_ms = SIM.read(sim, "rolling_shutter_ms")
    cameras, timings = [], []
    bumps: dict[int, tuple[int, Camera]] = {}
    clocks: dict[int, StationClock] = {}
    for cam in arena.cameras:
        co = cam_over.sub(cam.id) if cam.id in cam_over.data else Section({}, arena.source, f"sim.cameras.{cam.id}")
        co = SIM_CAMERA.check(co)
        if not co.boolean("enabled", True):
            continue
        fps = co.number("fps", cam.fps, min=0.1, max=10000.0)
        station = cam.id
        clocks[station] = clock = _station_clock(sim, co, seed, station, start_ns)
        period = 1e9 / fps / (1.0 + clock.drift_ppm * 1e-6)
        if co.has("phase_ms"):
            phase = co.number("phase_ms", min=0.0) * 1e6
        elif phase_mode == "random":
            phase = float(rng_for(seed, TAG_PHASE, cam.id).uniform(0.0, period))
        else:
            phase = 0.0
        cameras.append(cam)
        if co.has("bump_at_s"):
            bumps[cam.id] = _bumped_camera(co, cam)
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
    return cameras, timings, clocks, bumps


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
    return parse_sim(arena, session=session, **sim_overrides)

register_section("sim", SIM, parse_sim)
