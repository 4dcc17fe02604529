"""Issue 29: the vehicles' IMU samples the pipeline takes are recorded (/fusion/imu) and a replay hands them over
again at the same point of the pipeline's input order, so a session with the IMU on replays to the same outputs."""

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from visionpos.analysis.replay import _ReplayLoop, load_settings, replay_log, write_trajectories_csv
from visionpos.recording import RecordingReader, RecordingWriter


def _imu_from_truth(t_ns, p, q_xyzw):
    """Body-frame specific force (N, 3) m/s^2 and rate (N, 3) rad/s by finite differences of the truth (z up)."""
    t = (t_ns - t_ns[0]) * 1e-9
    acc_world = np.gradient(np.gradient(p, t, axis=0), t, axis=0)
    R = Rotation.from_quat(q_xyzw)
    dR = R[1:] * R[:-1].inv()
    w_world = np.vstack([dR.as_rotvec() / np.diff(t)[:, None], np.zeros((1, 3))])
    return R.inv().apply(acc_world + [0.0, 0.0, 9.80665]), R.inv().apply(w_world)


def test_a_session_with_the_imu_on_replays_to_the_same_trajectories(thesis_log, tmp_path):
    reader = RecordingReader(thesis_log)
    arena = load_settings(reader.config, None, ["fusion.imu.enabled=true"])
    (name, (t, p, q)), = reader.truth().items()
    acc, gyro = _imu_from_truth(t, p, q)
    # "live": the thesis packets through the server's Ingest and a pipeline whose IMU source hands over the
    # samples up to 5 ms before the input's time (a link's delay), recorded as a server records
    live = _ReplayLoop(arena, None, None, None)
    rec = tmp_path / "imu.mcap"
    writer = RecordingWriter(rec, arena.raw, foxglove_rate_hz=None)
    live.ingest.recorder = writer
    live.pipe.imu_tap = writer.write_imu
    nxt, poses = [0], []

    class Source:  # as bridge/imu_feed.py's BridgeImu: drain(push), and the optical-only poses back
        def __call__(self, push):
            while nxt[0] < len(t) and t[nxt[0]] <= live.now_ns - 5_000_000:
                k = nxt[0]
                push(name, int(t[k]), acc[k], gyro[k], None)
                nxt[0] += 1

        def optical_pose(self, body, t_ns, R):
            poses.append((body, t_ns, R))

    live.pipe.add_imu_source(Source())
    for item in reader.packets_with_source():
        live.feed(item)
    got = live.result()
    writer.close()
    assert got.pipeline_stats["imu"][name]["used"] > 100 and not got.pipeline_stats["imu"][name]["dropped"]
    # the fusions' triangulated rotations went to the source while its samples were in the filter: the truth's
    assert len(poses) > 100 and {p[0] for p in poses} == {name}
    tp = np.array([p[1] for p in poses])
    ok = (tp >= t[0]) & (tp <= t[-1])
    truth_at = Slerp(t.astype(float), Rotation.from_quat(q))(tp[ok].astype(float))
    err = (Rotation.from_matrix([p[2] for p in poses])[ok].inv() * truth_at).magnitude()
    assert ok.sum() > 100 and np.degrees(err).max() < 2.0  # Kabsch noise, the sim's frame timing
    kinds = {r.at for r in RecordingReader(rec).inputs() if hasattr(r, "at")}
    assert kinds == {"frame", "tick"}  # samples taken by frames' pushes and by ticks were both recorded
    again = replay_log(rec)
    assert again.pipeline_stats["imu"][name] == got.pipeline_stats["imu"][name]
    write_trajectories_csv(got, tmp_path / "live.csv")
    write_trajectories_csv(again, tmp_path / "replay.csv")
    assert (tmp_path / "live.csv").read_bytes() == (tmp_path / "replay.csv").read_bytes()
    # without its IMU samples the same packets give other trajectories: the samples mattered
    write_trajectories_csv(replay_log(rec, overrides=["fusion.imu.enabled=false"]), tmp_path / "optical.csv")
    assert (tmp_path / "optical.csv").read_bytes() != (tmp_path / "live.csv").read_bytes()


def test_a_truncated_recording_gives_its_imu_samples_up_to_the_cut(tmp_path):
    import warnings

    from visionpos.recording import ImuRecord, RecordingDamagedWarning

    path = tmp_path / "t.mcap"
    with RecordingWriter(path, {"cameras": []}, foxglove_rate_hz=None) as w:
        for i in range(20):
            w.write_packet(i * 10, b"pkt%03d" % i)
            w.write_imu(i * 10, "quad", i * 10 - 3, [0.1 * i, 0.0, 9.8], [0.0, 0.01 * i, 0.0],
                        None if i % 2 else [0.0, 0.0, 0.05], "frame")
    data = path.read_bytes()
    path.write_bytes(data[:data.index(b'"t_ns":117') + 4])  # inside the 12th sample
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = list(RecordingReader(path).inputs())
    assert any(issubclass(c.category, RecordingDamagedWarning) for c in caught)
    imu = [r for r in got if isinstance(r, ImuRecord)]
    assert [r.t_ns for r in imu] == [i * 10 - 3 for i in range(12)]
    assert [r[0] for r in got if not isinstance(r, ImuRecord)] == [i * 10 for i in range(13)]
    r = imu[7]
    assert (r.log_ns, r.body, r.at, r.lever_arm) == (70, "quad", "frame", None)
    assert r.accel.tolist() == [0.1 * 7, 0.0, 9.8] and r.gyro.tolist() == [0.0, 0.01 * 7, 0.0]
    assert imu[6].lever_arm.tolist() == [0.0, 0.0, 0.05]


def test_the_server_records_the_imu_samples_its_pipeline_takes_while_it_records(tmp_path):
    from visionpos.server.service import FusionServer, load_config_with_overrides

    class Pipe:  # what the server needs of a pipeline here
        imu_tap = None
        identity = None

        def add_imu_source(self, drain):
            pass

    arena = load_config_with_overrides("thesis", ["server.insecure=true"])
    pipe = Pipe()
    with RecordingWriter(tmp_path / "a.mcap", arena.raw, foxglove_rate_hz=None) as w:
        server = FusionServer(arena, pipeline=pipe, recorder=w)
        assert pipe.imu_tap == w.write_imu
        server.detach_recording()
        assert pipe.imu_tap is None
        server.start_recording(w)  # the console's record button
        assert pipe.imu_tap == w.write_imu
