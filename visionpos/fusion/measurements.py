"""The pose measurement of the tracked bodies in one fusion (compiled; kernels._fuse_tracked calls it).

Per fusion: the views' spread in time (_view_spread), each body's motion prior and gates (_motion_priors),
the motion-compensated triangulation of its markers with the residual gate (a marker just above the floor has
the gate widened and its weight lowered by the pull of its merged reflection, matching.floor_gate), and the
weighted Kabsch fit with the pose covariance (_fit_bodies, pose_measurement_cov); _tracked_measurements strings
them together.
"""

from __future__ import annotations

import math

import numpy as np

from visionpos.fusion.layout import (
    PARAM_COMPENSATE_MAX_VEL_VAR,
    PARAM_IDENTIFY_TOL_M,
    PARAM_MAX_RESIDUAL_PX,
    POSE_P,
    POSE_ROT,
    STATE_DT_S,
    STATE_R_NOM,
    STATE_RATE_VAR,
    STATE_VEL_VAR,
    STATE_X,
    X_ACC,
    X_ANG_ACC,
    X_RATE,
)
from visionpos.fusion.matching import floor_gate, triangulate_irls
from visionpos.fusion.tracking import (
    predict_mean,
)
from visionpos.geometry.alignment import kabsch_horn_compiled
from visionpos.jit import cross3, dot3, matmul3, matvec3, njit


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
    C[POSE_P, POSE_P] = matmul3(oxC, ox.T)
    for i in range(3):
        C[i, i] += var / n
    C[POSE_P, POSE_ROT] = -oxC
    C[POSE_ROT, POSE_P] = -oxC.T
    C[POSE_ROT, POSE_ROT] = Crot
    return C


@njit
def _tracked_measurements(marker_xn: np.ndarray, views: tuple, tracked: tuple, dt: np.ndarray, states: np.ndarray,
                          compensate: bool, params: np.ndarray) -> tuple:
    """Pose measurements of the tracked bodies from one fusion of V views (compiled).

    marker_xn (cameras, all markers, 2): each camera's normalised observation of each
    marker (NaN = none); views: layout.ViewSet (tuple) of the fused cameras; tracked:
    layout.TrackedSet (tuple); dt (V,): view capture - reference (s). states
    (B, N_STATE_COLS): the bodies' filter states as _pack_states packs them.
    compensate: motion compensation on (velocity-gated per body). params: the fusion
    params (columns PARAM_*).

    Returns per body: R (B, 3, 3), t (B, 3), markers used (B,), fit residual sum
    of squares (B,), cameras seeing it (B,), pixel-variance sample (B,), unit-variance
    pose covariance (B, 6, 6), motion variance added to position / rotation (B,),
    fit tolerance (B,); the number of points refused by the residual gate; and per body
    h_t (B, 2): the mean over its fitted observations of dt and dt^2 / 2 (s, s^2) when
    its views were motion-compensated, else 0.

    A compensated pose is where the body was at the views' times moved to the reference
    with the filter's own velocity, acceleration and rate, so it measures p + h_t[0] (v -
    v_est) + h_t[1] (a - a_est) (and the rotation likewise with the rate and the angular
    acceleration): the filter update
    must see those columns (tracking._kf_update), or the views older than the reference
    feed the velocity error back into the velocity (an oscillation that grows once a
    manoeuvre has raised the process noise).
    """
    cameras, R, t, f, _ = views
    _, rows, sizes, _, local = tracked
    n_markers, n_views = rows.shape[0], cameras.shape[0]
    xn = np.empty((n_markers, n_views, 2))
    for q in range(n_markers):
        for v in range(n_views):
            xn[q, v, 0] = marker_xn[cameras[v], rows[q], 0]
            xn[q, v, 1] = marker_xn[cameras[v], rows[q], 1]
    dt2_mean, dt_max, centre, f_mean = _view_spread(dt, R, t, f)
    vel, acc, rate, ang_acc, Rb, var_p, var_r, gate, fit_tol, moving, compensated = _motion_priors(
        states, compensate, params, dt2_mean, dt_max, centre, f_mean)
    body = np.empty(n_markers, dtype=np.int64)
    k = 0
    for b in range(sizes.shape[0]):
        body[k : k + sizes[b]] = b
        k += sizes[b]
    has_offsets = compensate and dt_max > 0.0 and moving
    offsets = np.zeros((n_markers if has_offsets else 0, n_views, 3))
    if has_offsets:
        for q in range(n_markers):
            b = body[q]
            r = matvec3(Rb[b], local[q])  # lever arm, world
            wxr = cross3(rate[b], r)
            u1 = vel[b] + wxr
            u2 = 0.5 * (acc[b] + cross3(ang_acc[b], r) + cross3(rate[b], wxr))
            for v in range(n_views):  # marker displacement from ref to the view's capture time (2nd order)
                offsets[q, v] = u1 * dt[v] + u2 * (dt[v] * dt[v])
    X, rms, nv = triangulate_irls(xn, R, t, f, offsets, has_offsets, 2)
    w_fit = np.zeros(n_markers)
    refused = 0
    for q in range(n_markers):
        if nv[q] >= 2:
            g = gate[body[q]]
            if not rms[q] < g:  # near the floor a merged reflection may pull each view (matching.py)
                seen = np.zeros(n_views, dtype=np.bool_)
                for v in range(n_views):
                    seen[v] = not np.isnan(xn[q, v, 0])
                g_floor = floor_gate(X[q], R, t, f, seen, g)
                if rms[q] < g_floor:  # kept, weighted down by the pull it may carry
                    w_fit[q] = nv[q] * g * g / (g_floor * g_floor)
                    continue
            if rms[q] < g:
                w_fit[q] = nv[q]  # more rays, better-conditioned point
            else:
                refused += 1
    Rk, tk, count, res2, n_cams, px_var, cov, h_t = _fit_bodies(local, sizes, xn, X, rms, nv, w_fit, dt,
                                                                has_offsets, compensated)
    return Rk, tk, count, res2, n_cams, px_var, cov, var_p, var_r, fit_tol, refused, h_t


