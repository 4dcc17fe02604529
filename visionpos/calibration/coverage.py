"""How far a wand wave has got: image coverage per camera, frames shared per camera pair, "enough".

The console's calibration assistant (console/calibration.py) feeds a `WandCoverage` the frames of a
wand wave as they arrive, a chunk at a time, and shows its `summary()`. The wand is found by the
solver's own labeller (wand.label_camera: three collinear blobs, static blobs removed) and the
cameras are brought to common times by the solver's own rule (wand.align_tracks: a 50 Hz grid,
each camera interpolated between its labelled frames no more than 1.6 frame periods apart), so a
pair's shared frames are the time steps the solve would give that pair, before clock offsets
(the solve estimates those; the live count takes the stamps as they are).

"Enough" (`Thresholds`) is the solver's minimums with a margin, plus image coverage:
- every camera has labelled `min_camera_frames` wand frames (the solve refuses fewer than
  MIN_WAND_FRAMES = 100; it drops inconsistent ones, and more frames narrow each pose);
- `min_steps` time steps see the wand in two or more cameras (the solve needs MIN_WAND_FRAMES);
- the pairs sharing at least `min_pair_frames` time steps connect every camera (the solve chains
  relative poses along pairs sharing at least MIN_SHARED_FRAMES = 40);
- every camera has wand markers in `min_coverage` of its image cells (a grid of `cols` x `rows`, a
  cell counting once it holds `min_cell_markers` labelled markers). The solver needs no coverage,
  but a wave that stays in the middle of each image fits the distortion and the poses only there.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from visionpos.calibration.wand import (
    GRID_RATE_HZ,
    MIN_SHARED_FRAMES,
    MIN_WAND_FRAMES,
    CameraWandStats,
    WandSpec,
    align_tracks,
    label_camera,
)
from visionpos.camera.model import Camera
from visionpos.messages import BlobFrame


@dataclass(frozen=True)
class Thresholds:
    """When a wave is enough (module docstring); frame counts are time steps of the solver's grid."""

    min_camera_frames: int = 3 * MIN_WAND_FRAMES
    min_steps: int = 3 * MIN_WAND_FRAMES
    min_pair_frames: int = int(2.5 * MIN_SHARED_FRAMES)
    min_coverage: float = 0.5
    min_cell_markers: int = 3
    cols: int = 8
    rows: int = 6


def coverage_grid(pixels: np.ndarray, width_px: int, height_px: int, cols: int, rows: int) -> np.ndarray:
    """Markers per image cell: pixels (n, 3, 2) labelled A, B, C (px, NaN = none) -> (rows, cols) int64.

    The image (width_px x height_px) is split into cols x rows equal cells; each marker counts in
    the cell it lies in; markers outside the image or NaN are not counted.
    """
    p = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    ok = np.isfinite(p).all(axis=1) & (p[:, 0] >= 0) & (p[:, 0] < width_px) & (p[:, 1] >= 0) & (p[:, 1] < height_px)
    cx = (p[ok, 0] * cols / width_px).astype(np.int64)
    cy = (p[ok, 1] * rows / height_px).astype(np.int64)
    return np.bincount(cy * cols + cx, minlength=rows * cols).reshape(rows, cols)


def covered_fraction(counts: np.ndarray, min_markers: int) -> float:
    """Share of cells (0..1) of a coverage grid holding at least min_markers markers."""
    c = np.asarray(counts)
    return float((c >= min_markers).sum() / c.size) if c.size else 0.0


def shared_steps(seen: np.ndarray) -> np.ndarray:
    """Time steps each camera pair shares: seen (F, V) bool (camera v saw the whole wand at step f) -> (V, V) int64,
    the diagonal each camera's own steps."""
    s = np.asarray(seen, dtype=np.int64)
    return s.T @ s


def components(shared: np.ndarray, min_frames: int) -> list[list[int]]:
    """Groups of cameras (indices, ascending) connected through pairs sharing at least min_frames steps; one group
    holding every camera means the solve can chain a pose to each."""
    V = len(shared)
    parent = list(range(V))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for i in range(V):
        for j in range(i + 1, V):
            if shared[i, j] >= min_frames:
                parent[root(j)] = root(i)
    groups: dict[int, list[int]] = {}
    for v in range(V):
        groups.setdefault(root(v), []).append(v)
    return sorted(groups.values())


def verdict(names: Sequence[str], labelled: np.ndarray, coverage: np.ndarray, shared: np.ndarray, steps: int,
            th: Thresholds) -> list[str]:
    """What is still missing, in words (empty = enough).

    names: (V,) camera names; labelled: (V,) wand frames labelled per camera; coverage: (V,) covered fraction
    (0..1); shared: (V, V) time steps shared per pair; steps: time steps with the wand in >= 2 cameras.
    """
    out = []
    for v, name in enumerate(names):
        if labelled[v] < th.min_camera_frames:
            out.append(f"camera {name} has {int(labelled[v])} wand frames, want {th.min_camera_frames}")
        if coverage[v] < th.min_coverage:
            out.append(f"camera {name} covers {100 * coverage[v]:.0f} % of its image, want "
                       f"{100 * th.min_coverage:.0f} %: wave the wand where it sees little yet (its heat map)")
    if steps < th.min_steps:
        out.append(f"{steps} time steps see the wand in two or more cameras, want {th.min_steps}")
    groups = components(shared, th.min_pair_frames)
    if len(groups) > 1:
        biggest = max(groups, key=len)
        for g in groups:
            if g is biggest:
                continue
            best = max((int(shared[a, b]), a, b) for a in g for b in biggest)
            out.append(f"camera(s) {', '.join(names[v] for v in g)} not connected to the others: the best pair "
                       f"{names[best[1]]}-{names[best[2]]} shares {best[0]} frames, want {th.min_pair_frames} "
                       "(wave where their views overlap)")
    return out


