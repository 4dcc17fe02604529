"""Extrinsics from wand observations: pairwise init, chaining, bundle adjustment.

1. Every camera pair with enough shared wand frames gets an essential matrix
   (RANSAC, normalised 8-point), the cheirality-checked relative pose and the
   metric scale from the known wand lengths (thesis Eq. 2.18).
2. A maximum spanning tree over the pair graph (edge weight = inlier frames)
   chains all cameras into the frame of the reference camera.
3. A global bundle adjustment (scipy least_squares, trf, analytic sparse
   Jacobian, robust loss) refines all camera poses (optionally fx, fy, cx, cy)
   and one wand pose per frame. The wand is parametrised as its A position plus
   a direction, so B = A + AB u and C = A + AC u hold exactly: the wand lengths
   fix the scale and the wand's straightness is enforced.

Pose convention: x_cam = R x_world + t; the world is the reference camera's frame
until the ground-plane step moves it.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from visionpos.calibration.wand import (
    GRID_RATE_HZ,
    MIN_SHARED_FRAMES,
    MIN_WAND_FRAMES,
    CalibrationError,
    WandData,
    WandSpec,
)
from visionpos.camera.model import Camera, CameraModel
from visionpos.geometry.epipolar import decompose_essential, essential_from_points, sampson_distance
from visionpos.geometry.rotations import skew
from visionpos.geometry.triangulation import CameraRig, triangulate_normalized

log = logging.getLogger(__name__)

ProgressFn = Callable[[str, int, int], None]


def _no_progress(stage: str, done: int, total: int) -> None:
    return None


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
    progress: ProgressFn = _no_progress,
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


# ------------------------------------------------------------ bundle adjustment
def _left_jacobian(r: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian for rotation vectors r (V,3) -> (V,3,3)."""
    th = np.linalg.norm(r, axis=1)
    K = skew(r)
    K2 = K @ K
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th**2 / 24, (1 - np.cos(ths)) / ths**2)
    b = np.where(small, 1.0 / 6 - th**2 / 120, (ths - np.sin(ths)) / ths**3)
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * K2


