"""Wand observations: label A/B/C in every camera frame and align cameras in time.

The wand is three collinear markers A-B-C with known lengths AB and BC
(thesis Fig. 2.4: 5.4 cm and 10.3 cm). In each camera frame we look, in
undistorted normalised coordinates (where straight lines stay straight), for
a triple of blobs that is collinear; the middle one is B and the end nearer
to B is A. Perspective changes the AB:AC ratio a little, but never turns the
short side into the long one unless the wand points almost at the camera,
so frames whose ratio is too close to 1:2 are dropped as ambiguous.

Blobs that sit still for a large part of the recording (other cameras' LED
rings, floor reflections) are removed per camera before labelling.

Cameras are asynchronous: every camera's labelled A/B/C pixel tracks are
linearly interpolated to one common time grid (as the thesis did at 100 Hz);
a grid time is used for a camera only when labelled frames sit on both sides
of it within about one frame period.

Their clocks may also disagree (a station whose clock sync is off by a few to
tens of ms). `estimate_offsets` finds each camera's offset before the poses are
known: for every camera pair and every candidate offset on a grid, one track is
interpolated to the other's (shifted) frame times and a linear essential
matrix is fitted; the wand is moving, so only the right offset makes all
frames agree with one epipolar geometry (smallest Sampson residual). The pair
offsets are then combined per camera by least squares; the bundle adjustment
refines them (bundle.py).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from visionpos.camera.model import Camera
from visionpos.errors import VisionposError
from visionpos.geometry.epipolar import sampson_distance
from visionpos.messages import BlobFrame


class CalibrationError(VisionposError, ValueError):
    """Calibration input that cannot give a calibration; the message says what to capture or fix."""


WAND_SEGMENTS = ("ab", "bc", "ac")
# the wand solve's minimums (calibrate_wand, initial_poses) and its time grid; the console's
# calibration assistant (visionpos/calibration/coverage.py) judges a live wave against them
MIN_WAND_FRAMES = 100  # labelled frames per camera, and time steps with the wand in >= 2 cameras
MIN_SHARED_FRAMES = 40  # time steps a camera pair must share for its relative pose
GRID_RATE_HZ = 50.0  # the common time grid the cameras' tracks are brought to


@dataclass(frozen=True)
class WandSpec:
    """Collinear 3-marker wand: A and B are `ab` metres apart, B and C `bc` (A is nearer to B).

    known: the segment whose length is trusted (measured most precisely); it sets the scale
    and the wand check derives the other two from the measured ratio.
    """

    ab: float = 0.054
    bc: float = 0.103
    known: str = "ac"

    def __post_init__(self) -> None:
        if self.known not in WAND_SEGMENTS:
            raise CalibrationError(
                f"wand known length '{self.known}' is unknown; use one of {', '.join(WAND_SEGMENTS)}"
            )
        if not (self.ab > 0 and self.bc > 0):
            raise CalibrationError(f"wand lengths must be positive, got AB={self.ab} BC={self.bc}")
        if abs(self.ab - self.bc) < 0.15 * (self.ab + self.bc):
            raise CalibrationError(
                f"wand AB={self.ab} m and BC={self.bc} m are too similar to tell A from C; "
                "use a wand whose middle marker is clearly off-centre (e.g. 1:2)"
            )
        if self.ab > self.bc:
            raise CalibrationError(f"wand AB={self.ab} m must be the shorter side (BC={self.bc} m); swap them")

    @property
    def ac(self) -> float:
        return self.ab + self.bc

    @property
    def offsets(self) -> np.ndarray:
        """(3,) distance of A, B, C from A along the wand (m)."""
        return np.array([0.0, self.ab, self.ac])

    @property
    def ratio(self) -> float:
        """AB / AC."""
        return self.ab / self.ac

    def length(self, segment: str) -> float:
        """Configured length (m) of 'ab', 'bc' or 'ac'."""
        return {"ab": self.ab, "bc": self.bc, "ac": self.ac}[segment]

    def offsets_for_ratio(self, ratio: float) -> tuple[np.ndarray, np.ndarray]:
        """(offsets (3,) of A, B, C along the wand, d offsets / d ratio (3,)) for a wand with
        AB/AC = ratio and the `known` segment at its configured length."""
        r = float(ratio)
        if self.known == "ac":
            L = self.ac
            return np.array([0.0, r * L, L]), np.array([0.0, L, 0.0])
        if self.known == "ab":
            L = self.ab
            return np.array([0.0, L, L / r]), np.array([0.0, 0.0, -L / r**2])
        L = self.bc
        return np.array([0.0, L * r / (1 - r), L / (1 - r)]), np.array([0.0, L, L]) / (1 - r) ** 2


# ------------------------------------------------------------------ labelling
def label_triples(
    xn: np.ndarray,
    spec: WandSpec,
    tol: float | np.ndarray,
    min_length: float | np.ndarray = 0.0,
    ratio_tol: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Order blob triples as A, B, C.

    xn: (T, 3, 2) undistorted normalised coordinates of T candidate triples.
    tol: scalar or (T,), largest distance of the middle blob from the line
    through the end blobs (normalised units, i.e. px / focal length).
    min_length: scalar or (T,), shortest accepted image length A..C.
    Returns labelled (T, 3, 2) rows A, B, C (NaN where rejected) and ok (T,) bool.
    """
    P = np.asarray(xn, dtype=np.float64)
    T = len(P)
    out = np.full((T, 3, 2), np.nan)
    if T == 0:
        return out, np.zeros(0, bool)
    # pair distances opposite each vertex: d[:, m] = distance between the other two
    d = np.stack(
        [
            np.linalg.norm(P[:, 1] - P[:, 2], axis=1),
            np.linalg.norm(P[:, 0] - P[:, 2], axis=1),
            np.linalg.norm(P[:, 0] - P[:, 1], axis=1),
        ],
        axis=1,
    )
    mid = np.argmax(d, axis=1)  # the middle blob is opposite the longest side
    e1 = (mid + 1) % 3
    e2 = (mid + 2) % 3
    r = np.arange(T)
    Pm, P1, P2 = P[r, mid], P[r, e1], P[r, e2]
    L = d[r, mid]
    v = P2 - P1
    w = Pm - P1
    with np.errstate(divide="ignore", invalid="ignore"):
        perp = np.abs(v[:, 0] * w[:, 1] - v[:, 1] * w[:, 0]) / L
        d1 = np.linalg.norm(Pm - P1, axis=1)
        d2 = np.linalg.norm(Pm - P2, axis=1)
        ratio = np.minimum(d1, d2) / L
    ok = (
        np.isfinite(perp)
        & (L > min_length)
        & (perp < tol)
        & (np.abs(ratio - spec.ratio) < ratio_tol)
        & (ratio < 0.45)  # closer to 1:2 the ends cannot be told apart
    )
    a_first = d1 <= d2
    A = np.where(a_first[:, None], P1, P2)
    C = np.where(a_first[:, None], P2, P1)
    out[ok, 0] = A[ok]
    out[ok, 1] = Pm[ok]
    out[ok, 2] = C[ok]
    return out, ok


