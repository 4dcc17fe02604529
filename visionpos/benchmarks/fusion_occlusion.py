"""Fusion through occlusion (issue 15 item 1): a body that cannot be triangulated for a while.

Two scenarios on the thesis arena (the square test flight), each with a 2 s window of the
simulator's occlusion schedule (`sim.view_schedule`):
- one camera: only camera 1 sees the quad (all four markers), the other three see nothing of it;
- two cameras: camera 1 sees markers 0 and 1, camera 3 markers 2 and 3 (no marker in two views).

Measured over the window: tracked fraction of the 100 Hz outputs, position RMSE against truth,
the single-snapshot Cramer-Rao bound of the seeing cameras computed independently
(geometry.triangulation.pose_crb at the true pose, one snapshot of the seeing
cameras per frame period, with the simulated centroid noise), identity safety (no filter reset, no loss, no
second acquisition) and the NEES of the reported position covariance against its 95 %
chi-square interval. Successive 100 Hz outputs are strongly correlated (the filter averages
over many frames), so the interval is taken over samples one error-correlation time apart
(`_NEES_SPACING_S`), not over every tick.

    visionpos bench --only fusion
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from visionpos.benchmarks import BenchResult

SIGMA_PX = 0.2  # simulated centroid noise (px per axis)
_NEES_SPACING_S = 0.1  # NEES samples this far apart count as independent

# scenario name -> (what, the schedule's cameras mapping: camera id -> markers it sees)
SCENARIOS: dict[str, tuple[str, str]] = {
    "one": ("only camera 1 sees the quad (4 markers)", "{1: all}"),
    "two": ("camera 1 sees markers 0-1, camera 3 markers 2-3", "{1: [0, 1], 3: [2, 3]}"),
}


@dataclass
class OcclusionRun:
    """Figures of one occlusion flight over its window (see the module docstring)."""

    tracked_fraction: float
    pos_rmse_mm: float
    crb_pos_mm: float
    nees_mean: float
    nees_lo: float
    nees_hi: float
    sd_mm: float  # mean root trace of the reported position covariance
    views_fraction: float  # outputs whose last update was a single-view one
    swaps: int  # filter resets + losses + acquisitions after the first
    n_samples: int

    @property
    def rmse_over_crb(self) -> float:
        return self.pos_rmse_mm / self.crb_pos_mm


def occlusion_run(kind: str, seed: int = 0, duration_s: float = 5.0, start_s: float = 2.0, length_s: float = 2.0,
                  settings: dict | None = None) -> OcclusionRun:
    """Simulate the thesis flight with SCENARIOS[kind]'s window at [start_s, start_s + length_s) and
    replay it through FusionPipeline (frames in receive order, outputs at 100 Hz)."""
    from visionpos.fusion.pipeline import FusionPipeline
    from visionpos.geometry.triangulation import pose_crb
    from visionpos.sim import load_scenario, simulate

    _, cams = SCENARIOS[kind]
    window = f"[{{body: quad, start_s: {start_s}, end_s: {start_s + length_s}, cameras: {cams}}}]"
    sc = load_scenario("thesis", ["sim.view_schedule=" + window], duration=duration_s, seed=seed,
                       centroid_noise_px=SIGMA_PX)
    sim = simulate(sc)
    t0, t1 = sc.start_ns + int(start_s * 1e9), sc.start_ns + int((start_s + length_s) * 1e9)
    # the bound: one snapshot of the seeing cameras (each one's frame of the same frame period) at the
    # true pose of the period's start, for every frame period of the window
    body = sc.body("quad")
    qi = sc.bodies.index(body)
    cam_index = {c.id: i for i, c in enumerate(sc.cameras)}
    period = 10_000_000
    seen_by_slot: dict[int, np.ndarray] = {}
    for f, tr in zip(sim.frames, sim.frame_truth):
        if t0 <= tr.true_ns < t1:
            seen = seen_by_slot.setdefault((tr.true_ns - t0) // period, np.zeros((len(body.markers), len(sc.cameras)),
                                                                                 bool))
            seen[tr.marker[tr.body == qi], cam_index[f.camera_id]] = True
    crb_tr = []
    for slot, seen in sorted(seen_by_slot.items()):
        m = sc.motion_at("quad", [t0 + slot * period])
        mw = body.markers @ Rotation.from_quat(m.quaternions[0]).as_matrix().T + m.positions[0]
        crb_tr.append(np.trace(pose_crb(sc.cameras, mw, m.positions[0], SIGMA_PX, seen)[:3, :3]))
    crb_tr = np.array(crb_tr)
    # a slot with a dropped frame (sim.drop_probability) may not determine the pose: not a snapshot of the rig
    crb_pos_mm = float(np.sqrt(np.mean(crb_tr[np.isfinite(crb_tr)])) * 1e3)

    pipe = FusionPipeline(sc.arena, settings)
    frames = sorted(sim.frames, key=lambda f: (f.recv_ns, f.camera_id))
    ticks = np.arange((frames[0].recv_ns // period + 1) * period, frames[-1].recv_ns, period)
    i = 0
    ok, pos, cov, kinds = [], [], [], []
    for tk in ticks:
        while i < len(frames) and frames[i].recv_ns <= tk:
            pipe.push(frames[i])
            i += 1
        s = pipe.tick(int(tk))[0]
        ok.append(s.tracked)
        pos.append(s.position)
        cov.append(s.covariance[:3, :3])
        kinds.append(s.update_kind)
    during = (ticks >= t0) & (ticks < t1)
    ok_a = np.array(ok)
    sel = during & ok_a
    p_true, _ = sc.truth_at("quad", ticks[sel])
    err = np.array(pos)[sel] - p_true
    C = np.array(cov)[sel]
    nees = np.einsum("ni,ni->n", err, np.linalg.solve(C, err[:, :, None])[:, :, 0])
    step = max(1, int(round(_NEES_SPACING_S * 1e9 / period)))
    sample = nees[::step]
    n = len(sample)
    st = pipe.stats()
    return OcclusionRun(
        tracked_fraction=float(ok_a[during].mean()),
        pos_rmse_mm=float(np.sqrt((err**2).sum(1).mean()) * 1e3),
        crb_pos_mm=crb_pos_mm,
        nees_mean=float(sample.mean()),
        nees_lo=float(chi2.ppf(0.025, 3 * n) / n),
        nees_hi=float(chi2.ppf(0.975, 3 * n) / n),
        sd_mm=float(np.sqrt(np.trace(C, axis1=1, axis2=2)).mean() * 1e3),
        views_fraction=float(np.mean([k == "views" for k, d in zip(kinds, during) if d])),
        swaps=int(st["filter_resets"] + st["lost"] + max(st["acquisitions"] - 1, 0)),
        n_samples=n,
    )


def run_occlusion(quick: bool, res: BenchResult) -> None:
    """The occlusion section of the fusion group: metrics fusion_occlusion_{one,two}_* and a table."""
    seeds = [0] if quick else [0, 1, 2]
    tbl = [
        "| scenario | tracked | position RMSE (mm) | CRB (mm) | RMSE / CRB | reported std (mm) | NEES (95 % interval) "
        "| resets + losses + reacquisitions |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for kind, (what, _) in SCENARIOS.items():
        runs = [occlusion_run(kind, seed=s) for s in seeds]
        trk = min(r.tracked_fraction for r in runs)
        rmse = float(np.sqrt(np.mean([r.pos_rmse_mm**2 for r in runs])))
        crb = float(np.sqrt(np.mean([r.crb_pos_mm**2 for r in runs])))
        n = sum(r.n_samples for r in runs)
        nees = float(sum(r.nees_mean * r.n_samples for r in runs) / n)
        lo, hi = float(chi2.ppf(0.025, 3 * n) / n), float(chi2.ppf(0.975, 3 * n) / n)
        swaps = sum(r.swaps for r in runs)
        sd = float(np.mean([r.sd_mm for r in runs]))
        pre = f"fusion_occlusion_{kind}"
        res.metrics[f"{pre}_tracked_fraction"] = trk
        res.metrics[f"{pre}_pos_rmse_mm"] = rmse
        res.metrics[f"{pre}_crb_pos_mm"] = crb
        res.metrics[f"{pre}_rmse_over_crb"] = rmse / crb
        res.metrics[f"{pre}_nees"] = nees
        res.metrics[f"{pre}_nees_over_hi"] = nees / hi
        res.metrics[f"{pre}_nees_over_lo"] = nees / lo
        res.metrics[f"{pre}_swaps"] = float(swaps)
        tbl.append(f"| {what} | {100 * trk:.1f} % | {rmse:.2f} | {crb:.2f} | {rmse / crb:.2f} | {sd:.2f} | "
                   f"{nees:.2f} ({lo:.2f}-{hi:.2f}) | {swaps} |")
    tbl += [
        "",
        "CRB: single-snapshot Cramer-Rao bound of the pose from the seeing cameras' projections at the true pose "
        f"({SIGMA_PX} px), root of the mean position trace over the window's frames (pose_crb). NEES of "
        f"the reported position covariance, sampled every {_NEES_SPACING_S * 1e3:.0f} ms (about the error's "
        "correlation time), against the 95 % chi-square interval of its mean.",
    ]
    res.tables[
        f"Fusion: tracking through occlusion (thesis arena, square flight, 2 s window; {len(seeds)} seed(s))"
    ] = "\n".join(tbl)
