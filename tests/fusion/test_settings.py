import pytest

from visionpos.config.arena import ConfigError, load_arena
from visionpos.fusion.settings import FUSION, KALMAN, FusionSettings, KalmanSettings, parse_fusion


def test_defaults_equal_the_declared_ones():
    arena = load_arena("thesis")
    parsed = parse_fusion(arena, {})
    default = FusionSettings()
    for name in FusionSettings.__dataclass_fields__:
        if name not in ("window_ns", "grid_ns"):  # derived from the cameras
            assert getattr(parsed, name) == getattr(default, name), name
    assert KalmanSettings().nis_time_constant_s == 0.015 and KalmanSettings().reset_after_ns == 60_000_000
    assert FusionSettings().max_clock_lead_ns == 30_000_000


def test_units_converted_as_before():
    arena = load_arena("thesis")
    s = parse_fusion(arena, {"window_ms": 8, "kalman.lost_timeout_ms": 120, "naive_grid_hz": 300})
    assert s.window_ns == 8_000_000 and s.kalman.lost_timeout_ns == 120_000_000 and s.grid_ns == int(1e9 / 300)
    s = parse_fusion(arena, {"fusion": {"kalman": {"nis_time_constant_ms": 30}}})
    assert s.kalman.nis_time_constant_s == 30 * 1e-3


@pytest.mark.parametrize("settings, close", [({"windw_ms": 1}, "window_ms"), ({"kalman.gate_chi": 3}, "gate_chi2")])
def test_unknown_fusion_key(settings, close):
    with pytest.raises(ConfigError, match=f"did you mean `{close}`"):
        parse_fusion(load_arena("thesis"), settings)


def test_every_field_declared():
    declared = {s.field_name for s in FUSION.settings} | {s.field_name for s in KALMAN.settings}
    internal = {"init_velocity_sigma_m_s", "init_acceleration_sigma_m_s2", "init_angular_velocity_sigma_rad_s",
                "init_angular_acceleration_sigma_rad_s2",
                "auto_window"}  # window_ms was 0
    assert set(FusionSettings.__dataclass_fields__) | set(KalmanSettings.__dataclass_fields__) == declared | internal

