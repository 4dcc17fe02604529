"""The indoor-MAV trajectories (issue 15): slalom and dash, their dynamics and their config."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from visionpos.config.arena import ConfigError, Section, load_yaml, parse_arena, resolve_config_path
from visionpos.sim import load_scenario, parse_sim, simulate
from visionpos.sim import trajectories as T


def _dash() -> T.Dash:
    return T.from_config(Section({"trajectory": "dash"}, "<test>", "s"), np.random.default_rng(0))


def _slalom() -> T.Slalom:
    return T.from_config(Section({"trajectory": "slalom", "center": [0.0, 0.0, 1.0]}, "<test>", "s"),
                         np.random.default_rng(0))


@pytest.mark.parametrize("make", [_dash, _slalom])
def test_velocities_accelerations_and_body_rates_match_finite_differences(make):
    tr = make()
    dt = 1e-4
    t = np.arange(0.0, 15.0, dt)  # two dash loops: the heading carries on over the loop's end
    m = tr(t)
    _, v, a = tr.kinematics(t)
    assert np.abs((m.positions[2:] - m.positions[:-2]) / (2 * dt) - v[1:-1]).max() < 1e-5
    assert np.abs((v[2:] - v[:-2]) / (2 * dt) - a[1:-1]).max() < 1e-3
    rot = Rotation.from_quat(m.quaternions)
    fd_w = (rot[:-2].inv() * rot[2:]).as_rotvec() / (2 * dt)
    assert np.abs(fd_w - m.angular_velocities[1:-1]).max() < 1e-3 * np.abs(m.angular_velocities).max()
    # continuous body rate (the acceleration is smooth): no step between samples, only up to ~110 rad/s^2
    assert np.abs(np.diff(m.angular_velocities, axis=0)).max() < 300.0 * dt


def _mav_figures(tr: T.Trajectory, t: np.ndarray) -> dict[str, float]:
    m = tr(t)
    _, v, a = tr.kinematics(t)
    rot = Rotation.from_quat(m.quaternions)
    w_world = rot.apply(m.angular_velocities)
    return {
        "speed": float(np.linalg.norm(v, axis=1).max()),
        "accel": float(np.linalg.norm(a, axis=1).max()),
        "tilt_deg": float(np.degrees(np.arccos(np.clip(rot.apply([0, 0, 1])[:, 2], -1, 1))).max()),
        "yaw_rate_deg_s": float(np.degrees(np.abs(w_world[:, 2])).max()),
        "body_rate_deg_s": float(np.degrees(np.linalg.norm(m.angular_velocities, axis=1)).max()),
    }


def test_slalom_has_the_dynamics_of_an_indoor_mav():
    tr = _slalom()
    f = _mav_figures(tr, np.arange(0.0, 2 * np.pi / tr.omega, 1e-4))
    assert f["speed"] == pytest.approx(2.0, rel=1e-6)  # the cosines peak together at t = 0
    assert 5.0 < f["accel"] < 6.0 and 30.0 < f["tilt_deg"] <= tr.max_tilt_deg
    assert 2 * tr.omega * tr.yaw_amp == pytest.approx(np.pi)  # commanded heading rate peaks at 180 deg/s
    assert 150.0 < f["yaw_rate_deg_s"] < 200.0
    p = tr(np.arange(0.0, 10.0, 0.01)).positions
    assert np.allclose(p.min(axis=0), [-1.0, -0.3, 0.8], atol=1e-3) and np.allclose(p.max(axis=0), [1.0, 0.3, 1.2],
                                                                                       atol=1e-3)


def test_dash_flies_rest_to_rest_between_waypoints_with_sharp_attitude_changes():
    tr = _dash()
    legs = tr.legs
    starts = np.concatenate([[0.0], np.cumsum([mv.duration + tr.pause for mv, _, _ in legs])])
    wp = np.asarray(T.DASH_WAYPOINTS)
    for k, (move, turn, _) in enumerate(legs):
        # at rest on the waypoint at the leg's start, on the next one from its end through the pause
        for t, where in ((starts[k], wp[k]), (starts[k] + move.duration, wp[(k + 1) % 4]),
                         (starts[k + 1] - 1e-6, wp[(k + 1) % 4])):
            p, v, a = (x[0] for x in tr.kinematics(np.array([t])))
            assert np.allclose(p, where, atol=1e-9) and np.allclose(v, 0, atol=1e-6) and np.allclose(a, 0, atol=1e-4)
        assert turn is not None and np.radians(150.0) < turn.distance <= np.pi  # about a half turn per leg
    f = _mav_figures(tr, np.arange(0.0, starts[-1], 1e-4))
    assert f["speed"] == pytest.approx(2.0, rel=1e-6)
    assert f["accel"] == pytest.approx(5.0, rel=1e-6)
    assert 25.0 < f["tilt_deg"] < 31.0 and f["tilt_deg"] <= tr.max_tilt_deg + 1e-9
    assert 170.0 < f["yaw_rate_deg_s"] < 240.0  # 180 deg/s of heading, plus what the tilting adds about world z
    assert f["body_rate_deg_s"] > 300.0  # pitch/roll flicks: the thrust axis turns 27 deg within 0.2 s


def _arena_with_session(entry: dict):
    data = load_yaml(resolve_config_path("thesis"))
    data["sim"]["sessions"] = {"f": {"quad": entry}}
    return parse_arena(data, "<test thesis>")


@pytest.mark.parametrize(
    ("entry", "key", "match"),
    [
        ({"trajectory": "dash", "waypoints": [[0, 0, 1]]}, "waypoints", "at least 2"),
        ({"trajectory": "dash", "waypoints": [[0, 0, 1], [0, 0, 1], [1, 0, 1]]}, "waypoints", "repeats"),
        ({"trajectory": "dash", "waypoints": [[0, 0, 1], [0.1, 0, 1]]}, "waypoints", "too short"),
        ({"trajectory": "dash", "ramp": 1.0}, "ramp", "overshoots"),
        ({"trajectory": "dash", "max_accel": 30, "ramp": 0.01}, "peak_speed", "tilt"),
        ({"trajectory": "dash", "speed": 2}, "speed", "unknown key"),
        ({"trajectory": "slalom", "length": 0, "swing": 0, "height_amp": 0}, "length", "a point"),
        ({"trajectory": "slalom", "peak_speed": 6}, "peak_speed", "tilt"),
    ],
)
def test_mav_trajectory_config_errors_name_the_key(entry, key, match):
    with pytest.raises(ConfigError, match=match) as e:
        parse_sim(_arena_with_session(entry), session="f")
    assert e.value.key == f"sim.sessions.f.quad.{key}"


@pytest.mark.parametrize("session", ["slalom", "dash"])
def test_thesis_sessions_keep_the_body_in_view_of_the_cameras(session):
    sc = load_scenario("thesis", session=session, duration=3.0, seed=1)
    sim = simulate(sc)
    seen = {}
    for f, tr in zip(sim.frames, sim.frame_truth):
        seen.setdefault(f.capture_ns // 10_000_000, []).append(len(set(tr.marker[tr.body == 0].tolist())) >= 3)
    # in nearly every 10 ms slot at least 2 cameras see at least 3 markers
    assert np.mean([sum(v) >= 2 for v in seen.values()]) > 0.98
