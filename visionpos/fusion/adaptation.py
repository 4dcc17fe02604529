"""The process-noise adaptation of the body filter (tracking.py): the NIS-driven scales of its position and
rotation noise, the image-space manoeuvre detector that feeds them, and the cruise and multirotor floors
under both scales. Why each exists is in tracking.py's docstring; the settings are fusion.kalman's
(fusion/settings.py).

adapt (12,) and clock (3,) are one body's FilterBank rows (layout.ADAPT_*, layout.CLOCK_*); params its
packed settings (layout.KALMAN_*). Times are int64 ns on the capture clock, dt in s.
"""

from __future__ import annotations

import math

import numpy as np

from visionpos.fusion.layout import (
    ADAPT_NIS_CRUISE,
    ADAPT_NIS_CRUISE_R,
    ADAPT_NIS_IMG,
    ADAPT_NIS_IMG_R,
    ADAPT_NIS_P,
    ADAPT_NIS_R,
    ADAPT_NIS_SCALE_P,
    ADAPT_NIS_SCALE_R,
    ADAPT_SCALE_CRUISE,
    ADAPT_SCALE_CRUISE_R,
    ADAPT_SCALE_P,
    ADAPT_SCALE_R,
    ANG_ACC0,
    CLOCK_IMG_T_NS,
    CLOCK_T_NS,
    KALMAN_ANG_ACC_HOLD_S,
    KALMAN_ANG_JERK_PSD,
    KALMAN_CRUISE_MAX_SCALE,
    KALMAN_CRUISE_MAX_SCALE_R,
    KALMAN_CRUISE_NIS_THRESHOLD,
    KALMAN_CRUISE_RATE,
    KALMAN_CRUISE_TAU_S,
    KALMAN_GATE_CHI2,
    KALMAN_JERK_PSD,
    KALMAN_MAX_SCALE,
    KALMAN_NIS_TAU_S,
    KALMAN_NIS_THRESHOLD,
    KALMAN_TILT_JERK_S,
    RATE0,
)
from visionpos.jit import njit

_SCALE_DECAY_S = 0.2  # s, time constant of the process-noise scale's return to its floor
_G_M_S2 = 9.80665  # standard gravity: a hovering multirotor's thrust per unit mass
_IMG_NIS_FRESH_NS = 50_000_000  # an image-space NIS older than this no longer drives the noise scale


@njit
def _adapt_scale(scale: float, nis: float, alpha: float, decay: float, smax: float, nis_high: float) -> float:
    """One noise scale after one update: raised by (nis / nis_high)^(3 alpha) when the averaged NIS is above
    nis_high, else multiplied by decay; kept within [1, smax]."""
    if nis > nis_high:
        scale *= (nis / nis_high) ** (3.0 * alpha)
    else:
        scale *= decay
    return min(smax, max(1.0, scale))


@njit
def _cruise_floor(adapt: np.ndarray, nis_col: int, floor_col: int, nis: float, a_c: float, dt: float, cap: float,
                  cruise_max: float, params: np.ndarray) -> float:
    """One block's cruise floor after dt (s), in place (adapt[nis_col]: its slow NIS average, adapt[floor_col]:
    the floor): the average follows nis (capped) by a_c; the floor's logarithm moves by the cruise rate x (average -
    threshold) x dt, within [0, log cruise_max]. Returns the floor."""
    adapt[nis_col] += a_c * (min(nis, cap) - adapt[nis_col])
    log_floor = math.log(adapt[floor_col]) + max(dt, 0.0) * params[KALMAN_CRUISE_RATE] * (
        adapt[nis_col] - params[KALMAN_CRUISE_NIS_THRESHOLD])
    adapt[floor_col] = min(math.exp(max(log_floor, 0.0)), cruise_max)
    return adapt[floor_col]