@njit
def _view_spread(dt: np.ndarray, R: np.ndarray, t: np.ndarray, f: np.ndarray) -> tuple:
    """The fused views' spread in time and space: mean dt^2 (s^2) and largest |dt| (s) of their capture times
    against the reference, the mean camera centre (3,) m and the mean focal length (px): a px-per-metre
    scale."""
    n_views = dt.shape[0]
    dt2_mean = 0.0
    dt_max = 0.0
    centre = np.zeros(3)
    f_mean = 0.0
    for v in range(n_views):
        dt2_mean += dt[v] * dt[v] / n_views
        dt_max = max(dt_max, abs(dt[v]))
        f_mean += f[v] / n_views
        for i in range(3):
            for j in range(3):
                centre[i] -= R[v, j, i] * t[v, j] / n_views
    return dt2_mean, dt_max, centre, f_mean


@njit
def _motion_priors(states: np.ndarray, compensate: bool, params: np.ndarray, dt2_mean: float, dt_max: float,
                   centre: np.ndarray, f_mean: float) -> tuple:
    """Per body (B rows of states): the motion the compensation uses (velocity, acceleration, angular rate and
    acceleration (B, 3), predicted rotation (B, 3, 3)), the motion variance it adds to position and rotation
    (B,), the residual gate (B,) px and fit tolerance (B,) m widened by the motion the views may still disagree
    by, whether anything moves, and which bodies are compensated (their velocity known well enough)."""
    n_bodies = states.shape[0]
    max_residual_px, identify_tolerance = params[PARAM_MAX_RESIDUAL_PX], params[PARAM_IDENTIFY_TOL_M]
    compensate_max_vel_var = params[PARAM_COMPENSATE_MAX_VEL_VAR]
    vel = np.zeros((n_bodies, 3))
    acc = np.zeros((n_bodies, 3))
    rate = np.zeros((n_bodies, 3))
    ang_acc = np.zeros((n_bodies, 3))
    Rb = np.empty((n_bodies, 3, 3))
    var_p = np.empty(n_bodies)
    var_r = np.empty(n_bodies)
    gate = np.empty(n_bodies)
    fit_tol = np.empty(n_bodies)
    moving = False
    compensated = np.zeros(n_bodies, dtype=np.bool_)
    for b in range(n_bodies):
        x = states[b, STATE_X]
        sv2, sw2 = states[b, STATE_VEL_VAR], states[b, STATE_RATE_VAR]
        w = x[X_RATE] + x[X_ANG_ACC] * states[b, STATE_DT_S]
        p, Rb[b], v = predict_mean(x, states[b, STATE_R_NOM].reshape((3, 3)), states[b, STATE_DT_S])
        if compensate and sv2 < compensate_max_vel_var:
            compensated[b] = True
            vel[b], acc[b], rate[b], ang_acc[b] = v, x[X_ACC], w, x[X_ANG_ACC]
            moving = moving or np.any(v != 0.0) or np.any(x[X_ACC] != 0.0) or np.any(w != 0.0) or np.any(
                x[X_ANG_ACC] != 0.0)
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
    return vel, acc, rate, ang_acc, Rb, var_p, var_r, gate, fit_tol, moving, compensated


@njit
def _fit_bodies(local: np.ndarray, sizes: np.ndarray, xn: np.ndarray, X: np.ndarray, rms: np.ndarray,
                nv: np.ndarray, w_fit: np.ndarray, dt: np.ndarray, has_offsets: bool, compensated: np.ndarray
                ) -> tuple:
    """Each body's weighted Kabsch fit of its layout to its triangulated markers (weights w_fit: 0 = refused):
    R (B, 3, 3), t (B, 3), markers used (B,), fit residual sum of squares (B,) m^2, cameras seeing it (B,),
    pixel-variance sample (B,), unit-variance pose covariance (B, 6, 6) (NaN under 3 markers), and h_t (B, 2)
    (see _tracked_measurements)."""
    n_bodies, n_views = sizes.shape[0], xn.shape[1]
    Rk = np.empty((n_bodies, 3, 3))
    tk = np.empty((n_bodies, 3))
    count = np.zeros(n_bodies, dtype=np.int64)
    res2 = np.zeros(n_bodies)
    n_cams = np.zeros(n_bodies, dtype=np.int64)
    px_var = np.zeros(n_bodies)
    cov = np.full((n_bodies, 6, 6), np.nan)
    h_t = np.zeros((n_bodies, 2))
    k = 0
    for b in range(n_bodies):
        s = slice(k, k + sizes[b])
        Rk[b], tk[b] = kabsch_horn_compiled(local[s], X[s], w_fit[s])
        n_obs = 0
        for v in range(n_views):
            seen = False
            for q in range(k, k + sizes[b]):
                if not np.isnan(xn[q, v, 0]):
                    seen = True
                    if w_fit[q] > 0 and has_offsets and compensated[b]:
                        h_t[b, 0] += dt[v]
                        h_t[b, 1] += 0.5 * dt[v] * dt[v]
                        n_obs += 1
            n_cams[b] += seen
        if n_obs:
            h_t[b] /= n_obs
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
    return Rk, tk, count, res2, n_cams, px_var, cov, h_t
