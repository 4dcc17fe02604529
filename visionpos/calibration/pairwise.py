"""Initial camera poses from wand observations: pairwise essential matrices chained by a spanning tree.

1. Every camera pair with enough shared wand frames gets an essential matrix
   (RANSAC, normalised 8-point), the cheirality-checked relative pose and the
   metric scale from the known wand lengths (thesis Eq. 2.18).
2. A maximum spanning tree over the pair graph (edge weight = inlier frames)
   chains all cameras into the frame of the reference camera.
3. The wand is triangulated with those poses (initial_wand): the start of the
   bundle adjustment (calibration/bundle.py); check_motion says whether the wave
   can determine the cameras.

Pose convention: x_cam = R x_world + t; the world is the reference camera's frame
until the ground-plane step moves it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visionpos.calibration.bundle import ProgressFn, bundle_adjust, no_progress
from visionpos.calibration.wand import MIN_SHARED_FRAMES, CalibrationError, WandData, WandSpec
from visionpos.camera.model import Camera, CameraModel
from visionpos.geometry.epipolar import decompose_essential, essential_from_points, sampson_distance
from visionpos.geometry.triangulation import CameraRig, triangulate_normalized


# --------------------------------------------------------------------- pairs
@dataclass
class PairPose:
    """Relative pose of camera j w.r.t. camera i: x_j = R x_i + t (t in metres)."""

    i: int
    j: int
    R: np.ndarray
    t: np.ndarray
    shared: int
    inliers: int
    scale: float
    flatness: float  # smallest / largest spread of the triangulated markers


def wand_scale(points: np.ndarray, spec: WandSpec) -> np.ndarray:
    """Per-frame scale estimates of thesis Eq. 2.18.

    points: (n, 3, 3) triangulated A, B, C in an arbitrary-scale frame.
    Returns (n,) the mean of L_AC/|A-C|, L_AB/|A-B|, L_BC/|B-C| per frame;
    Eq. 2.18's lambda is their mean over frames.
    """
    A, B, C = points[:, 0], points[:, 1], points[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return (
            spec.ac / np.linalg.norm(A - C, axis=1)
            + spec.ab / np.linalg.norm(A - B, axis=1)
            + spec.bc / np.linalg.norm(B - C, axis=1)
        ) / 3.0


class DegenerateMotion(CalibrationError):
    """The wand points seen by a camera pair do not span 3D (one plane, or too small a volume)."""


def _check_not_planar(x1: np.ndarray, x2: np.ndarray, threshold: float) -> None:
    """Raise DegenerateMotion when one homography explains nearly all correspondences
    (N, 2): the points lie in one plane (or the volume is too small), and the essential
    matrix is then not determined."""
    import cv2

    spread = min(float(np.sqrt(np.trace(np.cov(x.T)))) for x in (x1, x2))
    if spread < 0.03:
        raise DegenerateMotion(
            f"the wand points span only {np.degrees(spread):.1f} deg of the view: the wand covered too small a volume"
        )
    H, mask = cv2.findHomography(x1, x2, cv2.RANSAC, threshold, maxIters=500, confidence=0.99)
    if H is not None and mask is not None and mask.mean() > 0.9:
        raise DegenerateMotion(
            f"{mask.mean() * 100:.0f} % of the wand points fit one homography: the wand stayed in (nearly) one plane "
            "or a small volume"
        )


def pair_pose(
    xn_i: np.ndarray, xn_j: np.ndarray, spec: WandSpec, threshold: float, max_frames: int = 600, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """Metric relative pose from the wand seen by two cameras.

    xn_i, xn_j: (n, 3, 2) undistorted normalised A, B, C in both cameras (same frames).
    threshold: RANSAC Sampson threshold (normalised units).
    Returns R (3,3), t (3,) metres with x_j = R x_i + t, inlier frames (n,) bool,
    the scale lambda (Eq. 2.18 over inlier frames) and the flatness of the marker cloud.
    """
    n = len(xn_i)
    rng = np.random.default_rng(seed)
    sel = np.sort(rng.choice(n, max_frames, replace=False)) if n > max_frames else np.arange(n)
    p1 = xn_i[sel].reshape(-1, 2)
    p2 = xn_j[sel].reshape(-1, 2)
    _check_not_planar(p1, p2, threshold)
    E, inl = essential_from_points(p1, p2, threshold=threshold, rng=seed)
    # RANSAC over minimal 8-point samples can settle on a poor model when the wand cloud is
    # compact (near bas-relief ambiguity); the linear fit on all points is then often better
    E_all, _ = essential_from_points(p1, p2)
    inl_all = sampson_distance(E_all, p1, p2) < threshold
    if inl_all.sum() > inl.sum():
        E, inl = essential_from_points(p1[inl_all], p2[inl_all])[0], inl_all
    R, t_unit, front = decompose_essential(E, p1[inl], p2[inl])
    # triangulate every shared frame with the unit baseline
    Rs = np.stack([np.eye(3), R])
    ts = np.stack([np.zeros(3), t_unit])
    xn = np.stack([xn_i.reshape(-1, 2), xn_j.reshape(-1, 2)], axis=1)
    tri = triangulate_normalized(xn, Rs, ts, refine=False)
    pts = tri.points.reshape(n, 3, 3)
    res = tri.residuals.reshape(n, 3, 2)
    s = wand_scale(pts, spec)
    z1 = pts[..., 2]
    z2 = (pts @ R.T + t_unit)[..., 2]
    good = np.isfinite(s) & (s > 0) & (z1 > 0).all(axis=1) & (z2 > 0).all(axis=1)
    good &= (np.nan_to_num(res, nan=np.inf) < 3 * threshold).all(axis=(1, 2))
    if good.sum() < 8:
        raise CalibrationError(
            f"only {int(good.sum())} of {n} shared wand frames agree with one relative pose (need 8)"
        )
    med = np.median(s[good])
    good &= np.abs(s / med - 1) < 0.05  # thesis phase 3 dropped frames whose L_AC was off by > 1 %
    lam = float(np.mean(s[good]))  # Eq. 2.18
    cloud = pts[good].reshape(-1, 3)
    ev = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(cloud.T)), 0))
    flat = float(ev[0] / ev[2]) if ev[2] > 0 else 0.0
    if flat < 0.03:  # degenerate: a refinement would only polish an arbitrary solution
        return R, lam * t_unit, good, lam, flat
    # the linear 8-point estimate is biased by noise: a two-view wand bundle adjustment
    # (normalised coordinates, so unit intrinsics) brings the pair to the noise level
    idx = np.flatnonzero(good)
    if len(idx) > 300:  # an initial value only: a few hundred frames are plenty
        idx = np.sort(rng.choice(idx, 300, replace=False))
    P = pts[idx] * lam
    d = P[:, 2] - P[:, 0]
    u0 = d / np.linalg.norm(d, axis=1, keepdims=True)
    A0 = P.mean(axis=1) - spec.offsets.mean() * u0
    unit = CameraModel("pinhole", 1, 1, 1.0, 1.0, 0.0, 0.0)
    cams = [Camera(0, "i", unit, np.eye(3), np.zeros(3)), Camera(1, "j", unit, R, lam * t_unit)]
    obs = np.stack([xn_i[idx], xn_j[idx]], axis=1)  # (n, 2, 3, 2)
    out, _, _, _, _ = bundle_adjust(
        obs, cams, np.stack([np.eye(3), R]), np.stack([np.zeros(3), lam * t_unit]), A0, u0, spec,
        f_scale=threshold, max_nfev=30,
    )
    return out[1].R, out[1].t, good, lam, flat


def undistort_wand(data: WandData) -> np.ndarray:
    """(F, V, 3, 2) pixels -> normalised coordinates (NaN stays NaN)."""
    rig = CameraRig(data.cameras)
    F, V = data.pixels.shape[:2]
    px = data.pixels.transpose(0, 2, 1, 3).reshape(F * 3, V, 2)
    xn = rig.undistort(px)
    return xn.reshape(F, 3, V, 2).transpose(0, 2, 1, 3)


def initial_poses(
    data: WandData, spec: WandSpec, ref: int = 0, min_shared: int = MIN_SHARED_FRAMES,
    progress: ProgressFn = no_progress,
    hint: str = "",
) -> tuple[np.ndarray, np.ndarray, list[PairPose]]:
    """Pairwise essential matrices + Eq. 2.18 scale, chained by a spanning tree.

    The tree is grown from camera `ref` (Prim), always over the unused pair that
    shares the most wand frames; a pair's pose is only estimated when the tree
    needs it, and a pair that fails is passed over for the next best one.
    Returns R (V,3,3), t (V,3) (world = camera `ref`) and the pairs used.
    """
    xn = undistort_wand(data)
    seen = data.seen
    V = len(data.cameras)
    names = [c.name for c in data.cameras]
    f_mean = np.mean([0.5 * (c.model.fx + c.model.fy) for c in data.cameras])
    threshold = 2.0 / f_mean
    shared = np.einsum("fi,fj->ij", seen.astype(np.int64), seen.astype(np.int64))
    tried: dict[tuple[int, int], PairPose | None] = {}
    failures: list[str] = []
    degenerate: list[str] = []

    def pair(i: int, j: int) -> PairPose | None:
        key = (min(i, j), max(i, j))
        if key not in tried:
            a, b = key
            both = seen[:, a] & seen[:, b]
            try:
                R, tt, good, lam, flat = pair_pose(xn[both, a], xn[both, b], spec, threshold)
                tried[key] = PairPose(a, b, R, tt, int(both.sum()), int(good.sum()), lam, flat)
            except DegenerateMotion as e:
                degenerate.append(f"{names[a]}-{names[b]}: {e}")
                tried[key] = None
            except (CalibrationError, ValueError) as e:
                failures.append(f"{names[a]}-{names[b]}: {e}")
                tried[key] = None
        return tried[key]

    R = np.full((V, 3, 3), np.nan)
    t = np.full((V, 3), np.nan)
    R[ref], t[ref] = np.eye(3), np.zeros(3)
    done = [ref]
    used: list[PairPose] = []
    while len(done) < V:
        cand = sorted(
            ((shared[a, b], a, b) for a in done for b in range(V) if b not in done and shared[a, b] >= min_shared),
            reverse=True,
        )
        attached = False
        for _, a, b in cand:
            p = pair(a, b)
            if p is None:
                continue
            if p.flatness < 0.03:
                raise CalibrationError(
                    f"degenerate wand motion: cameras {names[p.i]} and {names[p.j]} saw the wand markers in (nearly) "
                    "one plane; wave the wand through the whole volume, up and down as well as sideways, tilting it"
                    + _other_causes(p.inliers, p.shared, hint)
                )
            Rab, tab = (p.R, p.t) if p.i == a else (p.R.T, -p.R.T @ p.t)
            R[b] = Rab @ R[a]
            t[b] = Rab @ t[a] + tab
            done.append(b)
            used.append(p)
            attached = True
            progress("pairs", len(done) - 1, V - 1)
            break
        if not attached:
            missing = [v for v in range(V) if v not in done]
            if degenerate:
                raise CalibrationError(
                    "degenerate wand motion: " + "; ".join(degenerate) + ". Wave the wand through the whole "
                    "tracking volume, up and down as well as sideways, tilting and turning it"
                    + _other_causes(None, None, hint)
                )
            detail = "".join(
                f"\n  {names[v]}: {int(shared[v, done].max())} wand frames shared with a connected camera"
                for v in missing
            )
            why = ("\n  pairs that failed: " + "; ".join(failures)) if failures else ""
            raise CalibrationError(
                f"camera(s) {', '.join(names[v] for v in missing)} cannot be connected to "
                f"{', '.join(names[v] for v in sorted(done))} (need >= {min_shared} wand frames seen together):"
                f"{detail}{why}\nlikely causes: too few frames where each of them and a connected camera see "
                "the wand at the same time (wave it where their views overlap); wand lengths that do not match "
                "the wand (calibration.wand, --ab/--bc); wrong intrinsics for the camera" + hint
            )
    return R, t, used


def _other_causes(consistent: int | None, shared: int | None, hint: str) -> str:
    """The causes besides the motion that make a pair's wand points look degenerate."""
    frac = (f" (only {consistent} of {shared} shared frames were consistent)"
            if consistent is not None and shared else "")
    return (f"\nif the wand did sweep the volume{frac}, other likely causes: wand lengths that do not match the "
            "wand (calibration.wand, --ab/--bc); wrong intrinsics" + hint)


