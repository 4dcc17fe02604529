"""Single-marker (point) bodies: position-only tracks kept apart by continuity. Pure numpy, no I/O.

A body with one marker (`markers: [[0, 0, 0]]`) has no attitude and no geometry to identify it by: the
pipeline tracks it from the triangulated points no rigid body claimed (match_unlabeled over the free blobs
of a fusion's frames), at most every POINT_INTERVAL_NS of capture time:

- each tracked point body's constant-acceleration Kalman filter (position, velocity, acceleration; white jerk)
  is predicted to the fusion's time, and the points are assigned to the predictions (Hungarian on the
  squared distance normalised by the innovation covariance, gated at GATE_NIS plus GATE_FLOOR_M);
- an assigned point updates its track at the point's own time, the mean capture time of the views that saw
  it (the cameras are asynchronous: a fusion's frames saw a moving marker at different instants); a track
  without a point for the lost timeout is lost;
- a point no track takes, seen by at least ACQUIRE_VIEWS cameras in CONFIRM_HITS fusions in a row near the
  same place, is a candidate: the pipeline names it as it names identical rigid bodies (IdentityBook: the
  nearest lost body by last position, a body never seen by the parking order), and the identity book marks
  two point tracks that come within its swap distance 'unresolved: two candidates'.

Positions m world, velocities m/s, accelerations m/s^2, times ns on the capture clock.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from visionpos.fusion.tracking import white_jerk_coefficients

N_POINT_STATE = 9  # position (3), velocity (3), acceleration (3)
# white-jerk spectral density (m^2/s^5); on the fleet plan (thesis arena) 400 gave 2.9 mm RMSE, 10 gave 1.8 mm
JERK_PSD = 10.0
GATE_NIS = 16.27  # chi-square, 3 dof, p = 0.001: a point farther from a prediction is not its marker ...
GATE_FLOOR_M = 0.02  # ... unless within this (a tight filter must still follow an unmodelled jerk)
POINT_INTERVAL_NS = 4_000_000  # point tracking at most this often (capture clock)
ACQUIRE_VIEWS = 3  # a new point is seen by this many cameras (two static reflections rarely meet a third ray)
CONFIRM_HITS = 5  # ... in this many point fusions in a row within the gate floor of its last position
INIT_VEL_VAR = 0.25  # m^2/s^2: a new track's velocity prior (a drone acquired in flight, up to ~1 m/s)
INIT_ACC_VAR = 4.0  # m^2/s^4


def ca_transition(dt_s: float) -> np.ndarray:
    """The constant-acceleration transition (9, 9) over dt_s seconds."""
    F = np.eye(N_POINT_STATE)
    i3 = np.eye(3)
    F[0:3, 3:6] = dt_s * i3
    F[0:3, 6:9] = 0.5 * dt_s * dt_s * i3
    F[3:6, 6:9] = dt_s * i3
    return F


def ca_process_noise(dt_s: float, jerk_psd: float = JERK_PSD) -> np.ndarray:
    """The white-jerk process noise (9, 9) over dt_s seconds (m^2 ... m^2/s^4), jerk_psd m^2/s^5."""
    return np.kron(jerk_psd * white_jerk_coefficients(float(dt_s)), np.eye(3))


def predict(x: np.ndarray, P: np.ndarray, dt_s: np.ndarray, jerk_psd: float = JERK_PSD
            ) -> tuple[np.ndarray, np.ndarray]:
    """States (K, 9) and covariances (K, 9, 9) moved on by dt_s (K,) s each."""
    F = np.stack([ca_transition(float(d)) for d in np.asarray(dt_s, float).reshape(-1)])
    Q = np.stack([ca_process_noise(float(d), jerk_psd) for d in np.asarray(dt_s, float).reshape(-1)])
    return np.einsum("kij,kj->ki", F, x), F @ P @ F.transpose(0, 2, 1) + Q


def update(x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update of states (K, 9), covariances (K, 9, 9) with positions z (K, 3) m of covariance R (K, 3, 3)
    (Joseph form: stays symmetric positive definite)."""
    S = P[:, :3, :3] + R
    K = np.linalg.solve(S, P[:, :3, :]).transpose(0, 2, 1)  # P H^T S^-1, (K, 9, 3); S and P symmetric
    x = x + np.einsum("kij,kj->ki", K, z - x[:, :3])
    IKH = np.tile(np.eye(N_POINT_STATE), (len(x), 1, 1))
    IKH[:, :, :3] -= K
    P = IKH @ P @ IKH.transpose(0, 2, 1) + K @ R @ K.transpose(0, 2, 1)
    return x, 0.5 * (P + P.transpose(0, 2, 1))


