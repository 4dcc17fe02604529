"""Ground plane and world frame from a static marker set on the floor.

A triangle or L-frame of markers (known layout, e.g. an L with 10/40 cm and
20 cm arms) lies still on the floor. Each camera's static blobs are averaged
over all frames; markers are matched across cameras by triangulating every
two-camera candidate and counting the cameras that agree; the layout is found
among the triangulated points by its distances; the world frame then gets
z up (the floor normal, towards the cameras), its origin at the chosen marker
(moved down by the marker height so z = 0 is the floor) and x towards the
chosen second marker.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from visionpos.calibration.wand import CalibrationError
from visionpos.camera.model import Camera
from visionpos.geometry.alignment import kabsch_svd
from visionpos.geometry.triangulation import triangulate_pixels
from visionpos.messages import BlobFrame


def static_blobs(frames: Sequence[BlobFrame], radius_px: float = 1.5, min_fraction: float = 0.5) -> np.ndarray:
    """Blobs present at one place in at least min_fraction of one camera's frames.

    Returns their mean pixel positions (K, 2).
    """
    xy = [np.asarray(f.blobs, float).reshape(-1, 4)[:, :2] for f in frames]
    xy = [p[np.isfinite(p).all(axis=1)] for p in xy]
    if not xy or not any(len(p) for p in xy):
        return np.zeros((0, 2))
    n = len(xy)
    counts = np.array([len(p) for p in xy])
    seeds = xy[int(np.argsort(counts)[len(counts) // 2])]  # a frame with the typical blob count
    if len(seeds) == 0:
        seeds = xy[int(np.argmax(counts))]
    allp = np.concatenate(xy)
    out = []
    for s in seeds:
        near = np.linalg.norm(allp - s, axis=1) < 3 * radius_px
        m = allp[near].mean(axis=0)
        near = np.linalg.norm(allp - m, axis=1) < radius_px
        if near.sum() >= min_fraction * n:
            out.append(allp[near].mean(axis=0))
    if not out:
        return np.zeros((0, 2))
    out = np.array(out)
    # seeds of one blob can produce duplicates
    keep = []
    for p in out:
        if all(np.linalg.norm(p - q) > radius_px for q in keep):
            keep.append(p)
    return np.array(keep)


def match_static(
    cameras: list[Camera], blobs: list[np.ndarray], max_px: float = 2.0
) -> tuple[np.ndarray, np.ndarray]:
    """3D points seen consistently by >= 2 cameras.

    blobs: per camera (K_v, 2) pixel positions. Returns points (N, 3) and the
    number of cameras supporting each (N,), best supported first.
    """
    V = len(cameras)
    cands = []
    for i, j in itertools.combinations(range(V), 2):
        if len(blobs[i]) == 0 or len(blobs[j]) == 0:
            continue
        ai, bj = np.meshgrid(np.arange(len(blobs[i])), np.arange(len(blobs[j])), indexing="ij")
        ai, bj = ai.ravel(), bj.ravel()
        px = np.full((len(ai), V, 2), np.nan)
        px[:, i] = blobs[i][ai]
        px[:, j] = blobs[j][bj]
        tri = triangulate_pixels(cameras, px)
        ok = np.isfinite(tri.points).all(axis=1) & (np.nan_to_num(tri.residuals, nan=0).max(axis=1) < max_px)
        cands.extend(tri.points[ok])
    if not cands:
        return np.zeros((0, 3)), np.zeros(0, int)
    cands = np.array(cands)
    # support: cameras with a blob within max_px of the candidate's projection
    px_all = np.full((len(cands), V, 2), np.nan)
    support = np.zeros(len(cands), int)
    for v, cam in enumerate(cameras):
        if len(blobs[v]) == 0:
            continue
        uv = cam.project(cands)
        d = np.linalg.norm(uv[:, None, :] - blobs[v][None], axis=2)
        d = np.where(np.isfinite(d), d, np.inf)
        k = np.argmin(d, axis=1)
        hit = d[np.arange(len(cands)), k] < max_px
        px_all[hit, v] = blobs[v][k[hit]]
        support += hit
    order = np.argsort(-support, kind="stable")
    pts, sup, used_px = [], [], []
    for c in order:
        if support[c] < 2:
            break
        if any(np.linalg.norm(cands[c] - p) < 0.01 for p in pts):
            continue
        pts.append(cands[c])
        sup.append(int(support[c]))
        used_px.append(px_all[c])
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, int)
    refined = triangulate_pixels(cameras, np.array(used_px)).points
    return refined, np.array(sup)


def static_point_std(cameras: list[Camera], points: np.ndarray, blobs: list[np.ndarray], max_px: float = 2.0,
                     floor_px: float = 0.05) -> tuple[np.ndarray, float]:
    """How well each static point is measured: (std (N,) m, the effective pixel error used).

    The effective pixel error is the RMS distance between the points' projections and the cameras' static
    blobs: it holds the blobs' noise and what the calibration gets wrong, which is what separates the points'
    measured distances from the frame's. Each point's std is sqrt(trace/3) of its triangulation Cramér–Rao
    bound at that pixel error in the cameras that see it.
    """
    from visionpos.geometry.triangulation import triangulation_crb

    N, V = len(points), len(cameras)
    seen = np.zeros((N, V), bool)
    res = []
    for v, cam in enumerate(cameras):
        if len(blobs[v]) == 0 or N == 0:
            continue
        d = np.linalg.norm(cam.project(points)[:, None, :] - blobs[v][None], axis=2)
        d = np.where(np.isfinite(d), d, np.inf).min(axis=1)
        seen[:, v] = d < max_px
        res.extend(d[seen[:, v]])
    sigma_px = max(float(np.sqrt(np.mean(np.square(res)))) if res else floor_px, floor_px)
    crb = triangulation_crb(cameras, points, sigma_px, seen)
    return np.sqrt(np.trace(crb, axis1=1, axis2=2) / 3.0), sigma_px


def identify_layout(
    points: np.ndarray, layout: np.ndarray, support: np.ndarray | None = None, tol: float = 0.01,
    point_std: np.ndarray | None = None, layout_std: float = 0.001, n_sigma: float = 4.0,
    above: np.ndarray | None = None,
) -> np.ndarray:
    """Which measured point is which layout marker.

    points: (N, 3) measured; layout: (M, 3) known marker positions (M <= N);
    support: (N,) cameras behind each point (ties are broken towards more support).
    A pair of points matches a pair of layout markers when their distances differ by less than
    n_sigma standard deviations of that difference, sqrt(std_i^2 + std_j^2 + layout_std^2), with
    point_std (N,) m (`static_point_std`) and layout_std m (how well the frame's distances are known);
    without point_std, by less than tol (m). Of the assignments that fit the same points, the one whose
    distances agree best wins when the next one's chi-square is n_sigma^2 larger; otherwise the frame is
    too symmetric for the noise and CalibrationError says by how much its distances must differ.
    above: (V, 3) camera centres, which are above the floor: an assignment is kept only when the layout's
    +z, fitted to its points, points towards most of them. A frame and its mirror image have the same
    distances (an L with legs of 157 and 152 mm and the same L with its legs swapped), so this settles
    a near-isosceles frame whatever the noise; what remains ambiguous is a frame that matches itself
    turned in its own plane (an equilateral triangle).
    Returns (M,) indices into points.
    """
    M, N = len(layout), len(points)
    if N < M:
        raise CalibrationError(
            f"found {N} static markers seen by two or more cameras, the ground frame has {M}; make sure every "
            "marker of the frame is visible to at least two cameras and nothing hides them"
        )
    sup = np.ones(N) if support is None else np.asarray(support, float)
    Dl = np.linalg.norm(layout[:, None] - layout[None], axis=2)
    Dp = np.linalg.norm(points[:, None] - points[None], axis=2)
    if point_std is None:
        S = np.full((N, N), tol / n_sigma)  # std of a distance difference
    else:
        sd = np.asarray(point_std, float)
        S = np.sqrt(sd[:, None] ** 2 + sd[None] ** 2 + float(layout_std) ** 2)
    gate = n_sigma * S
    sols: list[tuple[float, float, tuple[int, ...]]] = []

    def extend(assigned: list[int]) -> None:
        k = len(assigned)
        if k == M:
            p = np.array(assigned)
            iu = np.triu_indices(M, 1)
            chi2 = float(np.sum(((Dp[np.ix_(p, p)] - Dl) / S[np.ix_(p, p)])[iu] ** 2))
            sols.append((-float(sup[p].sum()), chi2, tuple(assigned)))
            return
        ok = np.ones(N, bool)
        ok[assigned] = False
        for j, a in enumerate(assigned):
            ok &= np.abs(Dp[a] - Dl[k, j]) < gate[a]
        for c in np.flatnonzero(ok):
            extend(assigned + [int(c)])

    extend([])
    if not sols:
        within = (f"{n_sigma:g} sigma (about {1000 * float(np.median(gate)):.1f} mm)" if point_std is not None
                  else f"{tol * 1000:.0f} mm")
        raise CalibrationError(
            f"no {M} of the {N} static points match the ground frame's marker distances within {within}; "
            "check the frame's marker layout (and --marker-height) and that the cameras are calibrated"
        )
    sols.sort()
    if above is not None:
        facing = [s for s in sols if _faces(points[list(s[2])], layout, above)]
        if not facing:
            raise CalibrationError(
                "the ground frame's distances match the static points only with the frame's +z pointing away from "
                "the cameras: its layout is mirrored (list its markers counter-clockwise seen from above, or "
                "swap its x and y), or the cameras are not above the floor")
        sols = facing
    best = sols[0]
    for other in sols[1:]:
        if other[0] == best[0] and set(other[2]) == set(best[2]) and other[1] - best[1] < n_sigma**2:
            iu = np.triu_indices(M, 1)
            dl = np.sort(Dl[iu])
            closest = float(np.min(np.diff(dl))) if len(dl) > 1 else 0.0
            noise = float(np.median(S[np.ix_(list(best[2]), list(best[2]))][iu]))
            if above is not None:
                raise CalibrationError(
                    "the ground frame matches the static points in more than one way even with the cameras above "
                    "it: turned in its own plane it fits itself (its two closest distances differ by "
                    f"{closest * 1000:.1f} mm, a measured distance is uncertain by about {noise * 1000:.1f} mm, "
                    "1 sigma); make its legs differ by more than "
                    f"{2 * n_sigma * noise * 1000:.0f} mm, or move one marker so the frame is no longer symmetric "
                    "(an L with unequal arms, a scalene triangle)")
            raise CalibrationError(
                "the ground frame's marker distances match the static points in more than one way: its two closest "
                f"distances differ by {closest * 1000:.1f} mm, and a measured distance is uncertain by about "
                f"{noise * 1000:.1f} mm (1 sigma); use a frame whose distances all differ by more than "
                f"{2 * n_sigma * noise * 1000:.0f} mm (an L with clearly unequal arms or a scalene triangle), or "
                "calibrate the cameras better"
            )
        break
    return np.array(best[2])


def _faces(measured: np.ndarray, layout: np.ndarray, centers: np.ndarray) -> bool:
    """Whether the layout's +z, fitted to the measured points (M, 3) (a proper rotation: a mirrored
    assignment turns it over), points towards most camera centres (V, 3)."""
    Rl, tl = kabsch_svd(layout, measured)
    side = (np.asarray(centers, float) - measured.mean(axis=0)) @ Rl[:, 2]
    return int(np.sum(side > 0)) > len(side) / 2


@dataclass
class GroundResult:
    """New cameras in the ground frame and what was measured.

    R (3,3), t (3,): old world -> new world (X_new = R X_old + t).
    markers: (M, 3) measured marker centres in the new world; fit_rms: layout fit (m).
    static_points: (N, 3) every static point found, new world; marker_std: (M,) m, how well each
    marker was measured; sigma_px: the effective pixel error behind marker_std.
    """

    cameras: list[Camera]
    R: np.ndarray
    t: np.ndarray
    markers: np.ndarray
    fit_rms: float
    n_static: int
    static_points: np.ndarray | None = None
    marker_std: np.ndarray | None = None
    sigma_px: float = float("nan")


def world_from_layout(
    measured: np.ndarray, layout: np.ndarray, origin: int = 0, x_marker: int = 1, marker_height: float = 0.0
) -> tuple[np.ndarray, np.ndarray, float]:
    """World transform from identified markers.

    measured: (M, 3) marker centres in the old world, row k = layout marker k;
    layout: (M, 3) marker positions in the frame's own coordinates (markers on
    its x-y plane, z up). The new world has its origin under marker `origin`
    (marker centres at z = marker_height), x towards marker `x_marker` (in the
    floor plane), z along the layout's +z.
    Returns R (3,3), t (3,) with X_new = R X_old + t, and the fit RMS (m).
    """
    Rl, tl = kabsch_svd(layout, measured)  # measured ~ Rl layout + tl
    fit = float(np.sqrt(np.mean(np.sum((layout @ Rl.T + tl - measured) ** 2, axis=1))))
    z = Rl[:, 2]
    x = measured[x_marker] - measured[origin]
    x = x - z * (x @ z)
    nx = np.linalg.norm(x)
    if nx < 1e-6:
        raise CalibrationError(f"markers {origin} and {x_marker} do not define a direction on the floor")
    x /= nx
    y = np.cross(z, x)
    R = np.vstack([x, y, z])  # rows: new axes in old coordinates
    o = measured[origin] - marker_height * z
    return R, -R @ o, fit


def apply_world(cameras: Sequence[Camera], R: np.ndarray, t: np.ndarray) -> list[Camera]:
    """Re-express camera poses after X_new = R X_old + t: R_c' = R_c R^T, t_c' = t_c - R_c' t."""
    out = []
    for c in cameras:
        Rc = c.R @ R.T
        out.append(replace(c, R=Rc, t=c.t - Rc @ t))
    return out