@njit
def tilt_jerk_scale(x: np.ndarray, P: np.ndarray, R_nom: np.ndarray, params: np.ndarray) -> float:
    """The position scale's multirotor floor (fusion.kalman.tilt_jerk_ms): jerk density (g |w x z_body|)^2 x
    tilt_jerk_s over jerk_psd, within [1, max_noise_scale]. x (18,), P (18, 18): the state and its covariance
    (world angular rate w, rad/s), R_nom (3, 3) body->world (its third column: the body's z axis, along the
    thrust). |w x z|^2 is taken less what the rate's own variance adds to it (tr P_ww - z^T P_ww z), so a
    rate known poorly (a single view, a new track) raises nothing by its noise."""
    wx, wy, wz = x[RATE0], x[RATE0 + 1], x[RATE0 + 2]
    zx, zy, zz = R_nom[0, 2], R_nom[1, 2], R_nom[2, 2]
    cx, cy, cz = wy * zz - wz * zy, wz * zx - wx * zz, wx * zy - wy * zx  # w x z_body: the thrust's turn rate
    r = RATE0
    noise = P[r, r] + P[r + 1, r + 1] + P[r + 2, r + 2] - (
        zx * (P[r, r] * zx + P[r, r + 1] * zy + P[r, r + 2] * zz)
        + zy * (P[r + 1, r] * zx + P[r + 1, r + 1] * zy + P[r + 1, r + 2] * zz)
        + zz * (P[r + 2, r] * zx + P[r + 2, r + 1] * zy + P[r + 2, r + 2] * zz))
    q = _G_M_S2 * _G_M_S2 * max(cx * cx + cy * cy + cz * cz - noise, 0.0) * params[KALMAN_TILT_JERK_S]
    return min(max(q / params[KALMAN_JERK_PSD], 1.0), params[KALMAN_MAX_SCALE])


@njit
def angular_accel_scale(x: np.ndarray, P: np.ndarray, params: np.ndarray) -> float:
    """The rotation scale's multirotor floor (fusion.kalman.angular_accel_hold_ms): angular-jerk density
    |dw/dt|^2 / angular_accel_hold_s over angular_jerk_psd, within [1, max_noise_scale]. x (18,), P (18, 18):
    the state (angular acceleration dw/dt, rad/s^2) and its covariance; |dw/dt|^2 is taken less its variance's
    trace (as tilt_jerk_scale)."""
    if params[KALMAN_ANG_JERK_PSD] <= 0.0:
        return 1.0  # the constant-rate model: no angular acceleration is estimated
    a = ANG_ACC0
    a2 = max(x[a] ** 2 + x[a + 1] ** 2 + x[a + 2] ** 2 - (P[a, a] + P[a + 1, a + 1] + P[a + 2, a + 2]), 0.0)
    q = a2 / params[KALMAN_ANG_ACC_HOLD_S]
    return min(max(q / params[KALMAN_ANG_JERK_PSD], 1.0), params[KALMAN_MAX_SCALE])