def initial_state(position: np.ndarray, pos_var_m2: float) -> tuple[np.ndarray, np.ndarray]:
    """A new track's state (9,) at rest at position (3,) m and covariance (9, 9)."""
    x = np.zeros(N_POINT_STATE)
    x[:3] = position
    P = np.diag([pos_var_m2] * 3 + [INIT_VEL_VAR] * 3 + [INIT_ACC_VAR] * 3)
    return x, P


def associate(pred_m: np.ndarray, S: np.ndarray, points_m: np.ndarray, gate_nis: float = GATE_NIS,
              floor_m: float = GATE_FLOOR_M) -> np.ndarray:
    """Per prediction (K, 3) m with innovation covariance S (K, 3, 3) m^2, the index of its point among
    points_m (N, 3) m, or -1: the assignment of least total normalised squared distance among the pairs within
    the gate (NIS <= gate_nis, or closer than floor_m)."""
    K, N = len(pred_m), len(points_m)
    out = np.full(K, -1, dtype=np.int64)
    if K == 0 or N == 0:
        return out
    d = points_m[None, :, :] - pred_m[:, None, :]  # (K, N, 3)
    nis = np.einsum("kni,kij,knj->kn", d, np.linalg.inv(S), d)
    ok = (nis <= gate_nis) | ((d * d).sum(-1) <= floor_m * floor_m)
    if not ok.any():
        return out
    cost = np.where(ok, nis, 1e9)
    rows, cols = linear_sum_assignment(cost)
    keep = ok[rows, cols]
    out[rows[keep]] = cols[keep]
    return out


def confirm_candidates(cand_m: np.ndarray, hits: np.ndarray, points_m: np.ndarray,
                       floor_m: float = GATE_FLOOR_M) -> tuple[np.ndarray, np.ndarray]:
    """Candidates for new tracks (C, 3) m with hit counts (C,) against this fusion's unclaimed points (N, 3) m:
    a candidate with a point within floor_m moves there and counts one more hit, one without is dropped, a point
    no candidate takes starts one. Returns the new (C', 3), (C',)."""
    if len(points_m) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    match = associate(cand_m, np.tile(np.eye(3) * floor_m**2, (len(cand_m), 1, 1)), points_m, 0.0, floor_m)
    taken = match[match >= 0]
    fresh = np.setdiff1d(np.arange(len(points_m)), taken)
    pos = np.concatenate([points_m[taken], points_m[fresh]])
    count = np.concatenate([hits[match >= 0] + 1, np.ones(len(fresh), dtype=np.int64)])
    return pos, count


def close_pairs(positions_m: np.ndarray, distance_m: float) -> list[tuple[int, int]]:
    """Index pairs (i < j) of positions (K, 3) m closer than distance_m."""
    p = np.asarray(positions_m, float).reshape(-1, 3)
    d2 = ((p[:, None] - p[None]) ** 2).sum(-1)
    i, j = np.nonzero(np.triu(d2 < distance_m * distance_m, 1))
    return list(zip(i.tolist(), j.tolist()))


