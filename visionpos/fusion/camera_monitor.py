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
    Setting("min_pairs", "integer", 200, "fewest pairs in a camera's window for a fit", min=20),
    Setting("max_pairs", "integer", 4000, "most pairs kept per camera (the oldest go first)", min=100),
    Setting("max_step_deg", "number", 2.0, "largest rotation applied per correction step (deg)", min=0.01),
    Setting("max_step_m", "number", 0.05, "largest shift applied per correction step (m)", min=0.0001),
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
    min_pairs: int = 200
    max_pairs: int = 4000
    max_step_deg: float = 2.0
    max_step_m: float = 0.05


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
        skew = np.zeros((len(X), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2] = -P[:, 2], P[:, 1]
        skew[:, 1, 0], skew[:, 1, 2] = P[:, 2], -P[:, 0]
        skew[:, 2, 0], skew[:, 2, 1] = -P[:, 1], P[:, 0]
        J = np.concatenate([-Jc @ skew, Jc], axis=2)  # d pixel / d [omega, tau]
        r = np.where(ok[:, None], r, 0.0)
        rn = np.linalg.norm(r, axis=1)
        sigma = max(1.4826 * float(np.median(rn[ok])) / np.sqrt(2.0), 0.02) if ok.any() else 1.0
        w = np.where(ok, np.minimum(1.0, huber_px * 2.0 * sigma / np.maximum(rn, 1e-12)), 0.0) / sigma**2
        H = np.einsum("n,nia,nib->ab", w, J, J) + prior
        g = np.einsum("n,nia,ni->a", w, J, r) - prior @ delta
        try:
            step = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        delta += step
        cam = apply_correction(camera, delta)
        if np.abs(step).max() < 1e-8:
            break
    info = np.einsum("nia,nib->ab", J, J) / sigma**2
    disp = float(np.sqrt(np.mean(np.sum((J @ delta) ** 2, axis=1)))) if len(X) else 0.0
    return delta, info, sigma, disp


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
    pending: list = field(default_factory=list)  # frames' pairs waiting for their batch triangulation
    frames_seen: int = 0
    flagged: bool = False
    flagged_since_ns: int | None = None
    corrections: int = 0
    last: dict[str, float] = field(default_factory=dict)  # the last fit: disp_px, chi2, sigma_px, pairs, ...


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
        m, b = pair_blobs(w.camera.project(X), blobs, self.settings.gate_px)
        if not len(m):
            return
        self._last_px[v, rows[m]] = blobs[b]
        self._last_ns[v, rows[m]] = frame.capture_ns
        others = np.ones(len(self.cams), bool)
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
        while len(w.times_ns) > self.settings.max_pairs:
            w.times_ns.popleft()
            w.points.popleft()
            w.pixels.popleft()

    def step(self, now_ns: int) -> list[Correction]:
        """Fit one camera's correction per call (cameras in turn, each about once per step_s, so one call
        costs one small fit on the server's loop); flag the moved camera from every camera's latest fit and,
        with correct, return its corrected pose (the caller applies it: FusionPipeline.set_camera_pose)."""
        st = self.settings
        if self._next_step_ns is not None and now_ns < self._next_step_ns:
            return []
        ids = list(self.cams)
        self._next_step_ns = now_ns + int(st.step_s * 1e9 / len(ids))
        if self._turn % len(ids) == 0:
            self._round_end_ns = now_ns  # every fit of this round uses the pairs up to here: one moment
        cid = ids[self._turn % len(ids)]
        self._turn += 1
        w = self.cams[cid]
        self._triangulate_pending(w)
        while w.times_ns and w.times_ns[0] < now_ns - st.window_s * 1e9:
            w.times_ns.popleft()
            w.points.popleft()
            w.pixels.popleft()
        self._fits.pop(cid, None)
        times = np.fromiter(w.times_ns, np.int64, len(w.times_ns))
        upto = int(np.searchsorted(times, self._round_end_ns, side="right"))
        if upto < st.min_pairs:
            w.last = {"pairs": float(upto)}
        else:
            lo = max(0, upto - MAX_FIT_PAIRS)  # the newest up to the round's moment; bounds the fit's cost
            pts, pix = np.array(list(w.points)[lo:upto]), np.array(list(w.pixels)[lo:upto])
            delta, info, sigma, disp = pose_correction(w.camera, pts, pix)
            chi2 = float(delta @ info @ delta)
            w.last = {"pairs": float(len(w.times_ns)), "disp_px": disp, "chi2": chi2, "sigma_px": sigma,
                      "rotation_deg": float(np.degrees(np.linalg.norm(delta[:3]))),
                      "shift_mm": float(np.linalg.norm(delta[3:]) * 1e3)}
            self._fits[cid] = (delta, disp, chi2)
        if self._turn % len(ids):
            return []  # judge once every camera has a fit from this round: a stale fit would skew the comparison
        fits = self._fits
        out: list[Correction] = []
        moved = sorted(((disp, cid) for cid, (_, disp, chi2) in fits.items() if chi2 > st.chi2_min), reverse=True)
        worst = None
        if moved and moved[0][0] > st.flag_px:
            # the knocked camera dominates: the fused poses lean toward it, so the others show smaller corrections
            runner_up = max((d for d, c in ((fits[c][1], c) for c in fits) if c != moved[0][1]), default=0.0)
            if moved[0][0] > DOMINANCE * runner_up:
                worst = moved[0]
        window_full = {cid: bool(w.times_ns) and now_ns - w.times_ns[0] >= 0.8 * st.window_s * 1e9
                       for cid, w in self.cams.items()}
        # one camera at a time: while a flagged one is re-fitted its rays still bend the others' points
        if worst is not None and not any(w.flagged for w in self.cams.values()):
            w = self.cams[worst[1]]
            w.flagged, w.flagged_since_ns = True, now_ns
            msg = (f"camera {w.camera.name} (id {worst[1]}) has moved since calibration: its markers sit "
                   f"{w.last['disp_px']:.1f} px off where the other cameras put them" +
                   ("; re-fitting its pose while tracking goes on" if st.correct else
                    "; recalibrate (visionpos calibrate wand)"))
            self.events.append(msg)
            log.warning(msg)
            self._clear(w)  # the window mixes the old and the new pose: fit the new one on fresh pairs only
            return out
        for cid, w in self.cams.items():
            if not w.flagged or cid not in fits or not window_full[cid]:
                continue
            delta, disp, chi2 = fits[cid]
            if disp < SETTLED * st.flag_px:
                w.flagged, w.flagged_since_ns = False, None
                msg = (f"camera {w.camera.name} (id {cid}) agrees with the other cameras again"
                       + (f" after {w.corrections} pose correction(s)" if w.corrections else ""))
                self.events.append(msg)
                log.info(msg)
            elif st.correct:
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
                self._clear(w)
                log.info("camera %s (id %d): pose corrected by %.3f deg, %.1f mm", w.camera.name, cid,
                         np.degrees(np.linalg.norm(delta[:3])), 1e3 * np.linalg.norm(delta[3:]))
                out.append(Correction(cid, w.camera, float(np.degrees(np.linalg.norm(delta[:3]))),
                                      float(np.linalg.norm(delta[3:]))))
        return out

    def _clear(self, w: CameraWatch) -> None:
        self._fits.pop(w.camera.id, None)
        w.pending.clear()
        w.times_ns.clear()
        w.points.clear()
        w.pixels.clear()

    def report(self) -> dict[int, dict[str, Any]]:
        """Per camera: pairs in the window, the last fit (px moved, chi-square, residual), flagged, corrections."""
        return {cid: {**{k: round(v, 4) for k, v in w.last.items()}, "moved": w.flagged,
                      "corrections": w.corrections} for cid, w in self.cams.items()}
