"""PNG plots for replay reports: trajectory, error against time, latency histogram.

matplotlib is optional (the `plots` extra); it is imported only when a plot
is drawn, and a missing install raises PlotsUnavailable with the fix.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from visionpos.errors import VisionposError


class PlotsUnavailable(VisionposError, ImportError):
    """matplotlib is not installed."""


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")  # files only; never needs a display
        import matplotlib.pyplot as plt
    except ImportError:
        raise PlotsUnavailable(
            "matplotlib is not installed, so no PNG plots were written; "
            "install the plots extra: pip install 'visionpos[plots]'"
        ) from None
    return plt


def plot_trajectories(path: str | Path, bodies: dict[str, dict[str, np.ndarray]]) -> Path:
    """Top view (x, y) and height against time, estimate vs truth, one colour per body.

    bodies: name -> {'t': (N,) s, 'position': (N, 3) m, and optionally
    'truth_t': (T,) s, 'truth_position': (T, 3) m}. Untracked rows should be nan.
    """
    plt = _pyplot()
    fig, (ax_xy, ax_z) = plt.subplots(1, 2, figsize=(12, 5))
    for i, (name, d) in enumerate(bodies.items()):
        c = f"C{i % 10}"
        if "truth_position" in d:
            tp = d["truth_position"]
            ax_xy.plot(tp[:, 0], tp[:, 1], color=c, lw=3, alpha=0.3, label=f"{name} truth")
            ax_z.plot(d["truth_t"], tp[:, 2], color=c, lw=3, alpha=0.3)
        p = d["position"]
        ax_xy.plot(p[:, 0], p[:, 1], color=c, lw=0.8, label=f"{name} estimate")
        ax_z.plot(d["t"], p[:, 2], color=c, lw=0.8)
    ax_xy.set_xlabel("x [m]")
    ax_xy.set_ylabel("y [m]")
    ax_xy.set_aspect("equal", adjustable="datalim")
    ax_xy.set_title("trajectory, top view")
    ax_xy.legend(fontsize=8)
    ax_z.set_xlabel("time [s]")
    ax_z.set_ylabel("z [m]")
    ax_z.set_title("height")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_errors(path: str | Path, bodies: dict[str, dict[str, np.ndarray]]) -> Path:
    """Position error (mm) and rotation error (deg) against time per body.

    bodies: name -> {'t': (N,) s, 'position_error_mm': (N,), 'rotation_error_deg': (N,)}.
    """
    plt = _pyplot()
    fig, (ax_p, ax_r) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    for i, (name, d) in enumerate(bodies.items()):
        c = f"C{i % 10}"
        ax_p.plot(d["t"], d["position_error_mm"], color=c, lw=0.8, label=name)
        ax_r.plot(d["t"], d["rotation_error_deg"], color=c, lw=0.8)
    ax_p.set_ylabel("position error [mm]")
    ax_p.legend(fontsize=8)
    ax_p.grid(alpha=0.3)
    ax_r.set_ylabel("rotation error [deg]")
    ax_r.set_xlabel("time [s]")
    ax_r.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_latency(path: str | Path, latencies_ms: dict[str, np.ndarray]) -> Path:
    """Histogram of capture -> output latency per body. latencies_ms: name -> (N,) ms."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    allv = np.concatenate([np.asarray(v, float) for v in latencies_ms.values()] or [np.zeros(0)])
    bins = np.linspace(0.0, float(np.percentile(allv, 99.9)) * 1.1 + 1e-3, 60) if allv.size else 10
    for i, (name, v) in enumerate(latencies_ms.items()):
        ax.hist(v, bins=bins, alpha=0.5, color=f"C{i % 10}", label=name)
    ax.set_xlabel("capture -> output latency [ms]")
    ax.set_ylabel("outputs")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
