"""Calibration reports: terminal tables, PNG figures, progress bars.

matplotlib is optional (the `plots` extra); tqdm is optional too (a plain
stderr counter is used without it).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable

import numpy as np

from visionpos.calibration.intrinsics import IntrinsicsResult
from visionpos.calibration.wand_solve import WandCalibration


def progress_printer(enabled: bool = True, stream=None) -> Callable[[str, int, int], None]:
    """A ProgressFn(stage, done, total): one bar per stage on a terminal (tqdm when installed); into a log
    or a pipe, whole lines at each tenth of a stage (a carriage return there runs the updates together)."""
    if not enabled:
        return lambda stage, done, total: None
    out = sys.stderr if stream is None else stream
    if not (hasattr(out, "isatty") and out.isatty()):
        shown: dict[str, int] = {}

        def lines(stage: str, done: int, total: int) -> None:
            tenth = 10 if done >= total else (10 * done) // max(total, 1)
            if tenth > shown.get(stage, -1):
                shown[stage] = tenth
                print(f"{stage}: {done}/{total} ({10 * tenth} %)", file=out, flush=True)
            if done >= total:
                shown.pop(stage, None)

        return lines
    bars: dict[str, object] = {}
    try:
        from tqdm import tqdm
    except ImportError:  # plain counter, redrawn in place
        def plain(stage: str, done: int, total: int) -> None:
            end = "\n" if done >= total else ""
            print(f"\r{stage}: {done}/{total}", end=end, file=out, flush=True)

        return plain

    def bar(stage: str, done: int, total: int) -> None:
        b = bars.get(stage)
        if b is None:
            b = bars[stage] = tqdm(total=total, desc=stage, leave=True, file=out)
        b.n = done  # type: ignore[attr-defined]
        b.refresh()  # type: ignore[attr-defined]
        if done >= total:
            b.close()  # type: ignore[attr-defined]
            bars.pop(stage, None)

    return bar


def _table(header: list[str], rows: list[list[str]]) -> str:
    w = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(header)]
    line = "  ".join(h.rjust(w[i]) for i, h in enumerate(header))
    out = [line, "  ".join("-" * x for x in w)]
    out += ["  ".join(c.rjust(w[i]) for i, c in enumerate(r)) for r in rows]
    return "\n".join(out)


def wand_report(cal: WandCalibration, title: str = "wand calibration") -> str:
    """Terminal report: per-camera residuals and positions, wand-length errors (thesis Table 4.2)."""
    rows = []

    def sd(v: float, fmt: str) -> str:
        return format(v, fmt) if np.isfinite(v) else "-"

    for s in cal.camera_stats():
        c = s["center"]
        rows.append(
            [s["name"], str(s["id"]), str(s["views"]), f"{s['rms_px']:.3f}", f"{s['max_px']:.2f}",
             f"{c[0]:+.4f}", f"{c[1]:+.4f}", f"{c[2]:+.4f}", sd(s["center_std_mm"], ".2f"),
             sd(s["rot_std_deg"], ".4f"), f"{s['offset_ms']:+.2f}", sd(s["offset_std_ms"], ".3f")]
        )
    out = [f"== {title}: {len(cal.data.times_ns)} time steps, {len(cal.cameras)} cameras =="]
    out.append(_table(["camera", "id", "views", "rms px", "max px", "x m", "y m", "z m", "pos std mm",
                       "rot std deg", "clock offset ms", "std ms"], rows))
    out.append("(std: one standard deviation from the bundle adjustment's covariance; clock offsets against the "
               "first camera's clock: its stamps read true time + offset)")
    L = cal.length_stats()
    out.append("")
    out.append("wand lengths, freely triangulated with the calibrated cameras (mean error, std):")
    for name, true in (("AB", cal.spec.ab), ("BC", cal.spec.bc), ("AC", cal.spec.ac)):
        k = name.lower()
        out.append(
            f"  {name} {true * 100:6.2f} cm: {L[k + '_mean_err'] * 1000:+7.3f} mm, std {L[k + '_std'] * 1000:6.3f} mm"
        )
    if cal.check is not None:
        out.append("  " + cal.check.message())
    out += intrinsics_lines(cal.info)
    t = cal.timings
    out.append("")
    out.append(
        f"labelling and clock offsets {t.get('label_s', 0):.1f} s, pairwise init {t.get('init_s', 0):.1f} s, "
        f"bundle adjustment {t.get('bundle_s', 0):.1f} s ({cal.info.get('nfev', 0)} evaluations); "
        f"{cal.rejected_views} views rejected (> {cal.info.get('threshold_px', 0):.2f} px)"
    )
    for w in cal.warnings:
        out.append(f"warning: {w}")
    return "\n".join(out)


def intrinsics_lines(info: dict) -> list[str]:
    """What `--refine-intrinsics` changed (`info["intrinsics_change"]`): per camera and parameter the chessboard
    value, the refined one, its std and the parameter it trades with most; empty without the option."""
    change = info.get("intrinsics_change")
    if not change:
        return []
    refused = info.get("intrinsics_refused", False)
    rows = []
    for cam in change:
        for p in cam["params"]:
            rows.append([cam["name"], p["name"], f"{p['before']:.2f}", f"{p['after']:.2f}",
                         f"{p['after'] - p['before']:+.2f}", f"{p['std']:.2f}",
                         f"{p.get('partner', '-')} ({p.get('partner_corr', float('nan')):+.2f})"])
    head = ("refused, the chessboard intrinsics kept (the refined values, for comparison):" if refused
            else "applied:")
    dist = "; ".join(f"{c['name']} {[round(x, 5) for x in c['dist']]}" for c in change)
    return ["", f"--refine-intrinsics {head}",
            _table(["camera", "param", "before px", "after px", "change px", "std px", "trades most with (corr)"],
                   rows),
            f"distortion: not refined, unchanged: {dist}"]


def intrinsics_report(res: IntrinsicsResult) -> str:
    m = res.model
    out = [
        f"== intrinsics ({m.kind}, {m.width}x{m.height}): {len(res.views)} views used of {res.candidates} "
        f"with the board found ==",
        f"RMS reprojection error {res.rms_px:.3f} px",
        f"fx {m.fx:.3f}  fy {m.fy:.3f}  cx {m.cx:.3f}  cy {m.cy:.3f}",
        "dist " + " ".join(f"{v:.6g}" for v in m.to_dict()["dist"]),
    ]
    worst = np.argsort(-res.view_rms)[:5]
    out.append("worst views: " + ", ".join(f"{res.views[i]} {res.view_rms[i]:.3f} px" for i in worst))
    if res.rejected:
        out.append("rejected as outliers: " + ", ".join(res.rejected))
    return "\n".join(out)


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise RuntimeError(
            "the PNG report needs matplotlib: pip install 'visionpos[plots]' (or leave out --report/--plot)"
        ) from None
    return plt


def plot_wand(cal: WandCalibration, path: str | Path, truth: list | None = None) -> None:
    """PNG: camera poses in 3D with the wand positions, residual histograms, wand-length errors."""
    plt = _pyplot()
    fig = plt.figure(figsize=(14, 9))
    ax = fig.add_subplot(2, 2, 1, projection="3d")
    A = cal.A
    step = max(1, len(A) // 1500)
    ax.scatter(A[::step, 0], A[::step, 1], A[::step, 2], s=1, c="0.6", label="wand A")
    span = float(np.ptp(np.array([c.center for c in cal.cameras]), axis=0).max() or 1.0)
    for c in cal.cameras:
        C = c.center
        z = c.R[2] * 0.15 * span
        ax.quiver(C[0], C[1], C[2], z[0], z[1], z[2], color="C0")
        ax.text(C[0], C[1], C[2], f" {c.name}", fontsize=8)
    if truth is not None:
        T = np.array([c.center for c in truth])
        ax.scatter(T[:, 0], T[:, 1], T[:, 2], marker="x", c="C3", label="truth")
    allp = np.vstack([A[::step], np.array([c.center for c in cal.cameras])])
    ax.set_box_aspect(tuple(np.maximum(np.ptp(allp, axis=0), 0.1)))  # metres look like metres
    ax.set_title("cameras and wand")
    ax.set_xlabel("x m")
    ax.set_ylabel("y m")
    ax.set_zlabel("z m")
    ax.legend(loc="upper left", fontsize=8)
    ax2 = fig.add_subplot(2, 2, 2)
    r = np.linalg.norm(cal.residuals, axis=-1)
    hi = float(np.nanpercentile(r, 99.9)) if np.isfinite(r).any() else 1.0
    bins = np.linspace(0, hi, 60)
    for v, c in enumerate(cal.cameras):
        rv = r[:, v][np.isfinite(r[:, v])]
        ax2.hist(rv, bins=bins, histtype="step", label=c.name)
    ax2.set_xlabel("reprojection error px")
    ax2.set_ylabel("observations")
    ax2.set_title("residuals per camera")
    ax2.legend(fontsize=7, ncol=2)
    ax3 = fig.add_subplot(2, 2, 3)
    true = np.array([cal.spec.ab, cal.spec.bc, cal.spec.ac])
    L = cal.lengths[np.isfinite(cal.lengths).all(axis=1)]
    for k, name in enumerate(("AB", "BC", "AC")):
        ax3.hist((L[:, k] - true[k]) * 1000, bins=60, histtype="step", label=name)
    ax3.set_xlabel("triangulated length - true (mm)")
    ax3.set_title("wand lengths (thesis Table 4.2)")
    ax3.legend()
    ax4 = fig.add_subplot(2, 2, 4)
    stats = cal.camera_stats()
    ax4.bar([s["name"] for s in stats], [s["rms_px"] for s in stats])
    ax4.set_ylabel("RMS px")
    ax4.set_title("reprojection RMS per camera")
    ax4.tick_params(axis="x", rotation=45)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_ground(g, layout: np.ndarray, path: str | Path) -> None:
    """PNG of the ground step (a calibration.ground.GroundResult) in the new world: cameras, every static point
    found, the frame's markers as identified (numbered as in its layout) with the world axes, from above and
    from the side."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.5))
    C = np.array([c.center for c in g.cameras])
    pts = g.static_points if g.static_points is not None else np.zeros((0, 3))
    span = max(float(np.ptp(C[:, :2], axis=0).max()), 0.5)
    for ax, (i, j), name in ((axes[0], (0, 1), "from above (x, y)"), (axes[1], (0, 2), "from the side (x, z)")):
        ax.scatter(C[:, i], C[:, j], marker="^", c="k", s=50, label="cameras")
        for c, p in zip(g.cameras, C):
            ax.annotate(c.name, (p[i], p[j]), fontsize=7, xytext=(3, 3), textcoords="offset points")
        if len(pts):
            ax.scatter(pts[:, i], pts[:, j], c="0.6", s=12, label="static points")
        ax.scatter(g.markers[:, i], g.markers[:, j], c="tab:red", s=30, label="frame markers")
        for k, p in enumerate(g.markers):
            ax.annotate(str(k), (p[i], p[j]), color="tab:red", fontsize=8, xytext=(4, -10), textcoords="offset points")
        L = 0.15 * span
        for axis, colour in ((0, "tab:red"), (1, "tab:green"), (2, "tab:blue")):
            d = np.eye(3)[axis] * L
            ax.annotate("", xy=(d[i], d[j]), xytext=(0, 0), arrowprops=dict(arrowstyle="->", color=colour, lw=2))
        ax.set_title(name)
        ax.set_xlabel("xyz"[i] + " (m)")
        ax.set_ylabel("xyz"[j] + " (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=7)
    std = "" if g.marker_std is None else f", markers measured to {1000 * float(np.max(g.marker_std)):.2f} mm"
    fig.suptitle(f"ground frame: layout fit RMS {1000 * g.fit_rms:.2f} mm{std}; world axes x red, y green, z blue")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_intrinsics(res: IntrinsicsResult, path: str | Path) -> None:
    """PNG: corner coverage over the image coloured by residual, residual scatter, per-view RMS."""
    plt = _pyplot()
    m = res.model
    fig, axs = plt.subplots(1, 3, figsize=(16, 5))
    P = np.concatenate(res.pixels)
    E = np.linalg.norm(np.concatenate(res.residuals), axis=1)
    sc = axs[0].scatter(P[:, 0], P[:, 1], c=E, s=4, cmap="viridis")
    axs[0].set_xlim(-0.5, m.width - 0.5)
    axs[0].set_ylim(m.height - 0.5, -0.5)
    axs[0].set_aspect("equal")
    axs[0].set_title(f"corner coverage ({len(res.views)} views)")
    fig.colorbar(sc, ax=axs[0], label="residual px")
    Rr = np.concatenate(res.residuals)
    axs[1].scatter(Rr[:, 0], Rr[:, 1], s=2)
    lim = float(np.abs(Rr).max() * 1.1) if len(Rr) else 1.0
    axs[1].set_xlim(-lim, lim)
    axs[1].set_ylim(-lim, lim)
    axs[1].set_aspect("equal")
    axs[1].set_title(f"residuals, RMS {res.rms_px:.3f} px")
    axs[2].bar(range(len(res.views)), res.view_rms)
    axs[2].set_xlabel("view")
    axs[2].set_ylabel("RMS px")
    axs[2].set_title("per-view error")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