def static_blob_mask(points: Sequence[np.ndarray], cell: float = 2.0, min_fraction: float = 0.2) -> list[np.ndarray]:
    """Flag blobs that sit still across the recording (LED rings, reflections).

    points: per frame an (N_i, 2) pixel array. A blob is static when its
    `cell`-pixel grid cell (or a neighbouring one) holds a blob in at least
    `min_fraction` of the frames. Returns per frame an (N_i,) bool mask, True = static.
    """
    n_frames = len(points)
    if n_frames == 0:
        return []
    sizes = np.array([len(p) for p in points])
    allp = np.concatenate([np.asarray(p, float).reshape(-1, 2) for p in points]) if sizes.sum() else np.zeros((0, 2))
    if len(allp) == 0:
        return [np.zeros(0, bool) for _ in points]
    frame_of = np.repeat(np.arange(n_frames), sizes)
    cells = np.floor(allp / cell).astype(np.int64)
    ok = np.isfinite(allp).all(axis=1)
    key = cells[:, 0] * 1_000_003 + cells[:, 1]
    # count distinct frames per cell (a frame with two blobs in one cell counts once)
    pair = np.unique(np.stack([key[ok], frame_of[ok]], axis=1), axis=0)
    ukey, counts = np.unique(pair[:, 0], return_counts=True)
    static_cells = ukey[counts >= max(3, min_fraction * n_frames)]
    if static_cells.size == 0:
        return [np.zeros(s, bool) for s in sizes]
    flag = np.zeros(len(allp), bool)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            k2 = (cells[:, 0] + dx) * 1_000_003 + (cells[:, 1] + dy)
            flag |= np.isin(k2, static_cells)
    flag &= ok
    return list(np.split(flag, np.cumsum(sizes)[:-1]))