def _complement(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (F,3) orthogonal to u (F,3) and to each other."""
    helper = np.where(np.abs(u[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(u, e1)
    return e1, e2


class _Problem:
    """Residuals and the analytic sparse Jacobian of the wand bundle adjustment."""

    def __init__(
        self,
        pixels: np.ndarray,
        cameras: list[Camera],
        R0: np.ndarray,
        t0: np.ndarray,
        A0: np.ndarray,
        u0: np.ndarray,
        spec: WandSpec,
        ref: int,
        refine_intrinsics: bool,
        velocity: np.ndarray | None = None,
        estimate_ratio: bool = False,
    ):
        F, V = pixels.shape[:2]
        self.F, self.V, self.ref = F, V, ref
        ok = np.isfinite(pixels).all(axis=3)  # (F, V, 3)
        f_o, v_o, k_o = np.nonzero(ok)
        self.f_o, self.v_o, self.k_o = f_o, v_o, k_o
        self.uv = pixels[f_o, v_o, k_o]
        self.M = len(f_o)
        self.spec = spec
        self.estimate_ratio = estimate_ratio
        # wand points move during a clock offset: X(t - eps) = X(t) - eps * velocity
        self.vel = None if velocity is None else velocity[f_o, k_o]  # (M, 3) m/s
        self.R0 = R0.copy()
        self.u0 = u0.copy()
        self.e1, self.e2 = _complement(u0)
        # distortion with unit focal length and zero centre: xd and d xd / d xn
        self.unit_rig = CameraRig(
            [
                replace(c, model=replace(c.model, fx=1.0, fy=1.0, cx=0.0, cy=0.0), R=np.eye(3), t=np.zeros(3))
                for c in cameras
            ]
        )
        self.f_cam = np.array([[c.model.fx, c.model.fy] for c in cameras])
        self.c_cam = np.array([[c.model.cx, c.model.cy] for c in cameras])
        self.refine_intrinsics = refine_intrinsics
        # parameter layout: [cams except ref: rotvec(3) t(3)] [intrinsics: fx fy cx cy] [clock offsets
        # except ref (s)] [wand ratio AB/AC] [frames: A(3) a b]
        self.cam_index = np.full(V, -1)
        others = [v for v in range(V) if v != ref]
        self.cam_index[others] = np.arange(len(others))
        self.n_cam = 6 * len(others)
        self.n_intr = 4 * V if refine_intrinsics else 0
        self.off_offsets = self.n_cam + self.n_intr
        self.n_off = len(others) if velocity is not None else 0
        self.off_ratio = self.off_offsets + self.n_off
        self.off_frames = self.off_ratio + (1 if estimate_ratio else 0)
        self.n = self.off_frames + 5 * F
        self.x0 = np.zeros(self.n)
        ci = self.cam_index >= 0
        self.x0[: self.n_cam] = np.column_stack([np.zeros((len(others), 3)), t0[ci]]).ravel()
        if refine_intrinsics:
            self.x0[self.n_cam : self.off_offsets] = np.column_stack([self.f_cam, self.c_cam]).ravel()
        if estimate_ratio:
            self.x0[self.off_ratio] = spec.ratio
        self.t_ref = t0[ref].copy()
        fr = np.zeros((F, 5))
        fr[:, :3] = A0
        self.x0[self.off_frames :] = fr.ravel()
        self._build_pattern()
        self._cache_x: np.ndarray | None = None

    def _build_pattern(self) -> None:
        M = self.M
        rows2 = np.arange(2 * M).reshape(M, 2)
        # frame block: 5 columns for every observation
        fcols = self.off_frames + 5 * self.f_o[:, None] + np.arange(5)
        blocks_r = [np.repeat(rows2[:, :, None], 5, axis=2)]
        blocks_c = [np.broadcast_to(fcols[:, None, :], (M, 2, 5))]
        self.has_cam = self.cam_index[self.v_o] >= 0
        idx = np.flatnonzero(self.has_cam)
        ccols = 6 * self.cam_index[self.v_o[idx]][:, None] + np.arange(6)
        blocks_r.append(np.repeat(rows2[idx][:, :, None], 6, axis=2))
        blocks_c.append(np.broadcast_to(ccols[:, None, :], (len(idx), 2, 6)))
        if self.refine_intrinsics:
            icols = self.n_cam + 4 * self.v_o[:, None] + np.arange(4)
            blocks_r.append(np.repeat(rows2[:, :, None], 4, axis=2))
            blocks_c.append(np.broadcast_to(icols[:, None, :], (M, 2, 4)))
        if self.n_off:
            ocols = self.off_offsets + self.cam_index[self.v_o[idx]]
            blocks_r.append(rows2[idx])
            blocks_c.append(np.broadcast_to(ocols[:, None], (len(idx), 2)))
        if self.estimate_ratio:
            blocks_r.append(rows2)
            blocks_c.append(np.full((M, 2), self.off_ratio))
        self.cam_obs = idx
        self.jrows = np.concatenate([b.ravel() for b in blocks_r])
        self.jcols = np.concatenate([np.asarray(b).ravel() for b in blocks_c])

    # -- unpacking
    def cameras_from(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """R (V,3,3), t (V,3), rotvec (V,3), f (V,2), c (V,2)."""
        V = self.V
        cam = x[: self.n_cam].reshape(-1, 6)
        rv = np.zeros((V, 3))
        t = np.zeros((V, 3))
        ci = self.cam_index >= 0
        rv[ci] = cam[:, :3]
        t[ci] = cam[:, 3:]
        t[self.ref] = self.t_ref
        R = Rotation.from_rotvec(rv).as_matrix() @ self.R0
        if self.refine_intrinsics:
            intr = x[self.n_cam : self.off_offsets].reshape(V, 4)
            f, c = intr[:, :2], intr[:, 2:]
        else:
            f, c = self.f_cam, self.c_cam
        return R, t, rv, f, c

    def offsets_from(self, x: np.ndarray) -> np.ndarray:
        """(V,) clock offset (s) of each camera left after the grid's correction (ref: 0)."""
        eps = np.zeros(self.V)
        if self.n_off:
            ci = self.cam_index >= 0
            eps[ci] = x[self.off_offsets : self.off_ratio]
        return eps

    def lengths_from(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(wand offsets (3,), d offsets / d ratio (3,), ratio AB/AC)."""
        r = float(x[self.off_ratio]) if self.estimate_ratio else self.spec.ratio
        offs, doffs = self.spec.offsets_for_ratio(r)
        return offs, doffs, r

    def wand_from(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A (F,3), u (F,3), n (F,3) un-normalised direction."""
        fr = x[self.off_frames :].reshape(self.F, 5)
        n = self.u0 + fr[:, 3:4] * self.e1 + fr[:, 4:5] * self.e2
        u = n / np.linalg.norm(n, axis=1, keepdims=True)
        return fr[:, :3], u, n

    def _evaluate(self, x: np.ndarray) -> None:
        if self._cache_x is not None and np.array_equal(x, self._cache_x):
            return
        R, t, rv, f, c = self.cameras_from(x)
        A, u, n = self.wand_from(x)
        fo, vo = self.f_o, self.v_o
        offs, dL, _ = self.lengths_from(x)
        self.L, self.dL = offs[self.k_o], dL[self.k_o]
        X = A[fo] + self.L[:, None] * u[fo]
        if self.n_off:
            X = X - self.offsets_from(x)[vo][:, None] * self.vel
        Rv = R[vo]
        Z = np.einsum("mij,mj->mi", Rv, X)
        Xc = Z + t[vo]
        z = Xc[:, 2]
        z = np.where(np.abs(z) < 1e-9, 1e-9, z)
        xn = Xc[:, :2] / z[:, None]
        # distortion through the unit-focal rig, in the dense (F*3, V) layout it expects
        dense = np.zeros((self.F * 3, self.V, 2))
        slot = fo * 3 + self.k_o
        dense[slot, vo] = xn
        xd_d, Jd_d = self.unit_rig.distort(dense, with_jac=True)
        xd = xd_d[slot, vo]
        Jd = Jd_d[slot, vo]  # (M, 2, 2)
        fv = f[vo]
        self.res = xd * fv + c[vo] - self.uv
        self._fwd = (rv, u, n, Rv, Z, z, xn, xd, Jd, fv)
        self._cache_x = x.copy()
        self._jac_x: np.ndarray | None = None

    def _jacobian(self, x: np.ndarray) -> None:
        self._evaluate(x)
        if self._jac_x is not None:
            return
        rv, u, n, Rv, Z, z, xn, xd, Jd, fv = self._fwd
        fo, vo = self.f_o, self.v_o
        # d xn / d Xc
        Pz = np.zeros((self.M, 2, 3))
        Pz[:, 0, 0] = 1 / z
        Pz[:, 1, 1] = 1 / z
        Pz[:, 0, 2] = -xn[:, 0] / z
        Pz[:, 1, 2] = -xn[:, 1] / z
        G = np.einsum("mij,mjk->mik", fv[:, :, None] * Jd, Pz)  # (M,2,3) d uv / d Xc
        GR = np.einsum("mij,mjk->mik", G, Rv)  # d uv / d X world
        # direction: d u / d(a, b) = (I - u u^T) / |n| [e1 e2]
        nn = np.linalg.norm(n, axis=1)
        P_perp = (np.eye(3)[None] - u[:, :, None] * u[:, None, :]) / nn[:, None, None]
        Du = np.einsum("fij,fjk->fik", P_perp, np.stack([self.e1, self.e2], axis=2))  # (F,3,2)
        Jab = np.einsum("mij,mjk->mik", GR, Du[fo]) * self.L[:, None, None]
        parts = [np.concatenate([GR, Jab], axis=2)]  # (M,2,5)
        ci = self.cam_obs
        if len(ci):
            Jl = _left_jacobian(rv)  # (V,3,3)
            dZ = -np.einsum("mij,mjk->mik", skew(Z[ci]), Jl[vo[ci]])  # d Xc / d rotvec
            Jr = np.einsum("mij,mjk->mik", G[ci], dZ)
            parts.append(np.concatenate([Jr, G[ci]], axis=2))  # (Mc,2,6)
        if self.refine_intrinsics:
            Ji = np.zeros((self.M, 2, 4))
            Ji[:, 0, 0] = xd[:, 0]
            Ji[:, 1, 1] = xd[:, 1]
            Ji[:, 0, 2] = 1.0
            Ji[:, 1, 3] = 1.0
            parts.append(Ji)
        if self.n_off:
            parts.append(-np.einsum("mij,mj->mi", GR[ci], self.vel[ci]))  # (Mc, 2)
        if self.estimate_ratio:
            parts.append(np.einsum("mij,mj->mi", GR, u[fo]) * self.dL[:, None])  # (M, 2)
        self.jdata = np.concatenate([p.ravel() for p in parts])
        self._jframe = parts[0]
        self._jac_x = x

    def covariance(self, x: np.ndarray) -> tuple[np.ndarray, float]:
        """(covariance of the non-frame parameters (n_small, n_small), residual variance px^2) at x.

        sigma^2 (J^T J)^-1 restricted to cameras, intrinsics, offsets and ratio: the wand-pose
        blocks (5x5 per frame, block-diagonal) are eliminated by the Schur complement, so
        nothing larger than n_small x n_small is inverted. An undetermined direction comes
        out with a huge variance instead of being hidden.
        """
        self._jacobian(x)
        J = self.jac(x).tocsc()
        ns = self.off_frames
        Jc, Jf = J[:, :ns], J[:, ns:]
        U = (Jc.T @ Jc).toarray()
        W = (Jc.T @ Jf).toarray().reshape(ns, self.F, 5)
        Vb = np.zeros((self.F, 5, 5))
        np.add.at(Vb, self.f_o, np.einsum("mai,maj->mij", self._jframe, self._jframe))
        Vb += 1e-12 * np.eye(5) * np.trace(Vb, axis1=1, axis2=2)[:, None, None]
        Vinv = np.linalg.inv(Vb)
        S = U - np.einsum("afi,fij,bfj->ab", W, Vinv, W)
        d = 1.0 / np.sqrt(np.maximum(np.diag(S), 1e-300))
        Sn = S * d[:, None] * d[None, :]
        cov_n = np.linalg.inv(Sn + 1e-13 * np.eye(ns))
        dof = max(2 * self.M - self.n, 1)
        sigma2 = float(np.sum(self.res**2) / dof)
        return cov_n * d[:, None] * d[None, :] * sigma2, sigma2

    def parameter_std(self, x: np.ndarray) -> dict:
        """Standard deviations at x: per camera rot_deg (V,), center_m (V,) (RMS over the axes
        of the camera centre), f_px (V, 2), c_px (V, 2) (refined intrinsics only), offset_s (V,)
        (estimated offsets only); ratio (AB/AC, when estimated); sigma_px."""
        cov, sigma2 = self.covariance(x)
        V = self.V
        R, t, rv, _, _ = self.cameras_from(x)
        out: dict = {"sigma_px": float(np.sqrt(sigma2)), "rot_deg": np.zeros(V), "center_m": np.zeros(V)}
        Jl = _left_jacobian(rv)
        for v in range(V):
            k = self.cam_index[v]
            if k < 0:
                continue
            C6 = cov[6 * k : 6 * k + 6, 6 * k : 6 * k + 6]
            out["rot_deg"][v] = float(np.degrees(np.sqrt(max(np.trace(Jl[v] @ C6[:3, :3] @ Jl[v].T), 0) / 3)))
            # centre = -R^T t; a left rotation increment d moves it by R^T [t]x d
            Jc = np.hstack([-R[v].T @ skew(t[v][None])[0] @ Jl[v], -R[v].T])
            out["center_m"][v] = float(np.sqrt(max(np.trace(Jc @ C6 @ Jc.T), 0) / 3))
        sd = np.sqrt(np.maximum(np.diag(cov), 0))
        if self.refine_intrinsics:
            intr = sd[self.n_cam : self.off_offsets].reshape(V, 4)
            out["f_px"], out["c_px"] = intr[:, :2], intr[:, 2:]
        if self.n_off:
            off = np.zeros(V)
            off[self.cam_index >= 0] = sd[self.off_offsets : self.off_ratio]
            out["offset_s"] = off
        if self.estimate_ratio:
            out["ratio"] = float(sd[self.off_ratio])
        return out

    def fun(self, x: np.ndarray) -> np.ndarray:
        self._evaluate(x)
        return self.res.ravel()

    def jac(self, x: np.ndarray) -> sp.csr_matrix:
        self._jacobian(x)
        return sp.csr_matrix((self.jdata, (self.jrows, self.jcols)), shape=(2 * self.M, self.n))


def bundle_adjust(
    pixels: np.ndarray,
    cameras: list[Camera],
    R: np.ndarray,
    t: np.ndarray,
    A: np.ndarray,
    u: np.ndarray,
    spec: WandSpec,
    ref: int = 0,
    refine_intrinsics: bool = False,
    loss: str = "soft_l1",
    f_scale: float = 1.0,
    max_nfev: int = 50,
    progress: ProgressFn = _no_progress,
    velocity: np.ndarray | None = None,
    estimate_ratio: bool = False,
    covariance: bool = False,
) -> tuple[list[Camera], np.ndarray, np.ndarray, np.ndarray, dict]:
    """One least-squares solve over all cameras and wand poses.

    pixels: (F, V, 3, 2) observations (NaN = missing); R (V,3,3), t (V,3) initial
    poses; A (F,3), u (F,3) initial wand. Camera `ref` keeps its pose (gauge);
    the wand lengths fix the scale.
    velocity: (F, 3, 3) m/s of A, B, C: also estimate each camera's clock offset left
    in the observations' times (camera `ref` keeps 0). estimate_ratio: also estimate the
    wand's AB/AC with the spec's `known` segment fixed. covariance: add info['std']
    (Problem.parameter_std).
    Returns refined cameras, A, u, residuals (F, V, 3, 2) px (NaN where unobserved)
    and solver info (with offsets_s (V,) and ratio).
    """
    prob = _Problem(pixels, cameras, R, t, A, u, spec, ref, refine_intrinsics, velocity, estimate_ratio)
    calls = [0]

    def fun(x: np.ndarray) -> np.ndarray:
        calls[0] += 1
        progress("bundle adjustment", min(calls[0], max_nfev), max_nfev)
        return prob.fun(x)

    sol = least_squares(
        fun,
        prob.x0,
        jac=prob.jac,
        method="trf",
        loss=loss,
        f_scale=f_scale,
        x_scale="jac",
        tr_solver="lsmr",
        max_nfev=max_nfev,
        xtol=1e-8,
        ftol=1e-6,
        gtol=1e-8,
    )
    progress("bundle adjustment", max_nfev, max_nfev)  # converged: close the bar
    Rn, tn, _, f, c = prob.cameras_from(sol.x)
    A2, u2, _ = prob.wand_from(sol.x)
    prob._evaluate(sol.x)
    res = np.full(pixels.shape, np.nan)
    res[prob.f_o, prob.v_o, prob.k_o] = prob.res
    out = []
    for v, cam in enumerate(cameras):
        model = cam.model
        if refine_intrinsics:
            model = replace(model, fx=float(f[v, 0]), fy=float(f[v, 1]), cx=float(c[v, 0]), cy=float(c[v, 1]))
        out.append(replace(cam, model=model, R=Rn[v], t=tn[v]))
    info = {"nfev": int(sol.nfev), "cost": float(sol.cost), "message": str(sol.message), "n_params": prob.n,
            "n_residuals": 2 * prob.M, "offsets_s": prob.offsets_from(sol.x), "ratio": prob.lengths_from(sol.x)[2]}
    if covariance:
        info["std"] = prob.parameter_std(sol.x)
    return out, A2, u2, res, info


# ----------------------------------------------------------------- whole step
@dataclass
class WandCalibration:
    """Everything the wand step produced (world = reference camera frame).

    cameras: refined cameras (same order as the input); data: the aligned observations
    actually used (F frames); residuals: (F, V, 3, 2) px after the final solve (NaN
    where unobserved or rejected); lengths: (F, 3) freely triangulated |AB|, |BC|,
    |AC| (m) with the calibrated cameras, the thesis's figure of merit.
    """

    cameras: list[Camera]
    spec: WandSpec
    data: WandData
    residuals: np.ndarray
    lengths: np.ndarray
    pairs: list[PairPose]
    A: np.ndarray
    u: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    info: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    rejected_views: int = 0
    offsets_ns: np.ndarray | None = None  # (V,) each camera's clock offset against the reference camera
    offset_pairs: list = field(default_factory=list)
    check: "WandCheck | None" = None

    def camera_stats(self) -> list[dict]:
        """Per camera: name, id, views (frames used), rms_px, max_px, centre (3,), offset_ms and the
        standard deviations center_std_mm, rot_std_deg, offset_std_ms (NaN where not estimated)."""
        out = []
        std = self.info.get("std")
        r = np.linalg.norm(self.residuals, axis=-1)  # (F, V, 3)
        for v, c in enumerate(self.cameras):
            rv = r[:, v]
            ok = np.isfinite(rv)
            out.append(
                {
                    "name": c.name,
                    "id": c.id,
                    "views": int(np.isfinite(rv).all(axis=1).sum()),
                    "rms_px": float(np.sqrt(np.mean(rv[ok] ** 2))) if ok.any() else float("nan"),
                    "max_px": float(rv[ok].max()) if ok.any() else float("nan"),
                    "center": c.center,
                    "offset_ms": float(self.offsets_ns[v] / 1e6) if self.offsets_ns is not None else 0.0,
                    "center_std_mm": float(std["center_m"][v] * 1000) if std else float("nan"),
                    "rot_std_deg": float(std["rot_deg"][v]) if std else float("nan"),
                    "offset_std_ms": float(std["offset_s"][v] * 1000) if std and "offset_s" in std else float("nan"),
                }
            )
        return out

    def length_stats(self) -> dict[str, float]:
        """Mean error and std (m) of the triangulated AB, BC, AC lengths."""
        true = np.array([self.spec.ab, self.spec.bc, self.spec.ac])
        ok = np.isfinite(self.lengths).all(axis=1)
        L = self.lengths[ok]
        d = {}
        for k, name in enumerate(("ab", "bc", "ac")):
            d[f"{name}_mean_err"] = float(L[:, k].mean() - true[k]) if len(L) else float("nan")
            d[f"{name}_std"] = float(L[:, k].std()) if len(L) else float("nan")
        return d


def wand_lengths(cameras: list[Camera], pixels: np.ndarray) -> np.ndarray:
    """Freely triangulated wand lengths: pixels (F, V, 3, 2) -> (F, 3) |AB|, |BC|, |AC| (m)."""
    from visionpos.geometry.triangulation import triangulate_pixels

    F, V = pixels.shape[:2]
    tri = triangulate_pixels(cameras, pixels.transpose(0, 2, 1, 3).reshape(F * 3, V, 2))
    P = tri.points.reshape(F, 3, 3)
    return np.stack(
        [
            np.linalg.norm(P[:, 1] - P[:, 0], axis=1),
            np.linalg.norm(P[:, 2] - P[:, 1], axis=1),
            np.linalg.norm(P[:, 2] - P[:, 0], axis=1),
        ],
        axis=1,
    )


def wand_velocity(times_ns: np.ndarray, A: np.ndarray, u: np.ndarray, offsets: np.ndarray,
                  max_dt_s: float = 0.1) -> np.ndarray:
    """Velocity (F, 3, 3) m/s of the wand points A, B, C from neighbouring grid frames.

    times_ns (F,) sorted; A, u (F, 3); offsets (3,) along the wand. Central differences
    where both neighbours are within max_dt_s, one-sided where one is, else 0 (that frame
    then says nothing about clock offsets).
    """
    P = A[:, None, :] + offsets[None, :, None] * u[:, None, :]
    t = np.asarray(times_ns, np.float64) * 1e-9
    F = len(t)
    vel = np.zeros((F, 3, 3))
    if F < 2:
        return vel
    dt = np.diff(t)
    ok_step = (dt > 0) & (dt <= max_dt_s)
    fwd = np.zeros((F, 3, 3))
    fwd[:-1] = (P[1:] - P[:-1]) / np.where(ok_step, dt, 1.0)[:, None, None]
    has_r = np.zeros(F, bool)
    has_r[:-1] = ok_step
    has_l = np.zeros(F, bool)
    has_l[1:] = ok_step
    bwd = np.zeros((F, 3, 3))
    bwd[1:] = fwd[:-1]
    both = has_l & has_r
    vel[both] = 0.5 * (fwd[both] + bwd[both])
    vel[has_r & ~has_l] = fwd[has_r & ~has_l]
    vel[has_l & ~has_r] = bwd[has_l & ~has_r]
    return vel


@dataclass
class WandCheck:
    """The wand measured against the configured one.

    ratio, ratio_std: AB/AC from the bundle adjustment and its standard deviation;
    lengths: for each segment taken as known ('ab', 'bc', 'ac', at its configured length), the
    three lengths (m) and their standard deviations (m) that the measured ratio implies;
    mismatch: the configured ratio lies beyond the measured one's uncertainty.
    """

    spec: WandSpec
    ratio: float
    ratio_std: float
    lengths: dict[str, dict[str, tuple[float, float]]]
    mismatch: bool

    @classmethod
    def from_ratio(cls, spec: WandSpec, r: float, sr: float, floor_m: float = 1e-4) -> "WandCheck":
        lengths: dict[str, dict[str, tuple[float, float]]] = {}
        for k in ("ab", "bc", "ac"):
            L = spec.length(k)
            if k == "ac":
                d = {"ab": (r * L, L * sr), "bc": ((1 - r) * L, L * sr), "ac": (L, 0.0)}
            elif k == "ab":
                d = {"ab": (L, 0.0), "bc": (L * (1 - r) / r, L * sr / r**2), "ac": (L / r, L * sr / r**2)}
            else:
                g = L * sr / (1 - r) ** 2
                d = {"ab": (L * r / (1 - r), g), "bc": (L, 0.0), "ac": (L / (1 - r), g)}
            lengths[k] = d
        # a mismatch is a length off by more than 3 std and by more than floor_m (model errors
        # of real markers: their centroids are not exactly their centres)
        ref = lengths[spec.known]
        mismatch = any(abs(ref[k][0] - spec.length(k)) > max(3 * ref[k][1], floor_m) for k in ("ab", "bc", "ac"))
        return cls(spec, r, sr, lengths, mismatch)

    def message(self) -> str:
        """One paragraph: the measured ratio and lengths against the configured ones."""
        s = self.spec
        mm = {k: v * 1000 for k, v in (("ab", s.ab), ("bc", s.bc), ("ac", s.ac))}
        ref = self.lengths[s.known]
        meas = ", ".join(f"{k.upper()} {ref[k][0] * 1000:.2f} +- {ref[k][1] * 1000:.2f} mm (configured {mm[k]:.2f})"
                         for k in ("ab", "bc", "ac") if k != s.known)
        alt = "; ".join(
            f"with {k.upper()} = {mm[k]:.2f} mm: " + ", ".join(
                f"{q.upper()} {self.lengths[k][q][0] * 1000:.2f} mm" for q in ("ab", "bc", "ac") if q != k)
            for k in ("ab", "bc", "ac") if k != s.known
        )
        head = "the wand does not match the configured one" if self.mismatch else "the wand matches the configured one"
        return (f"{head}: measured AB/AC {self.ratio:.5f} +- {self.ratio_std:.5f} (configured {s.ratio:.5f}); "
                f"with {s.known.upper()} = {mm[s.known]:.2f} mm as configured (calibration.wand.known): {meas}; "
                f"{alt}" + (". Measure the wand (marker centre to centre) and set calibration.wand.ab/bc "
                            "(or --ab/--bc)" if self.mismatch else ""))


# limits of what the data must determine before a parameter is used (observability guards)
MAX_FOCAL_STD_REL = 0.003  # focal length std / focal length
MAX_CENTRE_STD_PX = 3.0  # principal point std (px)
MAX_OFFSET_STD_S = 0.5e-3  # clock offset std
MAX_CAMERA_CENTER_STD_M = 0.005  # camera position std (RMS over the axes)


def calibrate_wand(
    frames,
    cameras: list[Camera],
    spec: WandSpec = WandSpec(),
    ref: int = 0,
    rate_hz: float = GRID_RATE_HZ,
    refine_intrinsics: bool = False,
    min_frames: int = MIN_WAND_FRAMES,
    max_frames: int | None = None,
    progress: ProgressFn = _no_progress,
    align: str = "interpolate",
    max_offset_ms: float = 60.0,
) -> WandCalibration:
    """Wand extrinsics (and clock offsets) from BlobFrames of a wand wave.

    frames: iterable of BlobFrame (any order, any cameras; unknown camera ids are ignored).
    cameras: the arena's cameras with their intrinsics (poses are ignored).
    ref: index of the camera that defines the world frame (and whose clock is the reference).
    max_frames: keep at most this many grid frames (evenly spread), None = all.
    align: how asynchronous cameras are brought to common times ('interpolate' or 'nearest').
    max_offset_ms: largest clock offset of a camera searched for; 0 trusts the stamps.
    refine_intrinsics: also fit fx, fy, cx, cy, kept only where the data determine them.
    Raises CalibrationError with what to capture when the input cannot give a calibration.
    """
    from visionpos.calibration.wand import align_tracks, estimate_offsets, label_all

    cameras = list(cameras)
    if len(cameras) < 2:
        raise CalibrationError(f"wand calibration needs at least 2 cameras, the config has {len(cameras)}")
    names = [c.name for c in cameras]
    timings: dict[str, float] = {}
    warnings: list[str] = []
    t0 = time.perf_counter()
    tracks, stats = label_all(frames, cameras, spec, min_labelled=min_frames)
    offsets_ns = np.zeros(len(cameras))
    offset_pairs = []
    if max_offset_ms > 0:
        est = estimate_offsets(cameras, tracks, stats, max_offset_ms, ref=ref)
        offsets_ns, offset_pairs = est.offsets_ns, est.pairs
        warnings += est.problems
    timings["offsets_s"] = time.perf_counter() - t0

    def aligned(off: np.ndarray) -> WandData:
        d = align_tracks(cameras, tracks, stats, off, rate_hz=rate_hz, align=align)
        if max_frames is not None and len(d.times_ns) > max_frames:
            d = d.subset(np.linspace(0, len(d.times_ns) - 1, max_frames).round().astype(int))
        return d

    data = aligned(offsets_ns)
    if len(data.times_ns) < min_frames:
        raise CalibrationError(
            f"only {len(data.times_ns)} time steps have the wand in two or more cameras at once (need {min_frames}); "
            "wave the wand longer in the middle of the volume where the cameras' views overlap"
        )
    timings["label_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    hint = _offset_hint(offsets_ns, names, max_offset_ms, warnings)
    R, t, pairs = initial_poses(data, spec, ref=ref, progress=progress, hint=hint)
    xn = undistort_wand(data)
    A, u, ok = initial_wand(xn, R, t, spec)
    if ok.sum() < min_frames:
        raise CalibrationError(
            f"only {int(ok.sum())} wand frames triangulate consistently after the pairwise step (need {min_frames}); "
            "likely causes: wand lengths that do not match the wand (calibration.wand, --ab/--bc), wrong "
            f"intrinsics{hint}"
        )
    warnings += check_motion(A[ok], u[ok], spec)
    data = data.subset(np.flatnonzero(ok))
    A, u = A[ok], u[ok]
    timings["init_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    c0 = time.process_time()
    use_offsets = max_offset_ms > 0
    offs = spec.offsets

    def vel(d: WandData, A_: np.ndarray, u_: np.ndarray) -> np.ndarray | None:
        return wand_velocity(d.times_ns, A_, u_, offs) if use_offsets else None

    # round 1: robust loss from the pairwise start
    cams, A, u, res, info = bundle_adjust(data.pixels, cameras, R, t, A, u, spec, ref=ref, progress=progress,
                                          velocity=vel(data, A, u), estimate_ratio=True)
    Rk = np.stack([c.R for c in cams])
    tk = np.stack([c.t for c in cams])
    if use_offsets:
        # re-interpolate every camera at its corrected times and start again from the refined cameras
        offsets_ns = offsets_ns + info["offsets_s"] * 1e9
        data = aligned(offsets_ns)
        A, u, ok = initial_wand(undistort_wand(data), Rk, tk, spec)
        data = data.subset(np.flatnonzero(ok))
        A, u = A[ok], u[ok]
        cams, A, u, res, info = bundle_adjust(data.pixels, cams, Rk, tk, A, u, spec, ref=ref, progress=progress,
                                              velocity=vel(data, A, u), estimate_ratio=True)
        Rk = np.stack([c.R for c in cams])
        tk = np.stack([c.t for c in cams])
    # drop whole views (all three markers of one camera at one time) with a large residual:
    # a mislabelled or merged blob, or a bad interpolation
    rn = np.linalg.norm(res, axis=-1)  # (F, V, 3)
    med = float(np.nanmedian(rn))
    thr = max(1.0, 4.5 * med)
    bad_view = np.nanmax(np.where(np.isfinite(rn), rn, 0.0), axis=2) > thr
    n_bad = int(bad_view.sum())
    pixels = data.pixels.copy()
    pixels[bad_view] = np.nan
    keep = np.isfinite(pixels).all(axis=(2, 3)).sum(axis=1) >= 2
    data = WandData(data.cameras, data.times_ns[keep], pixels[keep], data.stats, data.tracks, data.offsets_ns)
    A, u = A[keep], u[keep]
    final = bundle_adjust(data.pixels, cams, Rk, tk, A, u, spec, ref=ref, refine_intrinsics=refine_intrinsics,
                          progress=progress, velocity=vel(data, A, u), estimate_ratio=True, covariance=True)
    if refine_intrinsics:
        refused = _undetermined_intrinsics(final[4]["std"], final[0], names)
        if refused:
            warnings.append("--refine-intrinsics refused, keeping the chessboard intrinsics: " + "; ".join(refused))
            # same poses, the cameras' own intrinsics
            kept = [replace(c, R=k.R, t=k.t) for c, k in zip(cameras, final[0])]
            final = bundle_adjust(data.pixels, kept, np.stack([c.R for c in kept]), np.stack([c.t for c in kept]),
                                  final[1], final[2], spec, ref=ref, progress=progress, velocity=vel(data, A, u),
                                  estimate_ratio=True, covariance=True)
            info_refused = True
        else:
            info_refused = False
    cams, A, u, res, info = final
    if refine_intrinsics:
        info["intrinsics_refused"] = info_refused
    timings["bundle_s"] = time.perf_counter() - t0
    timings["bundle_cpu_s"] = time.process_time() - c0  # one core: the solver is single-threaded
    std = info["std"]
    offsets_ns = offsets_ns + info["offsets_s"] * 1e9
    for v, name in enumerate(names):
        if use_offsets and v != ref and std["offset_s"][v] > MAX_OFFSET_STD_S:
            warnings.append(f"camera {name} clock offset: std {std['offset_s'][v] * 1e3:.2f} ms — the wand moved too "
                            "little in its view to determine it; wave it faster")
        if v != ref and std["center_m"][v] > MAX_CAMERA_CENTER_STD_M:
            warnings.append(f"camera {name} position: std {std['center_m'][v] * 1000:.1f} mm — few wand frames "
                            "constrain it; wave the wand more where it overlaps other cameras")
    check = WandCheck.from_ratio(spec, info["ratio"], float(std.get("ratio", 0.0)))
    if check.mismatch:
        warnings.append(check.message())
    lengths = wand_lengths(cams, data.pixels)
    info["frames"] = len(data.times_ns)
    info["threshold_px"] = thr
    return WandCalibration(cams, spec, data, res, lengths, pairs, A, u, timings, info, warnings, n_bad,
                           offsets_ns=offsets_ns - offsets_ns[ref], offset_pairs=offset_pairs, check=check)


def _offset_hint(offsets_ns: np.ndarray, names: list[str], max_offset_ms: float, problems: list[str]) -> str:
    """The clock part of a failure's likely causes."""
    if max_offset_ms <= 0:
        return ("; cameras' clocks that disagree (clock offsets were not estimated: give a maximum clock offset, "
                "--max-clock-offset-ms)")
    est = ", ".join(f"{n} {o / 1e6:+.1f} ms" for n, o in zip(names, offsets_ns))
    more = ("; " + "; ".join(problems)) if problems else ""
    return (f"; a clock offset beyond the search range (+-{max_offset_ms:.0f} ms; estimated offsets: {est}{more})")


def _undetermined_intrinsics(std: dict, cams: list[Camera], names: list[str]) -> list[str]:
    """Reasons (one per parameter) why refined intrinsics cannot be trusted: std beyond the guards."""
    out = []
    for v, (c, name) in enumerate(zip(cams, names)):
        for k, axis in enumerate("xy"):
            f = (c.model.fx, c.model.fy)[k]
            sf = std["f_px"][v, k]
            if not np.isfinite(sf) or sf > MAX_FOCAL_STD_REL * f:
                out.append(f"camera {name} focal length f{axis}: std {sf:.1f} px ({100 * sf / f:.1f} %) — the data "
                           "cannot determine it")
            sc = std["c_px"][v, k]
            if not np.isfinite(sc) or sc > MAX_CENTRE_STD_PX:
                out.append(f"camera {name} principal point c{axis}: std {sc:.1f} px — the data cannot determine it")
    return out


def compare_cameras(
    estimated: list[Camera], truth: list[Camera], similarity: bool = True
) -> tuple[np.ndarray, np.ndarray, float]:
    """Pose errors against known cameras.

    With similarity, the estimated centres are first mapped onto the true ones by
    the best similarity (Umeyama; for two cameras the rotation comes from their
    orientations); orientations are compared after the same rotation.
    Returns centre errors (V,) m, orientation errors (V,) deg and the scale applied.
    """
    from visionpos.geometry.alignment import umeyama_svd

    Ce = np.array([c.center for c in estimated])
    Ct = np.array([c.center for c in truth])
    if similarity and len(Ce) >= 3:
        s, Ra, ta = umeyama_svd(Ce, Ct)
    elif similarity:
        # two centres leave the turn about the baseline free: take the rotation from the
        # orientations (R_e = R_t Ra for every camera), then scale and shift from the centres
        from visionpos.geometry.rotations import average_rotations

        Ra = average_rotations(np.stack([t.R.T @ e.R for e, t in zip(estimated, truth)]))
        P = Ce @ Ra.T
        dp, dt = P - P.mean(axis=0), Ct - Ct.mean(axis=0)
        s = float((dp * dt).sum() / max((dp * dp).sum(), 1e-300))
        ta = Ct.mean(axis=0) - s * P.mean(axis=0)
    else:
        s, Ra, ta = 1.0, np.eye(3), np.zeros(3)
    cerr = np.linalg.norm(s * Ce @ Ra.T + ta - Ct, axis=1)
    # camera rotation in the aligned world: R_e Ra^T
    rerr = np.array(
        [np.degrees(Rotation.from_matrix(t.R @ (e.R @ Ra.T).T).magnitude()) for e, t in zip(estimated, truth)]
    )
    return cerr, rerr, float(s)
