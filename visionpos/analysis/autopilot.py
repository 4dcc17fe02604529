"""What an autopilot's own sensors say about the poses we send it: pure math, no I/O.

Two questions, both answered from the autopilot's telemetry (its gyro and its
attitude estimate, stamped on its own boot clock) against the optical body
(stamped on the server clock):

- Is it the same vehicle? (`identity_statistic`) Roll, pitch and the body rates
  do not depend on how the arena's yaw is aligned to north, so a wrong pairing
  (swapped sysids, drone A's pose sent to drone B, a mirrored marker layout)
  shows as residuals far outside the noise of the two estimates.
- Which vehicle is which, for a fleet of identical marker layouts? (`assign_identities`) Every
  optical body against every vehicle's telemetry: the assignment of least total residual, and per
  body the margin by which it beats the best assignment that gives that body another vehicle.
- What does each vehicle's accelerometer say? (`gaussian_kernel`, `optical_specific_force`,
  `accel_residuals`) The optical track's acceleration, rotated into the body frame with gravity removed and
  low-passed, against the IMU's specific force low-passed the same way: a vertical climb (no attitude, no
  rates) is a strong signal, and drones that take off in turn are told apart at their own take-off.
- How late does a pose reach the autopilot? (`estimate_lag`, `vision_delay_ns`)
  Cross-correlating the two angular rates gives the autopilot-clock time of the
  instant the optics stamped at a given server time (the clock offset, plus any
  bias of the optical stamps); TIMESYNC answers give the autopilot-clock time
  at which a packet sent at a known server time arrived. Their difference is the
  capture-to-autopilot delay on the vehicle's clock, which is what ArduPilot's
  VISO_DELAY_MS and PX4's EKF2_EV_DELAY want, whatever the link adds one way.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

from visionpos.geometry.frames import GRAVITY_M_S2

__all__ = ["LagEstimate", "estimate_lag", "body_rates_from_attitudes", "vision_delay_ns", "theil_sen_at",
           "weighted_time_ns", "identity_residuals", "identity_statistic", "wrap_angle", "IdentityAssignment",
           "assign_identities", "gaussian_kernel", "lowpass", "optical_specific_force",
           "accel_residuals"]


class LagEstimate(NamedTuple):
    """lag_ns: x_sig(t + lag) best matches x_ref(t); correlation: the normalised correlation at that lag
    (1 = identical shapes); samples: reference samples used."""

    lag_ns: float
    correlation: float
    samples: int


def _correlation_at(lags_ns: np.ndarray, q_ns: np.ndarray, xr: np.ndarray, nr: float, ts: np.ndarray,
                    x_sig: np.ndarray) -> np.ndarray:
    """Normalised correlation of the mean-free reference xr (n, K) (norm nr) with x_sig interpolated at
    q_ns + lag, for each lag in lags_ns (L,). The interpolation is a cubic spline: a linear one is exact at
    the samples only, which pulls the peak towards lags that put the reference on them."""
    q = q_ns[None, :] + lags_ns[:, None]  # (L, n)
    spline = CubicSpline(ts, x_sig, axis=0)(q.ravel()).reshape(q.shape + (x_sig.shape[1],))
    corr = np.zeros(len(lags_ns))
    ns = np.zeros(len(lags_ns))
    for j in range(x_sig.shape[1]):
        s = spline[..., j]
        s = s - s.mean(axis=1, keepdims=True)
        corr += s @ xr[:, j]
        ns += (s * s).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return corr / (nr * np.sqrt(ns))


def estimate_lag(t_ref_ns: np.ndarray, x_ref: np.ndarray, t_sig_ns: np.ndarray, x_sig: np.ndarray,
                 lag0_ns: float, max_lag_ns: float, step_ns: float = 1e6) -> LagEstimate | None:
    """The lag between two sampled vector signals by normalised cross-correlation.

    t_ref_ns (N,), x_ref (N, K): the reference (optical angular rate, server clock);
    t_sig_ns (M,), x_sig (M, K): the other signal (the autopilot's gyro, its clock);
    both time arrays increasing. Finds the lag in lag0_ns +- max_lag_ns at which
    x_sig(t + lag) best matches x_ref(t): first on a uniform grid of step_ns by FFT
    (both signals resampled), then with the signal interpolated at the reference's own
    times around that peak, refined by a parabola through the best lag and its
    neighbours a quarter step apart. Returns None when fewer than 20 reference samples
    overlap the signal at every lag tried, or a signal has no variation.
    """
    t_ref = np.asarray(t_ref_ns, dtype=np.float64)
    t_sig = np.asarray(t_sig_ns, dtype=np.float64)
    x_ref = np.asarray(x_ref, dtype=np.float64).reshape(len(t_ref), -1)
    x_sig = np.asarray(x_sig, dtype=np.float64).reshape(len(t_sig), -1)
    if len(t_sig) < 4 or len(t_ref) < 20:
        return None
    # times relative to t_sig[0]: float64 keeps sub-microsecond resolution on large clocks
    base = t_sig[0]
    ts = t_sig - base
    tr = t_ref - base + lag0_ns  # reference times moved onto the signal's clock
    keep = (tr - max_lag_ns >= ts[0]) & (tr + max_lag_ns <= ts[-1])
    if keep.sum() < 20:
        return None
    tr, xr = tr[keep], x_ref[keep] - x_ref[keep].mean(axis=0)
    nr = float(np.sqrt((xr * xr).sum()))
    if nr == 0:
        return None
    # coarse: both on a uniform grid, every lag at once
    k = int(np.ceil(max_lag_ns / step_ns))
    g_ref = np.arange(tr[0], tr[-1], step_ns)
    g_sig = g_ref[0] - k * step_ns + step_ns * np.arange(len(g_ref) + 2 * k)
    m = len(g_ref)
    num = np.zeros(2 * k + 1)
    den = np.zeros(2 * k + 1)
    nfft = 1 << (len(g_sig) + m - 1).bit_length()
    for j in range(x_ref.shape[1]):
        a = np.interp(g_ref, tr, xr[:, j])
        a = a - a.mean()
        b = np.interp(g_sig, ts, x_sig[:, j])
        c = np.fft.irfft(np.fft.rfft(b, nfft) * np.conj(np.fft.rfft(a, nfft)), nfft)
        num += c[: 2 * k + 1]  # c[i] = sum_m b[m + i] a[m]: lag (i - k) steps
        # the signal's variance over each lag's window (a is mean-free, so its mean drops out of num)
        c1 = np.concatenate([[0.0], np.cumsum(b)])
        c2 = np.concatenate([[0.0], np.cumsum(b * b)])
        s1 = c1[m: m + 2 * k + 1] - c1[: 2 * k + 1]
        s2 = c2[m: m + 2 * k + 1] - c2[: 2 * k + 1]
        den += s2 - s1 * s1 / m
    full = num / np.sqrt(np.maximum(den, 1e-300))
    i = int(np.argmax(full))
    # fine: the signal's spline at the reference times, a quarter step apart around the peak (moved along
    # while the best is at an edge: the resampled coarse peak can be a step or two off)
    h = step_ns / 4
    centre = (i - k) * step_ns
    for _ in range(8):
        lags = centre + h * np.arange(-4, 5)
        corr = _correlation_at(lags, tr, xr, nr, ts, x_sig)
        if not np.all(np.isfinite(corr)):
            return None
        j = int(np.argmax(corr))
        if 0 < j < len(lags) - 1 or abs(lags[j]) + h > max_lag_ns:
            break
        centre = lags[j]
    lag = lags[j]
    if 0 < j < len(lags) - 1:
        a_, b_, c_ = corr[j - 1], corr[j], corr[j + 1]
        den = a_ - 2 * b_ + c_
        if den < 0:
            lag += 0.5 * (a_ - c_) / den * h
    lag += lag0_ns
    return LagEstimate(float(lag), float(corr[j]), int(keep.sum()))


def body_rates_from_attitudes(t_ns: np.ndarray, quaternions: np.ndarray, span: int = 2,
                              max_gap_ns: float = 100e6) -> tuple[np.ndarray, np.ndarray]:
    """Body rates from an attitude series by symmetric differences, so they lag nothing.

    t_ns (N,) increasing; quaternions (N, 4) xyzw body -> frame. The rate between samples i and
    i + 2*span is the rotation vector of R_i^T R_(i+2 span) over their time apart, in the body
    frame, stamped at their mid-time (a Kalman filter's own rate estimate trails the motion when
    it accelerates; its attitude does not). Pairs further apart than max_gap_ns are dropped.
    Returns (t_mid_ns (M,) float64, rates (M, 3) rad/s).
    """
    t = np.asarray(t_ns, dtype=np.float64)
    k = 2 * span
    if len(t) <= k:
        return np.zeros(0), np.zeros((0, 3))
    R = Rotation.from_quat(np.asarray(quaternions, dtype=np.float64))
    dt = t[k:] - t[:-k]
    ok = (dt > 0) & (dt <= max_gap_ns)
    rv = (R[:-k].inv() * R[k:]).as_rotvec()
    return (0.5 * (t[k:] + t[:-k]))[ok], rv[ok] / (dt[ok, None] * 1e-9)


def vision_delay_ns(send_minus_stamp_ns: np.ndarray, timesync_s1_ns: np.ndarray, timesync_tc1_ns: np.ndarray,
                    clock_lag_ns: float, at_ns: float | None = None, local_ns: float = 3e9) -> float:
    """Capture-to-autopilot delay (ns) on the autopilot's clock.

    send_minus_stamp_ns (N,): for each sent pose, its send time less its stamp (server clock);
    timesync_s1_ns (M,), timesync_tc1_ns (M,): our TIMESYNC requests' send times (server clock)
    and the autopilot's receive times of them (its clock), so tc1 - s1 is the forward link's
    latency plus the clock offset; clock_lag_ns: the autopilot-clock time less the server
    stamp of one physical instant (estimate_lag on the angular rates). The clock offset
    cancels: delay = median(send - stamp) + (tc1 - s1) - clock_lag, with tc1 - s1 taken at at_ns
    (server clock: the instant clock_lag stands for, `weighted_time_ns`) on a robust line through
    the answers, as the two clocks drift apart (a simulator behind real time, a crystal's ppm: 0.1 ms/s
    is 1 ms over 10 s), or their median without at_ns or with fewer than 3 answers. The line goes through the
    answers within local_ns of at_ns where there are 3 or more: a clock whose rate wanders (PX4 SIH's lockstep
    clock, 1.15-1.6 % slow as the host's load comes and goes) bends away from one line over half a minute.
    """
    s1 = np.asarray(timesync_s1_ns, dtype=np.float64)
    fwd = np.asarray(timesync_tc1_ns, dtype=np.float64) - s1
    if at_ns is not None and np.count_nonzero(near := np.abs(s1 - at_ns) <= local_ns) >= 3:
        s1, fwd = s1[near], fwd[near]
    f = np.median(fwd) if at_ns is None else theil_sen_at(s1, fwd, at_ns)
    return float(np.median(send_minus_stamp_ns) + f - clock_lag_ns)


def theil_sen_line(t: np.ndarray, y: np.ndarray) -> tuple[float, float, float] | None:
    """The Theil-Sen line through (t, y): (t0, y at t0, slope), t0 the median of t, the slope the median of the
    pairwise slopes, the intercept the median of the residuals (a few late answers do not move it); None for
    fewer than 3 points or no spread of t."""
    t = np.asarray(t, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if len(t) < 3 or np.ptp(t) <= 0:
        return None
    i, j = np.triu_indices(len(t), 1)
    dt = t[j] - t[i]
    ok = dt != 0
    slope = float(np.median((y[j] - y[i])[ok] / dt[ok]))
    t0 = float(np.median(t))
    return t0, float(np.median(y - slope * (t - t0))), slope


def theil_sen_at(t: np.ndarray, y: np.ndarray, at: float) -> float:
    """theil_sen_line through (t, y) evaluated at `at`; the median of y for fewer than 3 points or no spread
    of t."""
    line = theil_sen_line(t, y)
    if line is None:
        return float(np.median(np.asarray(y, dtype=np.float64)))
    t0, y0, slope = line
    return float(y0 + slope * (at - t0))


def weighted_time_ns(t_ns: np.ndarray, x: np.ndarray) -> float:
    """The instant a correlation of x (N, K) sampled at t_ns (N,) stands for: the mean time weighted by the
    signal's power (mean-free squares summed over the axes), where the correlation gets its lag from."""
    t = np.asarray(t_ns, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64).reshape(len(t), -1)
    w = ((x - x.mean(axis=0)) ** 2).sum(axis=1)
    sw = float(w.sum())
    return float((w * t).sum() / sw) if sw > 0 else float(np.median(t))


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles (rad, any shape) wrapped into [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + np.pi) % (2 * np.pi) - np.pi


def identity_residuals(att_ap: np.ndarray, rate_ap: np.ndarray, att_opt: np.ndarray, rate_opt: np.ndarray,
                       sigma_att_rad: float, sigma_rate_rad_s: float, rate_rel: float) -> np.ndarray:
    """Normalised residuals (N, 5) between the autopilot and the optical body at the same instants.

    att_ap, att_opt (N, 2): roll, pitch rad (FRD in NED); rate_ap, rate_opt (N, 3): body rates
    rad/s FRD. Noise model per sample: sigma_att_rad for roll and pitch; for each rate axis
    sigma_rate_rad_s + rate_rel * |rate_opt| (gyro noise and bias, plus the rate error of a
    timing mismatch, which grows with the motion).
    """
    ra = wrap_angle(np.asarray(att_ap, float) - np.asarray(att_opt, float)) / sigma_att_rad
    ro = np.asarray(rate_opt, float)
    sr = sigma_rate_rad_s + rate_rel * np.linalg.norm(ro, axis=1, keepdims=True)
    rr = (np.asarray(rate_ap, float) - ro) / sr
    return np.hstack([ra, rr])


def identity_statistic(residuals: np.ndarray) -> float:
    """Mean squared normalised residual of a window (N, K): about 1 (and under it for a noise model
    that is generous) when the two are the same vehicle; NaN for an empty window."""
    r = np.asarray(residuals, float)
    return float(np.mean(r * r)) if r.size else float("nan")


class IdentityAssignment(NamedTuple):
    """vehicle (B,) int: the vehicle index bound to each optical body, -1 for none; margin (B,): how much
    larger (in summed squared normalised residuals, i.e. twice the log-likelihood ratio) the best assignment
    that gives this body another vehicle, or none, is than the chosen one (inf when there is no other
    choice); candidates (B,) int: the vehicles whose own pair cost is within the margin threshold of the
    chosen pair's (how many this body could be)."""

    vehicle: np.ndarray
    margin: np.ndarray
    candidates: np.ndarray


def assign_identities(cost: np.ndarray, reject_cost: np.ndarray | float, ambiguity: float) -> IdentityAssignment:
    """Bind B optical bodies to V vehicles (a fleet with identical marker layouts) from their telemetry.

    cost (B, V): for each body-vehicle pair, the sum of squared normalised residuals (`identity_residuals`)
    over one window of shared instants, the same count of instants for every pair; NaN or inf where the pair
    cannot be compared (no telemetry, no optical pose). reject_cost (B,) or scalar: the cost at which a body
    is better left unbound (a chi-square quantile for its residuals' degrees of freedom: no vehicle moves
    like it). ambiguity: the margin (same units) under which a body's binding is not trusted, e.g.
    2 ln(1000) = 13.8 for odds of a thousand to one.

    Minimises the total cost over one-to-one assignments in which each body takes a vehicle or none (its
    reject cost), by the Hungarian method; then, for each bound body, solves again with its pair forbidden:
    the difference is its margin. Still vehicles and still bodies have near-zero rates and level attitudes:
    every pairing fits and every margin is small, so nothing is bound until the vehicles move.
    """
    from scipy.optimize import linear_sum_assignment

    c = np.asarray(cost, dtype=np.float64)
    B, V = c.shape
    reject = np.broadcast_to(np.asarray(reject_cost, dtype=np.float64), (B,))
    big = 1e12  # a forbidden pair: never chosen while the reject column is open
    full = np.full((B, V + B), big)
    full[:, :V] = np.where(np.isfinite(c), c, big)
    full[np.arange(B), V + np.arange(B)] = reject  # each body's own "no vehicle" column

    def solve(m: np.ndarray) -> tuple[float, np.ndarray]:
        rows, cols = linear_sum_assignment(m)
        out = np.full(B, -1)
        out[rows] = cols
        return float(m[rows, cols].sum()), out

    best, cols = solve(full)
    vehicle = np.where(cols < V, cols, -1)
    margin = np.full(B, np.inf)
    candidates = np.zeros(B, dtype=int)
    for b in range(B):
        if vehicle[b] < 0:
            continue
        m = full.copy()
        m[b, vehicle[b]] = big
        alt, _ = solve(m)
        margin[b] = alt - best if alt < big / 2 else np.inf
        pair = full[b, vehicle[b]]
        candidates[b] = int(np.sum(full[b, :V] <= pair + ambiguity))
    return IdentityAssignment(vehicle, margin, candidates)


def gaussian_kernel(sigma_s: float, dt_s: float) -> np.ndarray:
    """A Gaussian low-pass (2K+1,) for samples dt_s apart, sigma_s s wide, cut at 3 sigma, summing to 1: its
    response is exp(-2 pi^2 sigma^2 f^2) (0.95 at 1 Hz for sigma 50 ms, 0.64 at 3 Hz)."""
    k = max(1, int(np.ceil(3.0 * sigma_s / dt_s)))
    x = np.arange(-k, k + 1) * dt_s
    w = np.exp(-0.5 * (x / sigma_s) ** 2)
    return w / w.sum()


def lowpass(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """x (N, k) on a uniform grid convolved with kernel (2K+1,), centred (no lag): (N, k), NaN within K
    samples of either end and wherever the kernel covers a NaN sample."""
    x = np.asarray(x, dtype=np.float64)
    half = len(kernel) // 2
    out = np.full(x.shape, np.nan)
    if len(x) < len(kernel):
        return out
    for c in range(x.shape[1]):
        out[half: len(x) - half, c] = np.convolve(x[:, c], kernel[::-1], mode="valid")
    return out


def optical_specific_force(positions_m: np.ndarray, quaternions: np.ndarray, dt_s: float,
                           kernel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What an accelerometer on the optical body reads, low-passed: (N, 3) m/s^2 FRD, and the magnitude of its
    low-passed acceleration (N,) m/s^2 (gravity not included); NaN where not known.

    positions_m (N, 3) world z-up and quaternions (N, 4) xyzw body FLU -> world, on a uniform grid dt_s apart
    (NaN rows: no sample). The acceleration is the second difference of the positions; with gravity added
    (specific force: at rest the body reads +g up, -g on z down in FRD) it is rotated into the body at each
    instant, then low-passed with kernel: the same low-pass applied to the IMU's samples makes the two
    comparable (the second difference of noisy positions is all noise above a few hertz).
    """
    p = np.asarray(positions_m, dtype=np.float64)
    n = len(p)
    f = np.full((n, 3), np.nan)
    if n < 3:
        return f
    a = np.full((n, 3), np.nan)
    a[1:-1] = (p[2:] - 2.0 * p[1:-1] + p[:-2]) / (dt_s * dt_s)
    q = np.asarray(quaternions, dtype=np.float64)
    ok = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(a), axis=1)
    if ok.any():
        f_world = a[ok] + np.array([0.0, 0.0, GRAVITY_M_S2])
        f[ok] = Rotation.from_quat(q[ok]).inv().apply(f_world) * np.array([1.0, -1.0, -1.0])
    return lowpass(f, kernel), np.linalg.norm(lowpass(a, kernel), axis=1)


def accel_residuals(f_ap: np.ndarray, f_opt: np.ndarray, accel_opt_m_s2: np.ndarray, sigma_m_s2: float,
                    rel: float, bias_sigma_m_s2: float) -> np.ndarray:
    """Normalised residuals (..., N + 1, 3) between the autopilot's low-passed specific force f_ap (..., N, 3)
    m/s^2 FRD and the optical body's f_opt (..., N, 3) (optical_specific_force) at the same N instants, less the
    pair's accelerometer bias: the N instants' and, last, the bias's own (its estimate over bias_sigma_m_s2).
    Leading axes broadcast (every pair of a fleet at once).

    Noise per sample: sigma_m_s2 + rel * accel_opt_m_s2 (..., N), the optical body's acceleration (its track's
    error grows with the manoeuvre: the filter's lag, the clocks' timing). The bias is estimated per axis with
    a zero-mean prior of bias_sigma_m_s2 (a calibrated IMU's): the weighted mean residual shrunk towards zero.
    Without the prior (inf) a short stretch of steady acceleration (a climb's) would pass for a bias; with it
    the sum of squares is chi-square with 3 N degrees of freedom for a true pair (3 (N - 1) for inf: the mean
    residual is taken away).
    """
    e = np.asarray(f_ap, dtype=np.float64) - np.asarray(f_opt, dtype=np.float64)
    sig = sigma_m_s2 + rel * np.asarray(accel_opt_m_s2, dtype=np.float64)[..., None]  # (..., N, 1)
    w = 1.0 / sig**2
    bias = (w * e).sum(axis=-2, keepdims=True) / (w.sum(axis=-2, keepdims=True) + 1.0 / bias_sigma_m_s2**2)
    e, bias = np.broadcast_arrays(e, bias)
    return np.concatenate([(e - bias[..., :1, :]) / sig, bias[..., :1, :] / bias_sigma_m_s2], axis=-2)