class PointTracks:
    """The filters of the point bodies (global body indices `bodies`), their candidates and their counters."""

    def __init__(self, bodies: list[int], marker_sigma_m: float):
        K = len(bodies)
        self.bodies = list(bodies)
        self.x = np.zeros((K, N_POINT_STATE))
        self.P = np.tile(np.eye(N_POINT_STATE), (K, 1, 1))
        self.t_ns = np.zeros(K, dtype=np.int64)  # each filter's time
        self.tracked = np.zeros(K, dtype=bool)
        self.last_update_ns = np.zeros(K, dtype=np.int64)
        self.last_capture_ns = np.zeros(K, dtype=np.int64)
        self.n_cameras = np.zeros(K, dtype=np.int64)
        self.residual_px = np.full(K, np.nan)
        self.meas_var_floor = float(marker_sigma_m) ** 2
        self.cand = np.zeros((0, 3))
        self.hits = np.zeros(0, dtype=np.int64)
        self.last_ns = -(1 << 62)

    def due(self, ref_ns: int) -> bool:
        return not 0 <= ref_ns - self.last_ns < POINT_INTERVAL_NS

    def step(self, ref_ns: int, points_m: np.ndarray, var_m2: np.ndarray, n_views: np.ndarray,
             t_meas_ns: np.ndarray, capture_ns: int) -> np.ndarray:
        """One point fusion at ref_ns: points (N, 3) m triangulated from n_views (N,) cameras with variance
        var_m2 (N,) m^2 per axis, each at t_meas_ns (N,) (the mean capture time of its views: asynchronous
        cameras see a moving marker at different instants). Associates at ref_ns, updates each track that took a
        point at that point's time; returns per point the track index that took it (-1: none)."""
        self.last_ns = ref_ns
        used = np.full(len(points_m), -1, dtype=np.int64)
        live = np.flatnonzero(self.tracked)
        if not len(live) or not len(points_m):
            return used
        x, P = predict(self.x[live], self.P[live], (ref_ns - self.t_ns[live]) * 1e-9)
        R = np.maximum(var_m2, self.meas_var_floor)[:, None, None] * np.eye(3)
        match = associate(x[:, :3], P[:, :3, :3] + np.mean(R, axis=0), points_m)
        hit = match >= 0
        hit[hit] = t_meas_ns[match[hit]] > self.t_ns[live[hit]]  # the same frames again (older on average): no news
        if not hit.any():
            return used
        k, q = live[hit], match[hit]
        x, P = predict(self.x[k], self.P[k], (t_meas_ns[q] - self.t_ns[k]) * 1e-9)
        self.x[k], self.P[k] = update(x, P, points_m[q], R[q])
        self.t_ns[k] = t_meas_ns[q]
        self.last_update_ns[k] = ref_ns
        self.last_capture_ns[k] = capture_ns
        self.n_cameras[k] = n_views[q]
        used[q] = k
        return used

    def candidates(self, points_m: np.ndarray, n_views: np.ndarray) -> np.ndarray:
        """The unclaimed points (N, 3) m of this fusion: the candidates moved on (confirm_candidates, only
        points seen by ACQUIRE_VIEWS cameras); returns the positions (C, 3) m of the confirmed ones."""
        self.cand, self.hits = confirm_candidates(self.cand, self.hits, points_m[n_views >= ACQUIRE_VIEWS])
        return self.cand[self.hits >= CONFIRM_HITS]

    def start(self, k: int, ref_ns: int, position_m: np.ndarray, var_m2: float, capture_ns: int) -> None:
        """Track k starts at position_m; the candidate there is used up."""
        self.x[k], self.P[k] = initial_state(position_m, max(var_m2, self.meas_var_floor))
        self.t_ns[k] = self.last_update_ns[k] = ref_ns
        self.last_capture_ns[k] = capture_ns
        self.tracked[k] = True
        keep = ((self.cand - position_m) ** 2).sum(-1) > 1e-12
        self.cand, self.hits = self.cand[keep], self.hits[keep]

    def output_at(self, k: int, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Track k predicted to t_ns: position (3,) m, velocity (3,) m/s, their covariances (3, 3) each."""
        x, P = predict(self.x[k][None], self.P[k][None], np.array([(t_ns - self.t_ns[k]) * 1e-9]))
        return x[0, :3], x[0, 3:6], P[0, :3, :3], P[0, 3:6, 3:6]
