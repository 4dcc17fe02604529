"""The whole wand step: labelled tracks -> clock offsets -> initial poses -> bundle adjustment rounds.

calibrate_wand runs the stages in order (each a function below): label the wand in
every camera and estimate the clock offsets, align the tracks on a common grid,
chain the pairwise poses (calibration/pairwise.py), solve (calibration/bundle.py)
from them, re-align at the corrected clock offsets and solve again, drop views with a
large residual, then the final solve with the covariance; parameters the data cannot
determine are refused or warned about (observability guards). compare_cameras measures
a result against known cameras.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos.calibration.bundle import ProgressFn, bundle_adjust, no_progress
from visionpos.calibration.pairwise import (
    PairPose,
    check_motion,
    initial_poses,
    initial_wand,
    undistort_wand,
)
from visionpos.calibration.wand import GRID_RATE_HZ, MIN_WAND_FRAMES, CalibrationError, WandData, WandSpec
from visionpos.camera.model import Camera


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
# the intrinsics' guards hold for the std at this many time steps: a model error (distortion, blob bias, clock)
# does not average out over more frames, so a longer wave must not pass a geometry that cannot separate focal
# length from distance (two cameras: 0.24 % at 3000 steps, 0.42 % at 1000; four around a volume: 0.12-0.18 %)
INTRINSICS_REFERENCE_FRAMES = 1000
# a refined intrinsic that moved by more than this many std from the chessboard's is warned about
INTRINSICS_MOVE_SIGMA = 4.0
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
    progress: ProgressFn = no_progress,
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
    from visionpos.calibration.wand import label_all

    cameras = list(cameras)
    if len(cameras) < 2:
        raise CalibrationError(f"wand calibration needs at least 2 cameras, the config has {len(cameras)}")
    names = [c.name for c in cameras]
    timings: dict[str, float] = {}
    warnings: list[str] = []
    t0 = time.perf_counter()
    tracks, stats = label_all(frames, cameras, spec, min_labelled=min_frames)
    offsets_ns, offset_pairs = _clock_offsets(cameras, tracks, stats, max_offset_ms, ref, warnings)
    timings["offsets_s"] = time.perf_counter() - t0

    def aligned(off: np.ndarray) -> WandData:
        return _aligned(cameras, tracks, stats, off, rate_hz, align, max_frames)

    data = aligned(offsets_ns)
    if len(data.times_ns) < min_frames:
        raise CalibrationError(
            f"only {len(data.times_ns)} time steps have the wand in two or more cameras at once (need {min_frames}); "
            "wave the wand longer in the middle of the volume where the cameras' views overlap"
        )
    timings["label_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    hint = _offset_hint(offsets_ns, names, max_offset_ms, warnings)
    R, t, pairs, data, A, u = _initial_solution(data, spec, ref, progress, hint, min_frames, warnings)
    timings["init_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    c0 = time.process_time()
    use_offsets = max_offset_ms > 0

    def vel(d: WandData, A_: np.ndarray, u_: np.ndarray) -> np.ndarray | None:
        return wand_velocity(d.times_ns, A_, u_, spec.offsets) if use_offsets else None

    cams, Rk, tk, data, A, u, res, offsets_ns = _solve_rounds(data, cameras, R, t, A, u, spec, ref, progress, vel,
                                                              aligned if use_offsets else None, offsets_ns)
    data, A, u, thr, n_bad = _drop_bad_views(data, res, A, u)
    cams, A, u, res, info = _final_solve(data, cameras, cams, Rk, tk, A, u, spec, ref, refine_intrinsics, progress,
                                         vel, names, warnings)
    timings["bundle_s"] = time.perf_counter() - t0
    timings["bundle_cpu_s"] = time.process_time() - c0  # one core: the solver is single-threaded
    std = info["std"]
    offsets_ns = offsets_ns + info["offsets_s"] * 1e9
    warnings += _undetermined_poses(std, names, ref, use_offsets)
    check = WandCheck.from_ratio(spec, info["ratio"], float(std.get("ratio", 0.0)))
    if check.mismatch:
        warnings.append(check.message())
    lengths = wand_lengths(cams, data.pixels)
    info["frames"] = len(data.times_ns)
    info["threshold_px"] = thr
    return WandCalibration(cams, spec, data, res, lengths, pairs, A, u, timings, info, warnings, n_bad,
                           offsets_ns=offsets_ns - offsets_ns[ref], offset_pairs=offset_pairs, check=check)


def _clock_offsets(cameras: list[Camera], tracks, stats, max_offset_ms: float, ref: int,
                   warnings: list[str]) -> tuple[np.ndarray, list]:
    """Stage 1: each camera's clock offset (V,) ns against camera ref from the labelled tracks (zeros with
    max_offset_ms 0), and the pair estimates; the estimate's problems are appended to warnings."""
    from visionpos.calibration.wand import estimate_offsets

    if max_offset_ms <= 0:
        return np.zeros(len(cameras)), []
    est = estimate_offsets(cameras, tracks, stats, max_offset_ms, ref=ref)
    warnings += est.problems
    return est.offsets_ns, est.pairs


