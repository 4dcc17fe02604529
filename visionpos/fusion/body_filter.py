"""The filters' state as arrays the compiled kernels update in place, and the Python handles over them.

FilterBank holds the states of n body filters, one row each (fusion/tracking.py's kernels take its `arrays`);
BodyFilter is one row's filter with the methods the pipeline and the tests call (initialize, predict_to,
update, report_image_nis, pose_at, output_at); array_field exposes one cell of a packed row as an attribute.
"""

from __future__ import annotations

import numpy as np

from visionpos.fusion.adaptation import report_image_nis
from visionpos.fusion.layout import (
    ADAPT_SCALE_P,
    ADAPT_SCALE_R,
    CLOCK_T_NS,
    N_ADAPT,
    N_CLOCK,
    N_STATE,
    OUT_ACC,
    OUT_POS,
    OUT_POSE_COV,
    OUT_QUAT_XYZW,
    OUT_RATE_BODY,
    OUT_VEL,
    OUT_VEL_COV,
    X_ANG_ACC,
    X_RATE,
    FilterArrays,
)
from visionpos.fusion.settings import KALMAN_PARAMS, KalmanSettings, pack_params
from visionpos.fusion.tracking import (
    _count_folds,
    _kf_predict,
    _output_at,
    filter_initialize,
    filter_update,
    predict_mean,
)


class FilterBank:
    """The states of n body filters, one row each, so that compiled kernels update them in place.

    x (n, 18), P (n, 18, 18), R_nom (n, 3, 3); adapt (n, 12): process-noise scales
    and NIS averages [scale_p, scale_r, nis_p, nis_r, nis_img, nis_img_r, nis_cruise, scale_cruise, nis_cruise_r,
    scale_cruise_r, nis_scale_p, nis_scale_r]; clock (n, 3) int64:
    [filter time ns, last image-NIS time ns, folds]; params (N_KALMAN_PARAMS,): the settings
    the kernels read, packed as fusion/settings.py's KALMAN_PARAMS declares (layout.KALMAN_* indices).
    filters[i] is the BodyFilter over row i.
    """

    def __init__(self, n: int, settings: KalmanSettings, make_filters: bool = True):
        self.x = np.zeros((n, N_STATE))
        self.P = np.tile(np.eye(N_STATE), (n, 1, 1))
        self.R_nom = np.tile(np.eye(3), (n, 1, 1))
        self.adapt = np.ones((n, N_ADAPT))
        self.clock = np.zeros((n, N_CLOCK), dtype=np.int64)
        self.params = pack_params(KALMAN_PARAMS, settings)  # fusion/settings.py declares its entries
        # the kernels' argument (layout.FilterArrays as a plain tuple: cheaper for numba to dispatch)
        self.arrays = tuple(FilterArrays(self.x, self.P, self.R_nom, self.adapt, self.clock, self.params))
        self.filters = [BodyFilter(settings, self, i) for i in range(n)] if make_filters else []


def array_field(row: str, col, kind, doc: str = "") -> property:
    """An attribute kept in cell `col` of the array attribute `row` (a view of a packed state
    row, so compiled kernels read and write the same value), read through `kind`; assigning
    writes the cell. col = ... : the whole row (kind np.asarray: the view itself)."""

    def get(self):
        return kind(getattr(self, row)[col])

    def put(self, value):
        getattr(self, row)[col] = value

    return property(get, put, doc=doc)


