"""Per-camera capture simulation: what stations send, with ground truth.

`simulate(scenario)` returns every BlobFrame of a scenario (sorted by
capture_ns) plus the truth behind each one; `iter_frames(scenario)` streams
the same frames in capture (or receive) order for live use, chunk by chunk,
with exactly the same content.

Model per camera frame k (see scenario.py for the parameters):
  true exposure   start + phase + k * period + jitter_k   (server clock = true time);
                  with a rolling shutter, row y is exposed (y + 0.5) / height x readout later
  capture_ns      true + station sync residual(true) + stamp noise (what the station reports)
  recv_ns         true + latency (gamma, clipped)
  blobs           markers in the field of view, facing the camera and not behind any
                  body's occluder disc, projected through the camera model, with
                  Gaussian centroid noise; overlapping images merge; plus static floor
                  reflections, random glints and (glossy floor) mirror images of the
                  markers; shuffled, unlabeled; float32 (N, 4)
                  [x, y, area, peak]; area and peak from the marker's projected
                  diameter and range. Dropped frames are not emitted (seq skips).
"""

from __future__ import annotations

import heapq
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from visionpos.camera.model import Camera
from visionpos.messages import FLAG_TRUNCATED, BlobFrame
from visionpos.sim.scenario import TAG_FRAMES, TAG_STATIC, CameraTiming, Scenario, rng_for
from visionpos.sim.trajectories import Motion

CHUNK_S = 0.5  # frames are generated in windows of nominal exposure time this long
SPURIOUS_STATIC = -1  # FrameTruth.marker for a fixed floor reflection (body is -1)
SPURIOUS_RANDOM = -2  # FrameTruth.marker for a one-frame glint (body is -1)
SPURIOUS_MIRROR = -3  # FrameTruth.marker for a marker's mirror image in a glossy floor (body is -1)


@dataclass(frozen=True, slots=True)
class FrameTruth:
    """Ground truth of one emitted frame, row-aligned with its blobs.

    body (N,) int: index into scenario.bodies, -1 for a spurious blob.
    marker (N,) int: marker index in that body; for spurious blobs
      SPURIOUS_STATIC (-1), SPURIOUS_RANDOM (-2) or SPURIOUS_MIRROR (-3).
    true_xy (N, 2): noise-free pixel (for merged blobs the weighted mean of
      the true pixels of the parts). merged (N,) bool.
    true_ns: exact exposure time (of the first row with a rolling shutter);
    station_ns: the station's raw clock then.
    exposure_ns (N,) int64: exact exposure time of each blob: true_ns, plus
      its row's readout delay with a rolling shutter ((row + 0.5) / height x
      readout), which is when its marker was where the blob shows it.
    """

    camera_id: int
    seq: int
    true_ns: int
    station_ns: int
    body: np.ndarray
    marker: np.ndarray
    true_xy: np.ndarray
    merged: np.ndarray
    exposure_ns: np.ndarray


