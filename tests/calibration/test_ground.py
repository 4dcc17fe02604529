"""Ground plane step and the calibrate CLI, against known cameras."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from tests.support.calibration import ring_cameras
from visionpos.calibration.ground import apply_world, calibrate_ground, identify_layout, world_from_layout
from visionpos.calibration.wand import CalibrationError
from visionpos.calibration.wand_solve import compare_cameras
from visionpos.messages import BlobFrame

LFRAME = np.array([[0.0, 0.0, 0.0], [0.10, 0.0, 0.0], [0.40, 0.0, 0.0], [0.0, 0.20, 0.0]])
HEIGHT = 0.007


def _static_frames(cams, points, n=40, noise=0.2, reflections=2, seed=0, bias_px=0.0):
    """bias_px: a fixed error of each marker's blob in each camera (std, px): what calibration error does."""
    rng = np.random.default_rng(seed)
    frames = []
    for cam in cams:
        fixed = rng.uniform([30, 30], [cam.model.width - 30, cam.model.height - 30], (reflections, 2))
        uv = cam.project(points) + rng.normal(0, bias_px, (len(points), 2))
        for k in range(n):
            xy = np.vstack([uv + rng.normal(0, noise, uv.shape), fixed + rng.normal(0, noise, fixed.shape)])
            xy = xy[rng.permutation(len(xy))]
            blobs = np.column_stack([xy, np.full((len(xy), 2), 10.0)]).astype(np.float32)
            frames.append(BlobFrame(cam.id, k, k * 10_000_000, blobs))
    return frames


def test_ground_recovers_world_frame():
    true = ring_cameras(4, target=(0.0, 0.0, 0.5))
    # the frame lies on the floor with its corner at (0.3, -0.2), turned 30 deg
    Rf = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    markers_world = LFRAME @ Rf.T + np.array([0.3, -0.2, HEIGHT])
    # the wand step left the cameras in some other rigid frame (e.g. the first camera's)
    Rw = Rotation.from_rotvec([0.4, -0.3, 1.2]).as_matrix()
    moved = apply_world(true, Rw, np.array([1.0, -2.0, 0.5]))
    frames = _static_frames(true, markers_world)
    g = calibrate_ground(frames, moved, LFRAME, origin=0, x_marker=2, marker_height=HEIGHT)
    # expected world: origin under marker 0, x along the long arm = the true world moved by the frame pose
    expected = apply_world(true, Rf.T, -Rf.T @ np.array([0.3, -0.2, 0.0]))
    ce, re, _ = compare_cameras(g.cameras, expected, similarity=False)
    assert ce.max() < 3e-3
    assert re.max() < 0.05
    np.testing.assert_allclose(g.markers, LFRAME + [0, 0, HEIGHT], atol=1e-3)
    assert g.fit_rms < 1e-3


def test_identify_layout_picks_markers_among_reflections():
    rng = np.random.default_rng(1)
    pts = np.vstack([rng.uniform(-2, 2, (6, 3)), LFRAME + [0.5, 0.5, 0.0]])
    order = rng.permutation(len(pts))
    idx = identify_layout(pts[order], LFRAME)
    np.testing.assert_allclose(pts[order][idx], LFRAME + [0.5, 0.5, 0.0])


def test_symmetric_layout_is_rejected():
    iso = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.3, 0.0]])
    with pytest.raises(CalibrationError, match="more than one way"):
        identify_layout(iso + 1.0, iso)


def test_missing_markers_are_reported():
    with pytest.raises(CalibrationError, match="no 4 of the 4 static points"):
        identify_layout(LFRAME * 1.5, LFRAME)