@dataclass
class _Track:
    """One camera's labelled wand frames so far and its coverage grid."""

    times: list[np.ndarray] = field(default_factory=list)
    pixels: list[np.ndarray] = field(default_factory=list)
    counts: np.ndarray | None = None
    frames: int = 0
    labelled: int = 0
    period_ns: int = 0


class WandCoverage:
    """A live wand wave's labelled tracks, coverage grids and pair counts, fed in chunks (add_frames)."""

    def __init__(self, cameras: Sequence[Camera], spec: WandSpec, thresholds: Thresholds = Thresholds()):
        self.cameras = list(cameras)
        self.spec = spec
        self.th = thresholds
        self.index = {c.id: v for v, c in enumerate(self.cameras)}
        self.tracks = [_Track(counts=np.zeros((thresholds.rows, thresholds.cols), np.int64)) for _ in self.cameras]

    def add_frames(self, frames: Sequence[BlobFrame]) -> None:
        """Label the wand in a chunk of frames (any cameras and order; unknown cameras ignored). Static blobs are
        found within the chunk, so a chunk should span a fraction of a second or more."""
        by_cam: dict[int, list[BlobFrame]] = {}
        for f in frames:
            if f.camera_id in self.index:
                by_cam.setdefault(f.camera_id, []).append(f)
        for cid, fs in by_cam.items():
            v = self.index[cid]
            cam, tr = self.cameras[v], self.tracks[v]
            t, p, st = label_camera(fs, cam, self.spec)
            tr.frames += st.frames
            tr.labelled += len(t)
            if st.frame_period_ns:
                tr.period_ns = st.frame_period_ns
            if len(t):
                tr.times.append(t)
                tr.pixels.append(p)
                tr.counts += coverage_grid(p, cam.model.width, cam.model.height, self.th.cols, self.th.rows)

    def _aligned(self) -> np.ndarray:
        """(F, V) bool: the solver's time steps (grid, interpolation) with the wand in >= 2 cameras."""
        tracks, stats = [], {}
        for cam, tr in zip(self.cameras, self.tracks):
            if tr.times:
                t = np.concatenate(tr.times)
                p = np.concatenate(tr.pixels)
                order = np.argsort(t, kind="stable")
                tracks.append((t[order], p[order]))
            else:
                tracks.append((np.zeros(0, np.int64), np.zeros((0, 3, 2))))
            stats[cam.id] = CameraWandStats(frame_period_ns=tr.period_ns)
        return align_tracks(self.cameras, tracks, stats, rate_hz=GRID_RATE_HZ).seen

    def summary(self) -> dict:
        """JSON-ready: per camera its counts and coverage grid, per pair its shared steps, the verdict.

        {"cameras": [{"id", "name", "frames", "labelled", "coverage" (0..1), "grid" (rows x cols markers),
        "cols", "rows"}], "pairs": [{"a", "b" (camera ids), "frames"}], "steps", "enough", "missing": [str],
        "thresholds": {...}, "solvable": the solver's minimums are met}
        """
        seen = self._aligned()
        shared = shared_steps(seen)
        steps = int(len(seen))
        labelled = np.array([tr.labelled for tr in self.tracks])
        cov = np.array([covered_fraction(tr.counts, self.th.min_cell_markers) for tr in self.tracks])
        names = [c.name for c in self.cameras]
        missing = verdict(names, labelled, cov, shared, steps, self.th)
        solvable = (bool((labelled >= MIN_WAND_FRAMES).all()) and steps >= MIN_WAND_FRAMES
                    and len(components(shared, MIN_SHARED_FRAMES)) == 1)
        V = len(self.cameras)
        return {
            "cameras": [{"id": c.id, "name": c.name, "frames": tr.frames, "labelled": tr.labelled,
                         "coverage": round(float(cov[v]), 4), "grid": tr.counts.tolist(),
                         "width": c.model.width, "height": c.model.height}
                        for v, (c, tr) in enumerate(zip(self.cameras, self.tracks))],
            "pairs": [{"a": self.cameras[i].id, "b": self.cameras[j].id, "frames": int(shared[i, j])}
                      for i in range(V) for j in range(i + 1, V)],
            "steps": steps,
            "enough": not missing,
            "missing": missing,
            "solvable": solvable,
            "thresholds": {"camera_frames": self.th.min_camera_frames, "steps": self.th.min_steps,
                           "pair_frames": self.th.min_pair_frames, "coverage": self.th.min_coverage,
                           "cell_markers": self.th.min_cell_markers, "cols": self.th.cols, "rows": self.th.rows},
        }
