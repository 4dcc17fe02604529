"""The multirotor floors under the process-noise scales (fusion.kalman.tilt_jerk_ms, angular_accel_hold_ms;
adaptation.tilt_jerk_scale, angular_accel_scale): the values by hand, the NIS-driven part kept apart under them,
what they do on the flights, and a body that accelerates without tilting still followed by the NIS net."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from visionpos.benchmarks.fusion_replay import replay
from visionpos.fusion import layout as L
from visionpos.fusion.adaptation import adapt_noise_scales, angular_accel_scale, tilt_jerk_scale
from visionpos.fusion.settings import KALMAN, KALMAN_PARAMS, KalmanSettings, pack_params
from visionpos.sim import load_scenario, simulate
from visionpos.sim.trajectories import Trajectory

G = 9.80665


def _params(**fields) -> np.ndarray:
    return pack_params(KALMAN_PARAMS, KalmanSettings(**fields))


def _state(rate=(0.0, 0.0, 0.0), ang_acc=(0.0, 0.0, 0.0)) -> np.ndarray:
    x = np.zeros(L.N_STATE)
    x[L.X_RATE], x[L.X_ANG_ACC] = rate, ang_acc
    return x


def test_the_defaults_are_what_the_settings_and_the_architecture_say():
    assert KALMAN["tilt_jerk_ms"].default == 30.0 and KALMAN["angular_accel_hold_ms"].default == 150.0
    assert "(g |w x z_body|)^2 x this time" in KALMAN["tilt_jerk_ms"].doc
    assert "|dw/dt|^2 / this time" in KALMAN["angular_accel_hold_ms"].doc
    doc = " ".join((Path(__file__).resolve().parents[2] / "docs" / "architecture.md").read_text().split())
    assert "(g |w x z_body|)^2 x `tilt_jerk_ms` (30)" in doc and "|dw/dt|^2 / `angular_accel_hold_ms` (150)" in doc


def test_the_tilt_floor_by_hand():
    """jerk_psd 0.1 m^2/s^5, 30 ms: a level body rolling at 1 rad/s swings its thrust at 1 rad/s, so its jerk
    density is g^2 x 1 x 0.03 = 2.885 m^2/s^5, 28.85 x the floor; yawing swings nothing; tilted 90 deg about x, a
    yaw rate of 2 rad/s swings the thrust at 2 rad/s (4 x the square: 115.4)."""
    params, P0, level = _params(), np.zeros((L.N_STATE, L.N_STATE)), np.eye(3)
    assert tilt_jerk_scale(_state((1.0, 0.0, 0.0)), P0, level, params) == pytest.approx(G * G * 0.03 / 0.1)
    assert tilt_jerk_scale(_state((0.0, 0.0, 2.0)), P0, level, params) == 1.0
    on_side = Rotation.from_euler("x", 90, degrees=True).as_matrix()
    assert tilt_jerk_scale(_state((0.0, 0.0, 2.0)), P0, on_side, params) == pytest.approx(4 * G * G * 0.03 / 0.1)
    # the rate's own variance is taken off: 0.25 (rad/s)^2 per axis adds 0.5 to |w x z|^2 for z up
    P = P0.copy()
    P[L.X_RATE, L.X_RATE] = 0.25 * np.eye(3)
    assert tilt_jerk_scale(_state((1.0, 0.0, 0.0)), P, level, params) == pytest.approx(G * G * 0.5 * 0.03 / 0.1)
    assert tilt_jerk_scale(_state((0.5, 0.0, 0.0)), P, level, params) == 1.0  # all of it noise
    # within [1, max_noise_scale]; 0 ms: off (adapt_noise_scales does not call it then)
    assert tilt_jerk_scale(_state((10.0, 0.0, 0.0)), P0, level, params) == 1000.0
    assert tilt_jerk_scale(_state((1.0, 0.0, 0.0)), P0, level, _params(tilt_jerk_s=0.06)) == pytest.approx(
        2 * G * G * 0.03 / 0.1)


def test_the_angular_acceleration_floor_by_hand():
    """angular_jerk_psd 100 rad^2/s^5, 150 ms: 10 rad/s^2 gives 100 / 0.15 = 666.7 rad^2/s^5, 6.67 x the floor;
    its variance is taken off; the constant-rate model (angular_jerk_psd 0) has none."""
    params, P0 = _params(), np.zeros((L.N_STATE, L.N_STATE))
    assert angular_accel_scale(_state(ang_acc=(0.0, 10.0, 0.0)), P0, params) == pytest.approx(100 / 0.15 / 100)
    P = P0.copy()
    P[L.X_ANG_ACC, L.X_ANG_ACC] = 10.0 * np.eye(3)
    assert angular_accel_scale(_state(ang_acc=(0.0, 10.0, 0.0)), P, params) == pytest.approx(70 / 0.15 / 100)
    assert angular_accel_scale(_state(ang_acc=(3.0, 0.0, 0.0)), P0, params) == 1.0  # 9 / 0.15 = 60 < 100
    assert angular_accel_scale(_state(ang_acc=(0.0, 10.0, 0.0)), P0, _params(angular_jerk_psd=0.0)) == 1.0


def test_the_nis_driven_part_decays_under_the_floor_in_its_own_column():
    """A body rolling at 1 rad/s (tilt floor 28.85) after a burst that left the NIS-driven position scale at 500:
    with the NIS below its threshold the part decays (0.2 s) to 1 and the scale ends on the floor; with the floor
    off (0 ms) the scale itself is what decays, and the part's column is left alone."""
    x, P, R = _state((1.0, 0.0, 0.0)), np.zeros((L.N_STATE, L.N_STATE)), np.eye(3)
    for tilt_s, end in ((0.03, G * G * 0.03 / 0.1), (0.0, 1.0)):
        params = _params(tilt_jerk_s=tilt_s, cruise_max_noise_scale=1.0)
        adapt, clock = np.ones(L.N_ADAPT), np.zeros(L.N_CLOCK, dtype=np.int64)
        adapt[L.ADAPT_SCALE_P] = adapt[L.ADAPT_NIS_SCALE_P] = 500.0
        adapt[L.ADAPT_NIS_P] = 0.5
        adapt_noise_scales(adapt, clock, params, 10_000_000, 0.01, 0.5, 0.5, False, x, P, R)
        assert adapt[L.ADAPT_SCALE_P] == pytest.approx(500.0 * np.exp(-0.01 / 0.2))
        for _ in range(500):
            adapt_noise_scales(adapt, clock, params, 10_000_000, 0.01, 0.5, 0.5, False, x, P, R)
        assert adapt[L.ADAPT_SCALE_P] == pytest.approx(end)
        assert adapt[L.ADAPT_NIS_SCALE_P] == (1.0 if tilt_s else 500.0)