def initial_wand(
    xn: np.ndarray, R: np.ndarray, t: np.ndarray, spec: WandSpec
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wand pose per frame by triangulation.

    xn: (F, V, 3, 2) normalised; R (V,3,3), t (V,3).
    Returns A (F,3), u (F,3) unit direction A->C, ok (F,) (triangulated and lengths within 10 %).
    """
    F, V = xn.shape[:2]
    tri = triangulate_normalized(xn.transpose(0, 2, 1, 3).reshape(F * 3, V, 2), R, t)
    P = tri.points.reshape(F, 3, 3)
    A = P[:, 0]
    d = P[:, 2] - P[:, 0]
    L = np.linalg.norm(d, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = d / L[:, None]
        ok = np.isfinite(P).all(axis=(1, 2)) & (np.abs(L / spec.ac - 1) < 0.1)
        # line fit through all three: A is the point on the line at offset 0
        c = P.mean(axis=1)
        A = np.where(ok[:, None], c - spec.offsets.mean() * u, A)
    return A, u, ok


def check_motion(A: np.ndarray, u: np.ndarray, spec: WandSpec) -> list[str]:
    """Degenerate wand motion checks on metric wand poses A (F,3), u (F,3).

    Raises CalibrationError for a too small or flat volume; returns warnings
    (e.g. the wand kept in nearly one orientation).
    """
    pts = (A[:, None, :] + spec.offsets[None, :, None] * u[:, None, :]).reshape(-1, 3)
    ev = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(pts.T)), 0))
    if ev[2] < 0.15:
        raise CalibrationError(
            f"degenerate wand motion: the wand covered too small a volume (spread {ev[2] * 100:.0f} cm along its "
            "longest axis); wave it through the whole tracking volume"
        )
    if ev[0] < 0.05 or ev[0] / ev[2] < 0.04:
        raise CalibrationError(
            f"degenerate wand motion: the wand stayed in one plane (spread {ev[0] * 100:.1f} cm across it); "
            "wave it up and down as well as sideways"
        )
    warnings = []
    M = np.einsum("fi,fj->ij", u, u) / len(u)
    w = np.linalg.eigvalsh(M)
    if w[1] < 0.03:
        warnings.append(
            "the wand was held in nearly one orientation; turn it while waving for a better-conditioned calibration"
        )
    return warnings
