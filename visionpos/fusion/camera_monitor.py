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
from visionpos.geometry.triangulation import pixel_jacobians
from visionpos.messages import BlobFrame, BodyState

log = logging.getLogger(__name__)

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
    Setting("sample_every", "integer", 2, "pair one frame in this many of each camera (cost per packet)",
            min=1, max=100),
    Setting("min_pairs", "integer", 200, "fewest pairs in a camera's window for a fit", min=20),
    Setting("max_pairs", "integer", 4000, "most pairs kept per camera (the oldest go first)", min=100),
    Setting("max_step_deg", "number", 2.0, "largest rotation applied per correction step (deg)", min=0.01),
    Setting("max_step_m", "number", 0.05, "largest shift applied per correction step (m)", min=0.0001),
)
register_section("camera_monitor", MONITOR)


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

    @classmethod
    def from_arena(cls, arena: ArenaConfig) -> "MonitorSettings":
        return cls(**MONITOR.parse(MONITOR.check(arena.section("camera_monitor"))))


# ---------------------------------------------------------------------------------------------- math
def pose_correction(camera: Camera, points_world: np.ndarray, pixels: np.ndarray, iterations: int = 4,
                    huber_px: float = 1.0) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Small correction of a camera's pose that best reprojects known world points onto observed pixels.

    points_world: (N, 3) m; pixels: (N, 2) observed (distorted) pixels. The corrected camera is
    R' = exp([omega]) R, t' = t + tau (omega rad and tau m in the camera frame); returns (delta (6,) =
    [omega, tau], information (6, 6) = J^T J / sigma^2, sigma (px, robust residual std after the fit), and
    the RMS image displacement (px) the correction causes at these points). Robust: Huber weights at
    huber_px x sigma.
    """
    X = np.asarray(points_world, float).reshape(-1, 3)
    u = np.asarray(pixels, float).reshape(-1, 2)
    delta = np.zeros(6)
    cam = camera
    sigma = 1.0
    J = np.zeros((len(X), 2, 6))
    for _ in range(iterations):
        pred = cam.project(X)
        r = u - pred
        ok = np.isfinite(r).all(axis=1)
        Jw = pixel_jacobians([cam], X, ok[:, None])[:, 0]  # (N, 2, 3) d pixel / d X_world
        Jc = Jw @ cam.R.T  # d pixel / d X_camera
        P = X @ cam.R.T  # R X: the part the rotation acts on
        skew = np.zeros((len(X), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2] = -P[:, 2], P[:, 1]
        skew[:, 1, 0], skew[:, 1, 2] = P[:, 2], -P[:, 0]
        skew[:, 2, 0], skew[:, 2, 1] = -P[:, 1], P[:, 0]
        J = np.concatenate([-Jc @ skew, Jc], axis=2)  # d pixel / d [omega, tau]
        rn = np.linalg.norm(np.where(ok[:, None], r, 0.0), axis=1)
        sigma = max(1.4826 * float(np.median(rn[ok])) / np.sqrt(2.0), 0.02) if ok.any() else 1.0
        k = huber_px * sigma * 2.0
        w = np.where(ok, np.minimum(1.0, k / np.maximum(rn, 1e-12)), 0.0)
        H = np.einsum("n,nia,nib->ab", w, J, J)
        g = np.einsum("n,nia,ni->a", w, J, np.where(ok[:, None], r, 0.0))
        try:
            step = np.linalg.solve(H + 1e-12 * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        delta += step
        cam = apply_correction(camera, delta)
        if np.abs(step[:3]).max() < 1e-7 and np.abs(step[3:]).max() < 1e-7:
            break
    info = np.einsum("nia,nib->ab", J, J) / sigma**2
    disp = float(np.sqrt(np.mean(np.sum((J @ delta) ** 2, axis=1)))) if len(X) else 0.0
    return delta, info, sigma, disp


def apply_correction(camera: Camera, delta: np.ndarray) -> Camera:
    """The camera with R' = exp([omega]) R and t' = t + tau, delta = [omega (rad), tau (m)] (camera frame)."""
    dR = Rotation.from_rotvec(np.asarray(delta[:3], float)).as_matrix()
    return camera.with_pose(dR @ camera.R, camera.t + np.asarray(delta[3:], float))


def predict_markers(state: BodyState, markers_body: np.ndarray, at_ns: int) -> np.ndarray:
    """A body's markers (M, 3) in the world at `at_ns`: the state moved by its velocity and body-frame
    angular velocity over at_ns - state.time_ns."""
    dt = (int(at_ns) - int(state.time_ns)) * 1e-9
    rot = Rotation.from_quat(state.quaternion) * Rotation.from_rotvec(np.asarray(state.angular_velocity) * dt)
    return rot.apply(markers_body) + (np.asarray(state.position) + np.asarray(state.velocity) * dt)


def pair_blobs(predicted_px: np.ndarray, blobs_px: np.ndarray, gate_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Unambiguous pairs (marker index (K,), blob index (K,)): the nearest blob within gate_px of a predicted
    marker, when no other blob is within twice that distance of the marker and no other marker within twice
    that distance of the blob."""
    if len(predicted_px) == 0 or len(blobs_px) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    d = np.linalg.norm(predicted_px[:, None, :] - blobs_px[None, :, :], axis=2)
    d = np.where(np.isfinite(d), d, np.inf)
    m_idx, b_idx = [], []
    for m in range(len(predicted_px)):
        b = int(np.argmin(d[m]))
        dm = d[m, b]
        if not dm < gate_px:
            continue
        limit = max(2.0 * dm, 2.0)
        if np.sum(d[m] < limit) > 1 or np.sum(d[:, b] < limit) > 1:
            continue
        m_idx.append(m)
        b_idx.append(b)
    return np.array(m_idx, int), np.array(b_idx, int)


