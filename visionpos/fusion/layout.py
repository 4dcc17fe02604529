"""Every packed array layout of the fusion path, named in one place.

The compiled kernels exchange state through flat numpy arrays rather than
objects: numba handles arrays cheaply, each array crossing the Python/kernel
boundary costs microseconds, and the filters' rows must be updated in place
by the kernels and read by Python through views. The price is that a column
is just a number; this module gives each column (or slice of columns) its
name, so kernels and orchestrator read `states[b, STATE_VEL_VAR]` instead of
`states[b, 25]`. Plain ints and slices: numba freezes them as constants.
"""

from __future__ import annotations

from enum import IntEnum
from typing import NamedTuple

import numpy as np

from visionpos.fusion.settings import (  # noqa: F401  (SV_PARAM_*: the kernels import them from here)
    FUSION_PARAMS,
    KALMAN_PARAMS,
    SV_PARAM_ALWAYS,
    SV_PARAM_OCCLUSION,
    SV_PARAM_OFF,
)

# ---------------------------------------------------------------- filter state x (18,)
# [p (3) m, v (3) m/s, a (3) m/s^2, dtheta (3) rad, w (3) rad/s, dw/dt (3) rad/s^2], world frame (tracking.py)
N_STATE = 18
POS0, VEL0, ACC0, ROT_ERR0, RATE0, ANG_ACC0 = 0, 3, 6, 9, 12, 15  # first index of each 3-vector block
X_POS, X_VEL, X_ACC = slice(POS0, POS0 + 3), slice(VEL0, VEL0 + 3), slice(ACC0, ACC0 + 3)
X_ROT_ERR, X_RATE, X_ANG_ACC = slice(ROT_ERR0, ROT_ERR0 + 3), slice(RATE0, RATE0 + 3), slice(ANG_ACC0, ANG_ACC0 + 3)
X_POSE = (0, 1, 2, 9, 10, 11)  # the measured states: position, rotation error

# ---------------------------------------------------------------- pose measurement (6,) and its covariance (6, 6)
# [p (3) m, world rotation vector (3) rad]
POSE_P, POSE_ROT = slice(0, 3), slice(3, 6)
POSE_ROT0 = 3

# ---------------------------------------------------------------- FilterBank rows (tracking.py)
# adapt (n, 12) float: process-noise scales and NIS averages (fused pose: position, rotation; image: the
# translation and the rotation part of the residual), the position NIS's slow average and the cruise floor
# it moves, the same two for the rotation, and the NIS-driven part of each scale while a model floor
# (fusion.kalman.tilt_jerk_ms, angular_accel_hold_ms) lies under it (adaptation.adapt_noise_scales)
(ADAPT_SCALE_P, ADAPT_SCALE_R, ADAPT_NIS_P, ADAPT_NIS_R, ADAPT_NIS_IMG, ADAPT_NIS_IMG_R, ADAPT_NIS_CRUISE,
 ADAPT_SCALE_CRUISE, ADAPT_NIS_CRUISE_R, ADAPT_SCALE_CRUISE_R, ADAPT_NIS_SCALE_P, ADAPT_NIS_SCALE_R) = range(12)
N_ADAPT = 12
# clock (n, 3) int64: filter time ns, last image-NIS time ns, folds of the rotation error since the start
CLOCK_T_NS, CLOCK_IMG_T_NS, CLOCK_FOLDS = range(3)
N_CLOCK = 3
# params (N_KALMAN_PARAMS,) float: the KalmanSettings the kernels read; the KALMAN_* indices below

# ---------------------------------------------------------------- filter output row (61,) (tracking._output_at)
OUT_POS, OUT_QUAT_XYZW, OUT_VEL, OUT_RATE_BODY = slice(0, 3), slice(3, 7), slice(7, 10), slice(10, 13)
OUT_QUAT0, OUT_RATE_BODY0, OUT_POSE_COV0, OUT_VEL_COV0 = 3, 10, 13, 49  # first index, for loops
OUT_POSE_COV, OUT_VEL_COV = slice(13, 49), slice(49, 58)  # (6, 6) and (3, 3), row-major
OUT_ACC = slice(58, 61)  # world acceleration m/s^2
N_OUT = 61

