"""The settings dataclasses, the kernels' parameter layouts and the packed vectors all come from the
declarations in fusion/settings.py: they agree entry by entry, and a changed setting lands at its index."""

import dataclasses
import math

import numpy as np
import pytest

from visionpos.config.settings import Setting, section, settings_dataclass
from visionpos.fusion import layout
from visionpos.fusion.settings import (
    FUSION,
    FUSION_PARAMS,
    KALMAN,
    KALMAN_PARAMS,
    KALMAN_PRIORS,
    SINGLE_VIEW,
    FusionSettings,
    KalmanSettings,
    SingleViewSettings,
    pack_params,
)


@pytest.mark.parametrize("table, count", [(KALMAN_PARAMS, "N_KALMAN_PARAMS"), (FUSION_PARAMS, "N_PARAMS")])
def test_every_entry_has_its_index_constant(table, count):
    assert getattr(layout, count) == len(table)
    for i, p in enumerate(table):
        assert type(getattr(layout, p.name)) is int and getattr(layout, p.name) == i  # numba: a plain int
    assert len({p.name for p in table}) == len(table)


@pytest.mark.parametrize("cls, spec, extra", [
    (KalmanSettings, KALMAN, [n for n, _, _ in KALMAN_PRIORS]),
    (SingleViewSettings, SINGLE_VIEW, []),
    (FusionSettings, FUSION, ["auto_window"]),
])
def test_dataclass_fields_are_the_declared_settings(cls, spec, extra):
    fields = {f.name: f for f in dataclasses.fields(cls)}
    declared = [s for s in spec.settings if s.kind != "any"]
    assert sorted(fields) == sorted([s.field_name for s in declared] + extra)
    for s in declared:
        if s.kind != "section":
            assert fields[s.field_name].default == s.field_default, s.key


# per entry: the settings it reads changed to a new value, and the packed value expected (by hand)
_KALMAN_CHANGES = {
    "KALMAN_JERK_PSD": ({"jerk_psd": 0.7}, 0.7),
    "KALMAN_ANG_ACC_PSD": ({"angular_accel_psd": 1.5}, 1.5),
    "KALMAN_ANG_JERK_PSD": ({"angular_jerk_psd": 3.0}, 3.0),
    "KALMAN_MAX_SCALE": ({"max_noise_scale": 50.0}, 50.0),
    "KALMAN_NIS_TAU_S": ({"nis_time_constant_s": 0.03}, 0.03),
    "KALMAN_GATE_CHI2": ({"gate_chi2": 20.0}, 20.0),
    "KALMAN_INIT_VEL_VAR": ({"init_velocity_sigma_m_s": 3.0}, 9.0),
    "KALMAN_INIT_ACC_VAR": ({"init_acceleration_sigma_m_s2": 5.0}, 25.0),
    "KALMAN_INIT_RATE_VAR": ({"init_angular_velocity_sigma_rad_s": 2.0}, 4.0),
    "KALMAN_INIT_ANG_ACC_VAR": ({"init_angular_acceleration_sigma_rad_s2": 4.0}, 16.0),
    "KALMAN_NIS_THRESHOLD": ({"nis_threshold": 3.5}, 3.5),
    "KALMAN_NIS_UNSPLIT_COV": ({"nis_unsplit_cov": True}, 1.0),
    "KALMAN_GATE_RETEST": ({"gate_retest": False}, 0.0),
    "KALMAN_CRUISE_MAX_SCALE": ({"cruise_max_noise_scale": 30.0}, 30.0),
    "KALMAN_CRUISE_NIS_THRESHOLD": ({"cruise_nis_threshold": 1.3}, 1.3),
    "KALMAN_CRUISE_TAU_S": ({"cruise_time_constant_s": 0.5}, 0.5),
    "KALMAN_CRUISE_RATE": ({"cruise_rate_per_s": 5.0}, 5.0),
    "KALMAN_CRUISE_MAX_SCALE_R": ({"cruise_max_rotation_noise_scale": 4.0}, 4.0),
    "KALMAN_TILT_JERK_S": ({"tilt_jerk_s": 0.05}, 0.05),
    "KALMAN_ANG_ACC_HOLD_S": ({"angular_accel_hold_s": 0.4}, 0.4),
}
_KALMAN_DEFAULT = [0.1, 1.0, 100.0, 1000.0, 0.015, 40.0, 4.0, 100.0, 36.0, 900.0, 3.0, 0.0, 1.0,
                   100.0, 1.1, 1.0, 20.0, 10.0, 0.03, 0.15]