def _tick_errors(sc, sim, settings) -> tuple[float, float, int]:
    """Position RMSE (mm) and largest error (mm) of the output ticks after the first 0.5 s, and the gated
    measurements."""
    rep = replay(sc.arena, sim.frames, settings)
    t = rep.times_ns
    ok = rep.tracked["quad"] & (t >= sc.start_ns + 500_000_000)
    assert ok.sum() > 0.95 * (t >= sc.start_ns + 500_000_000).sum()
    p_true, _ = sc.truth_at("quad", t[ok])
    e = np.linalg.norm(rep.positions["quad"][ok] - p_true, axis=1) * 1e3
    return float(np.sqrt(np.mean(e**2))), float(e.max()), int(rep.pipeline.stats()["rejected_gate"])


OFF = {"kalman": {"tilt_jerk_ms": 0.0, "angular_accel_hold_ms": 0.0}}


@pytest.fixture(scope="module")
def sharp():
    sc = load_scenario("thesis", None, session="dash_sharp", duration=4.0, seed=1)
    return sc, simulate(sc)


def test_the_floors_bring_the_output_ticks_closer_on_a_sharp_dash(sharp):
    rmse_on, max_on, gated_on = _tick_errors(*sharp, None)
    rmse_off, _, _ = _tick_errors(*sharp, OFF)
    assert rmse_on < 0.92 * rmse_off, (rmse_on, rmse_off)
    assert gated_on == 0 and max_on < 3.0


@dataclasses.dataclass(frozen=True)
class _Level(Trajectory):
    """Another trajectory's path flown level (a ground robot, a body carried by hand): it accelerates without
    tilting, so the tilt floor never rises."""

    inner: Trajectory

    def kinematics(self, t):
        return self.inner.kinematics(t)

    def attitude(self, t):
        return Rotation.from_quat(np.tile([0.0, 0.0, 0.0, 1.0], (len(t), 1)))


def test_a_body_that_accelerates_without_tilting_is_followed_by_the_nis_net(sharp):
    """The sharp dash's path (5 m/s^2 within 0.2 s) with no tilt at all: nothing refused, and its ticks within
    10 % of the filter without the floors (whose NIS-driven scale is all it has then too)."""
    sc, _ = sharp
    body = sc.bodies[0]
    level = dataclasses.replace(sc, bodies=(dataclasses.replace(body, trajectory=_Level(body.trajectory)),)
                                + sc.bodies[1:])
    sim = simulate(level)
    rmse_on, max_on, gated_on = _tick_errors(level, sim, None)
    rmse_off, _, _ = _tick_errors(level, sim, OFF)
    assert gated_on == 0 and max_on < 4.0
    assert rmse_on < 1.1 * rmse_off, (rmse_on, rmse_off)
