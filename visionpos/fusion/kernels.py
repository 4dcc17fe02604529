"""The compiled per-frame and per-fusion kernels of the fusion pipeline (pipeline.py orchestrates).

Why kernels: a frame or a fusion touches a few dozen markers, where numpy's
per-call overhead, not arithmetic, sets the cost; each step is a loop compiled
by numba (visionpos.jit). Each Python -> kernel call also costs microseconds
per argument type it must check, so one frame is one call (_observe_frame)
and one fusion is one call (_fuse_tracked), state is updated in place in the
FilterBank and track arrays, and results come back packed in a few arrays.
Every packed layout and argument group is named in layout.py.

The arithmetic order of each kernel is part of its contract: replays are
compared byte for byte with earlier versions.
"""

from __future__ import annotations

import math

import numpy as np

from visionpos.camera.model import undistort_pixels
from visionpos.fusion.adaptation import adapt_to_pose, report_image_nis
from visionpos.fusion.layout import (
    CAMERA_COS_MAX,
    CAMERA_DIST,
    CAMERA_FISHEYE,
    CAMERA_INTRINSICS,
    CAMERA_R,
    CAMERA_T,
    CLOCK_T_NS,
    INTRINSICS_FX,
    INTRINSICS_FY,
    KALMAN_GATE_CHI2,
    KALMAN_NIS_UNSPLIT_COV,
    MEAS_COV,
    MEAS_FIT_RMS_M,
    MEAS_N_CAMERAS,
    MEAS_N_MARKERS,
    MEAS_POS,
    MEAS_ROT,
    MOTION_ACC,
    MOTION_POS,
    MOTION_VEL,
    N_MEAS,
    N_STATE_COLS,
    NO_TIME,
    PARAM_COMPENSATE_MAX_VEL_VAR,
    PARAM_MARKER_VAR_FLOOR,
    PARAM_MIN_MARKERS,
    PARAM_RESET_AFTER_NS,
    PARAM_SV_ENABLED,
    PARAM_SV_GATE_PER_DOF,
    PARAM_SV_MAX_POS_VAR,
    PARAM_SV_MAX_ROT_VAR,
    PARAM_SV_MIN_PX_VAR,
    PARAM_SV_WINDOW_NS,
    POS0,
    POSE_ROT0,
    RATE0,
    ROT_ERR0,
    STATE_DT_S,
    STATE_R_NOM,
    STATE_R_NOM0,
    STATE_RATE_VAR,
    STATE_VEL_VAR,
    STATE_X,
    SV_PARAM_ALWAYS,
    TRACK_FIRST_REJECT_NS,
    TRACK_LAST_CAPTURE_NS,
    TRACK_LAST_UPDATE_NS,
    TRACK_MARKER_VAR,
    TRACK_N_CAMERAS,
    TRACK_N_MARKERS,
    TRACK_PX_VAR,
    TRACK_RESETS,
    TRACK_RESIDUAL_MM,
    TRACK_UPDATE_KIND,
    TRACK_VIEWS_T_NS,
    UPDATE_POSE,
    UPDATE_VIEWS,
    VEL0,
    VERDICT_ACCEPTED,
    VERDICT_FIT_REJECTED,
    VERDICT_GATED,
    VERDICT_RESET,
    VERDICT_TOO_FEW,
    VERDICT_VIEWS,
    VERDICT_VIEWS_GATED,
    VERDICT_VIEWS_UNCONSTRAINED,
    X_ACC,
    X_ANG_ACC,
    X_RATE,
)
from visionpos.fusion.matching import associate_blobs, project_points
from visionpos.fusion.measurements import _tracked_measurements
from visionpos.fusion.tracking import (
    _spd_inverse,
    filter_initialize,
    filter_update,
    filter_update_view,
    pose_nis,
    predict_mean,
)
from visionpos.jit import cross3, dot3, matvec3, njit