@dataclass
class SimResult:
    """Frames as stations send them plus ground truth.

    frames: BlobFrames sorted by (capture_ns, camera_id); frame_truth aligned.
    truth_times_ns (T,) int64 at scenario.truth_rate_hz; truth: body name -> Motion at those times.
    dropped: camera id -> seq numbers (int64 array) of frames lost before sending.
    """

    scenario: Scenario
    frames: list[BlobFrame]
    frame_truth: list[FrameTruth]
    truth_times_ns: np.ndarray
    truth: dict[str, Motion]
    dropped: dict[int, np.ndarray] = field(default_factory=dict)

    def truth_at(self, body_name: str, times_ns) -> tuple[np.ndarray, np.ndarray]:
        """True positions (T, 3) and quaternions xyzw (T, 4) at any times (T,) int64 ns."""
        return self.scenario.truth_at(body_name, times_ns)

    def frames_by_camera(self) -> dict[int, list[BlobFrame]]:
        out: dict[int, list[BlobFrame]] = {t.camera_id: [] for t in self.scenario.timings}
        for f in self.frames:
            out[f.camera_id].append(f)
        return out

    def frames_by_recv(self) -> list[BlobFrame]:
        """The frames in the order a server would receive them."""
        return sorted(self.frames, key=lambda f: (f.recv_ns, f.camera_id))

    def summary(self) -> dict:
        """Counts per camera: frames, dropped, blobs, marker blobs, spurious blobs."""
        cams = {}
        for t in self.scenario.timings:
            cams[t.camera_id] = {
                "fps": t.fps,
                "frames": 0,
                "dropped": int(len(self.dropped.get(t.camera_id, ()))),
                "blobs": 0,
                "marker_blobs": 0,
                "spurious_blobs": 0,
            }
        for f, tr in zip(self.frames, self.frame_truth):
            c = cams[f.camera_id]
            c["frames"] += 1
            c["blobs"] += len(f.blobs)
            n_sp = int(np.count_nonzero(tr.body < 0))
            c["spurious_blobs"] += n_sp
            c["marker_blobs"] += len(f.blobs) - n_sp
        return {
            "session": self.scenario.session,
            "duration_s": self.scenario.duration_s,
            "bodies": [b.name for b in self.scenario.bodies],
            "frames": len(self.frames),
            "blobs": int(sum(len(f.blobs) for f in self.frames)),
            "cameras": cams,
        }


# --------------------------------------------------------------------- public
def simulate(scenario: Scenario) -> SimResult:
    """Run the whole scenario: every frame (capture order) and its truth."""
    frames, truths = [], []
    dropped: dict[int, list[int]] = {t.camera_id: [] for t in scenario.timings}
    for frame, truth in _ordered(scenario, scenario.duration_s, "capture", dropped):
        frames.append(frame)
        truths.append(truth)
    step = int(round(1e9 / scenario.truth_rate_hz))
    times = np.arange(scenario.start_ns, scenario.end_ns + 1, step, dtype=np.int64)
    truth = {b.name: scenario.motion_at(b.name, times) for b in scenario.bodies}
    return SimResult(
        scenario, frames, truths, times, truth, {k: np.asarray(v, np.int64) for k, v in dropped.items()}
    )


def iter_frames(
    scenario: Scenario, order: str = "capture", with_truth: bool = False, duration_s: float | None = None
) -> Iterator[BlobFrame] | Iterator[tuple[BlobFrame, FrameTruth]]:
    """Stream frames in `order` 'capture' (capture_ns) or 'recv' (recv_ns).

    duration_s: overrides the scenario's (float('inf') streams until closed).
    Yields BlobFrame, or (BlobFrame, FrameTruth) with with_truth. Content is
    identical to simulate() for the same scenario.
    """
    if order not in ("capture", "recv"):
        raise ValueError(f"order must be 'capture' or 'recv', got {order!r}")
    dur = scenario.duration_s if duration_s is None else float(duration_s)
    for frame, truth in _ordered(scenario, dur, order, None):
        yield (frame, truth) if with_truth else frame


def window_frames(scenario: Scenario, camera_index: int, window: int, t0_ns: float, t1_ns: float
                  ) -> list[tuple[BlobFrame, FrameTruth]]:
    """Frames of one camera (index into scenario.cameras) with nominal exposure in [t0_ns, t1_ns) after
    the scenario start, generated on demand (a live trajectory: call it once the truth for the window is
    known). window: this window's index, which seeds its random draws (give each window its own)."""
    cam, timing = _true_camera(scenario, scenario.cameras[camera_index], t0_ns), scenario.timings[camera_index]
    return _camera_chunk(scenario, cam, timing, window, float(t0_ns), float(t1_ns), None)


def _true_camera(scenario: Scenario, cam, t0_ns: float):
    """The camera as it really is from t0_ns (ns after the start) on: knocked (sim.cameras.ID.bump_*) or as
    the arena file says."""
    bump = scenario.bumps.get(cam.id)
    return bump[1] if bump is not None and t0_ns >= bump[0] else cam


