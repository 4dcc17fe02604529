"""Continuous calibration: a knocked camera is found from the tracked bodies, and its pose re-fitted."""

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from visionpos.config.arena import ConfigError, load_arena
from visionpos.fusion.camera_monitor import (
    CameraMonitor,
    MonitorSettings,
    apply_correction,
    parse_camera_monitor,
    pose_correction,
)


def _angle_deg(Ra, Rb):
    return math.degrees(Rotation.from_matrix(Ra @ Rb.T).magnitude())


def test_a_turn_keeps_the_camera_centre_and_is_recovered_from_points():
    cam = load_arena("thesis").cameras[1]
    turned = apply_correction(cam, np.array([math.radians(0.3), math.radians(0.4), 0, 0, 0, 0]))
    np.testing.assert_allclose(turned.center, cam.center, atol=1e-12)  # a knock turns it about itself
    assert math.isclose(_angle_deg(turned.R, cam.R), 0.5, rel_tol=1e-6)
    rng = np.random.default_rng(0)
    X = rng.uniform([-0.4, -0.4, 0.5], [0.4, 0.4, 1.1], (800, 3))
    u = turned.project(X) + rng.normal(0.0, 0.2, (800, 2))
    delta, info, sigma, disp = pose_correction(cam, X, u)
    fitted = apply_correction(cam, delta)
    assert _angle_deg(fitted.R, turned.R) < 0.02
    assert np.linalg.norm(fitted.center - cam.center) < 0.003
    assert 0.15 < sigma < 0.25 and disp > 5.0  # 0.5 deg at f = 720 px is about 6 px


def _flight(overrides, duration_s, seed=2):
    from visionpos.benchmarks.fusion import replay
    from visionpos.sim import load_scenario, simulate

    sc = load_scenario("thesis", overrides, session="flight", duration=duration_s, seed=seed)
    mon = CameraMonitor(sc.arena)
    rep = replay(sc.arena, simulate(sc).frames, monitor=mon)
    return sc, rep, mon


def test_a_knocked_camera_is_flagged_alone_and_its_pose_corrected():
    sc, rep, mon = _flight(["sim.cameras.2.bump_at_s=6", "sim.cameras.2.bump_rotation_deg=[0.3, 0.4, 0.0]"], 24.0)
    assert any("pi2 (id 2) has moved" in e for e in mon.events)
    assert not any("has moved" in e and "id 2)" not in e for e in mon.events)  # no other camera blamed
    assert mon.cams[2].corrections >= 1
    true_cam = sc.bumps[2][1]
    arena_cam = sc.arena.camera_by_id()[2]
    assert _angle_deg(arena_cam.R, true_cam.R) > 0.49
    # the pipeline now uses a pose within a fifth of the knock of the truth
    assert _angle_deg(rep.pipeline.cameras[2].R, true_cam.R) < 0.1
    name = sc.arena.bodies[0].name
    t = (rep.times_ns - sc.start_ns) * 1e-9
    late = (t > 18) & rep.tracked[name]
    p, _ = sc.truth_at(name, rep.times_ns[late])
    assert np.sqrt(((rep.positions[name][late] - p) ** 2).sum(1).mean()) < 0.6e-3


def test_no_camera_is_flagged_when_none_moved():
    _, _, mon = _flight([], 30.0, seed=4)
    assert mon.events == [] and all(w.corrections == 0 and not w.flagged for w in mon.cams.values())
    assert max(w.last.get("disp_px", 0.0) for w in mon.cams.values()) < 0.1


def test_flag_only_leaves_the_pose_alone():
    from visionpos.benchmarks.fusion import replay
    from visionpos.sim import load_scenario, simulate

    sc = load_scenario("thesis", ["sim.cameras.2.bump_at_s=4", "sim.cameras.2.bump_rotation_deg=[0.3, 0.4, 0.0]"],
                       session="flight", duration=14.0, seed=2)
    mon = CameraMonitor(sc.arena, replace(MonitorSettings(), correct=False))
    rep = replay(sc.arena, simulate(sc).frames, monitor=mon)
    assert mon.cams[2].flagged and mon.cams[2].corrections == 0
    assert "recalibrate" in mon.events[0]
    np.testing.assert_array_equal(rep.pipeline.cameras[2].R, sc.arena.camera_by_id()[2].R)


def test_settings_are_checked_and_the_server_reports_the_monitor(tmp_path):
    from visionpos.server.service import FusionServer, load_config_with_overrides

    arena = load_config_with_overrides("thesis", ["server.insecure=true", "camera_monitor.flag_px=0.3"])
    assert parse_camera_monitor(arena).flag_px == 0.3
    server = FusionServer(arena, port=0)
    assert set(server.health()["camera_monitor"]["cameras"]) == {c.id for c in arena.cameras}
    with pytest.raises(ConfigError, match="camera_monitor.flag_px"):
        parse_camera_monitor(load_config_with_overrides("thesis", ["camera_monitor.flag_px=-1"]))
    off = load_config_with_overrides("thesis", ["server.insecure=true", "camera_monitor.enabled=false"])
    assert FusionServer(off, port=0).monitor is None