@njit
def adapt_noise_scales(adapt: np.ndarray, clock: np.ndarray, params: np.ndarray, t_ns: int, dt: float,
                       nis_p: float, nis_r: float, use_image_nis: bool, x: np.ndarray, P: np.ndarray,
                       R_nom: np.ndarray) -> None:
    """The NIS-driven process-noise adaptation after one update over dt (s), in place.

    The NIS per block drives the process-noise scale (gated ones too, capped, so that a
    manoeuvre that starts outside the gate still opens it); the image-space detector
    (report_image_nis) sees lag the fused pose can hide. NIS/dof ~ 1 says nothing about q
    while the measurement noise dominates the innovation (a hovering body), so only a clear
    excess (> nis_threshold) raises q: innovations k x too big -> q x k^3 per averaging time
    (CA/CV scaling laws); otherwise q decays back to its floor. use_image_nis: False for the
    single-view updates, whose own innovation is the image-space residual with the full
    predicted covariance (the detector's expected size leaves out the rotation uncertainty,
    which matters while only 1-2 markers per view constrain it). The cruise floors
    (fusion.kalman.cruise_*) are the slow regime under those bursts: each block's NIS averaged
    over about a second moves the logarithm of a floor under its scale, up while the average
    exceeds its threshold and down while it does not (the rotation's capped lower: between
    flicks its rate, predicted on to the output ticks, must stay smooth). The multirotor floors
    (tilt_jerk_scale, angular_accel_scale; fusion.kalman.tilt_jerk_ms, angular_accel_hold_ms) lie
    under the scales, from the state x (18,), its covariance P (18, 18) and R_nom (3, 3) after the
    update: with one on, its block's NIS-driven scale evolves in its own column (ADAPT_NIS_SCALE_*)
    and the scale is the larger of the two.
    """
    cap = params[KALMAN_GATE_CHI2] / 3.0
    alpha = 1.0 - math.exp(-dt / params[KALMAN_NIS_TAU_S]) if dt > 0.0 else 0.05
    adapt[ADAPT_NIS_P] += alpha * (min(nis_p, cap) - adapt[ADAPT_NIS_P])
    adapt[ADAPT_NIS_R] += alpha * (min(nis_r, cap) - adapt[ADAPT_NIS_R])
    fresh = use_image_nis and t_ns - clock[CLOCK_IMG_T_NS] < _IMG_NIS_FRESH_NS
    nis_img = adapt[ADAPT_NIS_IMG] if fresh else 0.0  # the markers' common shift: position lag
    nis_img_r = adapt[ADAPT_NIS_IMG_R] if fresh else 0.0  # their spread about it: orientation lag
    decay = math.exp(-max(dt, 0.0) / _SCALE_DECAY_S)
    max_scale, nis_high = params[KALMAN_MAX_SCALE], params[KALMAN_NIS_THRESHOLD]
    tilt_on, accel_on = params[KALMAN_TILT_JERK_S] > 0.0, params[KALMAN_ANG_ACC_HOLD_S] > 0.0
    col_p = ADAPT_NIS_SCALE_P if tilt_on else ADAPT_SCALE_P  # where the NIS-driven part evolves
    col_r = ADAPT_NIS_SCALE_R if accel_on else ADAPT_SCALE_R
    adapt[col_p] = _adapt_scale(adapt[col_p], max(adapt[ADAPT_NIS_P], nis_img), alpha, decay, max_scale, nis_high)
    adapt[col_r] = _adapt_scale(adapt[col_r], max(adapt[ADAPT_NIS_R], nis_img_r), alpha, decay, max_scale, nis_high)
    # the cruise floors (fusion.kalman.cruise_*): the slow regime under the fast bursts, never above the
    # adaptation's own cap
    a_c = 1.0 - math.exp(-dt / params[KALMAN_CRUISE_TAU_S]) if dt > 0.0 else 0.0
    cruise_max = min(params[KALMAN_CRUISE_MAX_SCALE], max_scale)
    if cruise_max > 1.0:
        adapt[col_p] = max(adapt[col_p], _cruise_floor(adapt, ADAPT_NIS_CRUISE, ADAPT_SCALE_CRUISE, max(nis_p, nis_img),
                                                       a_c, dt, cap, cruise_max, params))
    cruise_max_r = min(params[KALMAN_CRUISE_MAX_SCALE_R], max_scale)
    if cruise_max_r > 1.0:
        adapt[col_r] = max(adapt[col_r], _cruise_floor(adapt, ADAPT_NIS_CRUISE_R, ADAPT_SCALE_CRUISE_R,
                                                       max(nis_r, nis_img_r), a_c, dt, cap, cruise_max_r, params))
    if tilt_on:
        adapt[ADAPT_SCALE_P] = max(adapt[col_p], tilt_jerk_scale(x, P, R_nom, params))
    if accel_on:
        adapt[ADAPT_SCALE_R] = max(adapt[col_r], angular_accel_scale(x, P, params))


@njit
def adapt_to_pose(adapt: np.ndarray, clock: np.ndarray, params: np.ndarray, dt: float, nis_p: float,
                  nis_r: float, x: np.ndarray, P: np.ndarray, R_nom: np.ndarray) -> None:
    """The NIS-driven adaptation after dt (s) of single-view updates, from the NIS per block of the
    triangulated pose of the same frames (pose_nis, taken before the views), in place; x, P, R_nom: the
    state after them (the multirotor floors)."""
    adapt_noise_scales(adapt, clock, params, int(clock[CLOCK_T_NS]), dt, nis_p, nis_r, True, x, P, R_nom)


@njit
def report_image_nis(adapt: np.ndarray, clock: np.ndarray, params: np.ndarray, t_ns: int, nis: float,
                     nis_rot: float) -> None:
    """Feed one body's manoeuvre detector (adapt (12,), clock (3,): its FilterBank rows)
    with one camera frame's prediction residual at t_ns, its translation part nis and its
    rotation part nis_rot (see BodyFilter.report_image_nis)."""
    dt = max((t_ns - clock[CLOCK_IMG_T_NS]) * 1e-9, 0.0)
    alpha = 1.0 - math.exp(-dt / params[KALMAN_NIS_TAU_S]) if clock[CLOCK_IMG_T_NS] != 0 else 1.0
    cap = params[KALMAN_GATE_CHI2] / 3.0
    adapt[ADAPT_NIS_IMG] += alpha * (min(nis, cap) - adapt[ADAPT_NIS_IMG])
    adapt[ADAPT_NIS_IMG_R] += alpha * (min(nis_rot, cap) - adapt[ADAPT_NIS_IMG_R])
    clock[CLOCK_IMG_T_NS] = t_ns