# ------------------------------------------------------------------ internals
def _ordered(scenario: Scenario, duration_s: float, order: str, dropped: dict[int, list[int]] | None):
    """Merge the per-chunk frames of all cameras into one exactly ordered stream.

    A frame of a later chunk has nominal exposure >= the chunk start, so its
    capture stamp is >= start - bound and its receive time >= start - jitter
    bound: frames keyed below that can be released.
    """
    bound = max(_time_bound(scenario, t) for t in scenario.timings)
    end_rel_ns = duration_s * 1e9
    heap: list = []
    counter = 0
    c = 0
    while True:
        t0, t1 = c * CHUNK_S * 1e9, (c + 1) * CHUNK_S * 1e9
        last = t1 >= end_rel_ns
        for timing, cam in zip(scenario.timings, scenario.cameras):
            cam = _true_camera(scenario, cam, t0)  # a knocked camera renders from its new pose
            for frame, truth in _camera_chunk(scenario, cam, timing, c, t0, min(t1, end_rel_ns), dropped):
                key = frame.capture_ns if order == "capture" else frame.recv_ns
                heapq.heappush(heap, (key, frame.camera_id, counter, frame, truth))
                counter += 1
        release = np.inf if last else scenario.start_ns + t1 - bound
        while heap and heap[0][0] < release:
            item = heapq.heappop(heap)
            yield item[3], item[4]
        if last:
            return
        c += 1


def _time_bound(s: Scenario, t: CameraTiming) -> float:
    """Largest |reported or true time - nominal exposure| (ns) a frame can have."""
    return 4 * t.jitter_ns + 4 * t.stamp_noise_ns + s.clocks[t.station_id].residual_bound_ns + 2.0


def _frame_range(t: CameraTiming, t0: float, t1: float) -> np.ndarray:
    """Frame indices k whose nominal exposure phase + k period lies in [t0, t1) ns."""
    k0 = max(0, int(np.ceil((t0 - t.phase_ns) / t.period_ns)))
    k1 = int(np.ceil((t1 - t.phase_ns) / t.period_ns))
    # guard the float edges so each k lands in exactly one chunk
    while k0 > 0 and t.phase_ns + (k0 - 1) * t.period_ns >= t0:
        k0 -= 1
    while t.phase_ns + k0 * t.period_ns < t0:
        k0 += 1
    while k1 > k0 and t.phase_ns + (k1 - 1) * t.period_ns >= t1:
        k1 -= 1
    while t.phase_ns + k1 * t.period_ns < t1:
        k1 += 1
    return np.arange(k0, max(k0, k1), dtype=np.int64)