# ---------------------------------------------------------------- packed body states (B, 30) (kernels._pack_states)
STATE_X = slice(0, N_STATE)  # the filter state x
STATE_R_NOM0 = N_STATE
STATE_R_NOM = slice(STATE_R_NOM0, STATE_R_NOM0 + 9)  # nominal rotation (3, 3), row-major
STATE_DT_S = STATE_R_NOM0 + 9  # reference time - filter time (s): how far to predict
STATE_VEL_VAR = STATE_DT_S + 1  # mean velocity variance (m^2/s^2)
STATE_RATE_VAR = STATE_DT_S + 2  # mean angular-rate variance (rad^2/s^2)
N_STATE_COLS = STATE_DT_S + 3

# ---------------------------------------------------------------- packed camera (28,) (matching.Projector.packed)
CAMERA_R, CAMERA_T = slice(0, 9), slice(9, 12)  # world -> camera rotation (3, 3) row-major, translation
CAMERA_INTRINSICS, CAMERA_DIST = slice(12, 18), slice(18, 26)  # lens (camera.model.lens_arrays)
INTRINSICS_FX, INTRINSICS_FY = 0, 1  # focal lengths (px) in the intrinsics (6,)
CAMERA_COS_MAX = 26  # visibility limit: cosine of the largest angle off the optical axis
CAMERA_FISHEYE = 27  # 1.0: Kannala-Brandt lens model, 0.0: pinhole
N_CAMERA = 28

# ---------------------------------------------------------------- marker motion (3, M, 3) (kernels._tracked_motion)
MOTION_POS, MOTION_VEL, MOTION_ACC = range(3)

# ---------------------------------------------------------------- kernel parameter vectors
# FilterBank.params (N_KALMAN_PARAMS,) and the fusion kernels' params (N_PARAMS,) (FusionPipeline): each
# entry's index constant (KALMAN_GATE_CHI2, PARAM_SV_WINDOW_NS, ...) is made here from its row in
# fusion/settings.py's KALMAN_PARAMS / FUSION_PARAMS, where its value and meaning are declared; a
# module-level int, so numba freezes it as a constant. Values of PARAM_SV_ENABLED: SV_PARAM_*.
KALMAN_PARAM_INDEX = {p.name: i for i, p in enumerate(KALMAN_PARAMS)}
FUSION_PARAM_INDEX = {p.name: i for i, p in enumerate(FUSION_PARAMS)}
globals().update(KALMAN_PARAM_INDEX)
globals().update(FUSION_PARAM_INDEX)
N_KALMAN_PARAMS = len(KALMAN_PARAMS)
N_PARAMS = len(FUSION_PARAMS)

# ---------------------------------------------------------------- track rows, one per body (tracks._Track)
# track_ints (bodies, 9) int64; TRACK_UPDATE_KIND: UpdateKind of the last measurement that kept the track;
# TRACK_VIEWS_T_NS: capture time of the newest frame in the single-view information (TrackRows.info)
(TRACK_LAST_UPDATE_NS, TRACK_LAST_CAPTURE_NS, TRACK_N_MARKERS, TRACK_N_CAMERAS, TRACK_FIRST_REJECT_NS,
 TRACK_TRACKED, TRACK_RESETS, TRACK_UPDATE_KIND, TRACK_VIEWS_T_NS) = range(9)
N_TRACK_INTS = 9
NO_TIME = np.iinfo(np.int64).min  # TRACK_FIRST_REJECT_NS: nothing rejected since the last accepted measurement
# track_floats (bodies, 3) float64
TRACK_PX_VAR, TRACK_MARKER_VAR, TRACK_RESIDUAL_MM = range(3)
N_TRACK_FLOATS = 3

# ---------------------------------------------------------------- per-body fusion results (kernels._fuse_tracked)
# measurement rows (B, 51), one array: each array a kernel returns costs a few microseconds to hand to Python
MEAS_ROT, MEAS_POS, MEAS_COV = slice(0, 9), slice(9, 12), slice(12, 48)  # R (3, 3), t (3,), covariance (6, 6)
MEAS_N_MARKERS, MEAS_N_CAMERAS, MEAS_FIT_RMS_M = 48, 49, 50
N_MEAS = 51


