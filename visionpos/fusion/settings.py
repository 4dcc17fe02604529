"""The `fusion:` section of the arena YAML: declared once here, validated into SI units.

What each key does and why is in pipeline.py and tracking.py; the reference table is
docs/configuration.md (generated from these declarations).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import numpy as np

from visionpos.config.arena import ArenaConfig, ConfigError, Section
from visionpos.config.overrides import merge_section
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, ms_to_ns, section, settings_dataclass
from visionpos.fusion.timealign import MODES, MOTION_COMPENSATED

# fusion.single_view.mode: when the single-view updates are used (kernels._fuse_tracked)
SV_OCCLUSION, SV_ALWAYS = "occlusion", "always"
SV_MODES = (SV_OCCLUSION, SV_ALWAYS)

# keys that no longer exist and cannot be renamed (their unit changed): the error says what to write
REMOVED = {
    "acquire_ray_distance_m": "removed: a gate in metres was too tight far from the cameras and too loose close "
    "to them; the acquisition gate is now in pixels at each ray's range: write `fusion.acquire_ray_gate_px` "
    "(default 3) instead",
}
KALMAN = section(
    "fusion.kalman",
    "The body filter (tracking.py): process noise, its innovation-driven adaptation, gating, timeouts.",
    Setting("jerk_psd", "number", 0.1, "floor of the white-jerk density (m^2/s^5; constant-acceleration model)",
            min=1e-12),
    Setting("angular_accel_psd", "number", 1.0, "floor of the white angular-acceleration density (rad^2/s^3)",
            min=1e-12),
    Setting("angular_jerk_psd", "number", 100.0, "floor of the white angular-jerk density (rad^2/s^5); above 0 "
            "the filter also estimates the angular acceleration (constant-angular-acceleration model: follows a "
            "multirotor's attitude ramps without lag; 0: the constant-rate model, which lags them; see tracking.py)",
            min=0.0),
    Setting("max_noise_scale", "number", 1000.0, "the innovation-driven (NIS) adaptation may raise both "
            "densities by up to this factor (higher: the rates it estimates in a manoeuvre get noisy, and so does "
            "the output predicted ahead with them)", min=1.0),
    Setting("cruise_max_noise_scale", "number", 100.0, "a floor under the position block's scale for a body that "
            "keeps moving off its model: while its position NIS averaged over cruise_time_constant_ms stays above "
            "cruise_nis_threshold (a flight: one manoeuvre after another) the floor rises, up to this factor, and "
            "it falls back to 1 while the average is below (a hover, a still or smoothly moving body). The flight "
            "then keeps its cruise noise between manoeuvres instead of lagging each onset from the hover floor. "
            "At most max_noise_scale; 1: off (docs/benchmarks.md: realistic flights)", min=1.0),
    Setting("cruise_max_rotation_noise_scale", "number", 10.0, "the same slow regime for the rotation block: "
            "its NIS (the fused pose's, the image residual's spread) averaged over cruise_time_constant_ms moves a "
            "floor under the rotation scale, up to this factor (same threshold and rate). A flight of attitude "
            "flicks then meets each onset from its cruise noise, not the hover floor; a higher cap makes the "
            "rate predicted to the output ticks noisier between flicks. At most max_noise_scale; 1: off "
            "(docs/benchmarks.md: realistic flights)", min=1.0),
    Setting("tilt_jerk_ms", "number", 30.0, "a multirotor accelerates by tilting its thrust, so its jerk is about "
            "g x its tilt rate |w x z_body| (z up in the body frame): the position's jerk density is kept at least "
            "(g |w x z_body|)^2 x this time, from the filter's own rate, which the cameras measure before the "
            "position shows the change; the NIS-driven scale stays above it as a net, which is all a body that "
            "accelerates without tilting (a wand, a ground robot) raises. 0: off", field="tilt_jerk_s",
            convert=lambda ms: ms * 1e-3, min=0.0),
    Setting("angular_accel_hold_ms", "number", 150.0, "a multirotor's angular acceleration comes in torque pulses "
            "that end or reverse without warning: the angular-jerk density is kept at least |dw/dt|^2 / this "
            "time (a change of |dw/dt| expected within it), from the filter's own estimate; the NIS-driven scale "
            "stays above it as a net. 0: off", field="angular_accel_hold_s", convert=lambda ms: ms * 1e-3,
            min=0.0),
    Setting("cruise_nis_threshold", "number", 1.1, "the averaged position NIS per degree of freedom above which "
            "the cruise floor rises (a still body's averages ~1.0)", min=0.1),
    Setting("cruise_time_constant_ms", "number", 1000.0, "averaging time of the NIS that moves the cruise floor",
            field="cruise_time_constant_s", convert=lambda ms: ms * 1e-3, min=10.0),
    Setting("cruise_rate_per_s", "number", 20.0, "how fast the cruise floor moves: its logarithm changes by this x "
            "(averaged NIS - cruise_nis_threshold) per second", min=0.0),
    Setting("nis_threshold", "number", 3.0, "the averaged NIS per degree of freedom above which the adaptation "
            "raises the process noise (below it the noise decays to its floor); ~1 while the model fits, so "
            "lower values react to smaller lags and smooth less (tests/fusion/test_manoeuvre.py). 3 (2 before "
            "the multirotor floors): the floors carry a multirotor's manoeuvres and this is the net for the lags "
            "they do not explain", min=1.0),
    Setting("nis_unsplit_cov", "boolean", False, "the fused pose's NIS that drives the adaptation uses the "
            "pose's own covariance, not the one split over the fusions that share its frames (the filter's "
            "update still uses the split one): its mean is then ~1 per dof while the model fits (0.28 split, "
            "which hid lags from the adaptation)"),
    Setting("nis_time_constant_ms", "number", 15.0, "averaging time of the NIS that drives the adaptation",
            field="nis_time_constant_s", convert=lambda ms: ms * 1e-3, min=0.1),
    Setting("marker_sigma_m", "number", 0.0001, "floor of the per-marker 3D noise used for the measurement "
            "covariance", min=1e-7),
    Setting("gate_chi2", "number", 40.0, "Mahalanobis^2 gate on the 6-dof innovation (chi2 with 6 dof)", min=1.0),
    Setting("gate_retest", "boolean", True, "a pose the gate refuses is tried again with the lagging block's "
            "process noise over its prediction raised 10, 100 or 1000 times (at most to max_noise_scale); the "
            "first that passes the gate is taken and the adaptation goes on from its scale (follows sudden "
            "manoeuvres the model lags, e.g. a flick's end under angular_jerk_psd, instead of refusing "
            "measurements for tens of ms; an outlier fits none)"),
    Setting("reset_after_ms", "number", 60.0, "measurements gated out for this long: the filter restarts at "
            "the measurement", field="reset_after_ns", convert=ms_to_ns, min=0.0),
    Setting("max_prediction_ms", "number", 50.0, "tick() predicts at most this far past the last update, "
            "else tracked=false", field="max_prediction_ns", convert=ms_to_ns, min=0.0),
    Setting("lost_timeout_ms", "number", 150.0, "no accepted measurement for this long: the body is lost and "
            "re-identified", field="lost_timeout_ns", convert=ms_to_ns, min=1.0),
)

SINGLE_VIEW = section(
    "fusion.single_view",
    "Tracking through occlusion (kernels._single_views, tracking.filter_update_view): a tracked body that "
    "cannot be triangulated (fewer than min_markers markers seen by 2 cameras) is updated from the 2-D "
    "markers each camera frame sees, at the frame's capture time. It never acquires or re-identifies a "
    "body; the track is kept only while the recent views' pose information bounds the pose. A new or "
    "reacquired track takes no single view (in either mode) until a triangulated pose has told it its velocity "
    "(velocity std under 0.3 m/s): one camera's view has no depth, and the update would take its residual for "
    "velocity.",
    Setting("enabled", "boolean", True, "use single-camera reprojection updates for tracked bodies that "
            "cannot be triangulated"),
    Setting("mode", "text", SV_ALWAYS, "always: a tracked body whose triangulated pose fits its layout is "
            "updated from each camera frame's markers at that frame's capture time instead of from the "
            "motion-compensated pose, which carries the compensation's error (identification, the fit check, the "
            "gate-and-restart rule and the process-noise adaptation stay on the triangulated pose; needs enabled); "
            "occlusion: the single views update a body only while it cannot be triangulated (docs/benchmarks.md: "
            "other filter settings on the flights)", choices=SV_MODES),
    Setting("gate_nis_per_dof", "number", 6.0, "a frame's reprojection innovation is refused when its "
            "squared Mahalanobis distance over its 2n degrees of freedom exceeds this per degree", min=0.5),
    Setting("unique_sigmas", "number", 4.0, "a marker's association is used only if no other blob lies within "
            "this many predicted pixel std of its prediction (nor another marker's prediction near its blob); the "
            "radius is at least 3 px and at most match_gate_px", min=1.0),
    Setting("window_ms", "number", 50.0, "time constant of the decaying pose information of recent single "
            "views (the observability check)", field="window_ns", convert=ms_to_ns, min=1.0),
    Setting("max_position_sigma_m", "number", 0.05, "the views' pose information must bound the position "
            "to this std (root of the covariance trace), else the updates do not keep the track (lost after "
            "lost_timeout_ms)", min=1e-5),
    Setting("max_rotation_sigma_deg", "number", 10.0, "likewise for the rotation (root of the trace)",
            min=1e-3),
    Setting("min_pixel_sigma_px", "number", 0.05, "floor of the per-axis pixel noise the updates assume (the "
            "measured one comes from the triangulation residuals)", min=1e-4),
)

IMU = section(
    "fusion.imu",
    "The vehicle's IMU in the prediction (fusion/imu.py): where the bridge feeds a body the accelerations and "
    "rates of the autopilot it is bound to (bridge/imu_feed.py), each sample, delay-corrected onto the capture "
    "clock, is a measurement of the filter's acceleration and angular rate between camera frames and up to the "
    "output ticks; its biases are estimated against the optical track. Without samples (none fed, the stream "
    "stopped, or refused) the filter is the optical one.",
    Setting("enabled", "boolean", False, "use the IMU samples fed to a body (FusionPipeline.push_imu): a body bound "
            "to a vehicle whose autopilot streams its IMU; the others (no vehicle, none streaming) stay optical; off: "
            "the samples are ignored"),
    Setting("accel_noise_m_s2", "number", 0.05, "std of one accelerometer sample per axis (m/s^2)", min=1e-6),
    Setting("gyro_noise_rad_s", "number", 0.003, "std of one gyro sample per axis (rad/s)", min=1e-7),
    Setting("jerk_psd", "number", 100.0, "white-jerk density between IMU samples (m^2/s^5): the acceleration "
            "may change this much from one sample to the next (the optical model's floor is far lower)", min=1e-6),
    Setting("angular_accel_psd", "number", 3.0, "white angular-acceleration density between IMU samples "
            "(rad^2/s^3)", min=1e-6),
    Setting("gate_chi2", "number", 60.0, "a sample whose innovation against the filter's acceleration and rate "
            "exceeds this (Mahalanobis^2, 6 dof) is refused", min=1.0),
    Setting("max_refused", "integer", 20, "this many refused samples in a row: the body's IMU input is dropped "
            "(said once) and the filter goes on optical only", min=1),
    Setting("max_age_ms", "number", 20.0, "an IMU stream with no sample this long is stopped: the outputs "
            "predict with the optical model again", field="max_age_ns", convert=ms_to_ns, min=1.0),
    Setting("bias_window_ms", "number", 1000.0, "the biases are fitted over windows this long: the optical "
            "positions and rotations against the IMU integrated over the window", field="bias_window_ns",
            convert=ms_to_ns, min=100.0),
    Setting("max_fit_residual_mm", "number", 5.0, "the optical positions of a bias window further than this (RMS) "
            "from the IMU integrated over it: the IMU is not this body's or not sane (stuck, another vehicle's, a "
            "clock that jumped); the body's IMU input is dropped (said once)", min=0.1),
    Setting("max_fit_residual_deg", "number", 2.0, "likewise for the optical rotations against the integrated "
            "gyro", min=0.01),
    Setting("max_accel_bias_m_s2", "number", 1.0, "a fitted accelerometer bias above this is not an IMU's "
            "bias: the body's IMU input is dropped (said once)", min=0.01),
)

FUSION = section(
    "fusion",
    "Fusion (pipeline.py): which camera frames are fused together, association, triangulation, "
    "acquisition of lost bodies. The output rate is the server's.",
    Setting("time_alignment", "text", MOTION_COMPENSATED, "motion_compensated, or naive: nearest-timestamp "
            "grouping on a fixed grid (the baseline)", choices=MODES),
    Setting("window_ms", "number", 0.0, "frames of other cameras captured within this of the newest are "
            "fused with it", field="window_ns", convert=ms_to_ns, min=0.0, max=1000.0,
            auto="1.2 x the slowest camera's measured frame interval (its configured fps until measured), so "
            "stations that deliver fewer frames than configured are still fused"),
    Setting("naive_grid_hz", "number", 0.0, "naive grouping grid", field="grid_ns",
            convert=lambda hz: int(1e9 / hz), min=0.0, max=10000.0, auto="the fastest camera's rate"),
    Setting("max_clock_lead_ms", "number", 30.0, "a frame stamped this far ahead of all other cameras is a "
            "clock jump: dropped", field="max_clock_lead_ns", convert=ms_to_ns, min=0.1),
    Setting("match_gate_px", "number", 12.0, "predicted marker -> blob association radius", min=0.1),
    Setting("max_residual_px", "number", 2.0, "a triangulated marker with a larger RMS reprojection residual "
            "is dropped", min=0.01),
    Setting("acquire_ray_gate_px", "number", 3.0, "acquisition: two rays may see the same marker when they pass "
            "within this many pixels of each other at their ranges (metres: this x sqrt((r1/f1)^2 + (r2/f2)^2), "
            "r the range along each ray, f the focal length in px); the default is about sqrt(2) x max_residual_px: "
            "a pair further apart triangulates to a larger RMS residual than that", min=0.05, max=100.0),
    Setting("identify_tolerance_m", "number", 0.008, "identification: marker distances and Kabsch RMS within "
            "this", min=1e-5),
    Setting("min_markers", "integer", 3, "fewest markers for a pose (tracking) and for identification", min=3),
    Setting("loose_points", "boolean", True, "triangulate blobs that belong to no body and report them"),
    Setting("acquire_interval_ms", "number", 10.0, "while a body is lost, acquisition runs at most this "
            "often (capture clock)", field="acquire_interval_ns", convert=ms_to_ns, min=0.0),
    Setting("acquire_step_ms", "number", 5.0, "acquisition's estimated work per fusion (fusion/steps.py): a larger "
            "first acquisition, such as a parked fleet's, goes on in steps acquire_interval_ms apart, so that it "
            "never holds up the frames behind it; the bodies it finds start from the frames it began on, and its "
            "rest runs at once when it began 2/3 of lost_timeout_ms ago. A body that moved since those frames, and "
            "every acquisition after that or of a body tracked before (it flies), runs at once; 0 = always at once",
            field="acquire_step_ns", convert=ms_to_ns, min=0.0),
    Setting("min_fusion_interval_ms", "number", 2.0, "rate limit of motion-compensated fusions for many fast "
            "cameras: a fusion is skipped when the last one is younger than this and another camera's next "
            "frame is due within it (so it lands at the end of a burst); 0 = off",
            field="min_fusion_interval_ns", convert=ms_to_ns, min=0.0),
    Setting("loose_points_interval_ms", "number", 50.0, "loose points are refreshed this often while every "
            "body is tracked", field="loose_points_interval_ns", convert=ms_to_ns, min=0.0),
    Setting("kalman", "section", {}, "the body filter", spec=KALMAN),
    Setting("single_view", "section", {}, "single-camera updates through occlusion", spec=SINGLE_VIEW),
    Setting("imu", "section", {}, "the vehicle's IMU in the prediction", spec=IMU),
    removed=REMOVED,
)


# (name, type, value): the filter's priors at (re)initialisation, not configurable
KALMAN_PRIORS = (
    ("init_velocity_sigma_m_s", float, 2.0),
    ("init_acceleration_sigma_m_s2", float, 10.0),
    ("init_angular_velocity_sigma_rad_s", float, 6.0),
    ("init_angular_acceleration_sigma_rad_s2", float, 30.0),
)

# The settings dataclasses come from the declarations above: a field per setting (the converted
# unit's name, e.g. window_ns), its default the declared one.
KalmanSettings = settings_dataclass(
    "KalmanSettings", KALMAN, "Noise, adaptation, gating and timeouts of the body filter (SI units; "
    "`fusion.kalman` in the YAML). init_*: prior std of the unmeasured derivatives at (re)initialisation "
    "(not configurable).", __name__, extra=KALMAN_PRIORS)
SingleViewSettings = settings_dataclass(
    "SingleViewSettings", SINGLE_VIEW, "The single-view path (`fusion.single_view` in the YAML; SI units).",
    __name__)
ImuSettings = settings_dataclass(
    "ImuSettings", IMU, "The IMU in the prediction (`fusion.imu` in the YAML; SI units).", __name__)
FusionSettings = settings_dataclass(
    "FusionSettings", FUSION, "Validated `fusion:` section (SI units). window_ns and grid_ns are 0 until "
    "derived from the cameras; auto_window: window_ms was 0, so the window follows the cameras' measured "
    "frame intervals (timealign.py) and window_ns is only its starting value.", __name__,
    nested={"kalman": KalmanSettings, "single_view": SingleViewSettings, "imu": ImuSettings},
    extra=(("auto_window", bool, True),))


class Param(NamedTuple):
    """One entry of a kernel parameter vector: `name` is its index constant in fusion/layout.py (a
    module-level int the compiled kernels read as a constant), `get` reads its value (a float) from
    the settings object the vector is packed from."""

    name: str
    get: Callable[[Any], float]


# motion compensation starts once the filter's velocity std is below this (m/s)
COMPENSATE_MAX_VEL_STD = 0.3

# The vectors the kernels read their settings from, in order: an entry's index is its position here
# (layout.py makes the constants). Adding a parameter is adding its row. Each vector is packed by
# pack_params from the object named above it.

# FilterBank.params, from KalmanSettings (tracking.py)
KALMAN_PARAMS: tuple[Param, ...] = (
    Param("KALMAN_JERK_PSD", lambda k: k.jerk_psd),
    Param("KALMAN_ANG_ACC_PSD", lambda k: k.angular_accel_psd),
    Param("KALMAN_ANG_JERK_PSD", lambda k: k.angular_jerk_psd),
    Param("KALMAN_MAX_SCALE", lambda k: k.max_noise_scale),
    Param("KALMAN_NIS_TAU_S", lambda k: k.nis_time_constant_s),
    Param("KALMAN_GATE_CHI2", lambda k: k.gate_chi2),
    Param("KALMAN_INIT_VEL_VAR", lambda k: k.init_velocity_sigma_m_s**2),
    Param("KALMAN_INIT_ACC_VAR", lambda k: k.init_acceleration_sigma_m_s2**2),
    Param("KALMAN_INIT_RATE_VAR", lambda k: k.init_angular_velocity_sigma_rad_s**2),
    # no angular jerk: the angular acceleration is not modelled (held at zero with no variance)
    Param("KALMAN_INIT_ANG_ACC_VAR",
          lambda k: k.init_angular_acceleration_sigma_rad_s2**2 if k.angular_jerk_psd > 0 else 0.0),
    Param("KALMAN_NIS_THRESHOLD", lambda k: k.nis_threshold),
    Param("KALMAN_NIS_UNSPLIT_COV", lambda k: float(k.nis_unsplit_cov)),
    Param("KALMAN_GATE_RETEST", lambda k: float(k.gate_retest)),
    Param("KALMAN_CRUISE_MAX_SCALE", lambda k: k.cruise_max_noise_scale),
    Param("KALMAN_CRUISE_NIS_THRESHOLD", lambda k: k.cruise_nis_threshold),
    Param("KALMAN_CRUISE_TAU_S", lambda k: k.cruise_time_constant_s),
    Param("KALMAN_CRUISE_RATE", lambda k: k.cruise_rate_per_s),
    Param("KALMAN_CRUISE_MAX_SCALE_R", lambda k: k.cruise_max_rotation_noise_scale),
    Param("KALMAN_TILT_JERK_S", lambda k: k.tilt_jerk_s),
    Param("KALMAN_ANG_ACC_HOLD_S", lambda k: k.angular_accel_hold_s),
)

# values of PARAM_SV_ENABLED: the single-view path off, on through occlusion, or for every frame of a
# triangulated body too (mode `always`)
SV_PARAM_OFF, SV_PARAM_OCCLUSION, SV_PARAM_ALWAYS = 0.0, 1.0, 2.0

# the fusion kernels' parameters (FusionPipeline), from FusionSettings: variances in m^2, rad^2, px^2
FUSION_PARAMS: tuple[Param, ...] = (
    Param("PARAM_MAX_RESIDUAL_PX", lambda f: f.max_residual_px),
    Param("PARAM_IDENTIFY_TOL_M", lambda f: f.identify_tolerance_m),
    Param("PARAM_COMPENSATE_MAX_VEL_VAR", lambda f: COMPENSATE_MAX_VEL_STD**2),
    Param("PARAM_MIN_MARKERS", lambda f: f.min_markers),
    Param("PARAM_MARKER_VAR_FLOOR", lambda f: f.kalman.marker_sigma_m**2),
    Param("PARAM_RESET_AFTER_NS", lambda f: f.kalman.reset_after_ns),
    Param("PARAM_SV_ENABLED", lambda f: SV_PARAM_OFF if not f.single_view.enabled
          else SV_PARAM_ALWAYS if f.single_view.mode == SV_ALWAYS else SV_PARAM_OCCLUSION),
    Param("PARAM_SV_GATE_PER_DOF", lambda f: f.single_view.gate_nis_per_dof),
    Param("PARAM_SV_WINDOW_NS", lambda f: f.single_view.window_ns),
    Param("PARAM_SV_MAX_POS_VAR", lambda f: f.single_view.max_position_sigma_m**2),
    Param("PARAM_SV_MAX_ROT_VAR", lambda f: np.radians(f.single_view.max_rotation_sigma_deg) ** 2),
    Param("PARAM_SV_MIN_PX_VAR", lambda f: f.single_view.min_pixel_sigma_px**2),
)


def pack_params(table: tuple[Param, ...], settings: Any) -> np.ndarray:
    """(len(table),) float64: each entry's value read from `settings`, at its index."""
    return np.array([float(p.get(settings)) for p in table], dtype=np.float64)