@dataclass
class CameraWandStats:
    """Per-camera labelling counts."""

    frames: int = 0
    with_blobs: int = 0
    labelled: int = 0
    static_blobs: int = 0
    ambiguous: int = 0
    frame_period_ns: int = 0


def label_camera(
    frames: Sequence[BlobFrame],
    camera: Camera,
    spec: WandSpec,
    tol_px: float = 1.5,
    min_length_px: float = 8.0,
    max_blobs: int = 8,
) -> tuple[np.ndarray, np.ndarray, CameraWandStats]:
    """Label the wand in one camera's frames.

    frames: this camera's BlobFrames in any order. Returns capture times (n,) int64
    (sorted), labelled pixels (n, 3, 2) rows A, B, C, and the counts.
    """
    frames = sorted(frames, key=lambda f: f.capture_ns)
    st = CameraWandStats(frames=len(frames))
    if not frames:
        return np.zeros(0, np.int64), np.zeros((0, 3, 2)), st
    times_all = np.array([f.capture_ns for f in frames], dtype=np.int64)
    if len(times_all) > 1:
        st.frame_period_ns = int(np.median(np.diff(times_all)))
    xy = [np.asarray(f.blobs, dtype=np.float64).reshape(-1, 4)[:, :2] for f in frames]
    static = static_blob_mask(xy)
    kept = [p[~s] for p, s in zip(xy, static)]
    st.static_blobs = int(sum(int(s.sum()) for s in static))
    counts = np.array([len(p) for p in kept])
    st.with_blobs = int((counts >= 3).sum())
    model = camera.model
    f_mean = 0.5 * (model.fx + model.fy)
    tol = tol_px / f_mean
    min_len = min_length_px / f_mean
    labelled = np.full((len(frames), 3, 2), np.nan)
    ok_all = np.zeros(len(frames), bool)
    # frames with exactly three blobs: one vectorised pass
    three = np.flatnonzero(counts == 3)
    if three.size:
        pix = np.stack([kept[i] for i in three])
        xn = model.undistort(pix.reshape(-1, 2)).reshape(-1, 3, 2)
        lab, ok = label_triples(xn, spec, tol, min_len)
        ok_all[three] = ok
        # keep the measured pixels (not undistorted) in A, B, C order
        order = _order_from_labels(xn, lab)
        labelled[three[ok]] = np.take_along_axis(pix[ok], order[ok][:, :, None], axis=1)
    # more blobs (glints, a hand near a marker): accept only one valid triple
    more = np.flatnonzero((counts > 3) & (counts <= max_blobs))
    for i in more:
        pts = kept[i]
        xn_pts = model.undistort(pts)
        combos = np.array(list(itertools.combinations(range(len(pts)), 3)))
        lab, ok = label_triples(xn_pts[combos], spec, tol, min_len)
        if ok.sum() == 1:
            c = combos[np.flatnonzero(ok)[0]]
            order = _order_from_labels(xn_pts[c][None], lab[ok])[0]
            labelled[i] = pts[c][order]
            ok_all[i] = True
        elif ok.sum() > 1:
            st.ambiguous += 1
    st.labelled = int(ok_all.sum())
    return times_all[ok_all], labelled[ok_all], st


def _order_from_labels(xn: np.ndarray, lab: np.ndarray) -> np.ndarray:
    """Index of the input blob that became A, B, C: xn (T,3,2), lab (T,3,2) -> (T,3) int."""
    d = np.linalg.norm(lab[:, :, None, :] - xn[:, None, :, :], axis=-1)  # (T, label, blob)
    d = np.where(np.isfinite(d), d, np.inf)
    return np.argmin(d, axis=2)


