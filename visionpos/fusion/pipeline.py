"""Fusion pipeline: camera frames in, one filtered pose per body out. Pure, no I/O.

    pipe = FusionPipeline(arena, settings)
    pipe.push(frame)            # every BlobFrame, in arrival order
    states = pipe.tick(now_ns)  # one BodyState per configured body, predicted to now_ns

Deterministic: the same frames in the same order and the same tick times
give identical outputs (replay depends on it). Only frame.capture_ns is
used as time; tick() never changes the filter state.

Per frame: undistort its blobs, associate them with the markers of tracked
bodies (prediction at the frame's capture time, see matching.py), then fuse
the newest frame of every camera in the time-alignment group (timealign.py)
at the reference time: motion-compensated triangulation of every tracked
marker, a weighted Kabsch pose per body, a gated Kalman update
(tracking.py). Leftover blobs go to acquisition: cross-view matching,
identification of lost bodies by marker geometry (rigidbody.py) and the
loose points.

Measurement covariance: from the rigid-body fit itself. The Kabsch residual
gives the per-marker noise (sigma^2 = sum |r|^2 / (3n - 6), averaged per body
over recent fusions, floored by `marker_sigma_m`); with the marker layout it
gives the pose covariance (rotation: sigma^2 (sum |r_i|^2 I - r_i r_i^T)^-1,
position: sigma^2 / n plus the lever arm of the body origin). So the filter
weighs measurements by what they are actually worth in this arena, with
these cameras, at this noise level, without per-arena tuning.

Measurement reuse: in motion-compensated mode one camera frame takes part
in about as many fusions as there are cameras in the group (its own and one
per other camera until it is replaced; fewer under the rate limit). The
filter is told so: each fused pose's measurement covariance is multiplied by
that count, which splits each frame's information over the fusions that
reuse it instead of counting it several times (an overconfident filter
would smooth too little and gate wrongly).

Motion compensation and its feedback loop: the offsets come from the
filter, so a wrong velocity would bias the measurement towards itself. Until
the filter's velocity std is below 0.3 m/s (a new or reacquired track) the
views are fused uncompensated and the motion between them is added to the
measurement covariance (|v|^2 + var v) * mean(dt^2), and the per-marker
residual gate and the rigid-fit tolerance are widened by the motion the
views may disagree by (so a body reacquired at 3 m/s is not refused); once
compensating, only the velocity's own uncertainty is added. The naive mode
gets the same treatment, so the comparison is with a fair baseline.

Outputs: tick() predicts each tracked body to now_ns (latency cancelled)
with its covariance; a body not updated for max_prediction_ms or lost is
tracked=False with a NaN pose (a stale pose is never sent).
reset_counter increments only when a tracked filter is restarted at a
measurement it kept rejecting (a jump), not on a dropout or reacquisition.

The `fusion:` section of the arena YAML (every key optional):

fusion:
  time_alignment: motion_compensated  # or naive (nearest-timestamp grouping on a fixed grid, the baseline)
  window_ms: 0            # frames of other cameras captured within this of the newest are fused with it;
                          #   0 = 1.2 x the slowest camera's frame period
  naive_grid_hz: 0        # naive grouping grid; 0 = the fastest camera's rate
  max_clock_lead_ms: 30   # a frame stamped this far ahead of all other cameras is a clock jump: dropped
  match_gate_px: 12       # predicted marker -> blob association radius
  max_residual_px: 2.0    # a triangulated marker with a larger RMS reprojection residual is dropped
  acquire_ray_distance_m: 0.01  # acquisition: two rays closer than this may see the same marker
  identify_tolerance_m: 0.008   # identification: marker distances and Kabsch RMS within this
  min_markers: 3          # fewest markers for a pose (tracking) and for identification
  loose_points: true      # triangulate blobs that belong to no body and report them
  loose_points_interval_ms: 50  # loose points are refreshed this often while every body is tracked
  acquire_interval_ms: 10 # while a body is lost, acquisition runs at most this often (capture clock)
  min_fusion_interval_ms: 2.0  # rate limit of motion-compensated fusions for many fast cameras: a fusion
                          #   is skipped when the last one is younger than this and another camera's
                          #   next frame is due within it (so it lands at the end of a burst); 0 = off
  kalman:
    jerk_psd: 0.1              # m^2/s^5, floor of the white-jerk density (constant-acceleration model)
    angular_accel_psd: 1.0     # rad^2/s^3, floor of the white angular-acceleration density
    max_noise_scale: 10000     # the innovation-driven (NIS) adaptation may raise both by up to this factor
    nis_time_constant_ms: 15   # averaging time of the NIS that drives the adaptation
    marker_sigma_m: 0.0001     # floor of the per-marker 3D noise used for the measurement covariance
    gate_chi2: 40.0            # Mahalanobis^2 gate on the 6-dof innovation (chi2 with 6 dof)
    reset_after_ms: 60         # measurements gated out for this long: the filter restarts at the measurement
    max_prediction_ms: 50      # tick() predicts at most this far past the last update, else tracked=False
    lost_timeout_ms: 150       # no accepted measurement for this long: the body is lost and re-identified
The output rate is the server's (tick() is called by it).
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from visionpos.config.arena import ArenaConfig, ConfigError
from visionpos.jit import COMPILED, cross3, dot3, matmul3, matvec3, njit
from visionpos.camera.model import undistort_pixels
from visionpos.fusion.matching import Projector, associate_blobs, match_unlabeled, project_points, triangulate_irls
from visionpos.messages import BlobFrame, BodyState, LoosePoints
from visionpos.fusion.rigidbody import BodyModel, identify, layout_ambiguities
from visionpos.geometry.alignment import kabsch_horn_compiled
from visionpos.fusion.settings import parse_fusion_settings
from visionpos.fusion.timealign import MOTION_COMPENSATED, Group, TimeAligner
from visionpos.fusion.tracking import (
    CLOCK_T, BodyFilter, FilterBank, array_field, filter_initialize, filter_update, predict_mean,
    report_image_nis,
)


# the image-space manoeuvre detector samples at most this often (capture clock)
_IMAGE_NIS_INTERVAL_NS = 2_000_000

# motion compensation starts once the filter's velocity std is below this (m/s)
_COMPENSATE_MAX_VEL_STD = 0.3


@dataclass
class _Obs:
    """Newest frame of one camera after association.

    xn: (N, 2) normalised coordinates; label: (N,) global marker index or -1;
    marker_xn: (P, 2) observation of every configured marker (NaN = none).
    """

    capture_ns: int
    xn: np.ndarray
    label: np.ndarray
    marker_xn: np.ndarray


# per-body track state, one row per body: FusionPipeline._ti (int64) and _tf (float64) columns
_LAST_UPDATE, _LAST_CAPTURE, _N_MARKERS, _N_CAMERAS, _FIRST_REJECT, _TRACKED, _RESETS = range(7)
_PX_VAR, _MARKER_VAR, _RESIDUAL_MM = range(3)
_NO_TIME = np.iinfo(np.int64).min  # _FIRST_REJECT: no measurement rejected since the last accepted one
_PX_VAR_PRIOR = 0.25  # px^2, per-axis pixel noise before any residual is seen
# _fuse_tracked's verdict per tracked body, and the columns of its measurement rows (one array:
# each array a kernel returns costs a few microseconds to hand to Python)
_TOO_FEW, _FIT_REJECTED, _ACCEPTED, _GATED, _RESET = range(5)
_M_ROT, _M_POS, _M_COV = slice(0, 9), slice(9, 12), slice(12, 48)  # R (3, 3), t (3,), covariance (6, 6)
_M_MARKERS, _M_CAMERAS, _M_FIT = 48, 49, 50  # markers used, cameras, fit RMS (m)


class _Track:
    """One body's tracking state: views of its rows of the pipeline's track arrays, and its filter."""

    tracked = array_field("i", _TRACKED, bool)
    last_update_ns = array_field("i", _LAST_UPDATE, int, "reference time of the last accepted measurement")
    last_capture_ns = array_field("i", _LAST_CAPTURE, int, "newest capture time in it")
    n_markers = array_field("i", _N_MARKERS, int)
    n_cameras = array_field("i", _N_CAMERAS, int)
    reset_counter = array_field("i", _RESETS, int)
    px_var = array_field("f", _PX_VAR, float, "running per-axis pixel noise variance (px^2) from triangulation residuals")
    marker_var = array_field("f", _MARKER_VAR, float, "running per-marker 3D noise variance (m^2) from fit residuals")
    residual_mm = array_field("f", _RESIDUAL_MM, float)

    def __init__(self, filter: BodyFilter, i: np.ndarray, f: np.ndarray):
        self.filter = filter
        self.i = i  # (7,) int64 row
        self.f = f  # (3,) float64 row

    @property
    def first_reject_ns(self) -> int | None:
        """When the filter began rejecting measurements (None: the last one was accepted)."""
        v = int(self.i[_FIRST_REJECT])
        return None if v == _NO_TIME else v

    @first_reject_ns.setter
    def first_reject_ns(self, value: int | None) -> None:
        self.i[_FIRST_REJECT] = _NO_TIME if value is None else value


@njit
def _inv3(A: np.ndarray) -> np.ndarray:
    """Inverse of a 3x3 matrix by the adjugate."""
    C = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            i1, i2, j1, j2 = (j + 1) % 3, (j + 2) % 3, (i + 1) % 3, (i + 2) % 3
            C[i, j] = A[i1, j1] * A[i2, j2] - A[i1, j2] * A[i2, j1]  # cofactor of A[j, i]
    return C / (A[0, 0] * C[0, 0] + A[0, 1] * C[1, 0] + A[0, 2] * C[2, 0])


@njit
def pose_measurement_cov(markers_world: np.ndarray, origin: np.ndarray, var: float) -> np.ndarray:
    """Covariance (6, 6) over [p, world rotation vector] of a Kabsch pose.

    markers_world: (n, 3) fitted marker positions, n >= 3 not collinear;
    origin: (3,) body origin; var: per-marker, per-axis noise variance (m^2).
    Small-error, equal weights.
    """
    n = markers_world.shape[0]
    c = np.zeros(3)
    for m in range(n):
        c += markers_world[m]
    c /= n
    J = np.zeros((3, 3))  # inertia-like sum (|r|^2 I - r r^T)
    for m in range(n):
        r = markers_world[m] - c
        rr = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
        for i in range(3):
            J[i, i] += rr
            for j in range(3):
                J[i, j] -= r[i] * r[j]
    Crot = var * _inv3(J)
    o = origin - c
    ox = np.array([[0.0, -o[2], o[1]], [o[2], 0.0, -o[0]], [-o[1], o[0], 0.0]])
    oxC = matmul3(ox, Crot)
    C = np.empty((6, 6))
    C[0:3, 0:3] = matmul3(oxC, ox.T)
    for i in range(3):
        C[i, i] += var / n
    C[0:3, 3:6] = -oxC
    C[3:6, 0:3] = -oxC.T
    C[3:6, 3:6] = Crot
    return C


@njit
def _marker_motion(states, sizes, local):
    """Marker positions, velocities and accelerations (P, 3) each, world, of B bodies.

    states (B, 27): filter states as _pack_states packs them, predicted by their
    state_dt; sizes (B,): marker counts; local (P, 3): body-frame markers, body
    by body. Includes the rotation's w x r and w x (w x r) terms.
    """
    P = local.shape[0]
    X0 = np.empty((P, 3))
    V = np.empty((P, 3))
    A = np.empty((P, 3))
    q = 0
    for b in range(sizes.shape[0]):
        x = states[b, 0:15]
        w = x[12:15]
        p, Rb, v = predict_mean(x, states[b, 15:24].reshape((3, 3)), states[b, 24])
        for _ in range(sizes[b]):
            r = matvec3(Rb, local[q])  # lever arm, world
            wxr = cross3(w, r)
            X0[q] = p + r
            V[q] = v + wxr
            A[q] = x[6:9] + cross3(w, wxr)
            q += 1
    return X0, V, A


@njit
def _pack_states(x, P, R_nom, clock, bodies, t_ns):
    """The kernels' packed input (B, 27) for the filters `bodies` (B,) of a FilterBank
    (x, P, R_nom, clock): per body its state x (15), R_nom (9, row-major), t_ns - filter
    time (s), mean velocity variance and mean angular-rate variance."""
    out = np.empty((bodies.shape[0], 27))
    for i in range(bodies.shape[0]):
        b = bodies[i]
        out[i, 0:15] = x[b]
        for r in range(3):
            for c in range(3):
                out[i, 15 + 3 * r + c] = R_nom[b, r, c]
        out[i, 24] = (t_ns - clock[b, CLOCK_T]) * 1e-9
        out[i, 25] = (P[b, 3, 3] + P[b, 4, 4] + P[b, 5, 5]) / 3.0
        out[i, 26] = (P[b, 12, 12] + P[b, 13, 13] + P[b, 14, 14]) / 3.0
    return out


@njit
def _tracked_motion(x, P, R_nom, clock, tracked, sizes, local):
    """The newest filter time t_c of the bodies `tracked` (B,) of a FilterBank (x, P, R_nom,
    clock) and their markers' positions, velocities and accelerations there, (3, P, 3)
    (_marker_motion; sizes (B,), local (P, 3) as there)."""
    t_c = clock[tracked[0], CLOCK_T]
    for i in range(tracked.shape[0]):
        t_c = max(t_c, clock[tracked[i], CLOCK_T])
    motion = np.empty((3, local.shape[0], 3))
    motion[0], motion[1], motion[2] = _marker_motion(_pack_states(x, P, R_nom, clock, tracked, t_c), sizes, local)
    return t_c, motion


@njit
def _finite_rows(px):
    """px (N, 2) itself when every row is finite, else a copy of its finite rows."""
    keep = np.empty(px.shape[0], dtype=np.bool_)
    n = 0
    for j in range(px.shape[0]):
        keep[j] = np.isfinite(px[j, 0]) and np.isfinite(px[j, 1])
        n += keep[j]
    return px if n == px.shape[0] else px[keep]


@njit
def _observe_frame(px, dt, motion, rows, marker_xn, camera, gate, image_nis, t_ns, tracked, body, tf, P, adapt, clock,
                   kalman):
    """One camera frame against the tracked bodies' predicted markers (compiled).

    px (N, 2) blob pixels; motion (3, M, 3): the tracked markers' positions X0, velocities V
    and accelerations A (_tracked_motion), so X0 + dt V + dt^2 / 2 A is where they are at the
    frame's capture time t_ns; rows (M,): their global rows; camera: the camera packed as
    matching.Projector.packed (pose, lens, visibility limit); gate px. Fills marker_xn (P, 2), each marker's
    observation (NaN = none). Returns normalised blobs xn (N, 2) and blob labels (N,)
    (global marker row or -1).

    image_nis: also feed each tracked body's manoeuvre detector (tracking.report_image_nis)
    with this frame's prediction residual over its expected size (_image_nis). tracked
    (B,): the bodies, body (M,): the index in it of each marker row; tf: the track rows
    (pixel variance); P, adapt, clock, kalman: the FilterBank's.
    """
    R, t, intrinsics, dist = camera[0:9].reshape((3, 3)), camera[9:12], camera[12:18], camera[18:26]
    fisheye, cos_max = camera[27] != 0.0, camera[26]
    xn = undistort_pixels(px, intrinsics, dist, fisheye)
    Xw = motion[0] + dt * (motion[1] + (0.5 * dt) * motion[2])
    pred = project_points(Xw, R, t, intrinsics, dist, fisheye, cos_max, gate)
    a = associate_blobs(pred, px, gate * gate)
    label = np.full(px.shape[0], -1, dtype=np.int64)
    marker_xn[:, :] = np.nan
    for q in range(a.shape[0]):
        if a[q] >= 0:
            label[a[q]] = rows[q]
            marker_xn[rows[q], 0] = xn[a[q], 0]
            marker_xn[rows[q], 1] = xn[a[q], 1]
    if image_nis:
        # expected: the body's pixel noise plus its position uncertainty seen from this camera
        B = tracked.shape[0]
        exp_px = np.empty(B)
        exp_pos = np.empty(B)
        for i in range(B):
            b = tracked[i]
            exp_px[i] = tf[b, _PX_VAR]
            exp_pos[i] = (P[b, 0, 0] + P[b, 1, 1] + P[b, 2, 2]) / 3.0
        nis, n = _image_nis(Xw, pred, px, a, body, exp_px, exp_pos, R[2], t[2], math.sqrt(intrinsics[0] * intrinsics[1]))
        for i in range(B):
            if n[i] >= 2:
                b = tracked[i]
                report_image_nis(adapt[b], clock[b], kalman, t_ns, nis[i])
    return xn, label


@njit
def _scaled_pose_cov(cov_unit, var, var_p, var_r):
    """cov_unit (6, 6) * var, plus var_p on the position and var_r on the rotation diagonal."""
    C = cov_unit * var
    for i in range(3):
        C[i, i] += var_p
        C[3 + i, 3 + i] += var_r
    return C


@njit
def _image_nis(Xw, pred, px, a, body, exp_px, exp_pos, R2, t2, f):
    """One frame's prediction residual per body over its expected size, per degree of freedom.

    Xw (P, 3) predicted markers, pred (P, 2) their pixels, px (N, 2) blobs, a (P,)
    associated blob or -1, body (P,) body of each row; per body (B,): pixel noise
    variance exp_px and position variance exp_pos; R2 (3,), t2, f: the camera's
    optical-axis row, its translation and focal length (depth -> pixels).
    Returns mean NIS (B,) and the number of markers behind it (B,).
    """
    B = exp_px.shape[0]
    nis = np.zeros(B)
    n = np.zeros(B, dtype=np.int64)
    for q in range(a.shape[0]):
        j = a[q]
        if j < 0:
            continue
        b = body[q]
        z = max(Xw[q, 0] * R2[0] + Xw[q, 1] * R2[1] + Xw[q, 2] * R2[2] + t2, 0.1)
        du, dv = px[j, 0] - pred[q, 0], px[j, 1] - pred[q, 1]
        nis[b] += (du * du + dv * dv) / (2.0 * (exp_px[b] + f * f * exp_pos[b] / (z * z)))
        n[b] += 1
    for b in range(B):
        if n[b] > 0:
            nis[b] /= n[b]
    return nis, n


@njit
def _tracked_measurements(marker_xn, views, rows, R, t, f, dt, states, compensate, sizes, local, params):
    """Pose measurements of the tracked bodies from one fusion of V views (compiled).

    marker_xn (cameras, all markers, 2): each camera's normalised observation of each
    marker (NaN = none); views (V,): the fused cameras' indices in it; rows (P,): the
    tracked bodies' marker rows, body by body. R (V, 3, 3), t (V, 3), f (V,): the views;
    dt (V,): view capture - reference (s). states (B, 27): per body its filter state as
    _pack_states packs it (x, R_nom, reference - filter time, velocity and rate
    variance); sizes (B,) marker counts; local (P, 3) body-frame markers of the rows.
    compensate: motion compensation on (velocity-gated per body). params: max
    residual px, identification tolerance m, the velocity variance below which a body
    is compensated.

    Returns per body: R (B, 3, 3), t (B, 3), markers used (B,), fit residual sum
    of squares (B,), cameras seeing it (B,), pixel-variance sample (B,), unit-variance
    pose covariance (B, 6, 6), motion variance added to position / rotation (B,),
    fit tolerance (B,); and the number of points refused by the residual gate.
    """
    max_residual_px, identify_tolerance, compensate_max_vel_var = params[0], params[1], params[2]
    P, V = rows.shape[0], views.shape[0]
    xn = np.empty((P, V, 2))
    for q in range(P):
        for v in range(V):
            xn[q, v, 0] = marker_xn[views[v], rows[q], 0]
            xn[q, v, 1] = marker_xn[views[v], rows[q], 1]
    B = sizes.shape[0]
    dt2_mean = 0.0
    dt_max = 0.0
    centre = np.zeros(3)
    f_mean = 0.0
    for v in range(V):
        dt2_mean += dt[v] * dt[v] / V
        dt_max = max(dt_max, abs(dt[v]))
        f_mean += f[v] / V
        for i in range(3):
            for j in range(3):
                centre[i] -= R[v, j, i] * t[v, j] / V  # mean camera centre: a px-per-metre scale
    vel = np.zeros((B, 3))
    acc = np.zeros((B, 3))
    rate = np.zeros((B, 3))
    Rb = np.empty((B, 3, 3))
    var_p = np.empty(B)
    var_r = np.empty(B)
    gate = np.empty(B)
    fit_tol = np.empty(B)
    moving = False
    for b in range(B):
        x = states[b, 0:15]
        sv2, sw2 = states[b, 25], states[b, 26]
        w = x[12:15]
        p, Rb[b], v = predict_mean(x, states[b, 15:24].reshape((3, 3)), states[b, 24])
        if compensate and sv2 < compensate_max_vel_var:
            vel[b], acc[b], rate[b] = v, x[6:9], w
            moving = moving or np.any(v != 0.0) or np.any(x[6:9] != 0.0) or np.any(w != 0.0)
            var_p[b], var_r[b] = dt2_mean * sv2, dt2_mean * sw2
            spread = 2.0 * math.sqrt(sv2)
        else:
            # velocity not known well enough (or naive mode): compensating with a wrong one
            # would bias the measurement towards it (a feedback loop); the views are treated
            # as simultaneous and the motion between them counts as measurement noise
            vv, ww = dot3(v, v), dot3(w, w)
            var_p[b], var_r[b] = dt2_mean * (vv + sv2), dt2_mean * (ww + sw2)
            spread = math.sqrt(vv) + 2.0 * math.sqrt(sv2)
        d = p - centre
        # residual gate widened by the motion the views may still disagree by
        gate[b] = max_residual_px + f_mean * spread * dt_max / max(math.sqrt(dot3(d, d)), 0.5)
        fit_tol[b] = identify_tolerance + spread * dt_max  # the rigid fit may disagree as much
    body = np.empty(P, dtype=np.int64)
    k = 0
    for b in range(B):
        body[k : k + sizes[b]] = b
        k += sizes[b]
    has_offsets = compensate and dt_max > 0.0 and moving
    offsets = np.zeros((P if has_offsets else 0, V, 3))
    if has_offsets:
        for q in range(P):
            b = body[q]
            r = matvec3(Rb[b], local[q])  # lever arm, world
            wxr = cross3(rate[b], r)
            u1 = vel[b] + wxr
            u2 = 0.5 * (acc[b] + cross3(rate[b], wxr))
            for v in range(V):  # marker displacement from ref to the view's capture time (2nd order)
                offsets[q, v] = u1 * dt[v] + u2 * (dt[v] * dt[v])
    X, rms, nv = triangulate_irls(xn, R, t, f, offsets, has_offsets, 2)
    w_fit = np.zeros(P)
    refused = 0
    for q in range(P):
        if nv[q] >= 2:
            if rms[q] < gate[body[q]]:
                w_fit[q] = nv[q]  # more rays, better-conditioned point
            else:
                refused += 1
    Rk = np.empty((B, 3, 3))
    tk = np.empty((B, 3))
    count = np.zeros(B, dtype=np.int64)
    res2 = np.zeros(B)
    n_cams = np.zeros(B, dtype=np.int64)
    px_var = np.zeros(B)
    cov = np.full((B, 6, 6), np.nan)
    k = 0
    for b in range(B):
        s = slice(k, k + sizes[b])
        Rk[b], tk[b] = kabsch_horn_compiled(local[s], X[s], w_fit[s])
        for v in range(V):
            for q in range(k, k + sizes[b]):
                if not np.isnan(xn[q, v, 0]):
                    n_cams[b] += 1
                    break
        fitted = np.empty((sizes[b], 3))
        n = 0
        for q in range(k, k + sizes[b]):
            if w_fit[q] > 0:
                fitted[n] = matvec3(Rk[b], local[q]) + tk[b]
                e = X[q] - fitted[n]
                res2[b] += dot3(e, e)
                # (the fitted point absorbs 3 of the 2 nv residual dof: E[rms^2] = sigma^2 (2 nv - 3) / nv)
                px_var[b] += rms[q] * rms[q] * nv[q] / (2.0 * nv[q] - 3.0)
                n += 1
        count[b] = n
        if n >= 3:
            px_var[b] /= n
            cov[b] = pose_measurement_cov(fitted[:n], tk[b], 1.0)
        k += sizes[b]
    return Rk, tk, count, res2, n_cams, px_var, cov, var_p, var_r, fit_tol, refused


@njit
def _track_measured(ti, tf, ref, cap, n, n_cams, fit_rms):
    """Record a measurement the filter took (or restarted at) in one body's track rows ti (7,),
    tf (3,): reference time ref, newest capture time cap, markers n, cameras n_cams, fit RMS (m)."""
    ti[_FIRST_REJECT] = _NO_TIME
    ti[_LAST_UPDATE] = ref
    ti[_LAST_CAPTURE] = cap
    ti[_N_MARKERS] = n
    ti[_N_CAMERAS] = n_cams
    tf[_RESIDUAL_MM] = fit_rms * 1e3


@njit
def _fuse_tracked(marker_xn, views, capture_ns, ref, R, t, f, tracked, rows, sizes, local, params, compensate, reuse,
                  x, P, R_nom, adapt, clock, kalman, ti, tf):
    """One fusion for the tracked bodies: pose measurements, their covariances and the
    filter updates, in place (compiled).

    marker_xn, views, R, t, f, rows, sizes, local, compensate: as _tracked_measurements;
    capture_ns (cameras,): each camera's newest capture time; ref: reference time (ns);
    tracked (B,): the bodies; params: _tracked_measurements' then the fewest markers for
    a pose, the floor of the per-marker variance (m^2) and how long (ns) a filter may
    reject measurements before it restarts at them; reuse: fusions that share each
    frame (multiplies the measurement covariance); x, P, R_nom, adapt, clock, kalman: the
    FilterBank's arrays and params; ti (bodies, 7), tf (bodies, 3): the track rows.

    Returns per tracked body its verdict (B,) (_TOO_FEW, _FIT_REJECTED, _ACCEPTED,
    _GATED, _RESET: the filter restarted at the measurement) and its measurement
    (B, 51) (columns _M_*: pose R and t, its covariance, markers used, cameras, fit RMS
    in m); the number of points refused by the residual gate; and, for the next frames,
    _tracked_motion after the updates (t_c, motion (3, P, 3)).
    """
    V = views.shape[0]
    dt = np.empty(V)
    cap = capture_ns[views[0]]
    for v in range(V):
        dt[v] = (capture_ns[views[v]] - ref) * 1e-9
        cap = max(cap, capture_ns[views[v]])
    Rk, tk, counts, res2, n_cams, px_var, cov_unit, var_p, var_r, fit_tol, refused = _tracked_measurements(
        marker_xn, views, rows, R, t, f, dt, _pack_states(x, P, R_nom, clock, tracked, ref), compensate, sizes,
        local, params)
    B = tracked.shape[0]
    verdict = np.full(B, _TOO_FEW, dtype=np.int64)
    meas = np.zeros((B, 51))
    for i in range(B):
        meas[i, _M_ROT] = Rk[i].ravel()
        meas[i, _M_POS] = tk[i]
        meas[i, _M_MARKERS] = counts[i]
        meas[i, _M_CAMERAS] = n_cams[i]
        n = counts[i]
        if n < params[3]:
            meas[i, _M_FIT] = np.nan
            continue
        fit = meas[i, _M_FIT] = math.sqrt(res2[i] / n)
        if fit > fit_tol[i]:
            verdict[i] = _FIT_REJECTED
            continue
        b = tracked[i]
        # pixel noise from the triangulation residuals of its markers; per-marker 3D noise
        # from the fit residual (3n - 6 degrees of freedom); both running averages per body
        tf[b, _PX_VAR] += 0.05 * (px_var[i] - tf[b, _PX_VAR])
        tf[b, _MARKER_VAR] += 0.05 * (res2[i] / (3 * n - 6) - tf[b, _MARKER_VAR])
        # reused frames: split their information over the fusions that share them
        cov = _scaled_pose_cov(cov_unit[i], max(tf[b, _MARKER_VAR], params[4]) * reuse, var_p[i], var_r[i])
        meas[i, _M_COV] = cov.ravel()
        accepted, _ = filter_update(x[b], P[b], R_nom[b], adapt[b], clock[b], kalman, ref, tk[i], Rk[i], cov, True)
        if accepted:
            verdict[i] = _ACCEPTED
        else:
            if ti[b, _FIRST_REJECT] == _NO_TIME:
                ti[b, _FIRST_REJECT] = ref
            if ref - ti[b, _FIRST_REJECT] < params[5]:
                verdict[i] = _GATED
                continue
            # persistently inconsistent: believe the measurements, restart the filter there
            filter_initialize(x[b], P[b], R_nom[b], adapt[b], clock[b], kalman, ref, tk[i], Rk[i], cov)
            ti[b, _RESETS] += 1
            verdict[i] = _RESET
        _track_measured(ti[b], tf[b], ref, cap, n, n_cams[i], fit)
    t_c, motion = _tracked_motion(x, P, R_nom, clock, tracked, sizes, local)
    return verdict, meas, refused, t_c, motion


log = logging.getLogger(__name__)
_warm = [False]  # kernels compiled (or loaded) in this process


def warm_up_kernels(arena: ArenaConfig, settings: dict[str, Any] | None = None) -> None:
    """Compile every kernel of the fusion path (or load it from numba's disk cache) now.

    The first compilation after an install takes tens of seconds; done lazily
    it would stall the server on its first packets. A throwaway pipeline over
    a synthetic hover of the first body, in front of the arena's cameras,
    runs the real code path, so each kernel meets exactly the argument types
    it will see. With no body visible to two cameras the rest compiles on
    first use.
    """
    if not arena.bodies:
        return
    cams = list(arena.cameras)
    # the point closest to every optical axis: where the cameras look
    A = np.zeros((3, 3))
    rhs = np.zeros(3)
    for c in cams:
        d = c.R[2]  # optical axis, world
        M = np.eye(3) - np.outer(d, d)
        A += M
        rhs += M @ (-c.R.T @ c.t)
    try:
        centre = np.linalg.solve(A, rhs)
    except np.linalg.LinAlgError:
        return
    markers = np.asarray(arena.bodies[0].markers, dtype=np.float64) + centre
    pipe = FusionPipeline(arena, settings, warm_up=False)
    notice = threading.Timer(2.0, lambda: log.warning(
        "compiling the fusion kernels: the first run after installing takes about a minute; "
        "later runs load them from numba's cache"))
    notice.daemon = True
    notice.start()
    views = []
    for c in cams:
        uv = Projector(c).project(markers)
        uv = uv[np.isfinite(uv[:, 0])]
        views.append(np.column_stack([uv, np.full(len(uv), 12.0), np.full(len(uv), 200.0)]).astype(np.float32))
    try:
        for k in range(12):
            for i, (c, blobs) in enumerate(zip(cams, views)):
                pipe.push(BlobFrame(c.id, k, 1_000_000_000 + k * 10_000_000 + i * 1_000_000, blobs))
            pipe.tick(1_000_000_000 + k * 10_000_000 + 9_000_000)
    finally:
        notice.cancel()


class FusionPipeline:
    """Asynchronous multi-camera fusion into filtered rigid-body poses (see module docstring)."""

    def __init__(self, arena: ArenaConfig, settings: dict[str, Any] | None = None, warm_up: bool = True):
        self.arena = arena
        if len(arena.cameras) < 2:
            raise ConfigError(arena.source, "cameras", f"fusion needs at least 2 cameras, the arena has "
                              f"{len(arena.cameras)}; add the calibrated cameras (`visionpos calibrate wand` writes them)")
        self.settings = parse_fusion_settings(arena, settings)
        st = self.settings
        self.models = [BodyModel(b.name, b.id, np.asarray(b.markers, float)) for b in arena.bodies]
        # layouts the geometry cannot tell apart would be swapped or flipped: refuse them
        problems = layout_ambiguities(self.models, 0.5 * st.identify_tolerance)
        if problems:
            raise ConfigError(
                arena.source, "bodies", "; ".join(problems) + ". Move a marker so every body's distances differ by > 1 cm."
            )
        sizes = [len(m.markers) for m in self.models]
        self._off = np.concatenate([[0], np.cumsum(sizes)]).astype(int)  # body b: markers off[b]:off[b+1]
        self.P = int(self._off[-1])
        self._marker_body = np.repeat(np.arange(len(self.models)), sizes)
        self._marker_local = np.concatenate([m.markers for m in self.models]) if self.models else np.zeros((0, 3))
        # cameras: stacked poses, indexed by the kernels
        self.cameras = {c.id: c for c in arena.cameras}
        self._cam_index = {c.id: i for i, c in enumerate(arena.cameras)}
        self._R = np.array([c.R for c in arena.cameras]).reshape(-1, 3, 3)
        self._t = np.array([c.t for c in arena.cameras]).reshape(-1, 3)
        self._f = np.array([np.sqrt(c.model.fx * c.model.fy) for c in arena.cameras])
        self._proj = {c.id: Projector(c) for c in arena.cameras}
        self._layout_cache: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        self._gate_px = float(st.match_gate_px)
        self._kernel_params = np.array([st.max_residual_px, st.identify_tolerance, _COMPENSATE_MAX_VEL_STD**2,
                                        st.min_markers, st.marker_sigma**2, st.reset_after_ns])
        self._view_cache: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        self.aligner = TimeAligner(
            st.time_alignment,
            st.window_ns,
            st.grid_ns,
            st.max_clock_lead_ns,
            periods_ns={c.id: int(1e9 / c.fps) for c in arena.cameras if c.fps > 0},
            min_interval_ns=st.min_fusion_interval_ns,
        )
        self.obs: dict[int, _Obs] = {}
        # each camera's newest observation of every marker (NaN = none); _Obs.marker_xn is its row,
        # so a fusion reads its views without stacking them
        self._marker_xn = np.full((len(arena.cameras), self.P, 2), np.nan)
        self._capture_ns = np.zeros(len(arena.cameras), dtype=np.int64)  # each camera's newest frame
        # per-body state in arrays the kernels update in place; tracks[b] is a view of row b
        self.bank = FilterBank(len(self.models), st.kalman)
        self._ti = np.zeros((len(self.models), 7), dtype=np.int64)
        self._ti[:, _FIRST_REJECT] = _NO_TIME
        self._tf = np.zeros((len(self.models), 3))
        self._tf[:, _PX_VAR] = _PX_VAR_PRIOR
        self._tf[:, _RESIDUAL_MM] = np.nan
        self.tracks = [_Track(fl, self._ti[b], self._tf[b]) for b, fl in enumerate(self.bank.filters)]
        self._motion: tuple[int, np.ndarray] | None = None  # see _motion_cache
        self._tracking_changed()
        self.loose_points: LoosePoints | None = None
        self._last_acquire_ns = -(1 << 62)
        self._last_img_ns = -(1 << 62)
        # a frame takes part in about (frame period / fusion spacing) fusions at most
        self._max_reuse = max(1.0, (st.window_ns / 1.2) / max(st.min_fusion_interval_ns, 1))
        self.last_raw: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}  # body -> (ref_ns, position, R) of the last Kabsch pose
        self._stats: dict[str, int] = {
            "frames": 0,
            "fusions": 0,
            "deferred": 0,
            "measurements": 0,
            "rejected_gate": 0,
            "rejected_residual": 0,
            "rejected_fit": 0,
            "unknown_camera": 0,
            "malformed": 0,
            "clock_jump": 0,
            "late": 0,
            "reordered": 0,
            "removed_camera": 0,
            "acquisitions": 0,
            "lost": 0,
            "filter_resets": 0,
        }
        self._per_camera: dict[int, int] = {}
        if warm_up and COMPILED and not _warm[0]:
            _warm[0] = True
            warm_up_kernels(arena, settings)

    # ------------------------------------------------------------------ input
    def push(self, frame: BlobFrame) -> None:
        """Take one camera frame (arrival order) and do the fusion work it enables."""
        self._stats["frames"] += 1
        cam = int(frame.camera_id)
        if cam not in self.cameras:
            self._stats["unknown_camera"] += 1
            return
        self._per_camera[cam] = self._per_camera.get(cam, 0) + 1
        blobs = np.asarray(frame.blobs)
        if blobs.ndim != 2 or (blobs.shape[0] and blobs.shape[1] < 2):
            self._stats["malformed"] += 1
            return
        px = _finite_rows(blobs[:, :2].astype(np.float64))
        t = int(frame.capture_ns)
        why = self.aligner.admit(cam, t)
        if why is not None:
            self._stats[why] += 1
            return
        before, after = self.aligner.add(cam, t)
        if self.aligner.mode == MOTION_COMPENSATED and not after:
            self._stats["deferred"] += 1
        for g in before:
            self._fuse(g)
        self.obs[cam] = self._observe(cam, t, px)
        for g in after:
            self._fuse(g)

    def remove_camera(self, camera_id: int) -> None:
        """A station vanished: stop using and waiting for its frames."""
        if camera_id in self.obs or camera_id in self.aligner.latest:
            self._stats["removed_camera"] += 1
        self.obs.pop(camera_id, None)
        self.aligner.remove(camera_id)

    # ------------------------------------------------------------ association
    def _tracking_changed(self) -> None:
        """Refresh the tracked-body set after a body was acquired or lost."""
        self._tracked = tuple(int(b) for b in np.flatnonzero(self._ti[:, _TRACKED]))
        self._tracked_idx = np.array(self._tracked, dtype=np.int64)
        # by blob label: free for acquisition unless a marker of a tracked body (label -1: the last entry)
        self._label_free = np.append(self._ti[self._marker_body, _TRACKED] == 0, True)
        self._motion = None

    def _motion_cache(self) -> tuple[int, np.ndarray]:
        """(t_c, motion (3, sum M_b, 3)): the tracked bodies' marker positions, velocities and
        accelerations at t_c, the newest filter time.

        The filters change only in fusions, and each fusion with tracked bodies
        leaves this for the next frames (_fuse_tracked), so each frame only
        evaluates X0 + dt V + dt^2 / 2 A (error ~ r (w dt)^3 / 6, micrometres).
        It is computed here after the tracked set changed.
        """
        if self._motion is None:
            bank = self.bank
            _, sizes, _, local = self._layout(self._tracked)
            t_c, motion = _tracked_motion(bank.x, bank.P, bank.R_nom, bank.clock, self._tracked_idx, sizes, local)
            self._motion = (int(t_c), motion)
        return self._motion

    def _observe(self, cam: int, t_ns: int, px: np.ndarray) -> _Obs:
        proj = self._proj[cam]
        v = self._cam_index[cam]
        self._capture_ns[v] = t_ns
        marker_xn = self._marker_xn[v]  # this camera's row of the shared array
        if not self._tracked or not len(px):
            marker_xn[:] = np.nan
            return _Obs(t_ns, proj.undistort(px), np.full(len(px), -1, dtype=np.int64), marker_xn)
        rows, _, body, _ = self._layout(self._tracked)
        t_c, motion = self._motion_cache()
        # the image-space manoeuvre detector: plenty often for a detector, and saves CPU
        image_nis = abs(t_ns - self._last_img_ns) >= _IMAGE_NIS_INTERVAL_NS
        if image_nis:
            self._last_img_ns = t_ns
        bank = self.bank
        xn, label = _observe_frame(
            px, (t_ns - t_c) * 1e-9, motion, rows, marker_xn, proj.packed, self._gate_px, image_nis, t_ns,
            self._tracked_idx, body, self._tf, bank.P, bank.adapt, bank.clock, bank.params,
        )
        return _Obs(t_ns, xn, label, marker_xn)

    # ----------------------------------------------------------------- fusion
    def _views(self, cams: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Camera indices (V,) of `cams` and their R (V, 3, 3), t (V, 3), f (V,) (cached per set)."""
        v = self._view_cache.get(cams)
        if v is None:
            vi = np.array([self._cam_index[c] for c in cams], dtype=np.int64)
            v = self._view_cache[cams] = (vi, self._R[vi], self._t[vi], self._f[vi])
        return v

    def _fuse(self, g: Group) -> None:
        obs = self.obs
        cams = g.cameras
        if not all(c in obs for c in cams):
            cams = tuple(c for c in cams if c in obs)
            if not cams:
                return
        st = self.settings
        ref = g.ref_ns
        self._stats["fusions"] += 1
        vi, R, t, f = self._views(cams)
        if self._tracked:
            self._update_tracked(cams, vi, R, t, f, ref, g.compensate)
        # acquisition is for lost bodies; with all tracked it only refreshes the loose points
        lost = len(self._tracked) < len(self.tracks)
        interval = st.acquire_interval_ns if lost else st.loose_points_interval_ns
        if (lost or st.loose_points) and (ref - self._last_acquire_ns >= interval or ref < self._last_acquire_ns):
            self._last_acquire_ns = ref
            self._acquire([obs[c] for c in cams], R, t, f, ref)
        # lost-track bookkeeping on the capture clock
        ti = self._ti
        gone = [b for b in self._tracked if ref - ti[b, _LAST_UPDATE] > st.lost_timeout_ns]
        if gone:
            ti[gone, _TRACKED] = 0
            self._stats["lost"] += len(gone)
            self._tracking_changed()

    def _layout(self, tracked: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For a set of tracked bodies (cached): global marker rows (P,), marker counts (B,),
        for each marker row the index of its body in `tracked` (P,), and the body-frame
        markers of the rows (P, 3)."""
        key = tuple(tracked)
        lay = self._layout_cache.get(key)
        if lay is None:
            sizes = np.array([self._off[b + 1] - self._off[b] for b in tracked], dtype=np.int64)
            rows = np.concatenate([np.arange(self._off[b], self._off[b + 1]) for b in tracked])
            lay = (rows, sizes, np.repeat(np.arange(len(tracked)), sizes), self._marker_local[rows])
            self._layout_cache[key] = lay
        return lay

    def _update_tracked(self, cams: tuple[int, ...], vi, R, t, f, ref: int, compensate: bool) -> None:
        tracked = self._tracked
        rows, sizes, _, local = self._layout(tracked)
        bank = self.bank
        reuse = min(len(cams), self._max_reuse) if compensate else 1.0
        verdict, meas, refused, t_c, motion = _fuse_tracked(
            self._marker_xn, vi, self._capture_ns, ref, R, t, f, self._tracked_idx, rows, sizes, local,
            self._kernel_params, bool(compensate), float(reuse), bank.x, bank.P, bank.R_nom, bank.adapt, bank.clock,
            bank.params, self._ti, self._tf,
        )
        # the filters moved: the next frames predict their markers from this fusion
        self._motion = (int(t_c), motion)
        stats = self._stats
        stats["rejected_residual"] += int(refused)
        for i, b in enumerate(tracked):
            v = verdict[i]
            if v == _FIT_REJECTED:
                stats["rejected_fit"] += 1
            elif v >= _ACCEPTED:
                m = meas[i]
                self.last_raw[b] = (ref, m[_M_POS], m[_M_ROT].reshape(3, 3))
                if v != _ACCEPTED:
                    stats["rejected_gate"] += 1
                if v != _GATED:
                    stats["measurements"] += 1
                if v == _RESET:
                    stats["filter_resets"] += 1

    def _acquire(self, obs: list[_Obs], R, t, f, ref: int) -> None:
        """Match leftover blobs across views; identify lost bodies; report loose points."""
        st = self.settings
        lost = [b for b in range(len(self.tracks)) if b not in self._tracked]
        if not lost and not st.loose_points:
            return
        free = [np.flatnonzero(self._label_free[o.label]) for o in obs]
        if sum(len(fr) > 0 for fr in free) < 2:
            self.loose_points = LoosePoints(ref, np.zeros((0, 3)), np.zeros(0))
            return
        xs = [o.xn[fr] for o, fr in zip(obs, free)]
        pts, idx, rms = match_unlabeled(xs, R, t, f, st.acquire_ray_distance, st.max_residual_px)
        if not lost or len(pts) < 3:
            self.loose_points = LoosePoints(ref, pts, rms)
            return
        left = np.ones(len(pts), dtype=bool)
        for ident in identify(pts, self.models, st.identify_tolerance, st.min_markers, only=lost):
            b = ident.body
            tr = self.tracks[b]
            matched = ident.point_index >= 0
            n_id = int(matched.sum())
            tr.marker_var = max(ident.rms**2 * n_id / max(n_id - 2, 1), st.marker_sigma**2)
            tr.filter.initialize(ref, ident.t, ident.R, pose_measurement_cov(pts[ident.point_index[matched]], ident.t, tr.marker_var))
            tr.tracked = True
            tr.first_reject_ns = None
            tr.last_update_ns = ref
            tr.last_capture_ns = max(o.capture_ns for o in obs)
            tr.n_markers = ident.n_markers
            tr.residual_mm = ident.rms * 1e3
            self._stats["acquisitions"] += 1
            # label the blobs that made the body in the stored frames, so the
            # next fusions see it in every camera at once
            for m, q in enumerate(ident.point_index):
                if q < 0:
                    continue
                left[q] = False
                for v, o in enumerate(obs):
                    j = idx[q, v]
                    if j >= 0:
                        blob = free[v][j]
                        o.label[blob] = self._off[b] + m
                        o.marker_xn[self._off[b] + m] = o.xn[blob]
            tr.n_cameras = int(sum((o.label >= self._off[b]).any() and (o.label < self._off[b + 1]).any() for o in obs))
            self._tracking_changed()
        self.loose_points = LoosePoints(ref, pts[left], rms[left])

    # ----------------------------------------------------------------- output
    def tick(self, now_ns: int) -> list[BodyState]:
        """One BodyState per configured body, predicted to now_ns; does not change the filters.

        A body not updated within max_prediction (or lost) is reported with
        tracked=False and NaN pose: a stale pose is never re-sent.
        """
        st = self.settings
        out = []
        for b, (model, tr) in enumerate(zip(self.models, self.tracks)):
            last_update, last_capture, n_markers, n_cameras, _, tracked, resets = self._ti[b].tolist()
            age = now_ns - last_update
            if tracked and age <= st.max_prediction_ns and age <= st.lost_timeout_ns:
                p, q, v, w_body, cov, vcov = tr.filter.output_at(now_ns)
                out.append(
                    BodyState(
                        name=model.name,
                        body_id=model.id,
                        time_ns=int(now_ns),
                        capture_ns=last_capture,
                        position=p,
                        quaternion=q,
                        velocity=v,
                        angular_velocity=w_body,
                        covariance=cov,
                        velocity_covariance=vcov,
                        tracked=True,
                        n_markers=n_markers,
                        n_cameras=n_cameras,
                        residual_mm=float(self._tf[b, _RESIDUAL_MM]),
                        reset_counter=resets,
                    )
                )
            else:
                nan3 = np.full(3, np.nan)
                out.append(
                    BodyState(
                        name=model.name,
                        body_id=model.id,
                        time_ns=int(now_ns),
                        capture_ns=int(tr.last_capture_ns),
                        position=nan3,
                        quaternion=np.full(4, np.nan),
                        velocity=nan3.copy(),
                        angular_velocity=nan3.copy(),
                        covariance=np.full((6, 6), np.nan),
                        velocity_covariance=np.full((3, 3), np.nan),
                        tracked=False,
                        n_markers=0,
                        n_cameras=0,
                        reset_counter=tr.reset_counter,
                    )
                )
        return out

    def stats(self) -> dict[str, Any]:
        """Counters: frames, fusions, measurements, rejections by reason, per-camera frames, per-body state."""
        d: dict[str, Any] = dict(self._stats)
        d["per_camera_frames"] = dict(sorted(self._per_camera.items()))
        d["bodies"] = {
            m.name: {"tracked": tr.tracked, "reset_counter": tr.reset_counter, "n_markers": tr.n_markers}
            for m, tr in zip(self.models, self.tracks)
        }
        d["time_alignment"] = self.settings.time_alignment
        return d