# ---------------------------------------------------------------------------------------------- state
@dataclass
class CameraWatch:
    """One camera's recent pairs and verdict."""

    camera: Camera
    times_ns: deque = field(default_factory=deque)
    points: deque = field(default_factory=deque)  # (3,) world
    pixels: deque = field(default_factory=deque)  # (2,)
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
        self.settings = settings or MonitorSettings.from_arena(arena)
        self.cams = {c.id: CameraWatch(c) for c in arena.cameras}
        self.markers = {b.name: np.asarray(b.markers, float) for b in arena.bodies}
        self.states: list[BodyState] = []
        self._next_step_ns: int | None = None
        self.events: list[str] = []

    def observe_states(self, states: list[BodyState]) -> None:
        self.states = [s for s in states if s.tracked and s.name in self.markers]

    def observe_frame(self, frame: BlobFrame) -> None:
        w = self.cams.get(frame.camera_id)
        if w is None or not self.states:
            return
        w.frames_seen += 1
        if w.frames_seen % self.settings.sample_every:
            return
        blobs = np.asarray(frame.blobs, float).reshape(-1, 4)[:, :2]
        if not len(blobs):
            return
        X = np.concatenate([predict_markers(s, self.markers[s.name], frame.capture_ns) for s in self.states])
        px = w.camera.project(X)
        m, b = pair_blobs(px, blobs, self.settings.gate_px)
        for k, j in zip(m, b):
            w.times_ns.append(frame.capture_ns)
            w.points.append(X[k])
            w.pixels.append(blobs[j])
        while len(w.times_ns) > self.settings.max_pairs:
            w.times_ns.popleft()
            w.points.popleft()
            w.pixels.popleft()

    def step(self, now_ns: int) -> list[Correction]:
        """Fit every camera's correction (at most once per step_s); flag the moved camera and, with correct,
        return its corrected pose (the caller applies it, e.g. FusionPipeline.set_camera_pose)."""
        st = self.settings
        if self._next_step_ns is not None and now_ns < self._next_step_ns:
            return []
        self._next_step_ns = now_ns + int(st.step_s * 1e9)
        fits: dict[int, tuple[np.ndarray, float, float]] = {}
        for cid, w in self.cams.items():
            while w.times_ns and w.times_ns[0] < now_ns - st.window_s * 1e9:
                w.times_ns.popleft()
                w.points.popleft()
                w.pixels.popleft()
            if len(w.times_ns) < st.min_pairs:
                w.last = {"pairs": float(len(w.times_ns))}
                continue
            delta, info, sigma, disp = pose_correction(w.camera, np.array(w.points), np.array(w.pixels))
            chi2 = float(delta @ info @ delta)
            w.last = {"pairs": float(len(w.times_ns)), "disp_px": disp, "chi2": chi2, "sigma_px": sigma,
                      "rotation_deg": float(np.degrees(np.linalg.norm(delta[:3]))),
                      "shift_mm": float(np.linalg.norm(delta[3:]) * 1e3)}
            fits[cid] = (delta, disp, chi2)
        out: list[Correction] = []
        moved = [(disp, cid) for cid, (_, disp, chi2) in fits.items() if disp > st.flag_px and chi2 > st.chi2_min]
        worst = max(moved) if moved else None
        for cid, w in self.cams.items():
            was = w.flagged
            w.flagged = worst is not None and cid == worst[1]
            if w.flagged and not was:
                w.flagged_since_ns = now_ns
                msg = (f"camera {w.camera.name} (id {cid}) has moved since calibration: its markers sit "
                       f"{w.last['disp_px']:.1f} px off (rotation {w.last['rotation_deg']:.2f} deg, shift "
                       f"{w.last['shift_mm']:.1f} mm)" + ("; correcting its pose while tracking" if st.correct else
                                                          "; recalibrate (visionpos calibrate wand)"))
                self.events.append(msg)
                log.warning(msg)
            elif was and not w.flagged and worst is None and cid in fits:
                msg = f"camera {w.camera.name} (id {cid}) agrees with the tracked bodies again"
                self.events.append(msg)
                log.info(msg)
                w.flagged_since_ns = None
        if worst is not None and st.correct:
            cid = worst[1]
            w = self.cams[cid]
            delta = fits[cid][0].copy()
            rot = np.linalg.norm(delta[:3])
            if rot > np.radians(st.max_step_deg):
                delta[:3] *= np.radians(st.max_step_deg) / rot
            shift = np.linalg.norm(delta[3:])
            if shift > st.max_step_m:
                delta[3:] *= st.max_step_m / shift
            w.camera = apply_correction(w.camera, delta)
            w.corrections += 1
            w.times_ns.clear()
            w.points.clear()
            w.pixels.clear()
            out.append(Correction(cid, w.camera, float(np.degrees(np.linalg.norm(delta[:3]))),
                                  float(np.linalg.norm(delta[3:]))))
        return out

    def report(self) -> dict[int, dict[str, Any]]:
        """Per camera: pairs in the window, the last fit (px moved, chi-square, residual), flagged, corrections."""
        return {cid: {**{k: round(v, 4) for k, v in w.last.items()}, "moved": w.flagged,
                      "corrections": w.corrections} for cid, w in self.cams.items()}