# -------------------------------------------------------------- time alignment
def common_grid(track_times: Sequence[np.ndarray], rate_hz: float) -> np.ndarray:
    """Grid times (F,) int64: at most one labelled frame time per 1/rate_hz bin,
    taken from the cameras' own frame times so synchronised cameras need no interpolation."""
    ts = [np.asarray(t, np.int64) for t in track_times if len(t)]
    if not ts:
        return np.zeros(0, np.int64)
    allt = np.sort(np.concatenate(ts))
    step = int(round(1e9 / rate_hz))
    t0 = allt[0]
    bins = (allt - t0) // step
    _, first = np.unique(bins, return_index=True)
    return allt[first]


def nearest_track(times: np.ndarray, pixels: np.ndarray, grid: np.ndarray, max_skew_ns: int) -> np.ndarray:
    """The alternative to interpolation: each grid time takes the camera's nearest labelled
    frame if it is within max_skew_ns. times (n,), pixels (n, 3, 2), grid (F,) -> (F, 3, 2)."""
    out = np.full((len(grid), 3, 2), np.nan)
    if len(times) == 0:
        return out
    r = np.clip(np.searchsorted(times, grid), 0, len(times) - 1)
    lft = np.clip(r - 1, 0, len(times) - 1)
    pick = np.where(np.abs(times[lft] - grid) < np.abs(times[r] - grid), lft, r)
    ok = np.abs(times[pick] - grid) <= max_skew_ns
    out[ok] = pixels[pick[ok]]
    return out


def interpolate_track(
    times: np.ndarray, pixels: np.ndarray, grid: np.ndarray, max_gap_ns: int
) -> np.ndarray:
    """Linear interpolation of one camera's labelled track to grid times.

    times: (n,) int64 sorted; pixels: (n, 3, 2); grid: (F,) int64.
    A grid time gets a value only where labelled frames lie on both sides of
    it no more than max_gap_ns apart (or one coincides with it within 1 us).
    Returns (F, 3, 2), NaN where not available.
    """
    F = len(grid)
    out = np.full((F, 3, 2), np.nan)
    n = len(times)
    if n == 0 or F == 0:
        return out
    right = np.searchsorted(times, grid, side="left")
    r = np.clip(right, 0, n - 1)
    lft = np.clip(right - 1, 0, n - 1)
    exact_r = np.abs(times[r] - grid) <= 1000
    exact_l = np.abs(times[lft] - grid) <= 1000
    gap = (times[r] - times[lft]).astype(np.float64)
    inside = (right > 0) & (right < n) & (gap > 0) & (gap <= max_gap_ns)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(inside, (grid - times[lft]) / np.where(gap > 0, gap, 1.0), 0.0)
    interp = pixels[lft] * (1 - w)[:, None, None] + pixels[r] * w[:, None, None]
    out[inside] = interp[inside]
    out[exact_l] = pixels[lft][exact_l]
    out[exact_r] = pixels[r][exact_r]
    return out


@dataclass
class WandData:
    """Labelled, time-aligned wand observations.

    camera_ids: (V,) ids in the order of `cameras`; times_ns: (F,) grid times;
    pixels: (F, V, 3, 2) distorted pixel positions of A, B, C (NaN = not seen).
    tracks: per camera its labelled frames (capture times (n,) int64, pixels (n, 3, 2)) as stamped;
    offsets_ns: (V,) clock offset of each camera's stamps that the grid was corrected for
    (a frame stamped s was captured at s - offset).
    """

    cameras: list[Camera]
    times_ns: np.ndarray
    pixels: np.ndarray
    stats: dict[int, CameraWandStats] = field(default_factory=dict)
    tracks: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    offsets_ns: np.ndarray | None = None

    @property
    def seen(self) -> np.ndarray:
        """(F, V) bool: camera v saw the whole wand at grid time f."""
        return np.isfinite(self.pixels).all(axis=(2, 3))

    def subset(self, idx: np.ndarray) -> "WandData":
        return WandData(self.cameras, self.times_ns[idx], self.pixels[idx], self.stats, self.tracks, self.offsets_ns)


