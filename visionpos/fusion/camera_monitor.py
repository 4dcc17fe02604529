"""Continuous calibration: notice a camera that was knocked, and correct its pose while tracking goes on.

Every tracked body is a calibration object of known geometry. For a sample of each camera's frames the
monitor predicts the tracked bodies' markers at the frame's capture time (the fused state moved by its
velocities), projects them with the camera's current pose, and pairs them with the frame's blobs when
the pairing is unambiguous. It keeps each camera's recent pairs (marker in the world, blob pixel), and
once a second fits a small correction of that camera's pose to them by robust Gauss-Newton
(geometry/resection.py's `pose_correction`, a 6-parameter resection with the markers held fixed).

A camera is flagged as moved when its correction is both significant (chi-square of the correction
against the fit's own noise) and visible (it moves the camera's markers by more than `flag_px` pixels
RMS in its image, well above what an unmoved camera shows), and it is the camera whose correction is
largest: the fused poses lean a little toward a knocked camera, so the others show small opposite
corrections. With `correct: true` the correction is applied to the pipeline's camera (bounded per
step), the camera's pairs are dropped, and the monitor keeps fitting until the camera agrees again.

A knock of a few degrees moves a camera's markers tens of pixels, beyond the pairing gate: each
sampled frame also votes with every blob-minus-prediction offset within `search_deg` of a prediction,
and when a camera pairs few of its predicted markers, the offset most votes agree on (the knock's
shift in its image) is added to its predictions until its pose is corrected. A flagged camera is
left out of the fusion (`exclude`, `admits`) until it agrees again; one whose fit cannot explain its
pairs, or needs more than `max_correction_deg` / `max_correction_m` in all, or whose markers cannot be
found at all, is flagged as not solvable and stays excluded: never a wrong "corrected". Two cameras knocked at
once: the second is the one without which the other unflagged cameras' rays meet (`_flag_second`), and two
cameras left are a reference when their rays meet at the flagged cameras' points (`_pair_agrees`).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos import jit
from visionpos.camera.lens import pixel_from_normalized
from visionpos.camera.model import Camera, lens_arrays, undistort_pixels
from visionpos.config.arena import ArenaConfig
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, section
from visionpos.fusion.matching import refine_in_pixels, triangulate
from visionpos.geometry.resection import apply_correction, misfit, pose_correction
from visionpos.geometry.rotations import matrix_from_quat
from visionpos.jit import njit
from visionpos.messages import BlobFrame, BodyState

log = logging.getLogger(__name__)

# The moved camera's correction must be this many times the next camera's: the leave-one-out points of
# the others still hold its rays, so they show a share of its error (measured: a 5 mm move showed 1.6x).
DOMINANCE = 1.4
# A flagged camera is re-fitted until its correction moves its markers by less than this part of flag_px.
SETTLED = 0.1
PAUSED_WHILE_COMPILING = ("waiting for the compiled kernels: a first start after an install compiles them in the "
                          "background, and run interpreted each fit would hold the server's loop for about 0.3 s")
PAUSED_WITHOUT_NUMBA = ("numba is not installed (no wheel for this platform): the kernels run as Python, and each fit "
                        "would hold the server's loop for about 0.3 s")
REFINE_STEPS = 3  # Gauss-Newton steps of a leave-one-out point from its linear start (1-2 converge)
MAX_FIT_PAIRS = 1000  # a fit uses at most this many of a camera's newest pairs: about 1 ms on the loop
# a flagged camera's fit must explain its pairs: robust residual std at most this many times the other cameras'
# median (and at least UNSOLVED_SIGMA_PX): otherwise the knock is not a rigid turn and shift of the camera
UNSOLVED_SIGMA_RATIO = 4.0
UNSOLVED_SIGMA_PX = 1.0
# the offset search acts when a camera paired less than this share of its predicted markers in a round ...
SEARCH_BELOW = 0.5
# ... and adopts an offset that at least this share of the predictions voted for (within SEARCH_BIN_PX)
SEARCH_SUPPORT = 0.3
SEARCH_BIN_PX = 3.0
FLAGGED_PRIOR_SHIFT_M = 0.05  # the prior std of a flagged camera's shift (a knock of centimetres) ...
SHIFT_EVIDENCE_CHI2 = 12.0  # ... taken when it lowers the pairs' chi-square by this much (3 more dof: p ~ 0.007)
SEARCH_MIN_PX = 2.0  # a found offset smaller than this is no knock: the gate pairs it anyway
# a camera that pairs less than this share of its predicted markers while the others pair most of theirs,
# for LOST_ROUNDS rounds, is lost: flagged as not solvable and excluded
LOST_BELOW = 0.1
LOST_ROUNDS = 3
# a second knocked camera: the other unflagged cameras' rays meet (triangulation residual) this many times better
# without it than any camera's others do with it
REF_SPLIT = 3.0
# two unflagged cameras left are a reference when their rays meet at the flagged cameras' points within this part
# of flag_px (px RMS; 0.1 px at 0.2 px centroid noise)
PAIR_AGREES = 0.5

MONITOR = section(
    "camera_monitor",
    "Continuous calibration (fusion/camera_monitor.py): per-camera residuals against the tracked bodies, "
    "moved cameras flagged in the health output and the log, and their poses corrected while tracking.",
    Setting("enabled", "boolean", True, "watch the cameras at all"),
    Setting("correct", "boolean", True, "apply the fitted correction to a flagged camera (false: only flag it)"),
    Setting("window_s", "number", 4.0, "pairs older than this are dropped", min=0.5, max=600.0),
    Setting("step_s", "number", 1.0, "how often each camera's correction is fitted", min=0.1, max=60.0),
    Setting("flag_px", "number", 0.5, "a correction that moves the camera's markers by more than this (RMS, px) "
            "in its image, and is significant, flags the camera", min=0.05),
    Setting("chi2_min", "number", 100.0, "significance of a correction (chi-square, 6 dof) needed to flag",
            min=1.0),
    Setting("gate_px", "number", 15.0, "a blob pairs with a predicted marker within this (px), when no other "
            "blob or marker is within twice the distance", min=1.0, max=200.0),
    Setting("sample_every", "integer", 2, "look at one frame in this many of each camera (the cost per "
            "packet)", min=1, max=100),
    Setting("min_pairs", "integer", 100, "fewest pairs in a camera's window for a fit", min=20),
    Setting("max_pairs", "integer", 4000, "most pairs kept per camera (the oldest go first)", min=100),
    Setting("max_step_deg", "number", 6.0, "largest rotation applied per correction step (deg)", min=0.01),
    Setting("max_step_m", "number", 0.06, "largest shift applied per correction step (m)", min=0.0001),
    Setting("fit_s", "number", 1.5, "a fit uses the pairs of the last this many seconds (at least min_pairs "
            "of them): older ones may hold the pose before a knock", min=0.2, max=600.0),
    Setting("settle_s", "number", 1.0, "after a flag or a correction, fresh pairs over this long are needed "
            "before the next fit acts", min=0.1, max=60.0),
    Setting("search_deg", "number", 6.0, "how far (deg of view) a knocked camera's markers are searched for "
            "when it pairs few of them", min=0.0, max=30.0),
    Setting("exclude", "boolean", True, "leave a flagged camera out of the fusion until it agrees again"),
    Setting("max_correction_deg", "number", 8.0, "a camera whose corrections would add up to more than this "
            "turn (deg) is flagged as not solvable and stays excluded", min=0.1),
    Setting("max_correction_m", "number", 0.15, "likewise for the move of its centre (m)", min=0.001),
)


@dataclass(frozen=True)
class MonitorSettings:
    enabled: bool = True
    correct: bool = True
    window_s: float = 4.0
    step_s: float = 1.0
    flag_px: float = 0.5
    chi2_min: float = 100.0
    gate_px: float = 15.0
    sample_every: int = 2
    min_pairs: int = 100
    max_pairs: int = 4000
    max_step_deg: float = 6.0
    max_step_m: float = 0.06
    fit_s: float = 1.5
    settle_s: float = 1.0
    search_deg: float = 6.0
    exclude: bool = True
    max_correction_deg: float = 8.0
    max_correction_m: float = 0.15


def parse_camera_monitor(arena: ArenaConfig) -> MonitorSettings:
    """The validated `camera_monitor:` section."""
    return MonitorSettings(**MONITOR.parse(MONITOR.check(arena.section("camera_monitor"))))


register_section("camera_monitor", MONITOR, parse_camera_monitor)


# ---------------------------------------------------------------------------------------------- math
@njit
def _pair_frame(blobs, t_ns, X0, V, rows, capture_ns, R, t, intrinsics, dist, fisheye, offset_px, gate_px, vote_r2, v,
                others, fresh_ns, last_px, last_ns):
    """One sampled frame of camera v (pose R, t; its lens as lens_arrays packs it): the tracked markers moved to
    its capture time (X0 (M, 3) m at t_ns (M,) ns, velocities V (M, 3) m/s; rows (M,): their rows in last_px),
    projected and paired with its blobs (B, 2) px once offset_px is added: a marker pairs with its nearest blob
    within gate_px when no other blob is within twice that distance of the marker and no other marker within
    twice that distance of the blob (at least 2 px either way). Writes each paired
    marker's blob and capture time as view v's newest (last_px (V, Mt, 2), last_ns (V, Mt), in place). Returns
    (markers predicted on its sensor, votes (K, 2): every blob-minus-prediction offset of an on-sensor marker
    within sqrt(vote_r2) px (none for vote_r2 <= 0), markers paired, and for each paired marker that two or
    more views in `others` (V,) bool saw within fresh_ns: those views' pixels (U, V, 2) (NaN elsewhere),
    their offsets (U, V, 3) m (the marker's motion from each view's capture to this one, 0 elsewhere), and
    this frame's blob (U, 2))."""
    M, B, n_views = X0.shape[0], blobs.shape[0], last_px.shape[0]
    pred = np.full((M, 2), np.nan)
    width, height = intrinsics[4], intrinsics[5]
    predicted = 0
    n_votes = 0
    votes = np.empty((M * B if vote_r2 > 0.0 else 0, 2))
    for m in range(M):
        dt = (capture_ns - t_ns[m]) * 1e-9
        x, y, z = X0[m, 0] + V[m, 0] * dt, X0[m, 1] + V[m, 1] * dt, X0[m, 2] + V[m, 2] * dt
        zc = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
        if not zc > 0.0:
            continue
        xc = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
        yc = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
        pred[m, 0], pred[m, 1] = pixel_from_normalized(xc / zc, yc / zc, intrinsics, dist, fisheye)
        if not (-0.5 <= pred[m, 0] <= width - 0.5 and -0.5 <= pred[m, 1] <= height - 0.5):
            continue
        predicted += 1
        if vote_r2 > 0.0:
            for b in range(B):
                dx, dy = blobs[b, 0] - pred[m, 0], blobs[b, 1] - pred[m, 1]
                if dx * dx + dy * dy < vote_r2:
                    votes[n_votes, 0], votes[n_votes, 1] = dx, dy
                    n_votes += 1
    # the pairing, on the predictions plus the search offset
    d = np.full((M, B), np.inf)
    for m in range(M):
        for b in range(B):
            dx = pred[m, 0] + offset_px[0] - blobs[b, 0]
            dy = pred[m, 1] + offset_px[1] - blobs[b, 1]
            dd = math.sqrt(dx * dx + dy * dy)
            if math.isfinite(dd):
                d[m, b] = dd
    pair_m = np.empty(M, np.int64)
    pair_b = np.empty(M, np.int64)
    paired = 0
    for m in range(M):
        best = 0
        for b in range(1, B):
            if d[m, b] < d[m, best]:
                best = b
        dm = d[m, best]
        if not dm < gate_px:
            continue
        limit = max(2.0 * dm, 2.0)
        near_blobs = 0
        for b in range(B):
            if d[m, b] < limit:
                near_blobs += 1
        near_markers = 0
        for k in range(M):
            if d[k, best] < limit:
                near_markers += 1
        if near_blobs == 1 and near_markers == 1:
            pair_m[paired], pair_b[paired] = m, best
            paired += 1
    for k in range(paired):
        r = rows[pair_m[k]]
        last_px[v, r, 0], last_px[v, r, 1] = blobs[pair_b[k], 0], blobs[pair_b[k], 1]
        last_ns[v, r] = capture_ns
    px = np.full((paired, n_views, 2), np.nan)
    offsets = np.zeros((paired, n_views, 3))
    pair_px = np.empty((paired, 2))
    used = 0
    for k in range(paired):
        m, r = pair_m[k], rows[pair_m[k]]
        n_fresh = 0
        for u in range(n_views):
            if others[u] and abs(capture_ns - last_ns[u, r]) < fresh_ns:
                n_fresh += 1
        if n_fresh < 2:
            continue
        for u in range(n_views):
            age_ns = capture_ns - last_ns[u, r]
            if others[u] and abs(age_ns) < fresh_ns:
                px[used, u, 0], px[used, u, 1] = last_px[u, r, 0], last_px[u, r, 1]
                for a in range(3):  # each other view saw the marker where it was at its own capture time
                    offsets[used, u, a] = -V[m, a] * (age_ns * 1e-9)
        pair_px[used, 0], pair_px[used, 1] = blobs[pair_b[k], 0], blobs[pair_b[k], 1]
        used += 1
    return predicted, votes[:n_votes].copy(), paired, px[:used].copy(), offsets[:used].copy(), pair_px[:used].copy()


def _rig_arrays(cameras: list[Camera]) -> tuple[np.ndarray, ...]:
    """The cameras as the compiled triangulation takes them: R (V, 3, 3), t (V, 3), f (V,) px (sqrt(fx fy)),
    intrinsics (V, 6), dist (V, 8), fisheye (V,) bool (camera.model.lens_arrays per camera)."""
    lenses = [lens_arrays(c.model) for c in cameras]
    return (np.ascontiguousarray([c.R for c in cameras], dtype=np.float64),
            np.ascontiguousarray([c.t for c in cameras], dtype=np.float64),
            np.array([np.sqrt(c.model.fx * c.model.fy) for c in cameras]),
            np.ascontiguousarray([x[0] for x in lenses]), np.ascontiguousarray([x[1] for x in lenses]),
            np.array([x[2] for x in lenses], dtype=np.bool_))


def leave_one_out_points(rig: tuple[np.ndarray, ...], pixels: np.ndarray, offsets: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Points (P, 3) m triangulated from pixels (P, V, 2) (NaN where a view does not see the point) with per-view
    offsets (P, V, 3) m (view v saw X + offsets[p, v]), and their residual (P,) px RMS: the compiled linear
    start (fusion/matching.triangulate), refined on the reprojection error in pixels through each lens. NaN
    where fewer than 2 views see a point or a view sees it from behind. rig: _rig_arrays."""
    R, t, f, intrinsics, dist, fisheye_ = rig
    px = np.array(pixels, dtype=np.float64)  # a copy: unseen views are marked in it
    xn = np.empty_like(px)
    for v in range(px.shape[1]):
        xn[:, v] = undistort_pixels(np.ascontiguousarray(px[:, v]), intrinsics[v], dist[v], bool(fisheye_[v]))
    px[np.isnan(xn)] = np.nan  # beyond a lens's fold: no view
    off = np.ascontiguousarray(offsets, dtype=np.float64)
    X, _, _ = triangulate(xn, R, t, f, off)
    return refine_in_pixels(X, px, off, True, R, t, intrinsics, dist, fisheye_, REFINE_STEPS)


def warm_up_monitor_kernels(arena: ArenaConfig, points_world: np.ndarray) -> None:
    """Run the monitor's compiled kernels once on the first body's markers at points (M, 3) m in front of the
    cameras (fusion/warmup.py), so that a live server's first frame and fit do not compile them on its loop."""
    cameras = list(arena.cameras)
    X = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    px = np.stack([c.project(X) for c in cameras], axis=1)
    mon = CameraMonitor(arena, MonitorSettings(sample_every=1))
    mon._motion = (np.zeros(len(X), np.int64), X, np.zeros_like(X), np.arange(len(X)))
    blobs = np.column_stack([np.nan_to_num(px[:, 0]), np.full((len(X), 2), 10.0)]).astype(np.float32)
    mon.observe_frame(BlobFrame(cameras[0].id, 0, 0, blobs))
    leave_one_out_points(_rig_arrays(cameras), px, np.zeros(px.shape[:2] + (3,)))
    pose_correction(cameras[0], X, px[:, 0], iterations=1)


def marker_motion(state: BodyState, markers_body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(markers (M, 3) in the world at state.time_ns, their velocities (M, 3) m/s) from the state's pose,
    velocity and body-frame angular velocity: X(t) ~ X + V (t - time_ns) over a frame's few milliseconds.
    A single-marker body's state has no rotation (NaN quaternion): its marker sits at its position."""
    position = np.asarray(state.position, float)
    velocity = np.asarray(state.velocity, float)
    q = np.asarray(state.quaternion, float)
    if not np.isfinite(q).all():
        n = len(markers_body)
        return np.tile(position, (n, 1)), np.tile(velocity, (n, 1))
    R = matrix_from_quat(q)
    lever = markers_body @ R.T
    w = R @ np.asarray(state.angular_velocity, float)
    marker_velocity = np.column_stack([w[1] * lever[:, 2] - w[2] * lever[:, 1], w[2] * lever[:, 0] - w[0] * lever[:, 2],
                                       w[0] * lever[:, 1] - w[1] * lever[:, 0]]) + velocity
    return lever + position, marker_velocity


# ---------------------------------------------------------------------------------------------- state
@dataclass
class CameraWatch:
    """One camera's recent pairs and verdict."""

    camera: Camera
    times_ns: deque = field(default_factory=deque)
    points: deque = field(default_factory=deque)  # (3,) world
    pixels: deque = field(default_factory=deque)  # (2,)
    ref_px: deque = field(default_factory=deque)  # the other views' triangulation residual at each point (px RMS)
    pending: list = field(default_factory=list)  # frames' pairs waiting for their batch triangulation
    frames_seen: int = 0
    flagged: bool = False
    flagged_since_ns: int | None = None
    corrections: int = 0
    last: dict[str, float] = field(default_factory=dict)  # the last fit: disp_px, chi2, sigma_px, pairs, ...
    offset_px: np.ndarray = field(default_factory=lambda: np.zeros(2))  # the knock's shift found by the search
    votes: deque = field(default_factory=deque)  # (capture_ns, dx, dy): blob - prediction offsets, for the search
    predicted: int = 0  # markers predicted in its image, this round
    paired: int = 0  # of them paired, this round
    cleared_ns: int = 0  # its pairs were dropped here (a flag or a correction)
    excluded: bool = False  # left out of the fusion
    unsolvable: str = ""  # why its knock cannot be corrected (then it stays excluded)
    lost_rounds: int = 0
    moved: dict[str, float] = field(default_factory=dict)  # the fit that flagged it: disp_px, rotation_deg, ...
    applied: list = field(default_factory=list)  # its corrections: dicts of time_ns, rotation_deg, shift_mm
    agreed_again_ns: int | None = None  # when it last agreed again after a flag
    since: Camera | None = None  # its pose when it was flagged


@dataclass(frozen=True)
class Correction:
    camera_id: int
    camera: Camera  # the corrected camera
    rotation_deg: float
    shift_m: float


class CameraMonitor:
    """Feed it frames (observe_frame) and the output states (observe_states); step(now) once in a while
    returns the cameras to re-pose. report() is the per-camera health."""

    def __init__(self, arena: ArenaConfig, settings: MonitorSettings | None = None):
        self.settings = settings or parse_camera_monitor(arena)
        self.cams = {c.id: CameraWatch(c) for c in arena.cameras}
        self.markers = {b.name: np.asarray(b.markers, float) for b in arena.bodies}
        self._motion: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._index = {c.id: i for i, c in enumerate(arena.cameras)}
        self._rig = _rig_arrays(list(arena.cameras))
        # the offset search's votes: blob-minus-prediction offsets within search_deg of view (px^2; none at 0)
        self._vote_r2 = {c.id: float(np.tan(np.radians(self.settings.search_deg)) * c.model.fx) ** 2
                         if self.settings.search_deg > 0 else -1.0 for c in arena.cameras}
        starts = np.cumsum([0] + [len(b.markers) for b in arena.bodies])
        self._marker_rows = {b.name: np.arange(starts[i], starts[i + 1]) for i, b in enumerate(arena.bodies)}
        # each camera's newest paired view of every marker: pixel (V, M, 2) and capture time (V, M)
        self._last_px = np.full((len(arena.cameras), int(starts[-1]), 2), np.nan)
        self._last_ns = np.full((len(arena.cameras), int(starts[-1])), -(1 << 62), np.int64)
        # another camera's view is used while younger than this (motion-compensated): sampled frames come
        # sample_every periods apart
        self._fresh_ns = int(max(25e6, (self.settings.sample_every + 0.5) * 1e9 / max(min(c.fps for c in
                                                                                      arena.cameras), 1.0)))
        self._next_step_ns: int | None = None
        self._turn = 0
        self._round_end_ns = 0
        self._fits: dict[int, tuple[np.ndarray, float, float]] = {}  # each camera's latest fit
        self.events: list[str] = []

    def observe_states(self, states: list[BodyState]) -> None:
        """The newest output states: their markers and marker velocities, for the frames that follow."""
        moving = [(s, *marker_motion(s, self.markers[s.name])) for s in states
                  if s.tracked and s.name in self.markers]
        self._motion = None
        if moving:
            self._motion = (np.concatenate([np.full(len(m[1]), m[0].time_ns, np.int64) for m in moving]),
                            np.concatenate([m[1] for m in moving]), np.concatenate([m[2] for m in moving]),
                            np.concatenate([self._marker_rows[m[0].name] for m in moving]))

    def observe_frame(self, frame: BlobFrame) -> None:
        """For one frame in sample_every of each camera: pair its blobs with the tracked markers, note them as
        this camera's newest views, and queue each paired marker for triangulation from the OTHER cameras'
        newest views (leave-one-out: the fused pose leans toward a knocked camera, the other cameras' rays do
        not) with this blob. The other frames cost a counter."""
        v = self._index.get(frame.camera_id)
        if v is None or self._motion is None or self.paused:
            return
        w = self.cams[frame.camera_id]
        w.frames_seen += 1
        if w.frames_seen % self.settings.sample_every:
            return
        blobs = np.ascontiguousarray(np.asarray(frame.blobs, dtype=np.float64).reshape(-1, 4)[:, :2])
        if not len(blobs):
            return
        _, _, _, intrinsics, dist, fisheye_ = self._rig  # view v's lens, as lens_arrays packs it
        # leave-one-out, and flagged cameras left out too: a knocked camera's rays would bend the others' points
        others = np.array([not x.flagged for x in self.cams.values()])
        others[v] = False
        predicted, votes, paired, px, offsets, pair_px = _pair_frame(
            blobs, *self._motion, frame.capture_ns, w.camera.R, w.camera.t, intrinsics[v], dist[v], bool(fisheye_[v]),
            w.offset_px,
            float(self.settings.gate_px), self._vote_r2[frame.camera_id], v, others,
            self._fresh_ns, self._last_px, self._last_ns)
        w.predicted += predicted
        w.paired += paired
        if len(votes):
            w.votes.append((frame.capture_ns, votes))
        if len(pair_px):
            # triangulated in one batch per camera at the next step(): per frame only this bookkeeping
            w.pending.append((frame.capture_ns, px, offsets, pair_px))

    def _triangulate_pending(self, w: CameraWatch) -> None:
        """The leave-one-out points of a camera's pending pairs, in one triangulation."""
        if not w.pending:
            return
        px = np.concatenate([p[1] for p in w.pending])
        offsets = np.concatenate([p[2] for p in w.pending])
        blobs = np.concatenate([p[3] for p in w.pending])
        times = np.concatenate([np.full(len(p[3]), p[0], np.int64) for p in w.pending])
        w.pending.clear()
        points, ref_px = leave_one_out_points(self._rig, px, offsets)
        good = np.isfinite(points).all(axis=1)
        w.times_ns.extend(times[good].tolist())
        w.points.extend(points[good])
        w.pixels.extend(blobs[good])
        w.ref_px.extend(ref_px[good])
        while len(w.times_ns) > self.settings.max_pairs:
            self._drop_oldest(w)

    @staticmethod
    def _drop_oldest(w: CameraWatch) -> None:
        w.times_ns.popleft()
        w.points.popleft()
        w.pixels.popleft()
        w.ref_px.popleft()

    def _search(self, w: CameraWatch, since_ns: int) -> None:
        """When the camera paired few of its predicted markers: the image offset most of its blob-minus-prediction
        offsets since since_ns agree on (a knock's shift) becomes its offset_px, if SEARCH_SUPPORT of the
        predictions voted for it; an offset within SEARCH_MIN_PX of zero is no knock (offset_px stays)."""
        while w.votes and w.votes[0][0] < since_ns:
            w.votes.popleft()
        if w.predicted < 20 or w.paired >= SEARCH_BELOW * w.predicted or not w.votes:
            return
        d = np.concatenate([v[1] for v in w.votes])
        radius = np.tan(np.radians(self.settings.search_deg)) * w.camera.model.fx
        n_bins = int(np.ceil(2 * radius / SEARCH_BIN_PX))
        hist, ex, ey = np.histogram2d(d[:, 0], d[:, 1], bins=n_bins, range=[[-radius, radius], [-radius, radius]])
        smooth = sum(np.roll(np.roll(hist, i, 0), j, 1) for i in (-1, 0, 1) for j in (-1, 0, 1))
        i, j = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
        peak = np.array([0.5 * (ex[i] + ex[i + 1]), 0.5 * (ey[j] + ey[j + 1])])
        near = np.linalg.norm(d - peak, axis=1) < 1.5 * SEARCH_BIN_PX
        if near.sum() >= SEARCH_SUPPORT * w.predicted:
            found = d[near].mean(axis=0)
            if np.linalg.norm(found) > SEARCH_MIN_PX:
                w.offset_px = found
                w.last["search_offset_px"] = float(np.linalg.norm(found))

    def admits(self, camera_id: int) -> bool:
        """Whether the fusion should take this camera's frames: not while it is excluded (flagged with
        `exclude`, or not solvable). The monitor itself keeps watching it (observe_frame)."""
        w = self.cams.get(camera_id)
        return w is None or not w.excluded

    def _fit_camera(self, w: CameraWatch, now_ns: int) -> None:
        """One camera's correction from its pairs of the last fit_s (at least min_pairs, none from before its
        last clear) up to the round's moment; its pairing share and the offset search."""
        st = self.settings
        self._triangulate_pending(w)
        while w.times_ns and w.times_ns[0] < now_ns - st.window_s * 1e9:
            self._drop_oldest(w)
        self._fits.pop(w.camera.id, None)
        share = w.paired / w.predicted if w.predicted else float("nan")
        w.last = {"predicted": float(w.predicted), "paired_share": share}
        self._search(w, now_ns - int(st.step_s * 1e9))
        w.predicted = w.paired = 0
        times = np.fromiter(w.times_ns, np.int64, len(w.times_ns))
        upto = int(np.searchsorted(times, self._round_end_ns, side="right"))
        first = int(np.searchsorted(times, w.cleared_ns))
        lo = max(first, int(np.searchsorted(times, self._round_end_ns - int(st.fit_s * 1e9))))
        lo = max(first, min(lo, upto - st.min_pairs), upto - MAX_FIT_PAIRS)
        w.last["pairs"] = float(upto - lo)
        if upto - lo < st.min_pairs:
            return
        pts, pix = np.array(list(w.points)[lo:upto]), np.array(list(w.pixels)[lo:upto])
        w.last["ref_px"] = float(np.median(list(w.ref_px)[lo:upto]))
        delta, info, sigma, disp = pose_correction(w.camera, pts, pix, iterations=8)
        if w.flagged:
            # a knocked camera may have moved centimetres: the shift the pairs' parallax shows, when a loose
            # prior explains them significantly better (SHIFT_EVIDENCE_CHI2; a turn alone fits as well under either,
            # and the tight prior keeps the turn/shift trade-off of a small volume out of it)
            loose = pose_correction(w.camera, pts, pix, iterations=8, prior_shift_m=FLAGGED_PRIOR_SHIFT_M)
            gain = (misfit(w.camera, delta, pts, pix, sigma) - misfit(w.camera, loose[0], pts, pix, sigma))
            w.last["shift_evidence_chi2"] = float(gain)
            if gain > SHIFT_EVIDENCE_CHI2:
                delta, info, sigma, disp = loose
        chi2 = float(delta @ info @ delta)
        w.last.update({"disp_px": disp, "chi2": chi2, "sigma_px": sigma,
                       "rotation_deg": float(np.degrees(np.linalg.norm(delta[:3]))),
                       "shift_mm": float(np.linalg.norm(delta[3:]) * 1e3)})
        self._fits[w.camera.id] = (delta, disp, chi2)

    def step(self, now_ns: int) -> list[Correction]:
        """Fit one camera's correction per call (cameras in turn, each about once per step_s, so one call
        costs one small fit on the server's loop); once every camera has its fit of the round: find a lost
        camera, flag the moved one and, with correct, return the corrected poses of the flagged ones (the caller
        applies them: FusionPipeline.set_camera_pose)."""
        st = self.settings
        if self._next_step_ns is not None and now_ns < self._next_step_ns:
            return []
        if self.paused:
            return []
        ids = list(self.cams)
        self._next_step_ns = now_ns + int(st.step_s * 1e9 / len(ids))
        if self._turn % len(ids) == 0:
            self._round_end_ns = now_ns  # every fit of this round uses the pairs up to here: one moment
        cid = ids[self._turn % len(ids)]
        self._turn += 1
        self._fit_camera(self.cams[cid], now_ns)
        if self._turn % len(ids):
            return []  # judge once every camera has a fit from this round: a stale fit would skew the comparison
        self._watch_lost(now_ns)
        if self._flag(now_ns):
            return []
        return self._act(now_ns)

    @property
    def paused(self) -> str:
        """Why the monitor watches nothing now, else "": its kernels would run as Python (a first start that
        compiles them in the background, fusion/warmup.py, or no numba at all), and one fit would hold the
        server's loop for about 0.3 s."""
        if not jit.COMPILED:
            return PAUSED_WITHOUT_NUMBA
        if jit.interpreting():
            return PAUSED_WHILE_COMPILING
        return ""

    def _say(self, msg: str) -> None:
        """An operator-visible line: the log's WARNING and the health's events."""
        self.events.append(msg)
        log.warning(msg)

    def _watch_lost(self, now_ns: int) -> None:
        """A camera that pairs almost none of its predicted markers, while the others pair most of theirs,
        for LOST_ROUNDS rounds (the offset search found nothing either) is flagged as not solvable."""
        shares = {cid: w.last.get("paired_share", float("nan")) for cid, w in self.cams.items()
                  if w.last.get("predicted", 0.0) >= 20}
        for cid, share in shares.items():
            w = self.cams[cid]
            others = [x for c, x in shares.items() if c != cid]
            if others and np.median(others) > 0.5 and share < LOST_BELOW:
                w.lost_rounds += 1
            else:
                w.lost_rounds = 0
            if w.lost_rounds == LOST_ROUNDS and not w.unsolvable:
                self._unsolvable(w, now_ns, f"its blobs match {100 * share:.0f} % of the tracked markers it should "
                                 f"see (the others {100 * float(np.median(others)):.0f} %), and no shift within "
                                 f"{self.settings.search_deg:g} deg of view explains them: knocked further than the "
                                 "monitor can solve, or covered")

    def _unsolvable(self, w: CameraWatch, now_ns: int, why: str) -> None:
        if not w.flagged:
            w.flagged, w.flagged_since_ns, w.since = True, now_ns, w.camera
            self._clear(w, now_ns)  # it agrees again only on pairs from after this
        w.unsolvable, w.excluded = why, True
        self._say(f"camera {w.camera.name} (id {w.camera.id}) cannot be corrected: {why}; it is left out of the "
                  "fusion; recalibrate it (visionpos calibrate wand)")

    def _flag(self, now_ns: int) -> bool:
        """Flag the unflagged camera whose correction is significant, visible and clearly the largest among the
        unflagged ones, while two others remain to check it against. True if one was flagged: then every
        camera's pairs are dropped, since theirs were triangulated with its rays too (flagged cameras' views
        are left out of the others' points from then on)."""
        st = self.settings
        fits = {c: f for c, f in self._fits.items() if not self.cams[c].flagged}
        moved = sorted(((disp, cid) for cid, (_, disp, chi2) in fits.items() if chi2 > st.chi2_min), reverse=True)
        if not moved or moved[0][0] <= st.flag_px or sum(not w.flagged for w in self.cams.values()) < 3:
            return False
        # the knocked camera dominates: the fused poses lean toward it, so the others show smaller corrections
        runner_up = max((fits[c][1] for c in fits if c != moved[0][1]), default=0.0)
        if moved[0][0] <= DOMINANCE * runner_up:
            return False
        w = self.cams[moved[0][1]]
        w.flagged, w.flagged_since_ns, w.since, w.excluded = True, now_ns, w.camera, st.exclude
        w.moved = {k: w.last[k] for k in ("disp_px", "rotation_deg", "shift_mm")}
        w.applied, w.agreed_again_ns = [], None
        self._say(f"camera {w.camera.name} (id {w.camera.id}) has moved since calibration: its markers sit "
                  f"{w.last['disp_px']:.1f} px off where the other cameras put them" +
                  ("; left out of the fusion" if st.exclude else "") +
                  ("; re-fitting its pose while tracking goes on" if st.correct else
                   "; recalibrate (visionpos calibrate wand)"))
        for x in self.cams.values():  # its window mixes the old and the new pose, the others' hold its rays
            self._clear(x, now_ns)
        return True

    def _act(self, now_ns: int) -> list[Correction]:
        """For each flagged camera with a fit on settle_s of fresh pairs: it agrees again, or its knock is not
        solvable (excluded), or (correct) its pose is corrected by the fit, bounded per step."""
        st, out = self.settings, []
        sigmas = [self._fits_sigma(c) for c, w in self.cams.items() if not w.flagged and c in self._fits]
        if not self._reference_holds(now_ns):
            return out
        for cid, w in self.cams.items():
            if not w.flagged or cid not in self._fits or now_ns - w.cleared_ns < st.settle_s * 1e9:
                continue
            delta, disp, chi2 = self._fits[cid]
            # agrees: its remaining correction is negligible, or small and not significant (correcting by the
            # noise would only move it around)
            if disp < SETTLED * st.flag_px or (chi2 < st.chi2_min and disp < 0.5 * st.flag_px):
                w.flagged, w.flagged_since_ns, w.excluded, w.unsolvable = False, None, False, ""
                w.agreed_again_ns = now_ns
                self._say(f"camera {w.camera.name} (id {cid}) agrees with the other cameras again"
                          + (f" after {w.corrections} pose correction(s)" if w.applied else "")
                          + ("; back in the fusion" if st.exclude or w.applied else ""))
                continue
            limit = max(UNSOLVED_SIGMA_PX, UNSOLVED_SIGMA_RATIO * float(np.median(sigmas))) if sigmas else np.inf
            total = apply_correction(w.camera, delta)
            turned = float(np.degrees(Rotation.from_matrix(total.R @ w.since.R.T).magnitude()))
            shifted = float(np.linalg.norm(total.center - w.since.center))
            why = ""
            if self._fits_sigma(cid) > limit:
                why = (f"its pairs do not fit one pose (residual {self._fits_sigma(cid):.2f} px after the fit, the "
                       f"other cameras {float(np.median(sigmas)):.2f} px)")
            elif turned > st.max_correction_deg or shifted > st.max_correction_m:
                why = (f"it would need a correction of {turned:.1f} deg and {shifted * 1e3:.0f} mm in all, beyond "
                       f"camera_monitor.max_correction_deg {st.max_correction_deg:g} / max_correction_m "
                       f"{st.max_correction_m:g}")
            if why:
                if w.unsolvable != why.split(" (")[0]:
                    self._unsolvable(w, now_ns, why)
                    w.unsolvable = why.split(" (")[0]
                continue
            if st.correct:
                out.append(self._correct(w, delta, now_ns))
        return out

    def _reference_holds(self, now_ns: int) -> bool:
        """Whether the unflagged cameras are a reference to correct a flagged one against: two or more of them
        fitted this round and none of them off by more than flag_px (significantly), or just two left whose rays
        meet at the flagged cameras' points (`ref_px` below PAIR_AGREES of flag_px). Otherwise no flagged camera is
        corrected or let back (it would be fitted to a bent reference: two cameras knocked at once). A bent
        reference of three or more is split when one camera is off and the others agree only without it
        (`_flag_second`); else after three such rounds each flagged camera is flagged as not solvable, with the
        reason, and stays out."""
        st = self.settings
        ref = {c: self._fits[c] for c, w in self.cams.items() if not w.flagged and c in self._fits}
        off = {c: f[1] for c, f in ref.items() if f[1] > st.flag_px and f[2] > st.chi2_min}
        if (len(ref) >= 2 and not off) or (not ref and self._pair_agrees()):
            self._bent_rounds = 0
            return True
        if off and len(ref) >= 3 and self._flag_second(ref, off, now_ns):
            return False
        self._bent_rounds = getattr(self, "_bent_rounds", 0) + bool(off)
        if self._bent_rounds == LOST_ROUNDS:
            names = ", ".join(f"{self.cams[c].camera.name} {d:.1f} px" for c, d in off.items())
            for w in self.cams.values():
                if w.flagged and not w.unsolvable:
                    self._unsolvable(w, now_ns, f"the other cameras disagree among themselves too ({names}): more "
                                     "than one camera moved, and which cannot be told")
        return False

    def _pair_agrees(self) -> bool:
        """Two unflagged cameras left: neither can be fitted (its points need two other views), but the flagged
        cameras' points are triangulated from exactly these two, and their rays meet there when they agree."""
        if sum(not w.flagged for w in self.cams.values()) != 2:
            return False
        meet = [w.last["ref_px"] for c, w in self.cams.items() if w.flagged and c in self._fits and "ref_px" in w.last]
        return bool(meet) and max(meet) <= PAIR_AGREES * self.settings.flag_px

    def _flag_second(self, ref: dict, off: dict, now_ns: int) -> bool:
        """A flagged camera left out and the unflagged ones still disagree: another camera moved too. Each
        unflagged camera's points come from the other unflagged ones, so their triangulation residual (`ref_px`)
        says whether those agree: the camera k without which the others' rays meet (its ref_px REF_SPLIT times
        below every other's) and whose own fit is off is the second knocked one: flagged and left out. True if
        flagged (every camera's pairs are dropped, as in `_flag`)."""
        meet = {c: self.cams[c].last.get("ref_px", np.nan) for c in ref}
        k = min(meet, key=lambda c: meet[c] if np.isfinite(meet[c]) else np.inf)
        rest = [v for c, v in meet.items() if c != k]
        if k not in off or not np.isfinite(meet[k]) or not min(rest) >= REF_SPLIT * max(meet[k], 0.05):
            return False
        w = self.cams[k]
        w.flagged, w.flagged_since_ns, w.since, w.excluded = True, now_ns, w.camera, self.settings.exclude
        w.moved = {x: w.last[x] for x in ("disp_px", "rotation_deg", "shift_mm")}
        w.applied, w.agreed_again_ns = [], None
        self._say(f"camera {w.camera.name} (id {k}) has moved too: its markers sit {w.last['disp_px']:.1f} px off "
                  f"where the other cameras put them, and those agree only without it (their rays miss by "
                  f"{meet[k]:.2f} px without it, {min(rest):.1f} px or more with it)"
                  + ("; left out of the fusion" if self.settings.exclude else ""))
        for x in self.cams.values():
            self._clear(x, now_ns)
        return True

    def _fits_sigma(self, cid: int) -> float:
        return float(self.cams[cid].last.get("sigma_px", np.nan))

    def _correct(self, w: CameraWatch, delta: np.ndarray, now_ns: int) -> Correction:
        """Apply the fitted correction (bounded per step) to the camera, drop its pairs and its search offset."""
        st = self.settings
        delta = delta.copy()
        rot = np.linalg.norm(delta[:3])
        if rot > np.radians(st.max_step_deg):
            delta[:3] *= np.radians(st.max_step_deg) / rot
        shift = np.linalg.norm(delta[3:])
        if shift > st.max_step_m:
            delta[3:] *= st.max_step_m / shift
        w.camera = apply_correction(w.camera, delta)
        self._rig = _rig_arrays([x.camera for x in self.cams.values()])
        w.corrections += 1
        w.offset_px = np.zeros(2)
        w.unsolvable = ""
        self._clear(w, now_ns)
        c = Correction(w.camera.id, w.camera, float(np.degrees(np.linalg.norm(delta[:3]))),
                       float(np.linalg.norm(delta[3:])))
        w.applied.append({"time_ns": int(now_ns), "rotation_deg": round(c.rotation_deg, 4),
                          "shift_mm": round(c.shift_m * 1e3, 2)})
        self._say(f"camera {w.camera.name} (id {w.camera.id}): pose corrected by {c.rotation_deg:.3f} deg, "
                  f"{c.shift_m * 1e3:.1f} mm (correction {w.corrections})")
        return c

    def _clear(self, w: CameraWatch, now_ns: int) -> None:
        self._fits.pop(w.camera.id, None)
        w.pending.clear()
        w.times_ns.clear()
        w.points.clear()
        w.pixels.clear()
        w.ref_px.clear()
        w.cleared_ns = now_ns

    def report(self) -> dict[int, dict[str, Any]]:
        """Per camera (the health's `camera_monitor.cameras`): name; state (ok, moved: flagged and being
        corrected, not_solvable); excluded (left out of the fusion); moved_px / moved_rotation_deg /
        moved_shift_mm (the fit that flagged it); corrections (count), corrections_applied (each: time_ns,
        rotation_deg, shift_mm), corrected_deg / corrected_mm (the pose now against the one it was flagged
        with); agrees_again (it agreed again after its last flag); why (not_solvable: the reason); warning
        (a line for the operator, or null); the last fit: pairs, disp_px, chi2, sigma_px, rotation_deg,
        shift_mm, paired_share, ref_px (the other cameras' triangulation residual at its points)."""
        out = {}
        for cid, w in self.cams.items():
            state = "not_solvable" if w.unsolvable else "moved" if w.flagged else "ok"
            r: dict[str, Any] = {**{k: round(v, 4) for k, v in w.last.items() if np.isfinite(v)},
                                 "name": w.camera.name, "state": state, "moved": w.flagged, "excluded": w.excluded,
                                 "corrections": w.corrections, "corrections_applied": list(w.applied[-10:]),
                                 "agrees_again": w.agreed_again_ns is not None and not w.flagged,
                                 "why": w.unsolvable or None, "warning": None}
            r.update({f"moved_{k}": round(v, 4) for k, v in w.moved.items()})
            if w.since is not None:
                r["corrected_deg"] = round(float(np.degrees(Rotation.from_matrix(w.camera.R @ w.since.R.T)
                                                            .magnitude())), 4)
                r["corrected_mm"] = round(float(np.linalg.norm(w.camera.center - w.since.center) * 1e3), 2)
            label = f"camera {cid} ({w.camera.name})"
            if w.unsolvable:
                r["warning"] = f"{label} moved and cannot be corrected ({w.unsolvable}); left out of the fusion"
            elif w.flagged:
                r["warning"] = (f"{label} has moved: its markers sat {w.moved.get('disp_px', 0.0):.1f} px off the "
                                f"other cameras'; {w.corrections} pose correction(s) so far"
                                + ("; left out of the fusion until it agrees again" if w.excluded else ""))
            out[cid] = r
        return out