def parse_fusion(arena: ArenaConfig, settings: dict[str, Any] | None = None) -> FusionSettings:
    """Read `fusion:` from the arena, overridden by `settings` (nested, dotted or {'fusion': {...}})."""
    base = arena.section("fusion").data  # a ConfigError naming the key unless a mapping
    data = merge_section(base, settings, "fusion")
    source = f"{arena.source} (+ overrides)" if settings else arena.source
    s = FUSION.check(Section(data, source, "fusion"))
    kalman = KALMAN.parse(s.sub("kalman"))
    single_view = SINGLE_VIEW.parse(s.sub("single_view"))
    sv_raw = data.get("single_view")
    explicit_always = isinstance(sv_raw, dict) and sv_raw.get("mode") == SV_ALWAYS
    if explicit_always and not single_view["enabled"]:  # the default mode simply has no effect then
        raise ConfigError(source, "fusion.single_view.mode", "`always` needs the single-view path: "
                          "`fusion.single_view.enabled` is false")
    fps = [c.fps for c in arena.cameras] or [100.0]
    derived = {"window_ms": 1.2e3 / min(fps), "naive_grid_hz": max(fps)}
    auto_window = FUSION["window_ms"].read(s) == 0
    return FusionSettings(**FUSION.parse(s, derived), auto_window=auto_window, kalman=KalmanSettings(**kalman),
                          single_view=SingleViewSettings(**single_view), imu=ImuSettings(**IMU.parse(s.sub("imu"))))


register_section("fusion", FUSION, parse_fusion)