def label_all(
    frames: Sequence[BlobFrame], cameras: Sequence[Camera], spec: WandSpec, min_labelled: int = MIN_WAND_FRAMES
) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict[int, CameraWandStats]]:
    """Label the wand in every camera: per camera (times (n,), pixels (n, 3, 2)) and the counts.
    Raises CalibrationError naming any camera that saw too few wand frames."""
    by_cam: dict[int, list[BlobFrame]] = {c.id: [] for c in cameras}
    for f in frames:
        if f.camera_id in by_cam:
            by_cam[f.camera_id].append(f)
    tracks = []
    stats: dict[int, CameraWandStats] = {}
    for cam in cameras:
        t, p, st = label_camera(by_cam[cam.id], cam, spec)
        tracks.append((t, p))
        stats[cam.id] = st
    few = [c for c in cameras if stats[c.id].labelled < min_labelled]
    if few:
        lines = [
            f"camera '{c.name}' (id {c.id}): {stats[c.id].labelled} wand frames labelled of {stats[c.id].frames} "
            f"({stats[c.id].with_blobs} with >= 3 blobs)"
            for c in few
        ]
        raise CalibrationError(
            "too few wand frames (need at least "
            f"{min_labelled} per camera):\n  " + "\n  ".join(lines) + "\nwave the wand longer inside the view of "
            "these cameras, with all three markers visible and the wand across the view (not pointed at the camera); "
            "a camera with frames but none labelled may have the wrong intrinsics, or a wand whose lengths "
            "(calibration.wand) do not match"
        )
    return tracks, stats


def _period_ns(cam: Camera, st: CameraWandStats) -> int:
    return st.frame_period_ns or int(1e9 / max(cam.fps, 1.0))


def align_tracks(
    cameras: Sequence[Camera],
    tracks: list[tuple[np.ndarray, np.ndarray]],
    stats: dict[int, CameraWandStats],
    offsets_ns: np.ndarray | None = None,
    rate_hz: float = GRID_RATE_HZ,
    max_gap_periods: float = 1.6,
    align: str = "interpolate",
    max_skew_ns: int = 2_000_000,
) -> WandData:
    """Labelled tracks -> WandData on a common time grid, each camera's stamps first corrected
    by its clock offset (offsets_ns (V,), None = all 0)."""
    if align not in ("interpolate", "nearest"):
        raise CalibrationError(f"time alignment '{align}' is unknown; use interpolate or nearest")
    V = len(cameras)
    off = np.zeros(V) if offsets_ns is None else np.asarray(offsets_ns, np.float64)
    shifted = [(t - np.int64(round(off[v])), p) for v, (t, p) in enumerate(tracks)]
    grid = common_grid([t for t, _ in shifted], rate_hz)
    pixels = np.full((len(grid), V, 3, 2), np.nan)
    for v, (cam, (t, p)) in enumerate(zip(cameras, shifted)):
        if align == "interpolate":
            pixels[:, v] = interpolate_track(t, p, grid, int(max_gap_periods * _period_ns(cam, stats[cam.id])))
        else:
            pixels[:, v] = nearest_track(t, p, grid, max_skew_ns)
    keep = np.isfinite(pixels).all(axis=(2, 3)).sum(axis=1) >= 2
    return WandData(list(cameras), grid[keep], pixels[keep], stats, list(tracks), off.copy())


def collect_wand(
    frames: Sequence[BlobFrame],
    cameras: Sequence[Camera],
    spec: WandSpec,
    rate_hz: float = GRID_RATE_HZ,
    max_gap_periods: float = 1.6,
    min_labelled: int = MIN_WAND_FRAMES,
    align: str = "interpolate",
    max_skew_ns: int = 2_000_000,
    offsets_ns: np.ndarray | None = None,
) -> WandData:
    """BlobFrames of a wand wave -> WandData on a common time grid.

    align: 'interpolate' (linear between the camera's labelled frames around each grid
    time) or 'nearest' (the camera's closest labelled frame within max_skew_ns).
    offsets_ns: (V,) clock offsets the cameras' stamps are corrected for (None = 0).
    Raises CalibrationError naming any camera that saw too few wand frames.
    """
    if align not in ("interpolate", "nearest"):
        raise CalibrationError(f"time alignment '{align}' is unknown; use interpolate or nearest")
    tracks, stats = label_all(frames, cameras, spec, min_labelled)
    return align_tracks(cameras, tracks, stats, offsets_ns, rate_hz, max_gap_periods, align, max_skew_ns)


