"""Replay: metrics against independent values, deterministic byte-identical outputs."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from visionpos.analysis import metrics as M

# ---------------------------------------------------------------- metrics (pure)


def test_interpolate_truth_matches_analytic_motion():
    # truth: straight line at 1 m/s and a constant yaw rate of 90 deg/s, sampled at 10 Hz
    t = np.arange(0, 11) * 100_000_000
    s = t * 1e-9
    pos = np.stack([s, 2 * s, np.ones_like(s)], axis=1)
    quat = Rotation.from_euler("z", 90 * s[:, None], degrees=True).as_quat()
    at = np.array([50_000_000, 333_000_000, 999_999_999, -1, 2_000_000_000])
    p, q, valid = M.interpolate_truth(t, pos, quat, at)
    assert valid.tolist() == [True, True, True, False, False]
    sa = at[:3] * 1e-9
    np.testing.assert_allclose(p[:3], np.stack([sa, 2 * sa, np.ones(3)], axis=1), atol=1e-12)
    yaw = Rotation.from_quat(q[:3]).as_euler("zyx", degrees=True)[:, 0]
    np.testing.assert_allclose(yaw, 90 * sa, atol=1e-9)


def test_rotation_errors_geodesic_and_sign_invariant():
    rng = np.random.default_rng(3)
    base = Rotation.random(50, random_state=4)
    angles = rng.uniform(0, np.pi, 50)
    axes = rng.normal(size=(50, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    est = Rotation.from_rotvec(axes * angles[:, None]) * base
    q = est.as_quat()
    q[::2] *= -1  # the same rotations with the other quaternion sign
    np.testing.assert_allclose(M.rotation_errors(q, base.as_quat()), angles, atol=1e-7)


def test_position_jitter_recovers_white_noise_on_smooth_motion():
    rng = np.random.default_rng(0)
    t = np.arange(2000, dtype=np.int64) * 10_000_000  # 100 Hz for 20 s
    s = t * 1e-9
    smooth = np.stack([0.5 * np.sin(0.5 * s), 0.3 * np.cos(0.4 * s), 1 + 0.1 * s], axis=1)
    sigma = 0.0007
    noisy = smooth + rng.normal(0, sigma, smooth.shape)
    assert M.position_jitter(t, noisy) == pytest.approx(sigma, rel=0.05)
    # a dropout gap is not counted as noise
    gap = np.concatenate([t[:1000], t[1000:] + 2_000_000_000])
    assert M.position_jitter(gap, smooth) < 1e-5


def test_body_metrics_against_hand_computed_values():
    t = np.arange(100, dtype=np.int64) * 10_000_000
    truth_p = np.zeros((100, 3))
    truth_q = np.tile([0, 0, 0, 1.0], (100, 1))
    est_p = truth_p.copy()
    est_p[:, 0] = np.where(np.arange(100) % 2 == 0, 0.003, -0.004)  # rms = sqrt((9+16)/2) mm
    est_q = Rotation.from_euler("x", np.full((100, 1), 2.0), degrees=True).as_quat()
    tracked = np.ones(100, bool)
    tracked[90:] = False
    lat = np.full(100, 5_000_000)
    m = M.body_metrics("b", t, tracked, est_p, est_q, lat, (t, truth_p, truth_q), n_ticks=100)
    assert m.tracked_fraction == pytest.approx(0.9)
    assert m.position_rmse_mm == pytest.approx(np.sqrt(12.5), rel=1e-9)
    assert m.rotation_rmse_deg == pytest.approx(2.0, rel=1e-6)
    assert m.latency_ms["p50"] == pytest.approx(5.0)
    assert m.n_scored == 90


# ---------------------------------------------------------------- replay of a simulated recording


def test_replay_is_byte_identical_across_runs_and_processes(thesis_log, tmp_path):
    import os
    import subprocess
    import sys

    from visionpos.cli import main

    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["replay", str(thesis_log), "--out", str(a), "--no-plots"]) == 0
    # a second run in a fresh interpreter with another hash seed: no hidden global or ordering state
    env = dict(os.environ, PYTHONHASHSEED="12345")
    proc = subprocess.run(
        [sys.executable, "-m", "visionpos", "replay", str(thesis_log), "--out", str(b), "--speed", "max", "--no-plots"],
        env=env, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    csv_a, csv_b = (a / "trajectories.csv").read_bytes(), (b / "trajectories.csv").read_bytes()
    assert csv_a == csv_b
    lines = csv_a.decode().splitlines()
    assert lines[0].startswith("body,tick_ns,time_ns")
    # one row per 100 Hz tick over the 3 s recording, for the one body
    assert 280 <= len(lines) - 1 <= 301
    assert all(line.startswith("quad,") for line in lines[1:])


def test_interpreted_kernels_give_the_compiled_result(tmp_path):
    """Without numba (VISIONPOS_NO_JIT, as on a platform with no wheel) the same kernels run as
    Python: the replay must give the same trajectories, to round-off. (1 s of recording: interpreted, the
    kernels take about 6 s a simulated second on 2 cores.)"""
    import os
    import subprocess
    import sys

    from visionpos.cli import main
    from visionpos.sim.write import write_recording

    thesis_log = tmp_path / "thesis1.mcap"
    write_recording("thesis", thesis_log, duration_s=1.0, seed=5)
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["replay", str(thesis_log), "--out", str(a), "--no-plots"]) == 0
    env = dict(os.environ, VISIONPOS_NO_JIT="1")
    code = "import visionpos.jit, sys; sys.exit(0 if not visionpos.jit.COMPILED else 3)"
    assert subprocess.run([sys.executable, "-c", code], env=env).returncode == 0
    proc = subprocess.run(
        [sys.executable, "-m", "visionpos", "replay", str(thesis_log), "--out", str(b), "--no-plots"],
        env=env, capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    ca = np.genfromtxt(a / "trajectories.csv", delimiter=",", skip_header=1)[:, 1:]
    cb = np.genfromtxt(b / "trajectories.csv", delimiter=",", skip_header=1)[:, 1:]
    assert ca.shape == cb.shape and ca.shape[0] > 80 and np.isfinite(ca[:, 3:6]).all(axis=1).sum() > 50
    # (columns 3:6 are x, y, z: tracked rows)
    assert np.array_equal(np.isnan(ca), np.isnan(cb))
    assert np.nanmax(np.abs(ca - cb)) < 1e-9


def test_replay_metrics_against_simulator_truth(thesis_log, tmp_path):
    from visionpos.analysis.replay import replay_log
    from visionpos.sim import load_scenario

    res = replay_log(thesis_log)
    quad = res.bodies["quad"]
    ok = quad.tracked
    assert ok.mean() > 0.8
    # independent truth: the scenario itself, not the truth stored in the log
    sc = load_scenario("thesis", ["sim.duration=3", "sim.seed=5"])
    tp, _ = sc.truth_at("quad", quad.time_ns[ok])
    err_mm = np.linalg.norm(quad.position[ok] - tp, axis=1) * 1e3
    m = {x.name: x for x in res.metrics()}["quad"]
    assert m.position_rmse_mm == pytest.approx(np.sqrt(np.mean(err_mm**2)), rel=0.02)
    assert m.position_rmse_mm < 10.0
    assert m.tracked_fraction == pytest.approx(ok.mean())


def test_replay_writes_metrics_json_and_changes_with_settings(thesis_log, tmp_path):
    from visionpos.cli import main

    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["replay", str(thesis_log), "--out", str(a), "--json"]) == 0
    assert main(["replay", str(thesis_log), "--out", str(b), "--no-plots", "--set", "server.output_rate_hz=50"]) == 0
    summ = json.loads((a / "metrics.json").read_text())
    for png in ("trajectory.png", "errors.png", "latency.png"):
        assert (a / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not (b / "trajectory.png").exists()
    assert summ["has_truth"] is True
    assert summ["bodies"][0]["name"] == "quad"
    # 50 Hz output: about half the rows of the 100 Hz replay
    na = len((a / "trajectories.csv").read_text().splitlines())
    nb = len((b / "trajectories.csv").read_text().splitlines())
    assert abs(nb - 1 - (na - 1) / 2) <= 2


def test_replay_missing_file_is_a_clear_error(tmp_path, capsys):
    from visionpos.cli import main

    assert main(["replay", str(tmp_path / "nope.mcap"), "--out", str(tmp_path / "o")]) == 2
    assert "no such recording" in capsys.readouterr().err


def test_replay_without_matplotlib_writes_everything_else(thesis_log, tmp_path, monkeypatch, capsys):
    import sys

    from visionpos.cli import main

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    monkeypatch.setitem(sys.modules, "matplotlib.pyplot", None)
    out = tmp_path / "o"
    assert main(["replay", str(thesis_log), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "matplotlib is not installed" in err and "visionpos[plots]" in err
    assert (out / "trajectories.csv").exists() and (out / "metrics.json").exists()
    assert not list(out.glob("*.png"))


def test_parse_speed():
    from visionpos.cli.replay import parse_speed

    assert parse_speed("max") is None
    assert parse_speed("1") == 1.0
    for bad in ("fast", "0", "-2"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_speed(bad)


def test_replay_of_realtime_stamped_stations_uses_the_recording_hosts_clocks(thesis_log, tmp_path):
    """Stations stamping CLOCK_REALTIME (PTP/chrony hosts): the server converts with its
    realtime - monotonic difference. A replay, on another host and day, must use the one the
    recording host had, so it reproduces the server-timebase replay exactly."""
    from visionpos import protocol as P
    from visionpos.analysis.replay import replay_log, write_trajectories_csv
    from visionpos.messages import BlobFrame
    from visionpos.recording import RecordingReader, RecordingWriter

    rt_minus_mono = 1_700_000_000_000_000_000 - 1_000_000_000_000  # a 2023 wall clock vs a 1000 s uptime
    src = RecordingReader(thesis_log)
    rt_log = tmp_path / "realtime.mcap"
    meta = {"wall_start_unix_ns": rt_minus_mono + 5_000_000_000, "monotonic_start_ns": 5_000_000_000}
    with RecordingWriter(rt_log, src.config, meta) as w:
        for recv_ns, data, source in src.packets_with_source():
            msg = P.decode(data)
            if isinstance(msg, P.Hello):
                data = P.encode(dataclass_replace(msg, timebase=P.Timebase.REALTIME))
            elif isinstance(msg, BlobFrame):
                data = P.encode_frame(dataclass_replace(msg, capture_ns=msg.capture_ns + rt_minus_mono))
            w.write_packet(recv_ns, data, source)
    a = write_trajectories_csv(replay_log(thesis_log), tmp_path / "a.csv").read_bytes()
    res = replay_log(rt_log)
    b = write_trajectories_csv(res, tmp_path / "b.csv").read_bytes()
    assert res.n_frames > 1000
    assert a == b


def dataclass_replace(obj, **changes):
    import dataclasses

    return dataclasses.replace(obj, **changes)