class Verdict(IntEnum):
    """What one fusion did with a tracked body's measurement."""

    TOO_FEW = 0  # fewer markers than a pose needs (and no single view used)
    FIT_REJECTED = 1  # the rigid fit residual is above its tolerance
    ACCEPTED = 2
    GATED = 3  # outside the filter's innovation gate
    RESET = 4  # gated for too long: the filter restarted at the measurement
    VIEWS = 5  # no pose: single-view updates taken, and they constrain the pose (the track is kept)
    VIEWS_UNCONSTRAINED = 6  # single-view updates taken, but their information leaves the pose unobservable
    VIEWS_GATED = 7  # every single view was outside its innovation gate


# the kernels' plain-int copies (numba reads module-level ints as constants)
(VERDICT_TOO_FEW, VERDICT_FIT_REJECTED, VERDICT_ACCEPTED, VERDICT_GATED, VERDICT_RESET, VERDICT_VIEWS,
 VERDICT_VIEWS_UNCONSTRAINED, VERDICT_VIEWS_GATED) = (int(v) for v in Verdict)


class UpdateKind(IntEnum):
    """Which kind of measurement last kept a body tracked (TRACK_UPDATE_KIND, BodyState.update_kind)."""

    NONE = 0  # not tracked yet
    POSE = 1  # a triangulated pose (or the identification that started the track)
    VIEWS = 2  # single-camera reprojection updates (fewer than min_markers triangulated)


UPDATE_NONE, UPDATE_POSE, UPDATE_VIEWS = (int(v) for v in UpdateKind)


# ---------------------------------------------------------------- argument groups of the kernels
# The kernels take these as plain tuples (tuple(group)) and unpack them in this field order: numba
# types a namedtuple argument in Python, about 1 us per call on the per-frame path, a plain tuple in C.


class FilterArrays(NamedTuple):
    """A FilterBank's arrays (tracking.py): one row per body, updated in place by the kernels."""

    x: np.ndarray  # (n, N_STATE) states
    P: np.ndarray  # (n, N_STATE, N_STATE) covariances
    R_nom: np.ndarray  # (n, 3, 3) nominal rotations body -> world
    adapt: np.ndarray  # (n, N_ADAPT) noise scales and NIS averages
    clock: np.ndarray  # (n, N_CLOCK) int64 times and fold counts
    params: np.ndarray  # (N_KALMAN_PARAMS,) settings


class TrackedSet(NamedTuple):
    """The tracked bodies and their markers, body by body (FusionPipeline._layout)."""

    bodies: np.ndarray  # (B,) int64 body indices
    rows: np.ndarray  # (M,) int64 global marker rows
    sizes: np.ndarray  # (B,) int64 marker counts
    body_of_row: np.ndarray  # (M,) int64 index into `bodies` of each row's body
    local: np.ndarray  # (M, 3) body-frame marker positions (m)


class ViewSet(NamedTuple):
    """The cameras of one fusion (FusionPipeline._views)."""

    cameras: np.ndarray  # (V,) int64 camera indices
    R: np.ndarray  # (V, 3, 3) world -> camera rotations
    t: np.ndarray  # (V, 3) translations (m)
    focal_px: np.ndarray  # (V,) geometric-mean focal lengths (px)
    packed: np.ndarray  # (V, N_CAMERA) the cameras packed as matching.Projector.packed (single-view path)


class TrackRows(NamedTuple):
    """The per-body track rows (tracks.Track views a row of each)."""

    ints: np.ndarray  # (bodies, N_TRACK_INTS) int64, columns TRACK_* above
    floats: np.ndarray  # (bodies, N_TRACK_FLOATS) float64
    view_ns: np.ndarray  # (bodies, cameras) int64: capture time of each camera's newest frame the body used
    info: np.ndarray  # (bodies, 6, 6) pose information [p, rotation] of its recent single views (decaying)