# ------------------------------------------------------------- clock offsets
@dataclass
class PairOffset:
    """Clock offset of camera j minus camera i (ns) from their wand tracks.

    frames: shared frames at that offset; residual: RMS Sampson distance there (normalised
    units); contrast: that residual over the median one across the search (small = a clear
    minimum); edge: the minimum lies at the end of the search range.
    """

    i: int
    j: int
    offset_ns: float
    frames: int
    residual: float
    contrast: float
    edge: bool

    @property
    def usable(self) -> bool:
        return not self.edge and self.contrast < 0.5


def _epipolar_cost(ti: np.ndarray, xi: np.ndarray, tj: np.ndarray, xj: np.ndarray, d_ns: float,
                   max_gap_ns: int, min_frames: int) -> tuple[float, int]:
    """(RMS Sampson distance of a linear essential-matrix fit, frames) with camera j's track read at
    camera i's times + d_ns; inf when fewer than min_frames frames are shared."""
    yj = interpolate_track(tj, xj, ti + np.int64(round(d_ns)), max_gap_ns)
    ok = np.isfinite(yj).all(axis=(1, 2))
    n = int(ok.sum())
    if n < min_frames:
        return float("inf"), n
    p1 = xi[ok].reshape(-1, 2)
    p2 = yj[ok].reshape(-1, 2)
    # linear fit of x2^T E x1 = 0 (9 unknowns) by the normal equations: only compared across offsets,
    # so neither Hartley normalisation (normalised coordinates are well scaled) nor rank 2 is needed
    M = np.einsum("ni,nj->nij", np.column_stack([p2, np.ones(len(p2))]),
                  np.column_stack([p1, np.ones(len(p1))])).reshape(-1, 9)
    E = np.linalg.eigh(M.T @ M)[1][:, 0].reshape(3, 3)
    s2 = np.sort(sampson_distance(E, p1, p2) ** 2)
    # the few mislabelled frames must not decide: the best 90 %
    return float(np.sqrt(s2[: max(1, int(0.9 * len(s2)))].mean())), n


def pair_offset(
    ti: np.ndarray, xi: np.ndarray, tj: np.ndarray, xj: np.ndarray, max_gap_ns: int, search_ns: float,
    step_ns: float = 1e6, min_frames: int = 40, max_frames: int = 300,
) -> PairOffset | None:
    """Clock offset of camera j minus camera i within +-search_ns.

    ti, tj: (n,) sorted stamps; xi, xj: (n, 3, 2) undistorted normalised A, B, C. A grid
    search (step_ns), then a finer one (step_ns / 10) around its best, then a parabola.
    Returns None when fewer than min_frames frames are shared at every offset.
    """
    if len(ti) > max_frames:  # camera i's frames only pick the times: a spread subset is plenty
        sel = np.linspace(0, len(ti) - 1, max_frames).round().astype(int)
        ti, xi = ti[sel], xi[sel]
    grid = np.arange(-search_ns, search_ns + 0.5 * step_ns, step_ns)
    cost = np.array([_epipolar_cost(ti, xi, tj, xj, d, max_gap_ns, min_frames)[0] for d in grid])
    finite = np.isfinite(cost)
    if not finite.any():
        return None
    b = int(np.argmin(np.where(finite, cost, np.inf)))
    edge = b < 2 or b > len(grid) - 3
    contrast = float(cost[b] / np.median(cost[finite])) if np.median(cost[finite]) > 0 else 1.0
    fine_step = step_ns / 10
    fine = grid[b] + np.arange(-15, 16) * fine_step
    fc = np.array([_epipolar_cost(ti, xi, tj, xj, d, max_gap_ns, min_frames)[0] for d in fine])
    k = int(np.argmin(fc))
    best = float(fine[k])
    if 0 < k < len(fine) - 1 and np.isfinite(fc[k - 1:k + 2]).all():
        y0, y1, y2 = fc[k - 1] ** 2, fc[k] ** 2, fc[k + 1] ** 2
        den = y0 - 2 * y1 + y2
        if den > 0:
            best += float(np.clip(0.5 * (y0 - y2) / den, -1, 1)) * fine_step
    res, n = _epipolar_cost(ti, xi, tj, xj, best, max_gap_ns, min_frames)
    return PairOffset(-1, -1, best, n, res, contrast, edge)