_FUSION_CHANGES = {
    "PARAM_MAX_RESIDUAL_PX": ({"max_residual_px": 1.5}, 1.5),
    "PARAM_IDENTIFY_TOL_M": ({"identify_tolerance_m": 0.004}, 0.004),
    "PARAM_MIN_MARKERS": ({"min_markers": 4}, 4.0),
    "PARAM_MARKER_VAR_FLOOR": ({"kalman": {"marker_sigma_m": 0.002}}, 4e-6),
    "PARAM_RESET_AFTER_NS": ({"kalman": {"reset_after_ns": 80_000_000}}, 8e7),
    "PARAM_SV_ENABLED": ({"single_view": {"mode": "occlusion"}}, 1.0),
    "PARAM_SV_GATE_PER_DOF": ({"single_view": {"gate_nis_per_dof": 9.0}}, 9.0),
    "PARAM_SV_WINDOW_NS": ({"single_view": {"window_ns": 20_000_000}}, 2e7),
    "PARAM_SV_MAX_POS_VAR": ({"single_view": {"max_position_sigma_m": 0.1}}, 0.01),
    "PARAM_SV_MAX_ROT_VAR": ({"single_view": {"max_rotation_sigma_deg": 180.0}}, math.pi**2),
    "PARAM_SV_MIN_PX_VAR": ({"single_view": {"min_pixel_sigma_px": 0.5}}, 0.25),
}
# PARAM_COMPENSATE_MAX_VEL_VAR is a constant (0.3 m/s)^2; PARAM_SV_ENABLED is 2.0 for the default mode `always`
_FUSION_DEFAULT = [2.0, 0.008, 0.09, 3.0, 1e-8, 6e7, 2.0, 6.0, 5e7, 0.0025, math.radians(10.0) ** 2, 0.0025]


def _changed(obj, change):
    """A copy of a settings dataclass with `change` applied (nested dicts change nested settings)."""
    return dataclasses.replace(obj, **{k: _changed(getattr(obj, k), v) if isinstance(v, dict) else v
                                       for k, v in change.items()})


@pytest.mark.parametrize("table, default, changes, settings", [
    (KALMAN_PARAMS, _KALMAN_DEFAULT, _KALMAN_CHANGES, KalmanSettings()),
    (FUSION_PARAMS, _FUSION_DEFAULT, _FUSION_CHANGES, FusionSettings()),
])
def test_a_changed_setting_lands_at_its_index(table, default, changes, settings):
    base = pack_params(table, settings)
    assert base.dtype == np.float64 and base.shape == (len(table),)
    np.testing.assert_allclose(base, default, rtol=1e-15)
    assert set(changes) | {"PARAM_COMPENSATE_MAX_VEL_VAR"} >= {p.name for p in table}
    for name, (change, expected) in changes.items():
        packed = pack_params(table, _changed(settings, change))
        i = getattr(layout, name)
        assert packed[i] == pytest.approx(expected, rel=1e-12), name
        assert np.array_equal(np.delete(packed, i), np.delete(base, i)), f"{name} moved another entry"


def test_the_single_view_switch_is_off_when_disabled():
    off = _changed(FusionSettings(), {"single_view": {"enabled": False}})
    assert pack_params(FUSION_PARAMS, off)[layout.PARAM_SV_ENABLED] == 0.0


def test_a_new_declaration_is_a_field_with_no_other_edit():
    spec = section("demo", "demo", Setting("rate_ms", "number", 2.0, "a rate", field="rate_ns",
                                           convert=lambda ms: int(ms * 1e6)),
                   Setting("name", "text", "x", "a name"), Setting("on", "boolean", True, "a switch"))
    cls = settings_dataclass("Demo", spec, "demo", __name__)
    assert cls() == cls(rate_ns=2_000_000, name="x", on=True)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cls().name = "y"
