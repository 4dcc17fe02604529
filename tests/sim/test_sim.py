"""Simulator: trajectories, scenario config, capture statistics against ground truth."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from visionpos.config.arena import ConfigError, load_arena, load_yaml, parse_arena, resolve_config_path
from visionpos.messages import FLAG_TRUNCATED
from visionpos.sim import iter_frames, load_scenario, parse_sim, simulate
from visionpos.sim import trajectories as T
from visionpos.sim.capture import SPURIOUS_MIRROR, SPURIOUS_RANDOM, SPURIOUS_STATIC

# ------------------------------------------------------------------ helpers


def _arena_with(sim: dict, bodies: list | None = None, name: str = "thesis"):
    """The built-in arena with its sim section (and optionally bodies) replaced."""
    data = load_yaml(resolve_config_path(name))
    data["sim"] = sim
    if bodies is not None:
        data["bodies"] = bodies
    return parse_arena(data, f"<test {name}>")


def _cv2_project(cam, pts: np.ndarray) -> np.ndarray:
    """Independent projection through OpenCV (world points (N, 3) -> pixels (N, 2))."""
    rvec, _ = cv2.Rodrigues(cam.R)
    if cam.model.kind == "fisheye":
        uv, _ = cv2.fisheye.projectPoints(
            pts.reshape(-1, 1, 3), rvec, cam.t.reshape(3, 1), cam.model.K, cam.model.dist[:4]
        )
    else:
        uv, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, cam.t.reshape(3, 1), cam.model.K, cam.model.dist)
    return uv.reshape(-1, 2)


QUIET = {  # a sim section with every nuisance switched off
    "duration": 2.0,
    "seed": 3,
    "centroid_noise_px": 0.0,
    "drop_probability": 0.0,
    "timing_jitter_us": 0,
    "sync_residual_us": 0,
    "spurious": {"static_per_camera": 0, "random_per_frame": 0.0},
    "merge_blobs": False,
}

# ------------------------------------------------------------ trajectories

_TRAJS = {
    "hover": lambda: T.hover([0, 0, 0.8], rng=np.random.default_rng(1)),
    "square": lambda: T.Square(np.array([0.0, 0.0, 0.8])),
    "figure8": lambda: T.Figure8(np.array([0.0, 0.0, 1.0])),
    "aggressive": lambda: T.Aggressive(np.array([0.0, 0.0, 1.5])),
    "wand_wave": lambda: T.wand_wave([0, 0, 1.1], [1.4, 1.4, 0.7], np.random.default_rng(2)),
    "static": lambda: T.Static(np.array([0.1, 0.2, 0.007]), Rotation.from_euler("z", 30, degrees=True).as_quat()),
}


@pytest.mark.parametrize("kind", sorted(_TRAJS))
def test_velocities_match_finite_differences(kind):
    tr = _TRAJS[kind]()
    dt = 1e-3
    t = np.arange(0.0, 12.0, dt)
    m = tr(t)
    fd_v = (m.positions[2:] - m.positions[:-2]) / (2 * dt)
    scale = max(1.0, np.abs(m.velocities).max())
    assert np.abs(fd_v - m.velocities[1:-1]).max() < 1e-4 * scale
    rot = Rotation.from_quat(m.quaternions)
    fd_w = (rot[:-2].inv() * rot[2:]).as_rotvec() / (2 * dt)  # body-frame rate
    wscale = max(1.0, np.abs(m.angular_velocities).max())
    assert np.abs(fd_w - m.angular_velocities[1:-1]).max() < 1e-3 * wscale
    assert np.allclose(np.linalg.norm(m.quaternions, axis=1), 1.0)


def test_square_is_half_metre_at_80cm():
    sq = T.Square(np.array([0.0, 0.0, 0.8]), side=0.5, edge_time=2.5, pause=0.5)
    m = sq(np.linspace(0, 12.0, 12001))  # one full lap
    p = m.positions
    assert np.allclose(p[:, 2], 0.8)
    assert np.isclose(p[:, 0].min(), -0.25) and np.isclose(p[:, 0].max(), 0.25)
    assert np.isclose(p[:, 1].min(), -0.25) and np.isclose(p[:, 1].max(), 0.25)
    # it flies the edges: every sample lies on the square's outline
    on_edge = np.isclose(np.abs(p[:, 0]), 0.25, atol=1e-9) | np.isclose(np.abs(p[:, 1]), 0.25, atol=1e-9)
    assert on_edge.all()
    # stops at each corner, and the body stays upright-ish (gentle flight)
    speed = np.linalg.norm(m.velocities, axis=1)
    assert speed.max() == pytest.approx(sq.peak_speed, rel=1e-3)
    tilt = np.degrees(np.arccos(Rotation.from_quat(m.quaternions).apply([0, 0, 1])[:, 2]))
    assert tilt.max() < 5


def test_aggressive_peaks_at_3_m_s_with_fast_yaw():
    ag = T.Aggressive(np.array([0.0, 0.0, 1.5]), radius=1.0, peak_speed=3.0, yaw_rate=3.0)
    t = np.linspace(0, 2 * np.pi / ag.omega, 20001)
    m = ag(t)
    speed = np.linalg.norm(m.velocities, axis=1)
    assert speed.max() == pytest.approx(3.0, rel=1e-4)
    assert speed.min() > 2.0
    assert np.abs(m.angular_velocities[:, 2]).mean() > 2.0  # fast yaw
    # thrust axis tilts into the turn: body z aligned with acceleration + g
    _, _, acc = ag.kinematics(t)
    zb = Rotation.from_quat(m.quaternions).apply([0, 0, 1])
    want = acc + [0, 0, T.GRAVITY]
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    assert np.allclose(zb, want, atol=1e-9)


def test_hover_stays_close_and_wand_sweeps_volume():
    hv = T.hover([0.5, -0.2, 1.0], drift_m=0.02, rng=np.random.default_rng(0))
    p = hv(np.linspace(0, 60, 6001)).positions
    assert np.abs(p - [0.5, -0.2, 1.0]).max() <= 0.02 + 1e-12
    ww = T.wand_wave([0, 0, 1.1], [1.4, 1.4, 0.7], np.random.default_rng(5))
    m = ww(np.linspace(0, 60, 6001))
    dev = m.positions - [0, 0, 1.1]
    assert (np.abs(dev) <= np.array([0.7, 0.7, 0.35]) + 1e-12).all()
    assert (dev.max(axis=0) - dev.min(axis=0) > 0.5 * np.array([1.4, 1.4, 0.7])).all()
    axis = Rotation.from_quat(m.quaternions).apply([1, 0, 0])
    # the wand points in widely varied directions: no dominant direction
    assert np.linalg.norm(axis.mean(axis=0)) < 0.6
    assert (axis.max(axis=0) > 0.7).all() and (axis.min(axis=0) < -0.7).all()


def test_trajectory_config_errors_name_the_key():
    arena = _arena_with({"sessions": {"f": {"quad": {"trajectory": "loop"}}}})
    with pytest.raises(ConfigError) as e:
        parse_sim(arena)
    assert e.value.key == "sim.sessions.f.quad.trajectory" and "square" in str(e.value)
    arena = _arena_with({"sessions": {"f": {"quad": {"trajectory": "square", "side": -1}}}})
    with pytest.raises(ConfigError) as e:
        parse_sim(arena)
    assert e.value.key == "sim.sessions.f.quad.side"
    arena = _arena_with({"sessions": {"f": {"quad": {"trajectory": "square", "speed": 2}}}})
    with pytest.raises(ConfigError, match="unknown key") as e:
        parse_sim(arena)
    assert e.value.key == "sim.sessions.f.quad.speed"
    arena = _arena_with({"sessions": {"f": {"quad": {"trajectory": "aggressive", "radius": 0.3, "peak_speed": 3}}}})
    with pytest.raises(ConfigError, match="tilt") as e:  # 30 m/s^2 centripetal: no quadrotor does that
        parse_sim(arena)
    assert e.value.key == "sim.sessions.f.quad.peak_speed"
    arena = _arena_with({"sessions": {"f": {"drone9": {"trajectory": "hover"}}}})
    with pytest.raises(ConfigError, match="no body or prop named 'drone9'"):
        parse_sim(arena)


def test_sim_section_errors_name_the_key():
    with pytest.raises(ConfigError) as e:
        load_scenario("thesis", ["sim.centroid_noise_px=-1"])
    assert e.value.key == "sim.centroid_noise_px" and "thesis_arena.yaml" in e.value.source
    with pytest.raises(ConfigError) as e:
        load_scenario("thesis", ["sim.noise=1"])
    assert e.value.key == "sim.noise"
    with pytest.raises(ConfigError) as e:
        load_scenario("thesis", ["sim.latency_ms.mean=fast"])
    assert e.value.key == "sim.latency_ms.mean"
    with pytest.raises(ConfigError) as e:
        load_scenario("thesis", ["sim.session=nope"])
    assert e.value.key == "sim.session" and "flight" in str(e.value)
    with pytest.raises(ConfigError) as e:
        load_scenario("thesis", ["sim.cameras.9.fps=50"])
    assert e.value.key == "sim.cameras.9"
    with pytest.raises(ConfigError, match="closer than 10 mm") as e:
        load_scenario("thesis", ["sim.props.0.markers=[[0, 0, 0], [0.005, 0, 0], [0.1, 0, 0]]"])
    assert e.value.key == "sim.props[0].markers"
    with pytest.raises(ConfigError) as e:
        load_scenario("thesis", ["sim.props.1.name=quad"])
    assert e.value.key == "sim.props[1].name"


# ---------------------------------------------------------------- configs


def test_thesis_arena_matches_the_thesis():
    a = load_arena("thesis")
    assert len(a.cameras) == 4
    # Table 4.1, V2 NoIR 960x640 (alpha, beta, u0, v0, k1..k4)
    table = [
        (720.313, 719.521, 481.014, 360.991, 0.396, 0.634, -2.417, 2.111),
        (768.113, 767.935, 472.596, 350.978, 0.369, 1.501, -7.941, 11.917),
        (728.237, 729.419, 459.854, 351.59, 0.276, 2.095, -9.980, 14.192),
        (750.149, 748.903, 492.144, 350.213, 0.401, 1.160, -7.103, 11.415),
    ]
    for cam, row in zip(a.cameras, table):
        m = cam.model
        assert (m.kind, m.width, m.height, cam.fps) == ("fisheye", 960, 640, 100.0)
        assert np.allclose([m.fx, m.fy, m.cx, m.cy, *m.dist], row)
    c = np.array([cam.center for cam in a.cameras])
    assert np.allclose(c[:, 2], 2.6)
    assert np.allclose(sorted(set(np.round(np.abs(np.diff(c[:, 0])), 6)) - {0.0}), [4.24])
    assert np.allclose(np.ptp(c[:, 0]), 4.24) and np.allclose(np.ptp(c[:, 1]), 4.82)
    # a 1.6 m x 1.6 m x 1.7 m flight volume (the thesis square and well beyond) is seen by all four
    g = np.array(
        list(itertools.product(np.linspace(-0.8, 0.8, 9), np.linspace(-0.8, 0.8, 9), np.linspace(0.3, 2.0, 6)))
    )
    assert all(cam.visible(g, margin=5).all() for cam in a.cameras)
    quad = a.bodies[0].markers
    assert 0.16 < np.max(np.linalg.norm(quad[:, None] - quad[None], axis=-1)) < 0.20
    # the wand prop: A-B 5.4 cm, B-C 10.3 cm, collinear
    sc = load_scenario("thesis", session="wand")
    w = sc.body("wand").markers
    assert np.isclose(np.linalg.norm(w[1] - w[0]), 0.054) and np.isclose(np.linalg.norm(w[2] - w[1]), 0.103)
    assert np.linalg.matrix_rank(w - w[0], tol=1e-9) == 1
    assert not sc.body("wand").tracked


def _sorted_distances(m: np.ndarray) -> np.ndarray:
    return np.sort([np.linalg.norm(a - b) for a, b in itertools.combinations(m, 2)])


@pytest.mark.parametrize("name", ["thesis", "arena8"])
def test_bodies_are_distinguishable(name):
    a = load_arena(name)
    ds = [_sorted_distances(b.markers) for b in a.bodies]
    for d in ds:
        assert np.diff(d).min() >= 0.01  # no near-duplicate internal distances
    for d1, d2 in itertools.combinations(ds, 2):
        assert len(d1) != len(d2) or np.abs(d1 - d2).max() >= 0.01
    # with one marker hidden: every marker triangle differs from every other by >= 1 cm in a side
    tris = [
        _sorted_distances(b.markers[list(c)])
        for b in a.bodies
        for c in itertools.combinations(range(len(b.markers)), 3)
    ]
    for t1, t2 in itertools.combinations(tris, 2):
        assert np.abs(t1 - t2).max() >= 0.01


def test_arena8_cameras_and_flight_in_view():
    a = load_arena("arena8")
    assert len(a.cameras) == 8 and {c.fps for c in a.cameras} == {100.0, 120.0}
    c = np.array([cam.center for cam in a.cameras])
    assert np.abs(c[:, :2]).max() <= 3.0 and np.allclose(c[:, 2], 3.0)
    sc = load_scenario("arena8", duration=10)
    times = sc.start_ns + np.arange(0, 10_000_000_000, 50_000_000)
    for b in sc.bodies:
        p, _ = sc.truth_at(b.name, times)
        assert (np.abs(p[:, :2]) < 2.6).all() and (p[:, 2] > 0.3).all()
        seen = sum(cam.visible(p).astype(int) for cam in sc.cameras)
        assert seen.min() >= 6
    # the three drones never come within 40 cm of each other
    ps = [sc.truth_at(b.name, times)[0] for b in sc.bodies]
    for p1, p2 in itertools.combinations(ps, 2):
        assert np.linalg.norm(p1 - p2, axis=1).min() > 0.4


# ---------------------------------------------------------------- capture


def _true_marker_world(sc, res):
    """Per blob of every frame (rows): camera id, world point of its true marker,
    blob xy, truth xy. Computed from the trajectories, not from the capture code."""
    cam_ids, pts, xy, txy = [], [], [], []
    for bi, b in enumerate(sc.bodies):
        rows = [(f.camera_id, tr.true_ns, tr.marker[j], f.blobs[j, :2], tr.true_xy[j])
                for f, tr in zip(res.frames, res.frame_truth) for j in np.nonzero(tr.body == bi)[0]]
        if not rows:
            continue
        c, t, m, a, b_ = zip(*rows)
        mo = sc.motion_at(b.name, np.array(t, dtype=np.int64))
        pts.append(Rotation.from_quat(mo.quaternions).apply(b.markers[np.array(m)]) + mo.positions)
        cam_ids.append(np.array(c)), xy.append(np.array(a)), txy.append(np.array(b_))
    return np.concatenate(cam_ids), np.vstack(pts), np.vstack(xy), np.vstack(txy)


def test_noiseless_blobs_reproject_exactly_from_truth():
    sc = load_scenario("arena8", duration=1.0, **{k: v for k, v in QUIET.items() if k != "duration"})
    res = simulate(sc)
    for f, tr in zip(res.frames, res.frame_truth):
        assert len(f.blobs) == len(tr.body) and f.blobs.dtype == np.float32
        assert (tr.body >= 0).all()  # nothing spurious configured
        assert f.capture_ns == tr.true_ns  # no sync error, no jitter configured
    cam_ids, pts, xy, txy = _true_marker_world(sc, res)
    assert len(pts) > 1000
    for cam in sc.cameras:
        sel = cam_ids == cam.id
        uv = _cv2_project(cam, pts[sel])
        assert np.abs(uv - xy[sel]).max() < 2e-4  # float32 storage
        assert np.abs(uv - txy[sel]).max() < 1e-6


def test_frame_timing_drops_and_jitter_statistics():
    sim = dict(QUIET, duration=20.0, drop_probability=0.1, timing_jitter_us=30, sync_residual_us=80)
    sim["latency_ms"] = {"mean": 5.0, "std": 1.0, "max": 9.0}
    sc = parse_sim(_arena_with(sim))
    res = simulate(sc)
    by_cam = {}
    for f, tr in zip(res.frames, res.frame_truth):
        by_cam.setdefault(f.camera_id, []).append((f.seq, tr.true_ns, f.capture_ns, f.recv_ns))
    phases = []
    for t in sc.timings:
        seq, true_ns, cap, recv = (np.array(v, dtype=np.int64) for v in zip(*by_cam[t.camera_id]))
        total = int(np.floor((20e9 - t.phase_ns) / t.period_ns)) + 1
        # drops: seq numbers missing from the stream, at the configured rate
        assert len(seq) + len(res.dropped[t.camera_id]) == total
        assert set(seq.tolist()).isdisjoint(res.dropped[t.camera_id].tolist())
        p = len(res.dropped[t.camera_id]) / total
        assert abs(p - 0.1) < 5 * np.sqrt(0.1 * 0.9 / total)
        # frame rate and phase: least-squares line through (seq, true time)
        A = np.column_stack([np.ones(len(seq)), seq.astype(float)])
        coef, *_ = np.linalg.lstsq(A, (true_ns - sc.start_ns).astype(float), rcond=None)
        assert coef[1] == pytest.approx(1e9 / t.fps, rel=2e-4)  # within crystal drift
        assert abs(coef[0] - t.phase_ns) < 5 * 30e3 * 2 / np.sqrt(len(seq))
        resid = (true_ns - sc.start_ns) - A @ coef
        assert np.std(resid) == pytest.approx(30e3, rel=0.1)
        phases.append(coef[0])
        # reported stamps carry the station's sync residual: bounded, ~80 us std overall
        err = (cap - true_ns).astype(float)
        assert np.abs(err).max() <= sc.clocks[t.station_id].residual_bound_ns + 1
        lat = (recv - true_ns) / 1e6
        assert 0 < lat.min() and lat.max() <= 9.0 and abs(lat.mean() - 5.0) < 0.1
    assert np.ptp(phases) > 0  # random phases differ between cameras
    caps = np.array([f.capture_ns for f in res.frames])
    assert (np.diff(caps) >= 0).all()


def test_occlusion_by_disc_and_marker_normal():
    bodies = [
        {"name": "probe", "id": 1, "markers": [[0.0, 0.0, 0.05], [0.0, 0.0, -0.05], [0.3, 0.0, 0.0], [-0.3, 0.0, 0.0]]}
    ]
    sim = dict(QUIET, sessions={"s": {"probe": {"trajectory": "static", "position": [0.0, 0.0, 0.8]}}})
    # a 20 cm disc between the lower marker and every (higher) camera; no normal cut
    sim["occlusion"] = {"disc_radius": 0.2, "normal_cutoff_deg": 180}
    res = simulate(parse_sim(_arena_with(sim, bodies)))
    for tr in res.frame_truth:
        assert sorted(tr.marker.tolist()) == [0, 2, 3]
    # normal cut: markers 0 and 1 sit on the body axis and face straight up;
    # every camera is ~61 deg off vertical from here
    for cutoff, want in ((55, []), (70, [0, 1])):
        sim["occlusion"] = {"disc_radius": 0.0, "normal_cutoff_deg": cutoff}
        res = simulate(parse_sim(_arena_with(sim, bodies)))
        elev = [
            np.degrees(np.arccos((c.center - [0, 0, 0.8])[2] / np.linalg.norm(c.center - [0, 0, 0.8])))
            for c in res.scenario.cameras
        ]
        assert all(55 < e < 70 for e in elev)
        for tr in res.frame_truth:
            # markers 2 and 3 are off-axis (normals lean outward): check 0 and 1 only
            assert sorted(set(tr.marker.tolist()) & {0, 1}) == want
    sim["occlusion"] = {"enabled": False}
    res = simulate(parse_sim(_arena_with(sim, bodies)))
    assert all(sorted(tr.marker.tolist()) == [0, 1, 2, 3] for tr in res.frame_truth)


def test_view_schedule_hides_markers_from_cameras_during_its_window():
    window = "[{body: quad, start_s: 0.3, end_s: 0.6, cameras: {1: [0, 2], 3: all}}]"
    sc = load_scenario("thesis", ["sim.view_schedule=" + window], duration=0.9, seed=4)
    plain = simulate(load_scenario("thesis", duration=0.9, seed=4))
    res = simulate(sc)
    t0, t1 = sc.start_ns + 300_000_000, sc.start_ns + 600_000_000
    seen: dict[tuple[bool, int], set[int]] = {}
    for f, tr, tp in zip(res.frames, res.frame_truth, plain.frame_truth):
        quad = set(tr.marker[tr.body == 0].tolist())
        during = t0 <= tr.true_ns < t1
        seen.setdefault((during, f.camera_id), set()).update(quad)
        if not during:  # outside the window nothing changes
            assert quad == set(tp.marker[tp.body == 0].tolist())
    assert seen[(True, 1)] == {0, 2} and seen[(True, 3)] == {0, 1, 2, 3}
    assert seen[(True, 2)] == set() and seen[(True, 4)] == set()
    assert all(seen[(False, c)] == {0, 1, 2, 3} for c in (1, 2, 3, 4))


@pytest.mark.parametrize("window, key, match", [
    ("[{body: drone, start_s: 1, end_s: 2}]", "body", "no body or prop 'drone'"),
    ("[{body: quad, start_s: 2, end_s: 1}]", "end_s", "after start_s"),
    ("[{body: quad, start_s: 1, end_s: 2, cameras: {9: all}}]", "cameras", "no simulated camera with id 9"),
    ("[{body: quad, start_s: 1, end_s: 2, cameras: {1: [4]}}]", "cameras.1", "marker indices 0..3"),
    ("[{body: quad, start_s: 1, end_s: 2, camera: {1: all}}]", "camera", "unknown key"),
])
def test_view_schedule_errors_name_the_key(window, key, match):
    with pytest.raises(ConfigError, match=match) as e:
        load_scenario("thesis", ["sim.view_schedule=" + window])
    assert e.value.key == f"sim.view_schedule[0].{key}"


def test_out_of_view_markers_absent():
    # a "body" of markers scattered over the whole arena, some outside some views
    rng = np.random.default_rng(4)
    pts = np.column_stack([rng.uniform(-3.5, 3.5, 40), rng.uniform(-3.5, 3.5, 40), rng.uniform(0.0, 2.5, 40)])
    bodies = [{"name": "cloud", "id": 1, "markers": pts.tolist()}]
    sim = dict(QUIET, duration=0.2, sessions={"s": {"cloud": {"trajectory": "static", "position": [0, 0, 0]}}})
    sim["occlusion"] = {"enabled": False}
    res = simulate(parse_sim(_arena_with(sim, bodies)))
    cams = res.scenario.arena.camera_by_id()
    some_hidden = False
    for f, tr in zip(res.frames, res.frame_truth):
        cam = cams[f.camera_id]
        pc = cam.to_camera(pts)
        uv = _cv2_project(cam, pts)
        w, h = cam.model.width, cam.model.height
        theta = np.arctan2(np.linalg.norm(pc[:, :2], axis=1), pc[:, 2])
        inside = (pc[:, 2] > 0) & (theta < np.radians(85)) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5)
        inside &= (uv[:, 1] >= -0.5) & (uv[:, 1] <= h - 0.5)
        assert set(tr.marker.tolist()) == set(np.nonzero(inside)[0].tolist())
        some_hidden |= not inside.all()
    assert some_hidden


def test_spurious_blobs_at_configured_rate():
    sim = dict(QUIET, duration=10.0, spurious={"static_per_camera": 3, "random_per_frame": 0.5})
    res = simulate(parse_sim(_arena_with(sim)))
    n_static = np.array([np.count_nonzero(tr.marker == SPURIOUS_STATIC) for tr in res.frame_truth])
    n_rand = np.array([np.count_nonzero(tr.marker == SPURIOUS_RANDOM) for tr in res.frame_truth])
    assert (n_static == 3).all()
    # glints land uniformly on the sensor: a few fall outside after rounding only at the border
    assert abs(n_rand.mean() - 0.5) < 5 * np.sqrt(0.5 / len(n_rand))
    for tr in res.frame_truth:
        assert (tr.body[tr.marker < 0] == -1).all()
    # static reflections do not move
    first = {}
    for f, tr in zip(res.frames, res.frame_truth):
        xy = tr.true_xy[tr.marker == SPURIOUS_STATIC]
        xy = xy[np.lexsort(xy.T)]
        if f.camera_id in first:
            assert np.array_equal(first[f.camera_id], xy)
        else:
            first[f.camera_id] = xy


def test_floor_mirror_images_and_blob_cap():
    sim = dict(QUIET, duration=1.0, spurious={"static_per_camera": 0, "random_per_frame": 0.0, "floor_mirror": 0.3})
    sc = parse_sim(_arena_with(sim))
    res = simulate(sc)
    quad = sc.bodies[0]
    n = 0
    for f, tr in zip(res.frames, res.frame_truth):
        cam = sc.arena.camera_by_id()[f.camera_id]
        mir = np.nonzero(tr.marker == SPURIOUS_MIRROR)[0]
        real = np.nonzero(tr.body == 0)[0]
        m = sc.motion_at(quad.name, [tr.true_ns])
        X = Rotation.from_quat(m.quaternions[0]).apply(quad.markers) + m.positions[0]
        X[:, 2] *= -1  # the mirror images below the floor
        uv = _cv2_project(cam, X)
        for j in mir:  # each mirror blob sits on the projection of some mirrored marker
            assert np.linalg.norm(uv - f.blobs[j, :2], axis=1).min() < 2e-4
            assert f.blobs[j, 3] < f.blobs[real, 3].max()  # dimmer than the real markers
        n += len(mir)
    assert n > 100
    # a detector cap: at most max_blobs per frame, flagged as truncated
    sim = dict(QUIET, duration=0.5, max_blobs=10, spurious={"static_per_camera": 0, "random_per_frame": 30.0})
    res = simulate(parse_sim(_arena_with(sim)))
    assert all(len(f.blobs) <= 10 for f in res.frames)
    assert sum(bool(f.flags & FLAG_TRUNCATED) for f in res.frames) > 0.9 * len(res.frames)
    with pytest.raises(ConfigError) as e:
        parse_sim(_arena_with(dict(QUIET, max_blobs=500)))
    assert e.value.key == "sim.max_blobs"


def test_centroid_noise_matches_sigma():
    sim = dict(QUIET, duration=3.0, centroid_noise_px=0.3)
    res = simulate(parse_sim(_arena_with(sim)))
    d = np.vstack([f.blobs[:, :2] - tr.true_xy for f, tr in zip(res.frames, res.frame_truth)])
    assert len(d) > 2000
    assert np.std(d) == pytest.approx(0.3, rel=0.05) and abs(d.mean()) < 0.02


def test_blob_area_shrinks_with_range():
    sc = load_scenario("thesis", duration=2.0, **{k: v for k, v in QUIET.items() if k != "duration"})
    res = simulate(sc)
    cams = sc.arena.camera_by_id()
    cam_ids, pts, _, _ = _true_marker_world(sc, res)
    blobs = np.vstack([f.blobs for f in res.frames])
    r = np.linalg.norm(pts - np.array([cams[c].center for c in cam_ids]), axis=1)
    fx = np.array([cams[c].model.fx for c in cam_ids])
    d_expected = fx * 0.014 / r  # small-angle projected diameter near the image centre
    d_got = 2 * np.sqrt(blobs[:, 2] / np.pi)
    assert np.median(d_got / d_expected) == pytest.approx(1.0, abs=0.1)
    assert np.corrcoef(1 / r, d_got)[0, 1] > 0.5
    # peaks fall with range^2 from the configured brightness (1000 at 1 m), clipped to 255
    want = np.clip(1000.0 / r**2 * np.minimum(1, d_got / 2), 20, 255)
    assert np.allclose(blobs[:, 3], want, rtol=1e-3)


def test_determinism_and_streaming_equivalence():
    sc = load_scenario("arena8", duration=1.0)
    a, b = simulate(sc), simulate(load_scenario("arena8", duration=1.0))
    assert len(a.frames) == len(b.frames)
    for f, g in zip(a.frames, b.frames):
        assert (f.camera_id, f.seq, f.capture_ns, f.recv_ns) == (g.camera_id, g.seq, g.capture_ns, g.recv_ns)
        assert np.array_equal(f.blobs, g.blobs)
    c = simulate(load_scenario("arena8", duration=1.0, seed=99))
    assert [f.capture_ns for f in c.frames] != [f.capture_ns for f in a.frames]
    streamed = list(iter_frames(sc, with_truth=True))
    assert [(f.camera_id, f.seq) for f, _ in streamed] == [(f.camera_id, f.seq) for f in a.frames]
    assert all(np.array_equal(f.blobs, g.blobs) for (f, _), g in zip(streamed, a.frames))
    by_recv = list(iter_frames(sc, order="recv"))
    recv = [f.recv_ns for f in by_recv]
    assert recv == sorted(recv) and len(by_recv) == len(a.frames)
    # truth_at agrees with the fine truth table
    name = sc.bodies[0].name
    p, q = a.truth_at(name, a.truth_times_ns[::7])
    assert np.allclose(p, a.truth[name].positions[::7]) and np.allclose(q, a.truth[name].quaternions[::7])


def test_sim_cli_writes_a_replayable_recording(tmp_path, capsys):
    from visionpos.cli import main
    from visionpos.messages import BlobFrame
    from visionpos.protocol import decode
    from visionpos.recording import RecordingReader

    out = tmp_path / "s.mcap"
    rc = main(
        ["sim", "--scenario", "thesis", "--duration", "1", "--seed", "5", "--set", "sim.centroid_noise_px=0.1",
         "--out", str(out)]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "frames" in text and "total" in text
    reader = RecordingReader(out)
    packets = list(reader.packets())
    frames = [decode(d) for _, d in packets]
    frames = [f for f in frames if isinstance(f, BlobFrame)]
    recv = [t for t, _ in packets]
    assert recv == sorted(recv)
    sc = load_scenario("thesis", ["sim.centroid_noise_px=0.1"], duration=1.0, seed=5)
    want = list(iter_frames(sc, order="recv"))
    assert len(frames) == len(want)
    assert all(np.array_equal(f.blobs, g.blobs) and f.capture_ns == g.capture_ns for f, g in zip(frames, want))
    truth = reader.truth()
    assert set(truth) == {"quad"} and len(truth["quad"][0]) == int(sc.truth_rate_hz) + 1
    assert reader.config["sim"]["centroid_noise_px"] == 0.1


def test_per_camera_overrides_and_endless_stream():
    sim = dict(QUIET, duration=1.0, cameras={2: {"fps": 50, "phase_ms": 3.0}, "4": {"enabled": False}})
    sc = parse_sim(_arena_with(sim))
    assert [t.camera_id for t in sc.timings] == [1, 2, 3]
    t2 = sc.timings[1]
    assert t2.fps == 50 and t2.phase_ns == 3e6
    res = simulate(sc)
    n = {c: len(v) for c, v in res.frames_by_camera().items()}
    assert n[2] == 50 and n[1] == 100
    first2 = min(tr.true_ns for f, tr in zip(res.frames, res.frame_truth) if f.camera_id == 2)
    assert first2 == sc.start_ns + 3_000_000
    # live use: an endless stream keeps going past the scenario's duration, in order
    stream = iter_frames(sc, duration_s=float("inf"))
    frames = list(itertools.islice(stream, 1000))
    caps = [f.capture_ns for f in frames]
    assert caps == sorted(caps) and caps[-1] - sc.start_ns > 3.5e9


def test_rolling_shutter_rows_expose_later():
    sim = dict(QUIET, duration=0.5, rolling_shutter_ms=8.0)
    sim["sessions"] = {"s": {"quad": {"trajectory": "aggressive", "center": [0.0, 0.0, 1.0], "radius": 0.8}}}
    sc = parse_sim(_arena_with(sim))
    res = simulate(sc)
    quad = sc.bodies[0]
    n = 0
    for f, tr in zip(res.frames, res.frame_truth):
        cam = sc.arena.camera_by_id()[f.camera_id]
        rows = np.nonzero((tr.body == 0) & ~tr.merged)[0]
        if not len(rows):
            continue
        delay = tr.exposure_ns[rows] - tr.true_ns
        # each blob's exposure is its row's readout slot
        want = (tr.true_xy[rows, 1] + 0.5) / cam.model.height * 8e6
        assert np.abs(delay - want).max() < 20.0  # ns (fixed-point residual: < 0.002 px of row)
        # and the marker was exactly there at that instant (independent projection)
        m = sc.motion_at(quad.name, tr.exposure_ns[rows])
        X = Rotation.from_quat(m.quaternions).apply(quad.markers[tr.marker[rows]]) + m.positions
        assert np.abs(_cv2_project(cam, X) - tr.true_xy[rows]).max() < 1e-3
        n += len(rows)
    assert n > 500
    # without a rolling shutter every blob is exposed at the frame time
    res = simulate(parse_sim(_arena_with(dict(sim, rolling_shutter_ms=0.0))))
    assert all((tr.exposure_ns == tr.true_ns).all() for tr in res.frame_truth)


def test_overlapping_markers_merge_into_one_blob():
    # two markers 12 mm apart look like one blob from 3-4 m; the third is far away
    bodies = [{"name": "pair", "id": 1, "marker_diameter": 0.014,
               "markers": [[0.0, 0.0, 0.0], [0.012, 0.0, 0.0], [0.3, 0.0, 0.0]]}]  # fmt: skip
    sim = dict(QUIET, duration=0.05, merge_blobs=True, occlusion={"enabled": False})
    sim["sessions"] = {"s": {"pair": {"trajectory": "static", "position": [0.0, 0.0, 1.0]}}}
    res = simulate(parse_sim(_arena_with(sim, bodies)))
    assert res.frames
    for f, tr in zip(res.frames, res.frame_truth):
        cam = res.scenario.arena.camera_by_id()[f.camera_id]
        uv = _cv2_project(cam, np.array([[0.0, 0.0, 1.0], [0.012, 0.0, 1.0], [0.3, 0.0, 1.0]]))
        assert len(f.blobs) == 2 and tr.merged.sum() == 1
        j = int(np.nonzero(tr.merged)[0][0])
        # the merged blob lies between the two projections, at their brightness-weighted mean
        a, b = uv[0], uv[1]
        t = np.dot(f.blobs[j, :2] - a, b - a) / np.dot(b - a, b - a)
        assert 0.3 < t < 0.7 and np.linalg.norm(a + t * (b - a) - f.blobs[j, :2]) < 1e-3
        assert np.abs(tr.true_xy[j] - f.blobs[j, :2]).max() < 2e-4
        k = 1 - j
        assert tr.marker[k] == 2 and np.abs(f.blobs[k, :2] - uv[2]).max() < 2e-4