@dataclass
class OffsetEstimate:
    """Per-camera clock offsets (V,) ns relative to camera `ref`, the pair estimates behind
    them and, per camera not reached by a usable pair, why."""

    offsets_ns: np.ndarray
    pairs: list[PairOffset]
    problems: list[str]


def estimate_offsets(
    cameras: Sequence[Camera],
    tracks: list[tuple[np.ndarray, np.ndarray]],
    stats: dict[int, CameraWandStats],
    max_offset_ms: float,
    ref: int = 0,
    max_gap_periods: float = 1.6,
    min_frames: int = 40,
) -> OffsetEstimate:
    """Each camera's clock offset (ns, camera `ref` = 0) from the wand tracks alone.

    Every camera pair is searched over +-2 max_offset_ms (both may be off by max_offset_ms
    in opposite directions); the usable pair offsets are combined by least squares, pairs
    that disagree with the rest by more than 1 ms dropped one at a time.
    """
    V = len(cameras)
    xn = [cam.model.undistort(p.reshape(-1, 2)).reshape(-1, 3, 2) if len(p) else p
          for cam, (_, p) in zip(cameras, tracks)]
    pairs: list[PairOffset] = []
    problems: list[str] = []
    search = 2 * max_offset_ms * 1e6
    for i, j in itertools.combinations(range(V), 2):
        ti, tj = tracks[i][0], tracks[j][0]
        if len(ti) < min_frames or len(tj) < min_frames:
            continue
        gap = int(max_gap_periods * _period_ns(cameras[j], stats[cameras[j].id]))
        po = pair_offset(ti, xn[i], tj, xn[j], gap, search, min_frames=min_frames)
        if po is None:
            continue
        po.i, po.j = i, j
        pairs.append(po)
    names = [c.name for c in cameras]
    use = [p for p in pairs if p.usable]
    offsets = np.zeros(V)
    while True:
        reached = {ref}
        changed = True
        while changed:  # cameras connected to ref through usable pairs
            changed = False
            for p in use:
                if (p.i in reached) != (p.j in reached):
                    reached |= {p.i, p.j}
                    changed = True
        idx = {v: k for k, v in enumerate(v for v in range(V) if v != ref and v in reached)}
        if not use or not idx:
            break
        rows = [p for p in use if p.i in reached and p.j in reached]
        Amat = np.zeros((len(rows), len(idx)))
        b = np.zeros(len(rows))
        w = np.array([np.sqrt(p.frames) / max(p.residual, 1e-12) for p in rows])
        for r, p in enumerate(rows):
            if p.j in idx:
                Amat[r, idx[p.j]] = 1.0
            if p.i in idx:
                Amat[r, idx[p.i]] = -1.0
            b[r] = p.offset_ns
        sol = np.linalg.lstsq(Amat * w[:, None], b * w, rcond=None)[0]
        err = np.abs(Amat @ sol - b)
        worst = int(np.argmax(err))
        if err[worst] > 1e6 and len(rows) > len(idx):
            use.remove(rows[worst])
            continue
        offsets[:] = 0.0
        for v, k in idx.items():
            offsets[v] = sol[k]
        break
    for v in range(V):
        if v == ref or any(p.usable and v in (p.i, p.j) for p in use):
            continue
        mine = [p for p in pairs if v in (p.i, p.j)]
        if not mine:
            why = "it shares too few wand frames with any other camera"
        elif all(p.edge for p in mine):
            why = (f"its best match with every other camera lies at the end of the search range "
                   f"(+-{2 * max_offset_ms:.0f} ms between two cameras): its clock may be off by more than "
                   f"{max_offset_ms:.0f} ms (check the station's clock sync, or raise the maximum clock offset)")
        else:
            why = (f"no offset within the search range (+-{2 * max_offset_ms:.0f} ms between two cameras) makes its "
                   "wand track agree with another camera's; likely causes: its clock off by more than "
                   f"{max_offset_ms:.0f} ms (check the station's clock sync, or raise the maximum clock offset), too "
                   "few frames shared with other cameras, the wand moving too little, wrong intrinsics, or blobs "
                   "that are not the wand")
        problems.append(f"camera {names[v]}: clock offset not estimated, kept at 0: {why}")
    return OffsetEstimate(offsets, pairs, problems)