@njit
def _marker_motion(
    states: np.ndarray, sizes: np.ndarray, local: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marker positions, velocities and accelerations (M, 3) each, world, of B bodies.

    states (B, N_STATE_COLS): filter states as _pack_states packs them, predicted
    by their STATE_DT_S; sizes (B,): marker counts; local (M, 3): body-frame
    markers, body by body. Includes the rotation's w x r, dw/dt x r and w x (w x r) terms.
    """
    n_markers = local.shape[0]
    X0 = np.empty((n_markers, 3))
    V = np.empty((n_markers, 3))
    A = np.empty((n_markers, 3))
    q = 0
    for b in range(sizes.shape[0]):
        x = states[b, STATE_X]
        dt = states[b, STATE_DT_S]
        w = x[X_RATE] + x[X_ANG_ACC] * dt
        p, Rb, v = predict_mean(x, states[b, STATE_R_NOM].reshape((3, 3)), dt)
        for _ in range(sizes[b]):
            r = matvec3(Rb, local[q])  # lever arm, world
            wxr = cross3(w, r)
            X0[q] = p + r
            V[q] = v + wxr
            A[q] = x[X_ACC] + cross3(x[X_ANG_ACC], r) + cross3(w, wxr)
            q += 1
    return X0, V, A


@njit
def _mean_velocity_var(P: np.ndarray) -> float:
    """The mean of a filter's three velocity variances (m^2/s^2), from its covariance P (18, 18)."""
    return (P[VEL0, VEL0] + P[VEL0 + 1, VEL0 + 1] + P[VEL0 + 2, VEL0 + 2]) / 3.0


@njit
def _pack_states(bank: tuple, bodies: np.ndarray, t_ns: int) -> np.ndarray:
    """The kernels' packed input (B, N_STATE_COLS) (columns STATE_*) for the filters `bodies` (B,)
    of a FilterBank (bank: layout.FilterArrays as a tuple) at t_ns: per body its state, nominal
    rotation, t_ns - filter time (s), mean velocity variance and mean angular-rate variance."""
    x, P, R_nom, _, clock, _ = bank
    out = np.empty((bodies.shape[0], N_STATE_COLS))
    for i in range(bodies.shape[0]):
        b = bodies[i]
        out[i, STATE_X] = x[b]
        for r in range(3):
            for c in range(3):
                out[i, STATE_R_NOM0 + 3 * r + c] = R_nom[b, r, c]
        out[i, STATE_DT_S] = (t_ns - clock[b, CLOCK_T_NS]) * 1e-9
        out[i, STATE_VEL_VAR] = _mean_velocity_var(P[b])
        out[i, STATE_RATE_VAR] = (P[b, RATE0, RATE0] + P[b, RATE0 + 1, RATE0 + 1] + P[b, RATE0 + 2, RATE0 + 2]) / 3.0
    return out


@njit
def _tracked_motion(bank: tuple, tracked: tuple) -> tuple[int, np.ndarray]:
    """The newest filter time t_c (ns) of the tracked bodies (tracked: layout.TrackedSet as a tuple)
    of a FilterBank (bank: layout.FilterArrays as a tuple) and their markers' positions, velocities
    and accelerations there, motion (3, M, 3) indexed by MOTION_* (_marker_motion)."""
    bodies, _, sizes, _, local = tracked
    _, _, _, _, clock, _ = bank
    t_c = clock[bodies[0], CLOCK_T_NS]
    for i in range(bodies.shape[0]):
        t_c = max(t_c, clock[bodies[i], CLOCK_T_NS])
    motion = np.empty((3, local.shape[0], 3))
    motion[MOTION_POS], motion[MOTION_VEL], motion[MOTION_ACC] = _marker_motion(
        _pack_states(bank, bodies, t_c), sizes, local)
    return t_c, motion


@njit
def _finite_rows(px: np.ndarray) -> np.ndarray:
    """px (N, 2) itself when every row is finite, else a copy of its finite rows."""
    keep = np.empty(px.shape[0], dtype=np.bool_)
    n = 0
    for j in range(px.shape[0]):
        keep[j] = np.isfinite(px[j, 0]) and np.isfinite(px[j, 1])
        n += keep[j]
    return px if n == px.shape[0] else px[keep]


_UNIQUE_MIN_PX = 3.0  # px: the single-view path's uniqueness radius is never smaller (blob merging, noise)


@njit
def _observe_frame(px: np.ndarray, dt_s: float, motion: np.ndarray, tracked: tuple, marker_xn: np.ndarray,
                   marker_ok: np.ndarray, camera: np.ndarray, gate_px: float, unique_sigmas: float, image_nis: bool,
                   t_ns: int, bank: tuple, track_floats: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One camera frame against the tracked bodies' predicted markers (compiled).

    px (N, 2) blob pixels; motion (3, M, 3): the tracked markers' positions, velocities and
    accelerations (_tracked_motion), so X0 + dt V + dt^2 / 2 A is where they are at the frame's
    capture time t_ns, dt_s (s) after them; tracked: layout.TrackedSet (tuple) of the bodies;
    camera (N_CAMERA,): the camera packed as matching.Projector.packed (columns CAMERA_*);
    gate_px: association radius. Fills marker_xn (all markers, 2), each marker's observation
    (NaN = none), and marker_ok (all markers,): True where the association is unambiguous,
    the only ones the single-view path uses: its blob is the only one within the marker's
    uniqueness radius and no other tracked marker is predicted within that radius of the
    blob. The radius is unique_sigmas predicted pixel std (pixel noise plus the body's
    position uncertainty at the marker's depth), at least _UNIQUE_MIN_PX, at most gate_px.
    Returns normalised blobs xn (N, 2), blob labels (N,) (global marker row or -1) and the
    tracked markers' predicted pixels (M, 2) (rows of `tracked`; NaN off the sensor), which the
    console draws.

    image_nis: also feed each tracked body's manoeuvre detector (tracking.report_image_nis)
    with this frame's prediction residual over its expected size (_image_nis); bank:
    layout.FilterArrays (tuple) of the FilterBank; track_floats: the track rows (pixel variance).
    """
    bodies, rows, _, body_of_row, _ = tracked
    _, P, _, adapt, clock, kalman = bank
    R, t = camera[CAMERA_R].reshape((3, 3)), camera[CAMERA_T]
    intrinsics, dist = camera[CAMERA_INTRINSICS], camera[CAMERA_DIST]
    fisheye, cos_max = camera[CAMERA_FISHEYE] != 0.0, camera[CAMERA_COS_MAX]
    xn = undistort_pixels(px, intrinsics, dist, fisheye)
    Xw = motion[MOTION_POS] + dt_s * (motion[MOTION_VEL] + (0.5 * dt_s) * motion[MOTION_ACC])
    pred = project_points(Xw, R, t, intrinsics, dist, fisheye, cos_max, gate_px)
    blob_of = associate_blobs(pred, px, gate_px * gate_px)
    label = np.full(px.shape[0], -1, dtype=np.int64)
    marker_xn[:, :] = np.nan
    marker_ok[:] = False
    focal_px = math.sqrt(intrinsics[INTRINSICS_FX] * intrinsics[INTRINSICS_FY])
    for q in range(blob_of.shape[0]):
        j = blob_of[q]
        if j >= 0:
            label[j] = rows[q]
            marker_xn[rows[q], 0] = xn[j, 0]
            marker_xn[rows[q], 1] = xn[j, 1]
            b = bodies[body_of_row[q]]
            z = max(Xw[q, 0] * R[2, 0] + Xw[q, 1] * R[2, 1] + Xw[q, 2] * R[2, 2] + t[2], 0.1)
            pos_var = (P[b, POS0, POS0] + P[b, POS0 + 1, POS0 + 1] + P[b, POS0 + 2, POS0 + 2]) / 3.0
            radius = unique_sigmas * math.sqrt(track_floats[b, TRACK_PX_VAR] + focal_px * focal_px * pos_var / (z * z))
            radius = min(max(radius, _UNIQUE_MIN_PX), gate_px)
            g2 = radius * radius
            inside = 0  # blobs in this marker's radius plus other predictions in its blob's radius
            for n in range(px.shape[0]):
                du, dv = px[n, 0] - pred[q, 0], px[n, 1] - pred[q, 1]
                inside += du * du + dv * dv < g2
            for r in range(pred.shape[0]):
                du, dv = px[j, 0] - pred[r, 0], px[j, 1] - pred[r, 1]
                inside += r != q and du * du + dv * dv < g2
            du, dv = px[j, 0] - pred[q, 0], px[j, 1] - pred[q, 1]
            marker_ok[rows[q]] = inside == 1 and du * du + dv * dv < g2
    if image_nis:
        # expected: the body's pixel noise plus its position uncertainty seen from this camera
        n_bodies = bodies.shape[0]
        exp_px = np.empty(n_bodies)
        exp_pos = np.empty(n_bodies)
        exp_rot = np.empty(n_bodies)
        for i in range(n_bodies):
            b = bodies[i]
            exp_px[i] = track_floats[b, TRACK_PX_VAR]
            exp_pos[i] = (P[b, POS0, POS0] + P[b, POS0 + 1, POS0 + 1] + P[b, POS0 + 2, POS0 + 2]) / 3.0
            exp_rot[i] = (P[b, ROT_ERR0, ROT_ERR0] + P[b, ROT_ERR0 + 1, ROT_ERR0 + 1]
                          + P[b, ROT_ERR0 + 2, ROT_ERR0 + 2]) / 3.0
        nis, nis_rot, n = _image_nis(Xw, pred, px, blob_of, body_of_row, exp_px, exp_pos, exp_rot, R[2], t[2],
                                     focal_px)
        for i in range(n_bodies):
            if n[i] >= 2:
                b = bodies[i]
                report_image_nis(adapt[b], clock[b], kalman, t_ns, nis[i], nis_rot[i])
    return xn, label, pred


@njit
def _scaled_pose_cov(cov_unit: np.ndarray, var: float, var_p: float, var_r: float) -> np.ndarray:
    """cov_unit (6, 6) * var, plus var_p on the position and var_r on the rotation diagonal."""
    C = cov_unit * var
    for i in range(3):
        C[i, i] += var_p
        C[POSE_ROT0 + i, POSE_ROT0 + i] += var_r
    return C


@njit
def _image_nis(Xw: np.ndarray, pred: np.ndarray, px: np.ndarray, blob_of: np.ndarray, body_of_row: np.ndarray,
               exp_px: np.ndarray, exp_pos: np.ndarray, exp_rot: np.ndarray, R2: np.ndarray, t2: float,
               focal_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame's prediction residual per body over its expected size, per degree of freedom,
    split into translation and rotation.

    Xw (M, 3) predicted markers, pred (M, 2) their pixels, px (N, 2) blobs, blob_of (M,)
    associated blob or -1, body_of_row (M,) body of each row; per body (B,): pixel noise
    variance exp_px, position variance exp_pos and rotation variance exp_rot (rad^2, per
    axis); R2 (3,), t2, focal_px: the camera's optical-axis row, its translation and focal
    length (depth -> pixels).

    A position error moves a body's markers together: the mean residual d_mean (2 dof,
    expected 2 (exp_px / n + f^2 exp_pos / z^2)). An orientation error turns them about
    the body: the residuals' spread about their mean (2 (n - 1) dof, expected
    2 (n - 1) exp_px + 4/3 f^2 exp_rot sum |X - X_mean|^2 / z^2 for a random rotation
    error seen from one side). Judging them apart sends each lag to its own process noise.
    Returns the translation NIS (B,), the rotation NIS (B,) and the markers behind them (B,).
    """
    n_bodies = exp_px.shape[0]
    n = np.zeros(n_bodies, dtype=np.int64)
    d_sum = np.zeros((n_bodies, 2))
    d2_sum = np.zeros(n_bodies)
    x_sum = np.zeros((n_bodies, 3))
    x2_sum = np.zeros(n_bodies)
    inv_z2 = np.zeros(n_bodies)
    for q in range(blob_of.shape[0]):
        j = blob_of[q]
        if j < 0:
            continue
        b = body_of_row[q]
        z = max(Xw[q, 0] * R2[0] + Xw[q, 1] * R2[1] + Xw[q, 2] * R2[2] + t2, 0.1)
        du, dv = px[j, 0] - pred[q, 0], px[j, 1] - pred[q, 1]
        d_sum[b, 0] += du
        d_sum[b, 1] += dv
        d2_sum[b] += du * du + dv * dv
        for k in range(3):
            x_sum[b, k] += Xw[q, k]
            x2_sum[b] += Xw[q, k] * Xw[q, k]
        inv_z2[b] += 1.0 / (z * z)
        n[b] += 1
    nis = np.zeros(n_bodies)
    nis_rot = np.zeros(n_bodies)
    f2 = focal_px * focal_px
    for b in range(n_bodies):
        m = n[b]
        if m == 0:
            continue
        iz2 = inv_z2[b] / m
        mean2 = (d_sum[b, 0] * d_sum[b, 0] + d_sum[b, 1] * d_sum[b, 1]) / (m * m)
        nis[b] = mean2 / (2.0 * (exp_px[b] / m + f2 * exp_pos[b] * iz2))
        if m >= 2:
            spread2 = max(d2_sum[b] - m * mean2, 0.0)  # sum |d - d_mean|^2
            lever2 = max(x2_sum[b] - dot3(x_sum[b], x_sum[b]) / m, 0.0)  # sum |X - X_mean|^2
            nis_rot[b] = spread2 / (2.0 * (m - 1) * exp_px[b] + (4.0 / 3.0) * f2 * exp_rot[b] * lever2 * iz2)
    return nis, nis_rot, n


@njit
def _track_measured(track_ints: np.ndarray, track_floats: np.ndarray, ref_ns: int, capture_ns: int, n_markers: int,
                    n_cameras: int, fit_rms_m: float) -> None:
    """Record a measurement the filter took (or restarted at) in one body's track rows
    track_ints (N_TRACK_INTS,), track_floats (N_TRACK_FLOATS,): reference time ref_ns,
    newest capture time capture_ns, markers, cameras, fit RMS (m)."""
    track_ints[TRACK_FIRST_REJECT_NS] = NO_TIME
    track_ints[TRACK_LAST_UPDATE_NS] = ref_ns
    track_ints[TRACK_LAST_CAPTURE_NS] = capture_ns
    track_ints[TRACK_N_MARKERS] = n_markers
    track_ints[TRACK_N_CAMERAS] = n_cameras
    track_floats[TRACK_RESIDUAL_MM] = fit_rms_m * 1e3


@njit
def _pose_observable(info: np.ndarray, max_pos_var: float, max_rot_var: float) -> bool:
    """Whether a pose information matrix info (6, 6) over [p (m), rotation (rad)] bounds the pose:
    positive definite (Cholesky pivots above 1e-9 of their diagonal) and its inverse's position
    and rotation traces at most max_pos_var (m^2) and max_rot_var (rad^2)."""
    for j in range(6):
        if not info[j, j] > 0.0:
            return False
    L = np.zeros((6, 6))
    for j in range(6):
        d = info[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 1e-9 * info[j, j]:
            return False
        L[j, j] = math.sqrt(d)
        for i in range(j + 1, 6):
            v = info[i, j]
            for k in range(j):
                v -= L[i, k] * L[j, k]
            L[i, j] = v / L[j, j]
    C = _spd_inverse(info)
    return C[0, 0] + C[1, 1] + C[2, 2] <= max_pos_var and C[3, 3] + C[4, 4] + C[5, 5] <= max_rot_var


@njit
def _single_views(b: int, local: np.ndarray, body_rows: np.ndarray, marker_xn: np.ndarray,
                  marker_ok: np.ndarray, capture_ns: np.ndarray, views: tuple, params: np.ndarray, bank: tuple,
                  tracks: tuple, adapt_noise: bool = True) -> tuple[int, int, int, int]:
    """The single-view path of one body b that could not be triangulated (compiled): each frame of the
    fusion's views that b has not used yet, oldest first, that sees >= 1 of its markers unambiguously
    (marker_ok) is one reprojection update (tracking.filter_update_view) at its own capture time.

    local (n, 3): the body's markers, body_rows (n,): their global marker rows; marker_xn, marker_ok
    (cameras, all markers, ...): each camera's observations; capture_ns (cameras,); views, params,
    bank, tracks: as _fuse_tracked.
    Accepted views add their pose information to tracks.info[b], decayed over the configured window;
    the body's track is refreshed (kept) only while that information bounds its pose (_pose_observable).
    Returns (verdict, distinct markers used, views used, newest capture used).
    """
    x, P, R_nom, adapt, clock, kalman = bank
    track_ints, track_floats, view_ns, info = tracks
    cameras, _, _, _, packed = views
    n_views = cameras.shape[0]
    order = np.argsort(capture_ns[cameras])
    var_px = max(track_floats[b, TRACK_PX_VAR], params[PARAM_SV_MIN_PX_VAR])
    seen = np.zeros(local.shape[0], dtype=np.bool_)
    n_taken, n_gated, newest = 0, 0, NO_TIME
    for o in range(n_views):
        v = order[o]
        cam = cameras[v]
        t_v = capture_ns[cam]
        if t_v <= view_ns[b, cam]:
            continue  # each frame once: its information is not counted twice
        n = 0
        for k in range(local.shape[0]):
            if marker_ok[cam, body_rows[k]] and not np.isnan(marker_xn[cam, body_rows[k], 0]):
                n += 1
        if n == 0:
            continue
        view_ns[b, cam] = t_v
        sel_local = np.empty((n, 3))
        sel_xn = np.empty((n, 2))
        n = 0
        for k in range(local.shape[0]):
            if marker_ok[cam, body_rows[k]] and not np.isnan(marker_xn[cam, body_rows[k], 0]):
                sel_local[n] = local[k]
                sel_xn[n, 0], sel_xn[n, 1] = marker_xn[cam, body_rows[k], 0], marker_xn[cam, body_rows[k], 1]
                seen[k] = True
                n += 1
        ok, _, frame_info = filter_update_view(x[b], P[b], R_nom[b], adapt[b], clock[b], kalman, t_v, sel_local,
                                               sel_xn, packed[v], var_px, params[PARAM_SV_GATE_PER_DOF],
                                               adapt_noise)
        if not ok:
            n_gated += 1
            continue
        decay = math.exp(-max(t_v - track_ints[b, TRACK_VIEWS_T_NS], 0) / params[PARAM_SV_WINDOW_NS])
        for i in range(6):
            for j in range(6):
                info[b, i, j] = decay * info[b, i, j] + frame_info[i, j]
        track_ints[b, TRACK_VIEWS_T_NS] = t_v
        n_taken += 1
        newest = max(newest, t_v)
    if n_taken == 0:
        return (VERDICT_VIEWS_GATED if n_gated else VERDICT_TOO_FEW), 0, 0, newest
    if not _pose_observable(info[b], params[PARAM_SV_MAX_POS_VAR], params[PARAM_SV_MAX_ROT_VAR]):
        return VERDICT_VIEWS_UNCONSTRAINED, int(seen.sum()), n_taken, newest
    return VERDICT_VIEWS, int(seen.sum()), n_taken, newest


@njit
def _velocity_known(P: np.ndarray, params: np.ndarray) -> bool:
    """Whether a body's filter (covariance P (18, 18)) knows its velocity well enough for single-camera views: its
    mean velocity variance under the motion compensation's threshold (m^2/s^2). A new or reacquired track does not
    yet (it starts at rest with the initial velocity sigma): one camera's view has no depth, and the update would
    take its residual for velocity (after a 1 s occlusion in SITL flights, 0.3-0.6 m/s of a hovering vehicle,
    and the next output 20-100 mm off); such a track waits for a triangulated pose."""
    return _mean_velocity_var(P) < params[PARAM_COMPENSATE_MAX_VEL_VAR]


@njit
def _fuse_tracked(marker_xn: np.ndarray, marker_ok: np.ndarray, capture_ns: np.ndarray, views: tuple, ref_ns: int,
                  tracked: tuple, params: np.ndarray, compensate: bool, reuse: float, bank: tuple,
                  tracks: tuple) -> tuple[np.ndarray, np.ndarray, int, int, np.ndarray]:
    """One fusion for the tracked bodies: pose measurements, their covariances and the
    filter updates, in place (compiled).

    marker_xn, views, tracked, compensate, params: as _tracked_measurements;
    marker_ok (cameras, all markers): unambiguous associations (_observe_frame);
    capture_ns (cameras,): each camera's newest capture time; ref_ns: reference time;
    params also give the fewest markers for a pose, the floor of the per-marker variance
    (m^2), how long (ns) a filter may reject measurements before it restarts at them and
    the single-view path's settings; reuse: fusions that share each frame (multiplies the
    measurement covariance); bank: layout.FilterArrays (tuple) of the FilterBank; tracks:
    layout.TrackRows (tuple).

    A body with fewer than min_markers triangulated markers takes the single-view path
    (_single_views) when it is on; a triangulated pose marks the fused frames used, so the
    single-view path never counts them again.

    Returns per tracked body its verdict (B,) (layout.Verdict) and its measurement
    (B, N_MEAS) (columns MEAS_*: pose R and t, its covariance, markers used, cameras, fit
    RMS in m); the number of points refused by the residual gate; and, for the next
    frames, _tracked_motion after the updates (t_c, motion (3, M, 3)).
    """
    x, P, R_nom, adapt, clock, kalman = bank
    track_ints, track_floats, view_ns, info = tracks
    bodies, rows, sizes, _, local = tracked
    cameras, _, _, _, _ = views
    n_views = cameras.shape[0]
    dt, newest_capture_ns = _view_times(capture_ns, cameras, ref_ns)
    Rk, tk, counts, res2, n_cams, px_var, cov_unit, var_p, var_r, fit_tol, refused, h_t = _tracked_measurements(
        marker_xn, views, tracked, dt, _pack_states(bank, bodies, ref_ns), compensate, params)
    n_bodies = bodies.shape[0]
    verdict = np.full(n_bodies, VERDICT_TOO_FEW, dtype=np.int64)
    meas = np.zeros((n_bodies, N_MEAS))
    first = 0
    for i in range(n_bodies):
        first += sizes[i - 1] if i > 0 else 0
        meas[i, MEAS_ROT], meas[i, MEAS_POS] = Rk[i].ravel(), tk[i]
        meas[i, MEAS_N_MARKERS], meas[i, MEAS_N_CAMERAS] = counts[i], n_cams[i]
        n = counts[i]
        if n < params[PARAM_MIN_MARKERS]:
            meas[i, MEAS_FIT_RMS_M] = np.nan
            if params[PARAM_SV_ENABLED] != 0.0 and _velocity_known(P[bodies[i]], params):
                b = bodies[i]
                s = slice(first, first + sizes[i])
                verdict[i], n_seen, n_views_used, newest = _single_views(
                    b, local[s], rows[s], marker_xn, marker_ok, capture_ns, views, params, bank, tracks)
                if verdict[i] == VERDICT_VIEWS:
                    _track_measured(track_ints[b], track_floats[b], ref_ns, newest, n_seen, n_views_used, np.nan)
                    track_ints[b, TRACK_UPDATE_KIND] = UPDATE_VIEWS
            continue
        fit = meas[i, MEAS_FIT_RMS_M] = math.sqrt(res2[i] / n)
        if fit > fit_tol[i]:
            verdict[i] = VERDICT_FIT_REJECTED
            continue
        b = bodies[i]
        # pixel noise from the triangulation residuals of its markers; per-marker 3D noise
        # from the fit residual (3n - 6 degrees of freedom); both running averages per body
        track_floats[b, TRACK_PX_VAR] += 0.05 * (px_var[i] - track_floats[b, TRACK_PX_VAR])
        track_floats[b, TRACK_MARKER_VAR] += 0.05 * (res2[i] / (3 * n - 6) - track_floats[b, TRACK_MARKER_VAR])
        # reused frames: split their information over the fusions that share them
        marker_var = max(track_floats[b, TRACK_MARKER_VAR], params[PARAM_MARKER_VAR_FLOOR]) * reuse
        cov = _scaled_pose_cov(cov_unit[i], marker_var, var_p[i], var_r[i])
        meas[i, MEAS_COV] = cov.ravel()
        kind = UPDATE_POSE
        sv_verdict = VERDICT_TOO_FEW
        nis_cov_scale = 1.0 / reuse if kalman[KALMAN_NIS_UNSPLIT_COV] != 0.0 else 1.0
        if params[PARAM_SV_ENABLED] == SV_PARAM_ALWAYS and _velocity_known(P[b], params):
            # mode `always`: each frame's own markers at its capture time instead of the compensated pose
            s = slice(first, first + sizes[i])
            d2, nis_p, nis_r = pose_nis(x[b], P[b], R_nom[b], adapt[b], clock[b], kalman, ref_ns, tk[i], Rk[i],
                                        cov, h_t[i, 0], h_t[i, 1], nis_cov_scale)
            t_before = clock[b, CLOCK_T_NS]
            # a pose outside the gate: the prediction the views were matched against is off (a manoeuvre
            # the model lags), so their labels may be too; the pose path below decides
            if d2 <= kalman[KALMAN_GATE_CHI2]:
                sv_verdict = _single_views(b, local[s], rows[s], marker_xn, marker_ok, capture_ns, views, params,
                                           bank, tracks, False)[0]
            if sv_verdict == VERDICT_VIEWS or sv_verdict == VERDICT_VIEWS_UNCONSTRAINED:  # the views were taken
                adapt_to_pose(adapt[b], clock[b], kalman, (clock[b, CLOCK_T_NS] - t_before) * 1e-9, nis_p, nis_r,
                              x[b], P[b], R_nom[b])
        if sv_verdict == VERDICT_TOO_FEW or sv_verdict == VERDICT_VIEWS_GATED:
            # mode occlusion; or no frame with an unambiguous marker, the pose outside the gate, or the gate
            # refused every view (a manoeuvre the model lags): the pose (and its retest under manoeuvre hypotheses)
            accepted, _ = filter_update(x[b], P[b], R_nom[b], adapt[b], clock[b], kalman, ref_ns, tk[i], Rk[i], cov,
                                        True, h_t[i, 0], h_t[i, 1], nis_cov_scale)
        else:  # the views of a triangulated body: its kind stays "pose" (UPDATE_VIEWS says occlusion)
            accepted = True
        verdict[i] = VERDICT_ACCEPTED if accepted else _refused(b, ref_ns, tk[i], Rk[i], cov, params, bank,
                                                                track_ints)
        if verdict[i] == VERDICT_GATED:
            continue
        _track_measured(track_ints[b], track_floats[b], ref_ns, newest_capture_ns, n, n_cams[i], fit)
        track_ints[b, TRACK_UPDATE_KIND] = kind
        if kind == UPDATE_POSE:
            info[b] = 0.0  # the single-view information starts afresh when the pose is lost again
        for v in range(n_views):
            view_ns[b, cameras[v]] = max(view_ns[b, cameras[v]], capture_ns[cameras[v]])
    t_c, motion = _tracked_motion(bank, tracked)
    return verdict, meas, refused, t_c, motion


@njit
def _view_times(capture_ns: np.ndarray, cameras: np.ndarray, ref_ns: int) -> tuple[np.ndarray, int]:
    """Each fused view's capture time less the reference (V,) s, and the newest capture time (ns)."""
    n_views = cameras.shape[0]
    dt = np.empty(n_views)
    newest_capture_ns = capture_ns[cameras[0]]
    for v in range(n_views):
        dt[v] = (capture_ns[cameras[v]] - ref_ns) * 1e-9
        newest_capture_ns = max(newest_capture_ns, capture_ns[cameras[v]])
    return dt, newest_capture_ns


@njit
def _refused(b: int, ref_ns: int, position: np.ndarray, R: np.ndarray, cov: np.ndarray, params: np.ndarray,
             bank: tuple, track_ints: np.ndarray) -> int:
    """Body b's filter refused its pose at ref_ns: VERDICT_GATED while it has refused for less than
    reset_after; after that the measurements are believed (persistently inconsistent) and the filter restarts
    there: VERDICT_RESET."""
    x, P, R_nom, adapt, clock, kalman = bank
    if track_ints[b, TRACK_FIRST_REJECT_NS] == NO_TIME:
        track_ints[b, TRACK_FIRST_REJECT_NS] = ref_ns
    if ref_ns - track_ints[b, TRACK_FIRST_REJECT_NS] < params[PARAM_RESET_AFTER_NS]:
        return VERDICT_GATED
    filter_initialize(x[b], P[b], R_nom[b], adapt[b], clock[b], kalman, ref_ns, position, R, cov)
    track_ints[b, TRACK_RESETS] += 1
    return VERDICT_RESET
