"""fusion.single_view.mode `always` (the default): a triangulated body updated from each camera frame's own
markers at that frame's capture time (kernels._fuse_tracked), instead of the motion-compensated pose; the
process noise follows the triangulated pose's NIS, and a pose outside the gate sends the body down the pose
path."""

import numpy as np
import pytest

from visionpos.benchmarks.fusion_flights import fly
from visionpos.config.arena import ConfigError, load_arena
from visionpos.fusion.pipeline import FusionPipeline
from visionpos.fusion.settings import parse_fusion
from visionpos.sim import load_scenario, simulate

ALWAYS = {"single_view": {"mode": "always"}}


def test_mode_is_declared_and_checked():
    arena = load_arena("thesis")
    assert parse_fusion(arena, {}).single_view.mode == "always"
    assert parse_fusion(arena, {"single_view.mode": "occlusion"}).single_view.mode == "occlusion"
    with pytest.raises(ConfigError, match="fusion.single_view.mode"):
        parse_fusion(arena, {"single_view.mode": "every"})
    with pytest.raises(ConfigError, match="needs the single-view path"):
        parse_fusion(arena, {"single_view": {"mode": "always", "enabled": False}})


def test_a_triangulated_body_is_kept_by_per_view_updates():
    """Four cameras see the whole quad: in mode `always` every output says `views`, every frame is one
    accepted update (none refused, no reset), and the track follows the truth."""
    sc = load_scenario("thesis", session="slalom", duration=2.0, seed=1)
    frames = sorted(simulate(sc).frames, key=lambda f: (f.recv_ns, f.camera_id))
    pipe = FusionPipeline(sc.arena, ALWAYS)
    kinds, errs = [], []
    i = 0
    for tk in range(sc.start_ns + 500_000_000, frames[-1].recv_ns, 10_000_000):
        while frames[i].recv_ns <= tk:
            pipe.push(frames[i])
            i += 1
        s = pipe.tick(tk)[0]
        kinds.append(s.update_kind)
        errs.append(np.linalg.norm(s.position - sc.truth_at("quad", np.array([tk]))[0][0]))
    st = pipe.stats()
    assert set(kinds) == {"pose"}  # triangulated throughout: the views of its frames, kind "pose"
    assert st["rejected_gate"] == 0 and st["filter_resets"] == 0 and st["lost"] == 0
    assert max(errs) < 0.004


def test_per_view_updates_reach_the_bound_on_the_slalom():
    """The issue-15 slalom (2 m/s, roll reversals, 180 deg/s yaw): the pose the bridge sends (moved back to
    its capture time) was at 1.2x (position) and 1.1x (rotation) the single-snapshot Cramer-Rao bound from
    the motion-compensated pose; per-view updates, whose measurements carry no compensation error, with the
    default jerk floor (0.1): within the issue's 1.2x and 1.0x on this stretch. With the views' own NIS
    driving the noise (before) that floor lagged the slalom: 2.2x in position."""
    r = fly("slalom", 3.0, 1, settings=ALWAYS)
    assert r["tracked_fraction"] == 1.0 and r["gated"] == 0
    assert r["pos_rmse_mm"] <= 1.2 * r["crb_pos_mm"]
    assert r["rot_rmse_deg"] <= 1.0 * r["crb_rot_deg"]
    assert r["max_err_mm"] <= 4.0


def test_a_pose_outside_the_gate_takes_the_pose_path():
    """dash_sharp (27 deg flicks in 0.2 s, 6000 deg/s^2), seed 2: at t = 6.9-7.0 s the prediction lags a flick,
    the views labelled against it were taken anyway (their per-dof gate passed) and the error ran to 26 mm
    before the track snapped back. A triangulated pose outside the 6-dof gate now sends the body down the
    pose path (with its retest): no stall, and the error stays within the issue's 4 mm (at the capture time)."""
    r = fly("dash_sharp", 10.0, 2, settings=ALWAYS)
    assert r["tracked_fraction"] == 1.0
    assert r["max_err_mm"] <= 4.0
    assert r["max_gap_periods"] <= 2.0


def test_pose_nis_is_what_the_update_would_see_and_changes_nothing():
    """tracking.pose_nis: the triangulated pose's squared distance against the filter predicted to its
    time, as filter_update's gate sees it, with the filter left untouched (mode `always` takes the views)."""
    from visionpos.fusion.body_filter import BodyFilter
    from visionpos.fusion.settings import KalmanSettings
    from visionpos.fusion.tracking import filter_update, pose_nis
    from visionpos.geometry.rotations import matrix_from_rotvec

    f = BodyFilter(KalmanSettings())
    cov = np.diag([0.0005**2] * 3 + [np.radians(0.3) ** 2] * 3)
    f.initialize(0, np.array([0.0, 0.0, 1.0]), np.eye(3), cov)
    for k in range(1, 20):
        f.update(k * 10_000_000, np.array([0.001 * k, 0.0, 1.0]), matrix_from_rotvec([0.0, 0.0, 0.002 * k]), cov)
    p, R = np.array([0.0215, 0.0004, 1.0002]), matrix_from_rotvec([0.0, 0.001, 0.043])
    before = (f.x.copy(), f.P.copy(), f.R_nom.copy(), f._adapt.copy(), f._clock.copy())
    d2, nis_p, nis_r = pose_nis(f.x, f.P, f.R_nom, f._adapt, f._clock, f.bank.params, 210_000_000, p, R, cov,
                                0.0, 0.0, 1.0)
    for a, b in zip(before, (f.x, f.P, f.R_nom, f._adapt, f._clock)):
        assert np.array_equal(a, b)
    assert d2 > 0 and nis_p > 0 and nis_r > 0
    _, d2_update = filter_update(f.x, f.P, f.R_nom, f._adapt, f._clock, f.bank.params, 210_000_000, p, R, cov,
                                 True, 0.0, 0.0)
    assert d2 == pytest.approx(d2_update, rel=1e-9)


def test_paused_view_updates_fuse_as_mode_occlusion_and_resume_as_always():
    """FusionPipeline.pause_view_updates (the server's load relief): while paused, the same frames give exactly
    what mode `occlusion` gives; resumed, the views are taken again (the output leaves occlusion's); a pipeline
    in mode `occlusion` has nothing to pause."""
    sc = load_scenario("thesis", session="slalom", duration=1.5, seed=1)
    frames = sorted(simulate(sc).frames, key=lambda f: (f.recv_ns, f.camera_id))
    ticks = list(range(sc.start_ns + 300_000_000, frames[-1].recv_ns, 10_000_000))
    resume_at = ticks[len(ticks) // 2]

    def run(settings, pause):
        pipe = FusionPipeline(sc.arena, settings)
        assert pipe.pause_view_updates(pause) is (pause and settings is None)
        out, i = [], 0
        for tk in ticks:
            if tk == resume_at:
                pipe.pause_view_updates(False)
            while frames[i].recv_ns <= tk:
                pipe.push(frames[i])
                i += 1
            out.append(np.r_[pipe.tick(tk)[0].position])
        return np.array(out)

    occlusion = run({"single_view": {"mode": "occlusion"}}, False)
    paused = run(None, True)
    always = run(None, False)
    half = len(ticks) // 2
    assert np.array_equal(paused[:half], occlusion[:half])  # paused: occlusion's output, bit for bit
    assert not np.array_equal(always[:half], occlusion[:half])  # the default differs from it
    assert not np.array_equal(paused[half + 5:], occlusion[half + 5:])  # resumed: the views are taken again