def _aligned(cameras: list[Camera], tracks, stats, offsets_ns: np.ndarray, rate_hz: float, align: str,
             max_frames: int | None) -> WandData:
    """Stage 2: the tracks at common grid times with the cameras' clocks corrected by offsets_ns (ns), at most
    max_frames grid frames (evenly spread)."""
    from visionpos.calibration.wand import align_tracks

    d = align_tracks(cameras, tracks, stats, offsets_ns, rate_hz=rate_hz, align=align)
    if max_frames is not None and len(d.times_ns) > max_frames:
        d = d.subset(np.linspace(0, len(d.times_ns) - 1, max_frames).round().astype(int))
    return d


def _initial_solution(data: WandData, spec: WandSpec, ref: int, progress: ProgressFn, hint: str, min_frames: int,
                      warnings: list[str]):
    """Stage 3: chained pairwise poses R (V,3,3), t (V,3), the pairs, and the frames whose wand triangulates
    consistently with them (data, A, u); warnings gets check_motion's."""
    R, t, pairs = initial_poses(data, spec, ref=ref, progress=progress, hint=hint)
    A, u, ok = initial_wand(undistort_wand(data), R, t, spec)
    if ok.sum() < min_frames:
        raise CalibrationError(
            f"only {int(ok.sum())} wand frames triangulate consistently after the pairwise step (need {min_frames}); "
            "likely causes: wand lengths that do not match the wand (calibration.wand, --ab/--bc), wrong "
            f"intrinsics{hint}"
        )
    warnings += check_motion(A[ok], u[ok], spec)
    return R, t, pairs, data.subset(np.flatnonzero(ok)), A[ok], u[ok]


def _solve_rounds(data: WandData, cameras: list[Camera], R: np.ndarray, t: np.ndarray, A: np.ndarray,
                  u: np.ndarray, spec: WandSpec, ref: int, progress: ProgressFn, vel, realign,
                  offsets_ns: np.ndarray):
    """Stage 4: round 1, robust loss from the pairwise start; with realign (clock offsets estimated), every
    camera re-interpolated at its corrected times and round 2 from the refined cameras.
    Returns cams, their R, t stacked, data, A, u, residuals and the offsets (ns) the data are aligned with."""
    cams, A, u, res, info = bundle_adjust(data.pixels, cameras, R, t, A, u, spec, ref=ref, progress=progress,
                                          velocity=vel(data, A, u), estimate_ratio=True)
    Rk = np.stack([c.R for c in cams])
    tk = np.stack([c.t for c in cams])
    if realign is not None:
        offsets_ns = offsets_ns + info["offsets_s"] * 1e9
        data = realign(offsets_ns)
        A, u, ok = initial_wand(undistort_wand(data), Rk, tk, spec)
        data = data.subset(np.flatnonzero(ok))
        A, u = A[ok], u[ok]
        cams, A, u, res, info = bundle_adjust(data.pixels, cams, Rk, tk, A, u, spec, ref=ref, progress=progress,
                                              velocity=vel(data, A, u), estimate_ratio=True)
        Rk = np.stack([c.R for c in cams])
        tk = np.stack([c.t for c in cams])
    return cams, Rk, tk, data, A, u, res, offsets_ns


