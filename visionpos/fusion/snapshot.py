"""What the operator console reads of the fusion: `FusionPipeline.snapshot() -> FusionSnapshot`.

The console (console/view.py, console/health.py) shows each camera's newest frame as fusion saw it,
which body is tracked and why one is not, and the loose markers. It reads them through this
typed snapshot, never the pipeline's attributes, so the pipeline may rearrange its state freely.
A snapshot is cheap (references, no copies; named tuples, which build faster than frozen dataclasses,
and the console takes one per update): its arrays are the pipeline's own, valid until the next frame;
read them on the server's loop and never write them.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from visionpos.messages import LoosePoints


class CameraFrame(NamedTuple):
    """One camera's newest frame as fused.

    capture_ns: its capture time (server clock). px: (N, 2) its blobs in pixels. xn: (N, 2) the same
    undistorted (normalised coordinates: the blobs' rays). label: (N,) each blob's marker row (the arena's
    markers, body by body, in order) or -1 for a blob of no body. pred_px: (M, 2) pixels where the filters
    predicted the tracked markers at capture_ns (the prediction the frame was matched against; NaN off the
    sensor) and pred_rows (M,) their marker rows; both None while no body is tracked.
    """

    capture_ns: int
    px: np.ndarray
    xn: np.ndarray
    label: np.ndarray
    pred_px: np.ndarray | None = None
    pred_rows: np.ndarray | None = None


class FusionSnapshot(NamedTuple):
    """The fusion as the console shows it.

    cameras: camera id -> CameraFrame (cameras with a frame only). filter_tracked: per body (arena order),
    whether its filter holds a track (even when no measurement came within fusion.max_prediction_ms).
    untracked_why: body index -> why it is not tracked, in words. loose_points: the newest loose markers
    (points of no body), or None. identity: per body its identity state (fusion/identity.py IdentityState:
    'unique layout', 'unresolved: two candidates', 'tracked-by-continuity', ...).
    """

    cameras: dict[int, CameraFrame]
    filter_tracked: tuple[bool, ...]
    untracked_why: dict[int, str]
    loose_points: LoosePoints | None = None
    identity: tuple[str, ...] = ()
