"""Camera planner: how well an arena's cameras see a flight volume, and where one more camera helps most.

Over a grid of the flight volume: how many cameras see a marker (each camera's field of view), the
Cramér–Rao bound of a triangulated marker (geometry/triangulation.py `triangulation_crb`) and of each
body's pose (`pose_crb`, from the markers that two or more cameras see, as the tracker triangulates
them; averaged over yaw, since a drone flies at any heading). Pixel noise is the blob centroid noise
(0.2 px by default: what the detector achieves on well-exposed 4-8 px blobs, docs/benchmarks.md).

The suggestion tries candidate cameras (the arena's first camera's lens) on a ring around the volume
at the existing cameras' mean height, each aimed at the volume centre, and ranks them by the
fraction of the volume that two or more cameras see, then by the marker bound over the volume.
Occlusion (propellers, the body itself, people) is not modelled: these are the bounds of the
geometry, which `visionpos bench --only planner` compares with simulated triangulations.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from visionpos.camera.model import Camera, look_at_rotation
from visionpos.config.arena import ArenaConfig, BodyConfig
from visionpos.geometry.triangulation import CameraRig, pose_crb, triangulation_crb

YAWS_DEG = (0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0)


@dataclass(frozen=True)
class Volume:
    """An axis-aligned box (m, world frame) and the grid step over it."""

    lo: np.ndarray  # (3,) x, y, z minimum
    hi: np.ndarray  # (3,) maximum
    step_m: float

    def grid(self) -> np.ndarray:
        """(N, 3) grid points, the box's faces included."""
        axes = [np.linspace(a, b, max(2, int(round((b - a) / self.step_m)) + 1)) for a, b in zip(self.lo, self.hi)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def default_volume(cameras: tuple[Camera, ...] | list[Camera], step_m: float = 0.25) -> Volume:
    """The box inside the cameras' horizontal footprint (shrunk by 20 % toward its centre) from 0.1 m up to
    two thirds of the lowest camera's height: where a lab flies with wall- or tripod-mounted cameras."""
    C = np.array([c.center for c in cameras])
    mid = 0.5 * (C[:, :2].min(0) + C[:, :2].max(0))
    half = 0.4 * (C[:, :2].max(0) - C[:, :2].min(0))
    top = max(0.5, 2.0 / 3.0 * float(C[:, 2].min()))
    return Volume(np.array([*(mid - half), 0.1]), np.array([*(mid + half), top]), step_m)


@dataclass
class Coverage:
    """Per grid point: cameras seeing it, the marker bound and each body's bounds (NaN where undetermined)."""

    points: np.ndarray  # (N, 3) m
    n_cameras: np.ndarray  # (N,) int
    marker_std_mm: np.ndarray  # (N,) sqrt(trace CRB): the 3-D RMS error of a triangulated marker
    body_position_std_mm: dict[str, np.ndarray] = field(default_factory=dict)  # (N,) 3-D RMS, mean over yaw
    body_rotation_std_deg: dict[str, np.ndarray] = field(default_factory=dict)  # (N,) RMS rotation angle

    def fraction_seen_by(self, k: int) -> float:
        return float(np.mean(self.n_cameras >= k))


def marker_coverage(cameras: list[Camera], points: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(n_cameras (N,), marker_std_mm (N,)) at world points (N, 3)."""
    rig = CameraRig(cameras)
    visible = np.stack([c.visible(points) for c in cameras], axis=1)
    crb = triangulation_crb(rig, points, sigma_px, visible)
    return visible.sum(1), np.sqrt(np.trace(crb, axis1=1, axis2=2)) * 1e3


def body_bounds(cameras: list[Camera], body: BodyConfig, origin: np.ndarray, sigma_px: float,
                yaws_deg=YAWS_DEG) -> tuple[float, float]:
    """(position std mm, rotation std deg) of `body` level at `origin` (3,), the CRB's RMS over the yaws;
    NaN where some yaw leaves the pose undetermined (fewer than 3 markers seen by 2+ cameras)."""
    rig = CameraRig(cameras)
    pos, rot = [], []
    for yaw in np.radians(yaws_deg):
        c, s = np.cos(yaw), np.sin(yaw)
        X = origin + body.markers @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
        visible = np.stack([cam.visible(X) for cam in cameras], axis=1)
        visible &= (visible.sum(1) >= 2)[:, None]  # the tracker triangulates: single views do not count here
        if visible.any(1).sum() < 3:
            return float("nan"), float("nan")
        C = pose_crb(rig, X, origin, sigma_px, visible)
        pos.append(np.trace(C[:3, :3]))
        rot.append(np.trace(C[3:, 3:]))
    return float(np.sqrt(np.mean(pos)) * 1e3), float(np.degrees(np.sqrt(np.mean(rot))))


def coverage(arena: ArenaConfig, volume: Volume, sigma_px: float = 0.2, with_bodies: bool = True) -> Coverage:
    cams = list(arena.cameras)
    pts = volume.grid()
    n, std = marker_coverage(cams, pts, sigma_px)
    cov = Coverage(pts, n, std)
    if with_bodies:
        for b in arena.bodies:
            pb = np.array([body_bounds(cams, b, p, sigma_px) for p in pts]).reshape(-1, 2)
            cov.body_position_std_mm[b.name] = pb[:, 0]
            cov.body_rotation_std_deg[b.name] = pb[:, 1]
    return cov


@dataclass(frozen=True)
class Suggestion:
    camera: Camera
    seen_by_2: float  # fraction of the volume two or more cameras see, with this camera added
    marker_rms_mm: float  # RMS of the marker bound over the points the current cameras cover (2+), with it


def _rms(a: np.ndarray) -> float:
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a**2))) if len(a) else float("nan")


def candidate_cameras(cameras: list[Camera], volume: Volume, n_azimuths: int = 16) -> list[Camera]:
    """Cameras with the first camera's lens on a ring around the volume at the cameras' mean height
    (radius: the cameras' mean horizontal distance from the volume centre), aimed at the volume centre."""
    centre = 0.5 * (volume.lo + volume.hi)
    C = np.array([c.center for c in cameras])
    radius = float(np.mean(np.linalg.norm(C[:, :2] - centre[:2], axis=1)))
    height = float(np.mean(C[:, 2]))
    next_id = max(c.id for c in cameras) + 1
    out = []
    for k in range(n_azimuths):
        a = 2 * np.pi * k / n_azimuths
        pos = np.array([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a), height])
        R = look_at_rotation(pos, centre)
        out.append(Camera(next_id, f"suggested{k}", cameras[0].model, R, -R @ pos, cameras[0].fps))
    return out


def suggest_camera(arena: ArenaConfig, volume: Volume, sigma_px: float = 0.2, top: int = 3) -> list[Suggestion]:
    """The `top` candidate cameras that most improve the volume's coverage, then its marker bound."""
    cams = list(arena.cameras)
    pts = volume.grid()
    n0, _ = marker_coverage(cams, pts, sigma_px)
    covered = n0 >= 2
    scored = []
    for cand in candidate_cameras(cams, volume):
        n, std = marker_coverage([*cams, cand], pts, sigma_px)
        scored.append(Suggestion(cand, float(np.mean(n >= 2)), _rms(std[covered]) if covered.any() else float("nan")))
    scored.sort(key=lambda s: (-round(s.seen_by_2, 3), s.marker_rms_mm))
    return scored[:top]


def summary_lines(arena: ArenaConfig, volume: Volume, cov: Coverage, suggestions: list[Suggestion],
                  sigma_px: float) -> list[str]:
    """The planner's printed report."""
    lines = [
        f"volume x {volume.lo[0]:.2f}..{volume.hi[0]:.2f}  y {volume.lo[1]:.2f}..{volume.hi[1]:.2f}  "
        f"z {volume.lo[2]:.2f}..{volume.hi[2]:.2f} m, {len(cov.points)} points every {volume.step_m:g} m; "
        f"{len(arena.cameras)} cameras; centroid noise {sigma_px:g} px",
        "cameras seeing a point: " + ", ".join(
            f">={k}: {100 * cov.fraction_seen_by(k):.0f} %" for k in range(1, min(len(arena.cameras), 4) + 1)),
    ]
    ok = np.isfinite(cov.marker_std_mm)
    if ok.any():
        m = cov.marker_std_mm[ok]
        lines.append(f"marker 3-D RMS bound (where 2+ cameras see it): median {np.median(m):.3f} mm, "
                     f"90th percentile {np.percentile(m, 90):.3f} mm, worst {m.max():.3f} mm")
    for name, pos in cov.body_position_std_mm.items():
        rot = cov.body_rotation_std_deg[name]
        good = np.isfinite(pos)
        if good.any():
            lines.append(f"body {name}: pose determined at {100 * good.mean():.0f} % of the volume; position bound "
                         f"median {np.median(pos[good]):.3f} mm (90th pct {np.percentile(pos[good], 90):.3f}), "
                         f"rotation median {np.median(rot[good]):.3f} deg "
                         f"(90th pct {np.percentile(rot[good], 90):.3f})")
        else:
            lines.append(f"body {name}: no point of the volume where 3 of its markers are seen by 2+ cameras")
    base2 = cov.fraction_seen_by(2)
    base_rms = _rms(cov.marker_std_mm)
    for i, s in enumerate(suggestions):
        c = s.camera.center
        lines.append(f"suggestion {i + 1}: a camera at ({c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f}) m aimed at the volume "
                     f"centre: seen by 2+ {100 * base2:.0f} % -> {100 * s.seen_by_2:.0f} %, marker RMS bound "
                     f"{base_rms:.3f} -> {s.marker_rms_mm:.3f} mm")
    return lines


def plot_coverage(path, arena: ArenaConfig, volume: Volume, cov: Coverage, suggestions: list[Suggestion]) -> None:
    """PNG: for three heights, the number of cameras seeing each point and the marker bound (mm), with the
    cameras (black) and the first suggestion (red) from above."""
    from visionpos.analysis.plots import _pyplot

    plt = _pyplot()
    zs = np.unique(cov.points[:, 2])
    levels = zs[np.unique(np.linspace(0, len(zs) - 1, min(3, len(zs))).round().astype(int))]
    fig, axes = plt.subplots(len(levels), 2, figsize=(10, 4 * len(levels)), squeeze=False)
    C = np.array([c.center for c in arena.cameras] + [s.camera.center for s in suggestions[:1]])
    xs, ys = np.unique(cov.points[:, 0]), np.unique(cov.points[:, 1])
    extent = (xs[0], xs[-1], ys[0], ys[-1])
    for row, z in zip(axes, levels):
        sel = cov.points[:, 2] == z
        count = cov.n_cameras[sel].reshape(len(xs), len(ys)).T
        std = cov.marker_std_mm[sel].reshape(len(xs), len(ys)).T
        for ax, img, title, cmap in ((row[0], count, "cameras seeing", "viridis"),
                                     (row[1], std, "marker bound (mm, 3-D RMS)", "magma")):
            im = ax.imshow(img, origin="lower", extent=extent, cmap=cmap, aspect="equal")
            fig.colorbar(im, ax=ax)
            ax.scatter(C[:len(arena.cameras), 0], C[:len(arena.cameras), 1], c="k", marker="^", label="cameras")
            if suggestions:
                s = suggestions[0].camera.center
                ax.scatter([s[0]], [s[1]], c="r", marker="*", s=120, label="suggested")
            ax.set_title(f"{title} at z = {z:.2f} m")
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
            pad = 0.3
            ax.set_xlim(min(xs[0], C[:, 0].min()) - pad, max(xs[-1], C[:, 0].max()) + pad)
            ax.set_ylim(min(ys[0], C[:, 1].min()) - pad, max(ys[-1], C[:, 1].max()) + pad)
        row[0].legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