def _drop_bad_views(data: WandData, res: np.ndarray, A: np.ndarray, u: np.ndarray):
    """Stage 5: drop whole views (all three markers of one camera at one time) with a residual over
    max(1 px, 4.5 x the median): a mislabelled or merged blob, or a bad interpolation; then the frames left with
    fewer than 2 views. Returns data, A, u, the threshold (px) and the views dropped."""
    rn = np.linalg.norm(res, axis=-1)  # (F, V, 3)
    med = float(np.nanmedian(rn))
    thr = max(1.0, 4.5 * med)
    bad_view = np.nanmax(np.where(np.isfinite(rn), rn, 0.0), axis=2) > thr
    pixels = data.pixels.copy()
    pixels[bad_view] = np.nan
    keep = np.isfinite(pixels).all(axis=(2, 3)).sum(axis=1) >= 2
    data = WandData(data.cameras, data.times_ns[keep], pixels[keep], data.stats, data.tracks, data.offsets_ns)
    return data, A[keep], u[keep], thr, int(bad_view.sum())


def _final_solve(data: WandData, cameras: list[Camera], cams: list[Camera], Rk: np.ndarray, tk: np.ndarray,
                 A: np.ndarray, u: np.ndarray, spec: WandSpec, ref: int, refine_intrinsics: bool,
                 progress: ProgressFn, vel, names: list[str], warnings: list[str]):
    """Stage 6: the final solve with the covariance (and the intrinsics when asked); refined intrinsics the
    data cannot determine are refused (warned) and the solve rerun with the cameras' own.
    Returns bundle_adjust's cams, A, u, residuals, info."""
    final = bundle_adjust(data.pixels, cams, Rk, tk, A, u, spec, ref=ref, refine_intrinsics=refine_intrinsics,
                          progress=progress, velocity=vel(data, A, u), estimate_ratio=True, covariance=True)
    if not refine_intrinsics:
        return final
    change = intrinsics_change(cameras, final[0], final[4]["std"])
    refused, moved = _undetermined_intrinsics(change, len(data.times_ns))
    warnings += moved
    if refused:
        warnings.append("--refine-intrinsics refused, keeping the chessboard intrinsics: " + "; ".join(refused))
        # same poses, the cameras' own intrinsics
        kept = [replace(c, R=k.R, t=k.t) for c, k in zip(cameras, final[0])]
        final = bundle_adjust(data.pixels, kept, np.stack([c.R for c in kept]), np.stack([c.t for c in kept]),
                              final[1], final[2], spec, ref=ref, progress=progress, velocity=vel(data, A, u),
                              estimate_ratio=True, covariance=True)
    final[4]["intrinsics_refused"] = bool(refused)
    final[4]["intrinsics_change"] = change
    return final


def _undetermined_poses(std: dict, names: list[str], ref: int, use_offsets: bool) -> list[str]:
    """Stage 7: warnings for clock offsets and camera positions beyond the guards (std from the final solve)."""
    out = []
    for v, name in enumerate(names):
        if use_offsets and v != ref and std["offset_s"][v] > MAX_OFFSET_STD_S:
            out.append(f"camera {name} clock offset: std {std['offset_s'][v] * 1e3:.2f} ms — the wand moved too "
                       "little in its view to determine it; wave it faster")
        if v != ref and std["center_m"][v] > MAX_CAMERA_CENTER_STD_M:
            out.append(f"camera {name} position: std {std['center_m'][v] * 1000:.1f} mm — few wand frames "
                       "constrain it; wave the wand more where it overlaps other cameras")
    return out


