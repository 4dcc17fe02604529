"""The process-noise adaptation of the body filter (tracking.py): the NIS-driven scales of its position and
rotation noise, the image-space manoeuvre detector that feeds them, and the cruise floors under both
scales. Why each exists is in tracking.py's docstring; the settings are fusion.kalman's (fusion/settings.py).

adapt (10,) and clock (3,) are one body's FilterBank rows (layout.ADAPT_*, layout.CLOCK_*); params its
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
    ADAPT_SCALE_CRUISE,
    ADAPT_SCALE_CRUISE_R,
    ADAPT_SCALE_P,
    ADAPT_SCALE_R,
    CLOCK_IMG_T_NS,
    CLOCK_T_NS,
    KALMAN_CRUISE_MAX_SCALE,
    KALMAN_CRUISE_MAX_SCALE_R,
    KALMAN_CRUISE_NIS_THRESHOLD,
    KALMAN_CRUISE_RATE,
    KALMAN_CRUISE_TAU_S,
    KALMAN_GATE_CHI2,
    KALMAN_MAX_SCALE,
    KALMAN_NIS_TAU_S,
    KALMAN_NIS_THRESHOLD,
)
from visionpos.jit import njit

_SCALE_DECAY_S = 0.2  # s, time constant of the process-noise scale's return to its floor
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
def adapt_noise_scales(adapt: np.ndarray, clock: np.ndarray, params: np.ndarray, t_ns: int, dt: float,
                       nis_p: float, nis_r: float, use_image_nis: bool) -> None:
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
    flicks its rate, predicted on to the output ticks, must stay smooth).
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
    adapt[ADAPT_SCALE_P] = _adapt_scale(adapt[ADAPT_SCALE_P], max(adapt[ADAPT_NIS_P], nis_img), alpha, decay, max_scale,
                                        nis_high)
    adapt[ADAPT_SCALE_R] = _adapt_scale(adapt[ADAPT_SCALE_R], max(adapt[ADAPT_NIS_R], nis_img_r), alpha, decay,
                                        max_scale, nis_high)
    # the cruise floors (fusion.kalman.cruise_*): the slow regime under the fast bursts, never above the
    # adaptation's own cap
    a_c = 1.0 - math.exp(-dt / params[KALMAN_CRUISE_TAU_S]) if dt > 0.0 else 0.0
    cruise_max = min(params[KALMAN_CRUISE_MAX_SCALE], max_scale)
    if cruise_max > 1.0:
        adapt[ADAPT_SCALE_P] = max(adapt[ADAPT_SCALE_P], _cruise_floor(adapt, ADAPT_NIS_CRUISE, ADAPT_SCALE_CRUISE,
                                                                       max(nis_p, nis_img), a_c, dt, cap, cruise_max,
                                                                       params))
    cruise_max_r = min(params[KALMAN_CRUISE_MAX_SCALE_R], max_scale)
    if cruise_max_r > 1.0:
        adapt[ADAPT_SCALE_R] = max(adapt[ADAPT_SCALE_R], _cruise_floor(adapt, ADAPT_NIS_CRUISE_R, ADAPT_SCALE_CRUISE_R,
                                                                       max(nis_r, nis_img_r), a_c, dt, cap,
                                                                       cruise_max_r, params))


@njit
def adapt_to_pose(adapt: np.ndarray, clock: np.ndarray, params: np.ndarray, dt: float, nis_p: float,
                  nis_r: float) -> None:
    """The NIS-driven adaptation after dt (s) of single-view updates, from the NIS per block of the
    triangulated pose of the same frames (pose_nis, taken before the views), in place."""
    adapt_noise_scales(adapt, clock, params, int(clock[CLOCK_T_NS]), dt, nis_p, nis_r, True)


@njit
def report_image_nis(adapt: np.ndarray, clock: np.ndarray, params: np.ndarray, t_ns: int, nis: float,
                     nis_rot: float) -> None:
    """Feed one body's manoeuvre detector (adapt (10,), clock (3,): its FilterBank rows)
    with one camera frame's prediction residual at t_ns, its translation part nis and its
    rotation part nis_rot (see BodyFilter.report_image_nis)."""
    dt = max((t_ns - clock[CLOCK_IMG_T_NS]) * 1e-9, 0.0)
    alpha = 1.0 - math.exp(-dt / params[KALMAN_NIS_TAU_S]) if clock[CLOCK_IMG_T_NS] != 0 else 1.0
    cap = params[KALMAN_GATE_CHI2] / 3.0
    adapt[ADAPT_NIS_IMG] += alpha * (min(nis, cap) - adapt[ADAPT_NIS_IMG])
    adapt[ADAPT_NIS_IMG_R] += alpha * (min(nis_rot, cap) - adapt[ADAPT_NIS_IMG_R])
    clock[CLOCK_IMG_T_NS] = t_ns
