"""Small synthetic inputs for calibration tests: a ring of cameras and a waved wand.

This is deliberately independent of visionpos.sim (it shares no code with it),
so calibration tests check against a second, simple generator; the benchmarks
use the full simulator.
"""

from __future__ import annotations

import numpy as np

from visionpos.calibration.wand import WandSpec
from visionpos.camera.model import Camera, CameraModel, look_at_rotation
from visionpos.messages import BlobFrame


def ring_cameras(
    n: int,
    radius: float = 3.0,
    height: float = 2.6,
    target: tuple[float, float, float] = (0.0, 0.0, 1.0),
    model: CameraModel | None = None,
    fps: float = 100.0,
) -> list[Camera]:
    """n cameras on a circle, all aimed at `target`; ids 1..n."""
    if model is None:
        model = CameraModel("pinhole", 960, 640, 720.0, 720.0, 479.5, 319.5, np.array([-0.1, 0.02, 0, 0, 0]))
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n + 0.3
        C = np.array([radius * np.cos(a), radius * np.sin(a), height])
        R = look_at_rotation(C, np.asarray(target, float))
        cams.append(Camera(i + 1, f"cam{i + 1}", model, R, -R @ C, fps))
    return cams


def wand_motion(
    times_s: np.ndarray,
    center=(0.0, 0.0, 1.0),
    extent=(1.2, 1.2, 0.6),
    seed: int = 0,
    planar: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Smooth wand A position (T,3) and unit direction (T,3) at times (T,) s.

    Sums of slow sinusoids (0.05-0.4 Hz) with random phases; `planar` keeps the
    wand horizontal at constant height (a degenerate capture).
    """
    rng = np.random.default_rng(seed)
    t = np.asarray(times_s, float)[:, None]
    fr = rng.uniform(0.05, 0.4, (3, 3))
    ph = rng.uniform(0, 2 * np.pi, (3, 3))
    pos = np.zeros((len(t), 3))
    for k in range(3):
        pos[:, k] = (np.sin(2 * np.pi * fr[k] * t + ph[k]) / 3).sum(axis=1)
    pos = np.asarray(center) + pos * np.asarray(extent) / 2
    yaw = 2 * np.pi * 0.07 * t[:, 0] + rng.uniform(0, 6)
    pitch = 0.8 * np.sin(2 * np.pi * 0.11 * t[:, 0] + rng.uniform(0, 6))
    if planar:
        pos[:, 2] = center[2]
        pitch[:] = 0.0
    u = np.column_stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
    return pos, u


def wand_frames(
    cameras: list[Camera],
    duration: float,
    spec: WandSpec = WandSpec(),
    noise_px: float = 0.2,
    seed: int = 0,
    time_offsets_s: np.ndarray | None = None,
    static_blobs: int = 0,
    planar: bool = False,
    extent=(1.2, 1.2, 0.6),
    center=(0.0, 0.0, 1.0),
    clock_errors_s: np.ndarray | None = None,
) -> list[BlobFrame]:
    """BlobFrames of a wand wave seen by `cameras` (each at its own fps and time offset).

    time_offsets_s: (V,) when each camera's first exposure happens (its phase; stamps are right);
    clock_errors_s: (V,) error of each camera's clock: its stamps read true time + this.
    static_blobs: fixed extra blobs per camera (LED rings of other cameras).
    """
    rng = np.random.default_rng(seed + 1)
    if time_offsets_s is None:
        time_offsets_s = rng.uniform(0, 0.01, len(cameras))
    errors = np.zeros(len(cameras)) if clock_errors_s is None else np.asarray(clock_errors_s, float)
    frames = []
    for ci, cam in enumerate(cameras):
        ts = np.arange(0.0, duration, 1.0 / cam.fps) + time_offsets_s[ci]
        A, u = wand_motion(ts, center=center, extent=extent, seed=seed, planar=planar)
        pts = A[:, None, :] + spec.offsets[None, :, None] * u[:, None, :]  # (T,3,3)
        flat = pts.reshape(-1, 3)
        vis = cam.visible(flat, margin=2.0).reshape(-1, 3).all(axis=1)
        uv = cam.project(flat).reshape(-1, 3, 2) + rng.normal(0, noise_px, (len(ts), 3, 2))
        fixed = rng.uniform([20, 20], [cam.model.width - 20, cam.model.height - 20], (static_blobs, 2))
        for k in range(len(ts)):
            xy = uv[k][rng.permutation(3)] if vis[k] else np.zeros((0, 2))
            if static_blobs:
                xy = np.vstack([xy, fixed + rng.normal(0, 0.05, fixed.shape)])
            blobs = np.column_stack([xy, np.full(len(xy), 12.0), np.full(len(xy), 200.0)]).astype(np.float32)
            frames.append(BlobFrame(cam.id, k, int(round((ts[k] + errors[ci]) * 1e9)), blobs))
    return frames