def _offset_hint(offsets_ns: np.ndarray, names: list[str], max_offset_ms: float, problems: list[str]) -> str:
    """The clock part of a failure's likely causes."""
    if max_offset_ms <= 0:
        return ("; cameras' clocks that disagree (clock offsets were not estimated: give a maximum clock offset, "
                "--max-clock-offset-ms)")
    est = ", ".join(f"{n} {o / 1e6:+.1f} ms" for n, o in zip(names, offsets_ns))
    more = ("; " + "; ".join(problems)) if problems else ""
    return (f"; a clock offset beyond the search range (+-{max_offset_ms:.0f} ms; estimated offsets: {est}{more})")


def intrinsics_change(before: list[Camera], after: list[Camera], std: dict) -> list[dict]:
    """What `--refine-intrinsics` changed, per camera: {name, params: [{name (fx, fy, cx, cy), before, after,
    std (px), correlation (the multiple correlation with every other parameter), partner (the most correlated
    other camera's or pose parameter, named), partner_corr}], dist (the distortion vector, not refined)}."""
    corr = std.get("intrinsics_correlation")
    out = []
    for v, (b, a) in enumerate(zip(before, after)):
        params = []
        for k, p in enumerate(("fx", "fy", "cx", "cy")):
            sd = (std["f_px"] if k < 2 else std["c_px"])[v, k % 2]
            entry = {"name": p, "before": float(getattr(b.model, p)), "after": float(getattr(a.model, p)),
                     "std": float(sd)}
            if corr is not None:
                name = corr["names"][int(corr["partner"][v, k])]
                cam_index, _, what = name.partition(" ")  # "cam{v} ...": the bundle's camera index -> its name
                partner = f"camera {before[int(cam_index[3:])].name} {what}" if cam_index[3:].isdigit() else name
                entry.update(correlation=float(corr["multiple"][v, k]), partner=partner,
                             partner_corr=float(corr["partner_corr"][v, k]))
            params.append(entry)
        out.append({"name": b.name, "params": params, "dist": [float(x) for x in np.ravel(b.model.dist)]})
    return out


def _undetermined_intrinsics(change: list[dict], frames: int) -> tuple[list[str], list[str]]:
    """(reasons to refuse, warnings) for refined intrinsics, one per parameter, from `intrinsics_change`:
    refused where the std, taken at INTRINSICS_REFERENCE_FRAMES time steps (std x sqrt(frames / that)), is beyond
    the guards (focal length 0.3 %, principal point 3 px); warned where a kept one moved by more than
    INTRINSICS_MOVE_SIGMA std. Each names the parameter's std and the parameter it trades with."""
    refuse, warn = [], []
    scale = np.sqrt(max(frames, 1) / INTRINSICS_REFERENCE_FRAMES)
    for cam in change:
        for p in cam["params"]:
            sd, f = p["std"], p["before"]
            geo = sd * max(scale, 1.0)
            trades = (f", trades most with {p['partner']} (correlation {p['partner_corr']:+.2f})"
                      if "correlation" in p else "")
            what = (f"camera {cam['name']} {'focal length' if p['name'][0] == 'f' else 'principal point'} {p['name']}: "
                    f"std {sd:.1f} px")
            limit = MAX_FOCAL_STD_REL * f if p["name"][0] == "f" else MAX_CENTRE_STD_PX
            if not np.isfinite(sd) or geo > limit:
                rel = f" ({100 * sd / f:.2f} %)" if p["name"][0] == "f" else ""
                at = f", {geo:.1f} px at {INTRINSICS_REFERENCE_FRAMES} time steps" if scale > 1.0 else ""
                refuse.append(f"{what}{rel}{at}{trades}: the data cannot determine it (it would have moved "
                              f"{p['before']:.1f} -> {p['after']:.1f} px)")
            elif abs(p["after"] - p["before"]) > INTRINSICS_MOVE_SIGMA * sd:
                warn.append(f"{what}: moved {p['before']:.1f} -> {p['after']:.1f} px, "
                            f"{abs(p['after'] - p['before']) / sd:.0f} std from the chessboard's{trades}; check the "
                            "chessboard calibration and the lens model")
    return refuse, warn


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