def test_world_from_layout_axes():
    R, t, fit = world_from_layout(LFRAME + [0, 0, HEIGHT], LFRAME, origin=0, x_marker=3, marker_height=HEIGHT)
    # x towards marker 3 (the layout's +y), z up: y must be the layout's -x
    np.testing.assert_allclose(R, [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(t, 0, atol=1e-12)


def test_cli_wand_then_ground_on_the_simulator(tmp_path, capsys):
    from visionpos.cli import main

    cal = tmp_path / "cal.yaml"
    png = tmp_path / "wand.png"
    rc = main(["calibrate", "wand", "--sim", "thesis", "--set", "sim.duration=8", "--out", str(cal), "--no-progress",
               "--report", str(png)])
    assert rc == 0
    assert png.stat().st_size > 1000
    out = capsys.readouterr().out
    assert "wand lengths" in out and "pi4" in out
    final = tmp_path / "final.yaml"
    rc = main(["calibrate", "ground", "--sim", "thesis", "--set", "sim.duration=1", "--config", str(cal),
               "--x-marker", "2", "--out", str(final), "--no-progress", "--plot", str(tmp_path / "ground.png")])
    assert rc == 0
    assert (tmp_path / "ground.png").stat().st_size > 10_000
    from visionpos.config.arena import load_arena

    got = load_arena(final).cameras
    truth = load_arena("thesis").cameras
    ce, re, _ = compare_cameras(list(got), list(truth), similarity=False)
    assert ce.max() < 6e-3 and re.max() < 0.1
    assert yaml.safe_load(final.read_text())["calibration"]["ground"]["x_marker"] == 2


def test_cli_reports_bad_input(tmp_path, capsys):
    from visionpos.cli import main

    rc = main(["calibrate", "wand", "--out", str(tmp_path / "x.yaml")])
    assert rc == 2
    assert "RECORDING or --sim" in capsys.readouterr().err


def test_cli_wand_from_a_recording(tmp_path, capsys):
    """The recording path: station packets in an MCAP file, config embedded, as the server writes them."""
    from visionpos.cli import main
    from visionpos.protocol import encode_frame
    from visionpos.recording import RecordingWriter
    from visionpos.sim import load_scenario, simulate

    sc = load_scenario("thesis", ["sim.duration=6"], session="wand")
    res = simulate(sc)
    path = tmp_path / "wand.mcap"
    with RecordingWriter(path, sc.arena.raw) as w:
        for f in res.frames_by_recv():
            w.write_packet(f.recv_ns, encode_frame(f))
    out = tmp_path / "cal.yaml"
    rc = main(["calibrate", "wand", str(path), "--out", str(out), "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    from visionpos.config.arena import load_arena

    ce, re, _ = compare_cameras(list(load_arena(out).cameras), list(sc.cameras))
    assert ce.max() < 4e-3 and re.max() < 0.08


NEAR_ISO = np.array([[0.0, 0.0, 0.0], [0.157, 0.0, 0.0], [0.0, 0.152, 0.0]])  # legs differ by 5 mm


def test_near_isosceles_frame_is_told_apart_by_its_leg_lengths():
    true = ring_cameras(4, target=(0.0, 0.0, 0.5))
    Rf = Rotation.from_euler("z", -50, degrees=True).as_matrix()
    world = NEAR_ISO @ Rf.T + np.array([-0.2, 0.1, HEIGHT])
    g = calibrate_ground(_static_frames(true, world, reflections=0), true, NEAR_ISO, origin=0, x_marker=1,
                         marker_height=HEIGHT)
    # the 157 mm leg is the x axis: a swapped leg would put marker 1 on y
    np.testing.assert_allclose(g.markers, NEAR_ISO + [0, 0, HEIGHT], atol=2e-3)
    assert g.marker_std.max() < 1e-3 and g.sigma_px > 0


def test_isosceles_frame_is_refused_with_the_difference_it_needs():
    iso = np.array([[0.0, 0.0, 0.0], [0.155, 0.0, 0.0], [0.0, 0.155, 0.0]])
    with pytest.raises(CalibrationError, match=r"differ by 0\.0 mm.*more than \d+ mm"):
        identify_layout(iso + 1.0, iso, point_std=np.full(3, 3e-4))


def test_distance_tolerance_scales_with_how_well_points_are_measured():
    measured = LFRAME * (1 + 0.04)  # every distance 4 % long: up to 16 mm off the layout
    # points known to 6 mm (far cameras, a rough calibration) -> a 16 mm difference is inside 4 sigma
    idx = identify_layout(measured, LFRAME, point_std=np.full(4, 6e-3))
    np.testing.assert_array_equal(idx, [0, 1, 2, 3])
    # known to 0.5 mm -> the same difference is not this frame
    with pytest.raises(CalibrationError, match="within 4 sigma"):
        identify_layout(measured, LFRAME, point_std=np.full(4, 5e-4))


@pytest.mark.parametrize("legs_mm", [(157.0, 152.0), (155.0, 152.0), (152.0, 152.0)])
def test_a_near_isosceles_frame_is_settled_by_the_cameras_above_it(legs_mm):
    # issue 30.4: MoCapRasp's triangle, legs 157 and 152 mm; and 3 mm, and equal legs. With 1 px of blob error
    # a distance is uncertain by a few mm, so the distances alone cannot tell 3 mm legs apart (refused without
    # the cameras); the frame's +z must point at the cameras, which only the right assignment does
    layout = np.array([[0.0, 0.0, 0.0], [legs_mm[0] / 1e3, 0.0, 0.0], [0.0, legs_mm[1] / 1e3, 0.0]])
    true = ring_cameras(4, target=(0.0, 0.0, 0.5))
    Rf = Rotation.from_euler("z", 110, degrees=True).as_matrix()
    world = layout @ Rf.T + np.array([0.2, -0.1, HEIGHT])
    frames = _static_frames(true, world, n=5, reflections=0, seed=3, bias_px=1.0)
    g = calibrate_ground(frames, true, layout, origin=0, x_marker=1, marker_height=HEIGHT)
    # marker 1 on +x and marker 2 on +y (to the bias's few mm): a swapped assignment turns the frame over,
    # marker 2 on -y and the cameras below the floor
    np.testing.assert_allclose(g.markers, layout + [0, 0, HEIGHT], atol=1.5e-2)
    assert min(c.center[2] for c in g.cameras) > 1.0
    from visionpos.calibration.ground import match_static, static_blobs, static_point_std
    by_cam = [static_blobs([f for f in frames if f.camera_id == c.id]) for c in true]
    pts, sup = match_static(true, by_cam)
    std, _ = static_point_std(true, pts, by_cam)
    if legs_mm[0] - legs_mm[1] <= 3.0:  # the distances alone: refused (157/152 passes them at this noise)
        with pytest.raises(CalibrationError, match="more than one way"):
            identify_layout(pts, layout, sup, point_std=std)


def test_a_frame_that_fits_itself_turned_is_refused_with_what_to_change():
    side = 0.15
    equilateral = np.array([[0.0, 0.0, 0.0], [side, 0.0, 0.0], [side / 2, side * np.sqrt(3) / 2, 0.0]])
    true = ring_cameras(4, target=(0.0, 0.0, 0.5))
    frames = _static_frames(true, equilateral + [0.1, 0.1, HEIGHT], n=5, reflections=0)
    with pytest.raises(CalibrationError, match=r"even with the cameras above it: turned in its own plane it fits "
                                               r"itself.*make its legs differ by more than \d+ mm"):
        calibrate_ground(frames, true, equilateral, origin=0, x_marker=1, marker_height=HEIGHT)


def test_a_mirrored_layout_is_named():
    true = ring_cameras(4, target=(0.0, 0.0, 0.5))
    scalene = np.array([[0.0, 0.0, 0.0], [0.40, 0.0, 0.0], [0.0, 0.20, 0.0]])
    frames = _static_frames(true, scalene + [0.1, 0.1, HEIGHT], n=5, reflections=0)
    # x and y swapped: the same distances, the other handedness
    with pytest.raises(CalibrationError, match="layout is mirrored"):
        calibrate_ground(frames, true, scalene[:, [1, 0, 2]], origin=0, x_marker=2, marker_height=HEIGHT)
