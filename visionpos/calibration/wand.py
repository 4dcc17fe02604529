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
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from visionpos.camera.model import Camera
from visionpos.errors import VisionposError
from visionpos.messages import BlobFrame


class CalibrationError(VisionposError, ValueError):
    """Calibration input that cannot give a calibration; the message says what to capture or fix."""


@dataclass(frozen=True)
class WandSpec:
    """Collinear 3-marker wand: A and B are `ab` metres apart, B and C `bc` (A is nearer to B)."""

    ab: float = 0.054
    bc: float = 0.103

    def __post_init__(self) -> None:
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
    """

    cameras: list[Camera]
    times_ns: np.ndarray
    pixels: np.ndarray
    stats: dict[int, CameraWandStats] = field(default_factory=dict)

    @property
    def seen(self) -> np.ndarray:
        """(F, V) bool: camera v saw the whole wand at grid time f."""
        return np.isfinite(self.pixels).all(axis=(2, 3))

    def subset(self, idx: np.ndarray) -> "WandData":
        return WandData(self.cameras, self.times_ns[idx], self.pixels[idx], self.stats)


def collect_wand(
    frames: Sequence[BlobFrame],
    cameras: Sequence[Camera],
    spec: WandSpec,
    rate_hz: float = 50.0,
    max_gap_periods: float = 1.6,
    min_labelled: int = 100,
    align: str = "interpolate",
    max_skew_ns: int = 2_000_000,
) -> WandData:
    """BlobFrames of a wand wave -> WandData on a common time grid.

    align: 'interpolate' (linear between the camera's labelled frames around each grid
    time) or 'nearest' (the camera's closest labelled frame within max_skew_ns).
    Raises CalibrationError naming any camera that saw too few wand frames.
    """
    if align not in ("interpolate", "nearest"):
        raise CalibrationError(f"time alignment '{align}' is unknown; use interpolate or nearest")
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
            "these cameras, with all three markers visible and the wand across the view (not pointed at the camera)"
        )
    grid = common_grid([t for t, _ in tracks], rate_hz)
    V = len(cameras)
    pixels = np.full((len(grid), V, 3, 2), np.nan)
    for v, (cam, (t, p)) in enumerate(zip(cameras, tracks)):
        period = stats[cam.id].frame_period_ns or int(1e9 / max(cam.fps, 1.0))
        if align == "interpolate":
            pixels[:, v] = interpolate_track(t, p, grid, int(max_gap_periods * period))
        else:
            pixels[:, v] = nearest_track(t, p, grid, max_skew_ns)
    keep = np.isfinite(pixels).all(axis=(2, 3)).sum(axis=1) >= 2
    return WandData(list(cameras), grid[keep], pixels[keep], stats)
