"""Per-body track state and per-camera observations of the fusion pipeline, as Python views.

The compiled kernels (kernels.py) update each body's track state in place in
two packed arrays, track_ints (bodies, N_TRACK_INTS) and track_floats
(bodies, N_TRACK_FLOATS) (columns in layout.py); Track gives one body's rows
names, so the orchestrator reads `track.n_markers` of the same memory.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visionpos.fusion.body_filter import BodyFilter, array_field
from visionpos.fusion.layout import (
    N_TRACK_FLOATS,
    N_TRACK_INTS,
    NO_TIME,
    TRACK_FIRST_REJECT_NS,
    TRACK_LAST_CAPTURE_NS,
    TRACK_LAST_UPDATE_NS,
    TRACK_MARKER_VAR,
    TRACK_N_CAMERAS,
    TRACK_N_MARKERS,
    TRACK_PX_VAR,
    TRACK_RESETS,
    TRACK_RESIDUAL_MM,
    TRACK_TRACKED,
    TRACK_UPDATE_KIND,
    TrackRows,
)

PX_VAR_PRIOR = 0.25  # px^2, per-axis pixel noise before any residual is seen


@dataclass
class Observation:
    """Newest frame of one camera after association.

    xn: (N, 2) normalised coordinates; label: (N,) global marker index or -1;
    marker_xn: (all markers, 2) observation of every configured marker (NaN = none);
    pred_px: (M, 2) pixels where the filters predicted the tracked markers at capture_ns,
    the prediction this frame was matched against (NaN off the sensor), and pred_rows (M,)
    their global marker rows; None while no body is tracked.
    """

    capture_ns: int
    xn: np.ndarray
    label: np.ndarray
    marker_xn: np.ndarray
    pred_px: np.ndarray | None = None
    pred_rows: np.ndarray | None = None


def new_track_rows(n_bodies: int, n_cameras: int = 0) -> TrackRows:
    """Track rows of n_bodies untracked bodies seen by n_cameras: nothing rejected, the pixel-noise
    prior, no residual, no frame used, no single-view information."""
    track_ints = np.zeros((n_bodies, N_TRACK_INTS), dtype=np.int64)
    track_ints[:, TRACK_FIRST_REJECT_NS] = NO_TIME
    track_floats = np.zeros((n_bodies, N_TRACK_FLOATS))
    track_floats[:, TRACK_PX_VAR] = PX_VAR_PRIOR
    track_floats[:, TRACK_RESIDUAL_MM] = np.nan
    view_ns = np.full((n_bodies, n_cameras), NO_TIME, dtype=np.int64)
    return TrackRows(track_ints, track_floats, view_ns, np.zeros((n_bodies, 6, 6)))


class Track:
    """One body's tracking state: views of its rows of the pipeline's track arrays, and its filter."""

    tracked = array_field("ints", TRACK_TRACKED, bool)
    last_update_ns = array_field("ints", TRACK_LAST_UPDATE_NS, int, "reference time of the last accepted measurement")
    last_capture_ns = array_field("ints", TRACK_LAST_CAPTURE_NS, int, "newest capture time in it")
    n_markers = array_field("ints", TRACK_N_MARKERS, int)
    n_cameras = array_field("ints", TRACK_N_CAMERAS, int)
    reset_counter = array_field("ints", TRACK_RESETS, int)
    update_kind = array_field("ints", TRACK_UPDATE_KIND, int, "layout.UpdateKind of the last measurement kept")
    px_var = array_field("floats", TRACK_PX_VAR, float,
                         "running per-axis pixel noise variance (px^2) from triangulation residuals")
    marker_var = array_field("floats", TRACK_MARKER_VAR, float,
                             "running per-marker 3D noise variance (m^2) from fit residuals")
    residual_mm = array_field("floats", TRACK_RESIDUAL_MM, float)

    def __init__(self, filter: BodyFilter, track_ints: np.ndarray, track_floats: np.ndarray):
        self.filter = filter
        self.ints = track_ints  # (N_TRACK_INTS,) int64 row
        self.floats = track_floats  # (N_TRACK_FLOATS,) float64 row

    @property
    def first_reject_ns(self) -> int | None:
        """When the filter began rejecting measurements (None: the last one was accepted)."""
        v = int(self.ints[TRACK_FIRST_REJECT_NS])
        return None if v == NO_TIME else v

    @first_reject_ns.setter
    def first_reject_ns(self, value: int | None) -> None:
        self.ints[TRACK_FIRST_REJECT_NS] = NO_TIME if value is None else value
