"""Continuous calibration: notice a camera that was knocked, and correct its pose while tracking goes on.

Every tracked body is a calibration object of known geometry. For a sample of each camera's frames the
monitor predicts the tracked bodies' markers at the frame's capture time (the fused state moved by its
velocities), projects them with the camera's current pose, and pairs them with the frame's blobs when
the pairing is unambiguous. It keeps each camera's recent pairs (marker in the world, blob pixel), and
once a second fits a small correction of that camera's pose to them by robust Gauss-Newton
(`pose_correction`, a 6-parameter resection with the markers held fixed).

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
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos.camera.model import Camera
from visionpos.config.arena import ArenaConfig
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, section
from visionpos.geometry.triangulation import CameraRig, pixel_jacobians, triangulate_pixels
from visionpos.messages import BlobFrame, BodyState

log = logging.getLogger(__name__)

# The moved camera's correction must be this many times the next camera's: the leave-one-out points of
# the others still hold its rays, so they show a share of its error (measured: a 5 mm move showed 1.6x).
DOMINANCE = 1.4
# A flagged camera is re-fitted until its correction moves its markers by less than this part of flag_px.
SETTLED = 0.1
MAX_FIT_PAIRS = 1000  # a fit uses at most this many of a camera's newest pairs: a few ms on the loop
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
def pose_correction(camera: Camera, points_world: np.ndarray, pixels: np.ndarray, iterations: int = 3,
                    huber_px: float = 1.0, prior_rotation_rad: float = 0.05, prior_shift_m: float = 0.005
                    ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Small correction of a camera's pose that best reprojects known world points onto observed pixels.

    points_world: (N, 3) m; pixels: (N, 2) observed (distorted) pixels. The corrected camera is
    R' = exp([omega]) R, t' = exp([omega]) t + tau (a turn about the camera's own centre, omega rad, then a
    shift tau m, both in the camera frame). Points seen from one
    camera in a small volume barely tell a turn from a shift (both move them across the image alike), so
    the fit has a zero-mean prior on each (std prior_rotation_rad, prior_shift_m): a knock, mostly a turn,
    comes out as a turn, and a shift only where the points' spread in depth shows it. Returns (delta (6,)
    = [omega, tau], information (6, 6) of the data = J^T J / sigma^2, sigma (px, robust residual std after
    the fit), the RMS image displacement (px) the correction causes at these points). Robust: Huber
    weights at huber_px x 2 sigma.
    """
    X = np.asarray(points_world, float).reshape(-1, 3)
    u = np.asarray(pixels, float).reshape(-1, 2)
    prior = np.diag([prior_rotation_rad ** -2] * 3 + [prior_shift_m ** -2] * 3)
    delta = np.zeros(6)
    cam = camera
    sigma = 1.0
    J = np.zeros((len(X), 2, 6))
    for _ in range(iterations):
        r = u - cam.project(X)
        ok = np.isfinite(r).all(axis=1)
        Jc = pixel_jacobians([cam], X, ok[:, None])[:, 0] @ cam.R.T  # d pixel / d X_camera (N, 2, 3)
        P = X @ cam.R.T + cam.t  # the points in the camera frame, which the turn acts on
        # d pixel / d [omega, tau]: a turn moves P by omega x P, so its rows are Jc [P]x = Jc_row x P
        J = np.concatenate([np.cross(P[:, None, :], Jc), Jc], axis=2)
        r = np.where(ok[:, None], r, 0.0)
        rn = np.linalg.norm(r, axis=1)
        sigma = max(1.4826 * float(np.median(rn[ok])) / np.sqrt(2.0), 0.02) if ok.any() else 1.0
        w = np.where(ok, np.minimum(1.0, huber_px * 2.0 * sigma / np.maximum(rn, 1e-12)), 0.0) / sigma**2
        Jf = J.reshape(-1, 6)  # (2N, 6): the normal equations in one BLAS product each
        JtW = Jf.T * np.repeat(w, 2)
        H = JtW @ Jf + prior
        g = JtW @ r.reshape(-1) - prior @ delta
        try:
            step = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        delta += step
        cam = apply_correction(camera, delta)
        if np.abs(step).max() < 1e-8:
            break
    Jf = J.reshape(-1, 6)
    info = Jf.T @ Jf / sigma**2
    # the image displacement, exact: a knock of degrees is far outside the linearisation
    moved = cam.project(X) - camera.project(X)
    ok = np.isfinite(moved).all(axis=1)
    disp = float(np.sqrt(np.mean(np.sum(moved[ok] ** 2, axis=1)))) if ok.any() else 0.0
    return delta, info, sigma, disp


def _misfit(camera: Camera, delta: np.ndarray, points_world: np.ndarray, pixels: np.ndarray, sigma_px: float
            ) -> float:
    """Robust chi-square of the pairs (N, 3) world / (N, 2) px under the corrected camera: sum of squared
    residuals / sigma_px^2, each clipped at 3 sigma (an outlier pair costs no more than that)."""
    r = np.linalg.norm(pixels - apply_correction(camera, delta).project(points_world), axis=1) / sigma_px
    return float(np.sum(np.minimum(np.nan_to_num(r, nan=3.0), 3.0) ** 2))


def apply_correction(camera: Camera, delta: np.ndarray) -> Camera:
    """The camera turned by omega about its own centre, then shifted by tau: R' = exp([omega]) R,
    t' = exp([omega]) t + tau; delta = [omega (rad), tau (m)], camera frame."""
    dR = Rotation.from_rotvec(np.asarray(delta[:3], float)).as_matrix()
    return camera.with_pose(dR @ camera.R, dR @ camera.t + np.asarray(delta[3:], float))