def calibrate_ground(
    frames: Sequence[BlobFrame],
    cameras: Sequence[Camera],
    layout: np.ndarray,
    origin: int = 0,
    x_marker: int = 1,
    marker_height: float = 0.0,
    n_sigma: float = 4.0,
    layout_std: float = 0.001,
) -> GroundResult:
    """Ground plane step on BlobFrames of a static marker frame on the floor. n_sigma and layout_std (m):
    the distance test of `identify_layout`, scaled to how well the points were measured."""
    cameras = list(cameras)
    layout = np.asarray(layout, float)
    if layout.ndim != 2 or layout.shape[1] != 3 or len(layout) < 3:
        raise CalibrationError(f"ground frame layout must be (M >= 3, 3) marker positions, got shape {layout.shape}")
    for name, k in (("origin", origin), ("x-axis", x_marker)):
        if not 0 <= k < len(layout):
            raise CalibrationError(f"{name} marker index {k} is out of range for a frame with {len(layout)} markers")
    if origin == x_marker:
        raise CalibrationError("origin and x-axis markers must differ")
    by_cam: dict[int, list[BlobFrame]] = {c.id: [] for c in cameras}
    for f in frames:
        if f.camera_id in by_cam:
            by_cam[f.camera_id].append(f)
    blobs = [static_blobs(by_cam[c.id]) for c in cameras]
    seen = [c.name for c, b in zip(cameras, blobs) if len(b)]
    if len(seen) < 2:
        raise CalibrationError(
            f"static markers found in {len(seen)} camera(s) ({', '.join(seen) or 'none'}); the ground frame must be "
            "seen by at least two cameras: record a few seconds with it still and in view"
        )
    pts, support = match_static(cameras, blobs)
    std, sigma_px = static_point_std(cameras, pts, blobs)
    idx = identify_layout(pts, layout, support, point_std=std, layout_std=layout_std, n_sigma=n_sigma,
                          above=np.array([c.center for c in cameras]))
    measured = pts[idx]
    R, t, fit = world_from_layout(measured, layout, origin, x_marker, marker_height)
    new = apply_world(cameras, R, t)
    if np.median([c.center[2] for c in new]) < 0:
        raise CalibrationError(
            "after the ground step the cameras are below the floor: the frame's layout is mirrored "
            "(its markers are listed clockwise where they should be counter-clockwise seen from above); fix the layout"
        )
    return GroundResult(new, R, t, measured @ R.T + t, fit, len(pts), pts @ R.T + t, std[idx], sigma_px)