class BodyFilter:
    """Error-state Kalman filter of one body; times are int64 ns (capture clock).

    State x (18,) and covariance P (18, 18) as in the module docstring, plus
    the nominal rotation R_nom (3, 3) body->world and the NIS-driven noise
    scales. They live in a row of a FilterBank (a bank of one when none is
    given). The linear algebra is in compiled kernels (visionpos.jit): the
    standard predict and Joseph-form update, checked against filterpy's
    KalmanFilter in the tests.
    """

    x = array_field("_x", ..., np.asarray, "state (18,)")
    P = array_field("_P", ..., np.asarray, "covariance (18, 18)")
    R_nom = array_field("_R_nom", ..., np.asarray, "nominal rotation (3, 3) body->world")
    t_ns = array_field("_clock", CLOCK_T_NS, int, "filter time, ns")
    scale_p = array_field("_adapt", ADAPT_SCALE_P, float, "process-noise scale of the position block")
    scale_r = array_field("_adapt", ADAPT_SCALE_R, float, "process-noise scale of the rotation block")

    def __init__(self, settings: KalmanSettings, bank: FilterBank | None = None, row: int = 0):
        self.s = settings
        if bank is None:  # a bank of its own
            bank, row = FilterBank(1, settings, make_filters=False), 0
            bank.filters.append(self)
        self.bank = bank
        self.row = row
        self._x, self._P, self._R_nom = bank.x[row], bank.P[row], bank.R_nom[row]
        self._adapt, self._clock = bank.adapt[row], bank.clock[row]

    # -------------------------------------------------------------- lifecycle
    def initialize(self, t_ns: int, position: np.ndarray, R: np.ndarray, meas_cov: np.ndarray | None = None) -> None:
        """Start (or restart) at a measured pose (filter_initialize); derivatives unknown (zero
        with a wide prior). meas_cov (6, 6) over [p, world rotation vector]; None: 1 mm, 0.6 deg."""
        if meas_cov is None:
            meas_cov = np.diag([1e-6] * 3 + [1e-4] * 3)
        filter_initialize(self.x, self.P, self.R_nom, self._adapt, self._clock, self.bank.params, int(t_ns),
                          np.asarray(position, dtype=np.float64), np.ascontiguousarray(R, dtype=np.float64),
                          np.ascontiguousarray(meas_cov, dtype=np.float64))

    def predict_to(self, t_ns: int) -> None:
        """Advance the filter (mutating) to t_ns; small backward steps are allowed."""
        dt = (int(t_ns) - self.t_ns) * 1e-9
        if dt != 0.0:
            folded = _kf_predict(self.x, self.P, self.R_nom, dt, self.s.jerk_psd * self.scale_p,
                                 self.s.angular_accel_psd * self.scale_r, self.s.angular_jerk_psd * self.scale_r)
            _count_folds(self.R_nom, self._clock, int(folded))
            self.t_ns = int(t_ns)

    # ------------------------------------------------------------ measurement
    def update(
        self, t_ns: int, position: np.ndarray, R: np.ndarray, meas_cov: np.ndarray, gate: bool = True
    ) -> tuple[bool, float]:
        """Predict to t_ns and fuse a pose measurement (filter_update on this row).

        position (3,), R (3, 3) body->world, meas_cov (6, 6) over
        [p, world rotation vector]. Returns (accepted, squared Mahalanobis
        distance); a gated measurement leaves the state predicted only.
        """
        accepted, d2 = filter_update(
            self.x, self.P, self.R_nom, self._adapt, self._clock, self.bank.params, int(t_ns),
            np.asarray(position, dtype=np.float64), np.ascontiguousarray(R, dtype=np.float64),
            np.ascontiguousarray(meas_cov, dtype=np.float64), bool(gate), 0.0, 0.0,
        )
        return bool(accepted), float(d2)

    def report_image_nis(self, t_ns: int, nis: float, nis_rot: float = 0.0) -> None:
        """Feed the manoeuvre detector with one camera frame's prediction residual.

        The residuals are the pixel offsets between the markers predicted to the
        frame's capture time and the blobs associated with them. nis: their mean
        (the body's translation error) squared over its expected value; nis_rot:
        their spread about that mean (the orientation error turns the markers
        about the body) squared over its expected value; both per degree of
        freedom (~1 while the model fits). They raise the position and the
        rotation noise respectively. They come from a single uncompensated view,
        so unlike the fused pose they cannot be pulled towards the prediction by
        motion compensation (which uses this filter's own velocity and rate).
        """
        report_image_nis(self._adapt, self._clock, self.bank.params, int(t_ns), float(nis), float(nis_rot))

    # -------------------------------------------------------------- read-outs
    def pose_at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Non-mutating mean prediction: position (3,), R (3, 3), velocity (3,), world angular rate (3,)."""
        dt = (int(t_ns) - self.t_ns) * 1e-9
        p, R, v = predict_mean(self.x, self.R_nom, dt)
        return p, R, v, self.x[X_RATE] + self.x[X_ANG_ACC] * dt

    def output_at(self, t_ns: int) -> tuple[np.ndarray, ...]:
        """Non-mutating prediction for the outputs: position (3,), quaternion xyzw (4,),
        velocity (3,), body-frame angular rate (3,), pose covariance (6, 6) over
        [p, world rotation vector], velocity covariance (3, 3) and world acceleration (3,) m/s^2."""
        a = self._adapt
        o = _output_at(self._x, self._P, self._R_nom, (int(t_ns) - int(self._clock[CLOCK_T_NS])) * 1e-9,
                       self.s.jerk_psd * a[ADAPT_SCALE_P], self.s.angular_accel_psd * a[ADAPT_SCALE_R],
                       self.s.angular_jerk_psd * a[ADAPT_SCALE_R])
        return (o[OUT_POS], o[OUT_QUAT_XYZW], o[OUT_VEL], o[OUT_RATE_BODY], o[OUT_POSE_COV].reshape(6, 6),
                o[OUT_VEL_COV].reshape(3, 3), o[OUT_ACC])