def marker_motion(state: BodyState, markers_body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(markers (M, 3) in the world at state.time_ns, their velocities (M, 3) m/s) from the state's pose,
    velocity and body-frame angular velocity: X(t) ~ X + V (t - time_ns) over a frame's few milliseconds."""
    R = Rotation.from_quat(state.quaternion).as_matrix()
    lever = markers_body @ R.T
    omega_world = R @ np.asarray(state.angular_velocity, float)
    return lever + np.asarray(state.position, float), np.cross(omega_world, lever) + np.asarray(state.velocity, float)


def pair_blobs(predicted_px: np.ndarray, blobs_px: np.ndarray, gate_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Unambiguous pairs (marker index (K,), blob index (K,)): the nearest blob within gate_px of a predicted
    marker, when no other blob is within twice that distance of the marker and no other marker within twice
    that distance of the blob (at least 2 px either way)."""
    if len(predicted_px) == 0 or len(blobs_px) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    d = np.linalg.norm(predicted_px[:, None, :] - blobs_px[None, :, :], axis=2)
    d = np.where(np.isfinite(d), d, np.inf)
    b = np.argmin(d, axis=1)
    m = np.arange(len(d))
    dm = d[m, b]
    limit = np.maximum(2.0 * dm, 2.0)
    lone_blob = (d < limit[:, None]).sum(axis=1) == 1
    lone_marker = (d[:, b] < limit[None, :]).sum(axis=0) == 1
    ok = (dm < gate_px) & lone_blob & lone_marker
    return m[ok], b[ok]


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
        self._rig = CameraRig(list(arena.cameras))
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
        if v is None or self._motion is None:
            return
        w = self.cams[frame.camera_id]
        w.frames_seen += 1
        if w.frames_seen % self.settings.sample_every:
            return
        blobs = np.asarray(frame.blobs, float).reshape(-1, 4)[:, :2]
        if not len(blobs):
            return
        t_ns, X0, V, rows = self._motion
        X = X0 + V * ((frame.capture_ns - t_ns) * 1e-9)[:, None]
        pred = w.camera.project(X)
        inside = np.isfinite(pred).all(axis=1) & w.camera.model.in_image(pred)
        w.predicted += int(inside.sum())
        self._vote(w, frame.capture_ns, pred[inside], blobs)
        m, b = pair_blobs(pred + w.offset_px, blobs, self.settings.gate_px)
        w.paired += len(m)
        if not len(m):
            return
        self._last_px[v, rows[m]] = blobs[b]
        self._last_ns[v, rows[m]] = frame.capture_ns
        # leave-one-out, and flagged cameras left out too: a knocked camera's rays would bend the others' points
        others = np.array([not x.flagged for x in self.cams.values()])
        others[v] = False
        r = rows[m]
        age_ns = frame.capture_ns - self._last_ns[:, r].T  # (K, V)
        fresh = others[None, :] & (np.abs(age_ns) < self._fresh_ns)
        use = fresh.sum(axis=1) >= 2
        if not use.any():
            return
        px = np.where(fresh[use][..., None], self._last_px[:, r[use]].transpose(1, 0, 2), np.nan)
        # each other view saw the marker where it was at its own capture time
        offsets = -V[m[use], None, :] * (age_ns[use] * 1e-9)[..., None]
        # triangulated in one batch per camera at the next step(): per frame only this bookkeeping
        w.pending.append((frame.capture_ns, px, np.where(fresh[use][..., None], offsets, 0.0), blobs[b[use]]))

    def _triangulate_pending(self, w: CameraWatch) -> None:
        """The leave-one-out points of a camera's pending pairs, in one triangulation."""
        if not w.pending:
            return
        px = np.concatenate([p[1] for p in w.pending])
        offsets = np.concatenate([p[2] for p in w.pending])
        blobs = np.concatenate([p[3] for p in w.pending])
        times = np.concatenate([np.full(len(p[3]), p[0], np.int64) for p in w.pending])
        w.pending.clear()
        tri = triangulate_pixels(self._rig, px, offsets=offsets)
        good = np.isfinite(tri.points).all(axis=1)
        w.times_ns.extend(times[good].tolist())
        w.points.extend(tri.points[good])
        w.pixels.extend(blobs[good])
        w.ref_px.extend(np.sqrt(np.nanmean(tri.residuals[good] ** 2, axis=1)))
        while len(w.times_ns) > self.settings.max_pairs:
            self._drop_oldest(w)

    @staticmethod
    def _drop_oldest(w: CameraWatch) -> None:
        w.times_ns.popleft()
        w.points.popleft()
        w.pixels.popleft()
        w.ref_px.popleft()

    def _vote(self, w: CameraWatch, capture_ns: int, pred: np.ndarray, blobs: np.ndarray) -> None:
        """Keep every blob-minus-prediction offset within search_deg of view (px) for the offset search."""
        if not len(pred) or self.settings.search_deg <= 0:
            return
        radius = np.tan(np.radians(self.settings.search_deg)) * w.camera.model.fx
        d = (blobs[None, :, :] - pred[:, None, :]).reshape(-1, 2)
        d = d[np.einsum("ij,ij->i", d, d) < radius**2]
        if len(d):
            w.votes.append((capture_ns, d))

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
            gain = (_misfit(w.camera, delta, pts, pix, sigma) - _misfit(w.camera, loose[0], pts, pix, sigma))
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
        self._rig = CameraRig([x.camera for x in self.cams.values()])
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