def _body_markers_at(s: Scenario, times_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All bodies' markers at per-marker times (K, Mtot) int64 -> world points and normals (K, Mtot, 3)."""
    W, N = np.empty((*times_ns.shape, 3)), np.empty((*times_ns.shape, 3))
    col = 0
    for b in s.bodies:
        M = len(b.markers)
        tt = times_ns[:, col : col + M].ravel()
        pos, rot = b.trajectory.pose((tt - s.start_ns).astype(np.float64) * 1e-9)
        mk = np.tile(b.markers, (times_ns.shape[0], 1))
        W[:, col : col + M] = (rot.apply(mk) + pos).reshape(-1, M, 3)
        N[:, col : col + M] = rot.apply(np.tile(b.normals, (times_ns.shape[0], 1))).reshape(-1, M, 3)
        col += M
    return W, N


def _rolling_shutter(s: Scenario, cam: Camera, readout_ns: float, true_ns: np.ndarray, W: np.ndarray, N: np.ndarray):
    """Re-place markers for a rolling shutter: row y is exposed (y + 0.5) / height x
    readout after the first. Fixed-point iteration on the row the marker lands in
    (3 rounds: each shrinks the row error by the image motion during one readout
    over the image height, a small factor; what is left is < 0.01 px).
    Returns W, N (K, Mtot, 3) and the per-marker delays (K, Mtot) ns."""
    H = cam.model.height
    dt = np.zeros(W.shape[:2])
    for _ in range(3):
        v = cam.project(W.reshape(-1, 3))[:, 1].reshape(W.shape[:2])
        dt = np.clip((np.nan_to_num(v, nan=0.0) + 0.5) / H, 0.0, 1.0) * readout_ns
        W, N = _body_markers_at(s, true_ns[:, None] + np.round(dt).astype(np.int64))
    return W, N, dt


def marker_geometry(
    camera: Camera, points_world: np.ndarray, diameter: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel centre (N, 2), projected diameter (N,) px and range (N,) m of spheres.

    points_world (N, 3); diameter (N,) m. The diameter is the geometric mean of
    the image extents along two directions perpendicular to the line of sight
    (fisheye images shrink spheres radially more than tangentially).
    """
    pc = camera.to_camera(points_world)
    uv = camera.model.project_camera(pc)
    rng_m = np.linalg.norm(pc, axis=1)
    ray = pc / np.maximum(rng_m, 1e-12)[:, None]
    ref = np.where(np.abs(ray[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(ray, ref)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(ray, e1)
    r = (np.asarray(diameter, float) / 2)[:, None]
    d1 = np.linalg.norm(camera.model.project_camera(pc + r * e1) - camera.model.project_camera(pc - r * e1), axis=1)
    d2 = np.linalg.norm(camera.model.project_camera(pc + r * e2) - camera.model.project_camera(pc - r * e2), axis=1)
    return uv, np.sqrt(d1 * d2), rng_m


def blob_photometry(s: Scenario, diameter_px: np.ndarray, range_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area (N,) px and peak (N,) 0..255 of marker blobs.

    Retro-reflected IR falls with range^2 (the ring lights the marker, the
    marker returns a narrow cone); blobs under ~2 px lose peak to the optics'
    blur. Area is the disc area (>= 1 px).
    """
    area = np.maximum(np.pi / 4 * diameter_px**2, 1.0)
    peak = s.peak_at_1m / np.maximum(range_m, 1e-3) ** 2 * np.minimum(1.0, diameter_px / 2.0)
    return area, np.clip(peak, s.min_peak, 255.0)


def _static_spurious(s: Scenario, cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fixed floor reflections of a camera: pixels (S, 2), area (S,), peak (S,).

    Spots sit where the floor (z = 0) is in view, as glossy-floor reflections of
    IR rings do; seeded per camera so they never move.
    """
    n = s.static_spurious_per_camera
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    rng = rng_for(s.seed, TAG_STATIC, cam.id)
    pts = np.column_stack([rng.uniform(-6, 6, 400), rng.uniform(-6, 6, 400), np.zeros(400)])
    ok = cam.visible(pts, margin=10)
    uv = cam.project(pts[ok])[:n]
    if len(uv) < n:  # the floor is out of view: anywhere on the sensor
        m = n - len(uv)
        uv = np.vstack(
            [uv, np.column_stack([rng.uniform(10, cam.model.width - 11, m), rng.uniform(10, cam.model.height - 11, m)])]
        )
    return uv, rng.uniform(6.0, 40.0, n), rng.uniform(120.0, 255.0, n)


@dataclass(slots=True)
class _Exposures:
    """One chunk's K frames of a camera: indices k (K,), exact exposure, reported capture, receive and raw
    station times (K,) int64 ns, and which frames the station drops (K,) bool."""

    k: np.ndarray
    true_ns: np.ndarray
    capture_ns: np.ndarray
    recv_ns: np.ndarray
    station_ns: np.ndarray
    drop: np.ndarray


def _exposures(s: Scenario, t: CameraTiming, k: np.ndarray, rng: np.random.Generator) -> _Exposures:
    """Exposure jitter, drops, the station's stamp (sync residual + noise) and the network latency of frames k."""
    K = len(k)
    clock = s.clocks[t.station_id]
    jit = np.clip(rng.standard_normal(K), -4, 4) * t.jitter_ns
    true_ns = s.start_ns + np.round(t.phase_ns + k * t.period_ns + jit).astype(np.int64)
    drop = rng.random(K) < t.drop_probability
    stamp = np.clip(rng.standard_normal(K), -4, 4) * t.stamp_noise_ns
    capture_ns = true_ns + np.round(clock.residual_ns(true_ns) + stamp).astype(np.int64)
    if s.latency_std_ns > 0 and s.latency_mean_ns > 0:
        shape = (s.latency_mean_ns / s.latency_std_ns) ** 2
        lat = rng.gamma(shape, s.latency_mean_ns / shape, K)
    else:
        lat = np.full(K, s.latency_mean_ns)
    recv_ns = true_ns + np.round(np.clip(lat, 0, s.latency_max_ns)).astype(np.int64)
    return _Exposures(k, true_ns, capture_ns, recv_ns, clock.raw_ns(true_ns), drop)


@dataclass(slots=True)
class _Markers:
    """Every body's markers at each of K exposures, Mt columns (bodies' markers side by side).

    world, normals (K, Mt, 3) m / unit; diameter_m, body, marker, cutoff_cos (Mt,); row_dt_ns (K, Mt) the
    rolling shutter's delay of each marker's row; discs [(position (K, 3), disc normal (K, 3), radius m)]."""

    world: np.ndarray
    normals: np.ndarray
    diameter_m: np.ndarray
    body: np.ndarray
    marker: np.ndarray
    cutoff_cos: np.ndarray
    row_dt_ns: np.ndarray
    discs: list


def _markers_at(s: Scenario, cam: Camera, t: CameraTiming, true_ns: np.ndarray) -> _Markers:
    """The bodies' markers at the exposures true_ns (K,), moved on to their row's time with a rolling shutter."""
    K = len(true_ns)
    world, normals, diam, b_idx, m_idx, cutoff = [], [], [], [], [], []
    discs = []
    for bi, b in enumerate(s.bodies):
        pos, rot = b.trajectory.pose((true_ns - s.start_ns).astype(np.float64) * 1e-9)
        R = rot.as_matrix()  # (K, 3, 3)
        world.append(np.einsum("kij,mj->kmi", R, b.markers) + pos[:, None, :])
        normals.append(np.einsum("kij,mj->kmi", R, b.normals))
        M = len(b.markers)
        diam.append(np.full(M, b.marker_diameter))
        b_idx.append(np.full(M, bi))
        m_idx.append(np.arange(M))
        cutoff.append(np.full(M, b.normal_cutoff_cos))
        if s.occlusion and b.disc_radius > 0:
            discs.append((pos, R[:, :, 2], b.disc_radius))
    if world:
        W = np.concatenate(world, axis=1)
        N = np.concatenate(normals, axis=1)
        diam_m = np.concatenate(diam)
        b_idx_a, m_idx_a, cut = np.concatenate(b_idx), np.concatenate(m_idx), np.concatenate(cutoff)
    else:
        W = np.zeros((K, 0, 3))
        N = W.copy()
        diam_m = np.zeros(0)
        b_idx_a = m_idx_a = np.zeros(0, int)
        cut = np.zeros(0)
    row_dt = np.zeros((K, W.shape[1]))
    if t.readout_ns > 0 and W.shape[1]:
        W, N, row_dt = _rolling_shutter(s, cam, t.readout_ns, true_ns, W, N)
    return _Markers(W, N, diam_m, b_idx_a, m_idx_a, cut, row_dt, discs)


def _visible(s: Scenario, cam: Camera, m: _Markers, ex: _Exposures) -> np.ndarray:
    """(K, Mt) bool: in the field of view, facing the camera, behind no body's disc, in a frame not dropped and
    not hidden by the occlusion schedule (on the true exposure time)."""
    K, Mt = m.world.shape[:2]
    W = m.world
    vis = cam.visible(W.reshape(-1, 3)).reshape(K, Mt)
    if s.occlusion and Mt:
        to_cam = cam.center[None, None, :] - W
        dist = np.linalg.norm(to_cam, axis=2)
        facing = np.einsum("kmi,kmi->km", m.normals, to_cam) / np.maximum(dist, 1e-12)
        vis &= facing >= m.cutoff_cos[None, :] - 1e-12
        for pos, nz, radius in m.discs:
            denom = np.einsum("kmi,ki->km", to_cam, nz)
            num = np.einsum("kmi,ki->km", pos[:, None, :] - W, nz)
            with np.errstate(divide="ignore", invalid="ignore"):
                sc = num / denom
            hit = (sc > 1e-6) & (sc < 1.0)
            x = W + sc[..., None] * to_cam
            inside = np.linalg.norm(x - pos[:, None, :], axis=2) < radius
            vis &= ~(hit & inside)
    vis &= ~ex.drop[:, None]
    for win in s.view_schedule:
        during = (ex.true_ns >= win.start_ns) & (ex.true_ns < win.end_ns)
        if during.any():
            cols = m.body == win.body
            vis[np.ix_(during, cols)] &= win.mask(cam.id, int(cols.sum()))[None, :]
    return vis


class _BlobColumns:
    """The blobs of a chunk's frames as parallel columns, gathered part by part (markers, mirror images,
    reflections, glints) and joined once: frame index, measured and true pixel (N, 2), area px^2, peak,
    diameter px, body and marker (truth labels), row delay ns."""

    NAMES = ("frame", "xy", "true_xy", "area", "peak", "diameter_px", "body", "marker", "row_dt_ns")

    def __init__(self) -> None:
        self.parts: list[tuple[np.ndarray, ...]] = []

    def add(self, frame, xy, true_xy, area, peak, diameter_px, body, marker, row_dt_ns) -> None:
        self.parts.append((frame, xy, true_xy, area, peak, diameter_px, body, marker, row_dt_ns))

    def joined(self) -> dict[str, np.ndarray]:
        cols = {}
        for i, name in enumerate(self.NAMES):
            arrays = [p[i] for p in self.parts]
            cols[name] = np.vstack(arrays) if arrays[0].ndim == 2 else np.concatenate(arrays)
        return cols


def _add_marker_blobs(s: Scenario, cam: Camera, m: _Markers, vis: np.ndarray, rng, blobs: _BlobColumns) -> None:
    """The visible markers' blobs, with centroid noise."""
    fi, mi = np.nonzero(vis)  # frame index, marker column
    uv, dpx, rng_m = marker_geometry(cam, m.world[fi, mi], m.diameter_m[mi])
    area, peak = blob_photometry(s, dpx, rng_m)
    xy = uv + rng.normal(0.0, s.centroid_noise_px, uv.shape) if s.centroid_noise_px > 0 else uv.copy()
    blobs.add(fi, xy, uv, area, peak, dpx, m.body[mi], m.marker[mi], m.row_dt_ns[fi, mi])


def _add_mirror_blobs(s: Scenario, cam: Camera, m: _Markers, ex: _Exposures, rng, blobs: _BlobColumns) -> None:
    """Glossy floor: every marker above it also shows as a dimmer mirror image."""
    K, Mt = m.world.shape[:2]
    if s.floor_mirror <= 0 or not Mt:
        return
    Wm = m.world * np.array([1.0, 1.0, -1.0])
    vis_m = cam.visible(Wm.reshape(-1, 3)).reshape(K, Mt) & (m.world[:, :, 2] > 0) & ~ex.drop[:, None]
    fm, mm = np.nonzero(vis_m)
    if not len(fm):
        return
    uv_m, d_m, r_m = marker_geometry(cam, Wm[fm, mm], m.diameter_m[mm])
    a_m, p_m = blob_photometry(s, d_m, r_m)
    noise_m = rng.normal(0.0, s.centroid_noise_px, uv_m.shape) if s.centroid_noise_px > 0 else 0.0
    blobs.add(fm, uv_m + noise_m, uv_m, a_m, np.maximum(p_m * s.floor_mirror, 1.0), d_m,
              np.full(len(fm), -1), np.full(len(fm), SPURIOUS_MIRROR), m.row_dt_ns[fm, mm])


def _add_spurious_blobs(s: Scenario, cam: Camera, ex: _Exposures, rng, blobs: _BlobColumns) -> None:
    """Static reflections in every frame the station keeps, and Poisson glints."""
    K = len(ex.k)
    keep = np.nonzero(~ex.drop)[0]
    suv, sarea, speak = _static_spurious(s, cam)
    S = len(suv)
    if S:
        sf = np.repeat(keep, S)
        s_true = np.tile(suv, (len(keep), 1))
        s_xy = s_true + (rng.normal(0.0, s.centroid_noise_px, s_true.shape) if s.centroid_noise_px > 0 else 0.0)
        blobs.add(sf, s_xy, s_true, np.tile(sarea, len(keep)), np.tile(speak, len(keep)),
                  np.tile(2 * np.sqrt(sarea / np.pi), len(keep)), np.full(len(sf), -1),
                  np.full(len(sf), SPURIOUS_STATIC), np.zeros(len(sf)))
    n_rand = rng.poisson(s.random_spurious_per_frame, K) * (~ex.drop)
    if n_rand.sum():
        rf = np.repeat(np.arange(K), n_rand)
        nr = len(rf)
        r_xy = np.column_stack([rng.uniform(0, cam.model.width - 1, nr), rng.uniform(0, cam.model.height - 1, nr)])
        r_area = rng.uniform(1.0, 12.0, nr)
        blobs.add(rf, r_xy, r_xy, r_area, rng.uniform(40.0, 255.0, nr), 2 * np.sqrt(r_area / np.pi),
                  np.full(nr, -1), np.full(nr, SPURIOUS_RANDOM), np.zeros(nr))


def _camera_chunk(s: Scenario, cam: Camera, t: CameraTiming, chunk: int, t0: float, t1: float, dropped):
    """Frames of one camera with nominal exposure in [t0, t1) ns after start: [(BlobFrame, FrameTruth)].

    The random draws happen in a fixed order (exposures, marker noise, mirror images, reflections, glints,
    the shuffle), so a chunk is the same for the same seed however it is reached."""
    k = _frame_range(t, t0, t1)
    if len(k) == 0:
        return []
    rng = rng_for(s.seed, TAG_FRAMES, cam.id, chunk)
    ex = _exposures(s, t, k, rng)
    m = _markers_at(s, cam, t, ex.true_ns)
    blobs = _BlobColumns()
    _add_marker_blobs(s, cam, m, _visible(s, cam, m, ex), rng, blobs)
    _add_mirror_blobs(s, cam, m, ex, rng, blobs)
    _add_spurious_blobs(s, cam, ex, rng, blobs)
    return _frames(s, cam, t, ex, blobs.joined(), rng, dropped)


def _frames(s: Scenario, cam: Camera, t: CameraTiming, ex: _Exposures, c: dict[str, np.ndarray], rng,
            dropped) -> list:
    """The chunk's frames from its blob columns: off-sensor centroids removed, each frame's blobs shuffled,
    overlapping blobs merged, the station's blob cap applied; dropped frames noted in `dropped`."""
    K = len(ex.k)
    inside = cam.model.in_image(c["xy"])  # a noisy centroid pushed off the sensor is not detected
    sel = np.nonzero(inside)[0]
    # shuffle within each frame: random key, then stable sort by frame
    order = sel[np.lexsort((rng.random(len(sel)), c["frame"][sel]))]
    fi, xy, true_xy = c["frame"][order], c["xy"][order], c["true_xy"][order]
    area, peak, dpx = c["area"][order], c["peak"][order], c["diameter_px"][order]
    body_col, marker_col = c["body"][order], c["marker"][order]
    dt_col = np.round(c["row_dt_ns"][order]).astype(np.int64)
    bounds = np.searchsorted(fi, np.arange(K + 1))
    needs_merge = _touching_frames(xy, dpx, bounds) if s.merge_blobs else np.zeros(K, bool)

    out = []
    for j in range(K):
        if ex.drop[j]:
            if dropped is not None:
                dropped[cam.id].append(int(ex.k[j]))
            continue
        a, b = bounds[j], bounds[j + 1]
        fxy, ftrue, farea, fpeak = xy[a:b], true_xy[a:b], area[a:b], peak[a:b]
        fbody, fmark, fd, fdt = body_col[a:b], marker_col[a:b], dpx[a:b], dt_col[a:b]
        merged = np.zeros(b - a, bool)
        if needs_merge[j]:
            fxy, ftrue, farea, fpeak, fbody, fmark, merged, fdt = _merge(
                fxy, ftrue, farea, fpeak, fbody, fmark, fd, fdt
            )
        flags = 0
        if len(fxy) > s.max_blobs:
            # detectors scan in raster order and stop at their cap
            ras = np.lexsort((fxy[:, 0], np.floor(fxy[:, 1])))[: s.max_blobs]
            ras.sort()
            fxy, ftrue, farea, fpeak, fbody, fmark, merged, fdt = (
                v[ras] for v in (fxy, ftrue, farea, fpeak, fbody, fmark, merged, fdt)
            )
            flags |= FLAG_TRUNCATED
        blobs = np.empty((len(fxy), 4), np.float32)
        blobs[:, 0:2] = fxy
        blobs[:, 2] = farea
        blobs[:, 3] = fpeak
        frame = BlobFrame(
            camera_id=cam.id,
            seq=int(ex.k[j]),
            capture_ns=int(ex.capture_ns[j]),
            blobs=blobs,
            station_id=t.station_id,
            flags=flags,
            recv_ns=int(ex.recv_ns[j]),
        )
        truth = FrameTruth(
            cam.id, int(ex.k[j]), int(ex.true_ns[j]), int(ex.station_ns[j]),
            fbody.astype(np.int64), fmark.astype(np.int64), np.asarray(ftrue, np.float64), merged,
            int(ex.true_ns[j]) + np.asarray(fdt, np.int64),
        )  # fmt: skip
        out.append((frame, truth))
    return out


def _touching_frames(xy: np.ndarray, dpx: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """(K,) bool: frame has two blobs whose discs overlap. xy (N, 2) and dpx (N,)
    sorted by frame; frame j owns rows bounds[j]:bounds[j+1]."""
    counts = np.diff(bounds)
    K = len(counts)
    if K == 0 or counts.max(initial=0) < 2:
        return np.zeros(K, bool)
    nmax = int(counts.max())
    pos = np.arange(len(xy)) - np.repeat(bounds[:-1], counts)
    frame = np.repeat(np.arange(K), counts)
    P = np.full((K, nmax, 2), np.nan)
    D = np.zeros((K, nmax))
    P[frame, pos] = xy
    D[frame, pos] = dpx
    d = np.linalg.norm(P[:, :, None] - P[:, None], axis=3)
    with np.errstate(invalid="ignore"):
        touch = d < (D[:, :, None] + D[:, None]) / 2
    touch[:, np.arange(nmax), np.arange(nmax)] = False
    return touch.any(axis=(1, 2))


def _merge(xy, true_xy, area, peak, body, marker, dpx, dt):
    """Merge blobs whose discs overlap (centre distance < sum of radii) into one.

    Centroid and true pixel are the area*peak weighted means; area adds, peak
    is the max; the label and row time offset dt are the heaviest part's.
    Returns the reduced arrays and a merged flag (N',)."""
    n = len(xy)
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    touch = d < (dpx[:, None] + dpx[None]) / 2
    np.fill_diagonal(touch, False)
    if not touch.any():
        return xy, true_xy, area, peak, body, marker, np.zeros(n, bool), dt
    # connected groups: transitive closure by repeated squaring of the adjacency
    reach = (touch | np.eye(n, dtype=bool)).astype(np.int32)
    while True:
        nxt = ((reach @ reach) > 0).astype(np.int32)
        if np.array_equal(nxt, reach):
            break
        reach = nxt
    _, inv = np.unique(reach.argmax(axis=1), return_inverse=True)  # group = its lowest member
    g = int(inv.max()) + 1
    w = area * peak
    wsum = np.bincount(inv, w, g)
    mean = lambda v: np.column_stack([np.bincount(inv, w * v[:, k], g) / wsum for k in range(2)])  # noqa: E731
    pk = np.zeros(g)
    np.maximum.at(pk, inv, peak)
    order = np.lexsort((w, inv))  # within each group, heaviest last
    heavy = order[np.searchsorted(inv[order], np.arange(g), side="right") - 1]
    merged = np.bincount(inv, minlength=g) > 1
    return mean(xy), mean(true_xy), np.bincount(inv, area, g), pk, body[heavy], marker[heavy], merged, dt[heavy]
