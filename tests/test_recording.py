"""MCAP recording: round trip, crash safety under SIGKILL, damaged and foreign files."""

from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from scipy.spatial.transform import Rotation

from visionpos.messages import BodyState
from visionpos.recording import (
    MAX_PACKET_SOURCES,
    TOPIC_PACKETS,
    TOPIC_STATES,
    RecordingDamagedWarning,
    RecordingError,
    RecordingReader,
    RecordingWriter,
    recover,
    writer,
)

ROOT = Path(__file__).resolve().parents[1]
CONFIG = {"cameras": [{"id": 1, "name": "c1"}], "server": {"port": 9870}, "note": "ünïcode"}


def _state(i: int, rng: np.random.Generator) -> BodyState:
    a = rng.normal(size=(6, 6))
    if i % 3 == 0:  # untracked: NaN pose, as the pipeline reports a lost body
        nan = np.full(3, np.nan)
        return BodyState(f"body{i % 2}", i % 2 + 1, 1_000_000 * i + 7, 1_000_000 * i, nan, np.full(4, np.nan),
                         nan, nan, np.full((6, 6), np.nan), np.full((3, 3), np.nan), False, reset_counter=i // 5)
    return BodyState(
        name=f"body{i % 2}", body_id=i % 2 + 1, time_ns=1_000_000 * i + 7, capture_ns=1_000_000 * i,
        position=rng.normal(size=3), quaternion=Rotation.random(random_state=i).as_quat(),
        velocity=rng.normal(size=3), angular_velocity=rng.normal(size=3),
        covariance=a @ a.T, velocity_covariance=np.diag(rng.uniform(size=3)),
        tracked=True, n_markers=4, n_cameras=3,
        residual_mm=float("nan") if i % 4 == 0 else float(rng.uniform()), reset_counter=i // 5,
        update_kind=("pose", "views")[i % 2],
    )


def _packet(i: int) -> bytes:
    # distinct, variable-length payloads so a shifted or cut record cannot pass as another
    return struct.pack("<I", i) + bytes((i * 7 + k) & 0xFF for k in range(i % 50))


def test_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    path = tmp_path / "r.mcap"
    states = [_state(i, rng) for i in range(20)]
    t_truth = np.arange(10, dtype=np.int64) * 5_000_000
    p_truth = rng.normal(size=(10, 3))
    q_truth = Rotation.random(10, random_state=3).as_quat()
    with RecordingWriter(path, CONFIG, {"scenario": "unit", "arr": np.arange(2)}) as w:
        for i in range(300):
            w.write_packet(10_000 + i, _packet(i), ("127.0.0.1", 4000 + i % 3))
        w.write_packet(99_999, b"anonymous")
        for s in states:
            w.write_state(s)
        for k in range(10)[::-1]:  # out of order on purpose: truth() sorts by time
            w.write_truth(int(t_truth[k]), "drone", p_truth[k], q_truth[k])
        w.write_json("/events", 5, {"kind": "station_lost", "camera": 3, "latency": np.float64("nan")})
        with pytest.raises(ValueError):
            w.write_json(TOPIC_STATES, 1, {})
    r = RecordingReader(path)
    assert r.complete and r.damage is None
    assert r.config == CONFIG
    assert r.meta["scenario"] == "unit" and r.meta["arr"] == [0, 1] and "wall_start_unix_ns" in r.meta
    pk = list(r.packets_with_source())
    assert len(pk) == 301
    assert [p[1] for p in pk[:300]] == [_packet(i) for i in range(300)]
    assert [p[0] for p in pk[:300]] == list(range(10_000, 10_300))
    assert [p[2] for p in pk[:3]] == [("127.0.0.1", 4000), ("127.0.0.1", 4001), ("127.0.0.1", 4002)]
    assert pk[300] == (99_999, b"anonymous", None)
    got = list(r.states())
    assert len(got) == len(states)
    for a, b in zip(got, states):
        assert (a.name, a.body_id, a.time_ns, a.capture_ns, a.tracked, a.reset_counter, a.update_kind) == (
            b.name, b.body_id, b.time_ns, b.capture_ns, b.tracked, b.reset_counter, b.update_kind)
        for f in ("position", "quaternion", "velocity", "angular_velocity", "covariance", "velocity_covariance"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))  # NaN == NaN here
        assert (np.isnan(a.residual_mm) and np.isnan(b.residual_mm)) or a.residual_mm == b.residual_mm
    tr = r.truth()
    np.testing.assert_array_equal(tr["drone"][0], t_truth)
    np.testing.assert_array_equal(tr["drone"][1], p_truth)
    np.testing.assert_array_equal(tr["drone"][2], q_truth)
    assert list(r.json("/events")) == [(5, {"kind": "station_lost", "camera": 3, "latency": None})]


def test_readable_by_plain_mcap_reader(tmp_path):
    """Other MCAP tools (Foxglove, mcap CLI) read the file through its summary."""
    from mcap.reader import make_reader

    path = tmp_path / "r.mcap"
    with RecordingWriter(path, CONFIG) as w:
        for i in range(10):
            w.write_packet(i, _packet(i))
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "visionpos"
        msgs = [m.data for _, _, m in reader.iter_messages(topics=["/station/packets"])]
        assert msgs == [_packet(i) for i in range(10)]
        assert reader.get_summary().statistics.message_count == 10


_CHILD = r"""
import struct, sys, time
sys.path.insert(0, sys.argv[2])
from visionpos.recording import RecordingWriter
w = RecordingWriter(sys.argv[1], {"cameras": []})
i = 0
while True:
    w.write_packet(time.monotonic_ns(), struct.pack("<I", i) + bytes(i % 50), ("127.0.0.1", 1))
    if i % 200 == 199:
        print(i, flush=True)   # packets 0..i have been handed to the writer
    i += 1
    time.sleep(0.0005)
"""


def test_sigkill_leaves_readable_log(tmp_path):
    """A writer killed with SIGKILL mid-stream: everything written more than ~1 s before is readable."""
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(path), str(ROOT)], stdout=subprocess.PIPE, text=True)
    try:
        checkpoint = -1
        deadline = time.monotonic() + 30
        while checkpoint < 1000 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            checkpoint = int(line)
        assert checkpoint >= 1000, "writer subprocess did not make progress"
        time.sleep(1.2)  # the writer keeps going; flushes happen every 0.25 s
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    # mcap's own reader, its default call, reads the killed file directly
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "visionpos"
        got = [(ch.topic, ch.metadata, m.data) for _, ch, m in reader.iter_messages()]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = RecordingReader(path)
        assert not r.complete
        pk = [d for _, d in r.packets()]
    assert r.config == {"cameras": []}
    assert len(pk) > checkpoint
    assert pk == [struct.pack("<I", i) + bytes(i % 50) for i in range(len(pk))]
    # a killed writer's file has no summary: the reader says so (one warning)
    assert [w.category for w in caught] == [RecordingDamagedWarning]
    assert r.damage is not None and r.end() is None

    assert got == [(TOPIC_PACKETS, {"host": "127.0.0.1", "port": "1"}, d) for d in pk]

    # recovered: a clean, indexed file whose summary counts every message
    out = tmp_path / "clean.mcap"
    report = recover(path, out)
    assert report["messages"] == len(pk) and not report["was_complete"]
    with open(out, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary().statistics.message_count == len(pk)
        assert [m.data for _, _, m in reader.iter_messages()] == pk
    r2 = RecordingReader(out)
    assert r2.complete and r2.damage is None and r2.config == {"cameras": []}
    assert [d for _, d in r2.packets()] == pk


def test_truncated_anywhere_reads_a_prefix(tmp_path):
    path = tmp_path / "full.mcap"
    n = 40
    with RecordingWriter(path, CONFIG) as w:
        for i in range(n):
            w.write_packet(i, _packet(i))
    data = path.read_bytes()
    cut_path = tmp_path / "cut.mcap"
    prev = 0
    errors = 0
    for cut in range(9, len(data), 7):
        cut_path.write_bytes(data[:cut])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RecordingDamagedWarning)
            try:
                r = RecordingReader(cut_path)
            except RecordingError as e:
                assert str(cut_path) in str(e)
                errors += 1
                continue
            pk = [d for _, d in r.packets()]
        assert pk == [_packet(i) for i in range(len(pk))]
        assert len(pk) >= prev  # a longer prefix never reads less
        prev = len(pk)
    assert prev == n
    assert errors > 0  # cuts inside the header/config are refused with a message


def test_truncated_mid_record_warns(tmp_path):
    path = tmp_path / "t.mcap"
    with RecordingWriter(path, CONFIG) as w:
        for i in range(50):
            w.write_packet(i, _packet(i))
    data = path.read_bytes()
    idx = data.index(_packet(30))  # cut inside packet 30's payload
    path.write_bytes(data[: idx + 2])
    with pytest.warns(RecordingDamagedWarning, match="t.mcap"):
        r = RecordingReader(path)
        pk = [d for _, d in r.packets()]
    assert pk == [_packet(i) for i in range(30)]
    assert r.damage is not None


def test_corrupt_length_field_is_bounded(tmp_path):
    path = tmp_path / "c.mcap"
    with RecordingWriter(path, CONFIG) as w:
        for i in range(20):
            w.write_packet(i, _packet(i))
    data = bytearray(path.read_bytes())
    idx = data.index(_packet(10))
    # record layout: opcode(1) len(8) channel(2) seq(4) log(8) pub(8) data: blow up the length
    start = idx - 22 - 9  # back to the opcode byte
    assert data[start] == 0x05
    data[start + 1:start + 9] = struct.pack("<Q", 2**62)
    path.write_bytes(bytes(data))
    with pytest.warns(RecordingDamagedWarning):
        pk = [d for _, d in RecordingReader(path).packets()]
    assert pk == [_packet(i) for i in range(10)]


def test_not_mcap(tmp_path):
    p = tmp_path / "notes.txt"
    p.write_text("hello, this is not a log\n")
    with pytest.raises(RecordingError, match=r"notes\.txt.*not an MCAP file"):
        RecordingReader(p)
    with pytest.raises(RecordingError, match="no such recording"):
        RecordingReader(tmp_path / "missing.mcap")


def test_foreign_profile_refused(tmp_path):
    p = tmp_path / "ros.mcap"
    with open(p, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="x")
        w.finish()
    with pytest.raises(RecordingError, match=r"ros\.mcap.*profile is 'ros2'"):
        RecordingReader(p)


def test_missing_config_and_wrong_schema(tmp_path):
    p = tmp_path / "noconf.mcap"
    with open(p, "wb") as f:
        w = Writer(f)
        w.start(profile="visionpos", library="x")
        w.finish()
    with pytest.raises(RecordingError, match="visionpos.config"):
        RecordingReader(p)

    p = tmp_path / "schema.mcap"
    with open(p, "wb") as f:
        w = Writer(f)
        w.start(profile="visionpos", library="x")
        w.add_metadata("visionpos.config", {"yaml": "cameras: []\n"})
        sid = w.register_schema("geometry_msgs/Pose", "ros2msg", b"float64 x")
        ch = w.register_channel(TOPIC_STATES, "cdr", sid)
        w.add_message(ch, 1, b"\x00" * 8, 1)
        w.finish()
    r = RecordingReader(p)
    with pytest.raises(RecordingError, match=r"schema\.mcap.*/fusion/states.*visionpos\.BodyState"):
        list(r.states())


def test_close_is_idempotent_and_flushes(tmp_path):
    p = tmp_path / "x.mcap"
    w = RecordingWriter(p, CONFIG, flush_interval_s=60.0)  # no periodic flush: close must write everything
    for i in range(1000):
        w.write_packet(i, _packet(i))
    w.close()
    w.close()
    with pytest.raises(RuntimeError):
        w.write_packet(0, b"late")
    assert [d for _, d in RecordingReader(p).packets()] == [_packet(i) for i in range(1000)]
    assert os.path.getsize(p) == w.stats()["bytes"]


def test_torn_end_is_recovered_into_a_clean_file(tmp_path):
    """A kill inside a flush's write (or a power cut) tears the end: mcap's reader gives up on
    such a file; `recover` rewrites every record before the tear as a clean file."""
    path = tmp_path / "full.mcap"
    with RecordingWriter(path, CONFIG) as w:
        for i in range(60):
            w.write_packet(i, _packet(i), ("10.0.0.2", 5000))
    data = path.read_bytes()
    torn = tmp_path / "torn.mcap"
    torn.write_bytes(data[: data.index(_packet(41)) + 3])  # cut inside packet 41
    with open(torn, "rb") as f, pytest.raises(Exception):  # noqa: B017 - whatever mcap raises: it cannot read it
        list(make_reader(f).iter_messages())
    out = tmp_path / "torn.recovered.mcap"
    report = recover(torn, out)
    assert report["messages"] == 41 and report["damage"] and not report["was_complete"]
    with open(out, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary().statistics.message_count == 41
        assert [m.data for _, _, m in reader.iter_messages()] == [_packet(i) for i in range(41)]
        md = {m.name: m.metadata for m in reader.iter_metadata()}
    assert set(md) == {"visionpos.config", "visionpos.meta", "visionpos.recovered"}
    assert RecordingReader(out).config == CONFIG
    with pytest.raises(RecordingError, match="another output"):
        recover(out, out)


def test_recovered_recording_replays_like_the_damaged_one(thesis_log, tmp_path):
    """A real recording (simulated stations) cut part-way: recover, then replay the clean file."""
    from visionpos.analysis.replay import replay_log

    full = list(RecordingReader(thesis_log).packets_with_source())
    keep = len(full) // 2
    data = thesis_log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: data.index(full[keep][1]) + 5])  # inside packet `keep`: about 1.5 s of 3 s
    out = tmp_path / "cut.recovered.mcap"
    recover(cut, out)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RecordingDamagedWarning)
        expect = list(RecordingReader(cut).packets_with_source())
    assert expect == full[:keep]
    assert list(RecordingReader(out).packets_with_source()) == expect
    res = replay_log(out)
    quad = res.bodies["quad"]
    assert len(quad.tracked) > 100 and quad.tracked.mean() > 0.8
    assert quad.time_ns[-1] <= max(t for t, _, _ in expect) + 50_000_000


class _FullDisk:
    """os.pwrite on a disk that holds `capacity` bytes of this file: a write past it is cut
    short there, and the next one fails with ENOSPC, as the kernel does."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.failures = 0
        self._pwrite = os.pwrite

    def __call__(self, fd: int, data, offset: int) -> int:
        room = self.capacity - offset
        if room <= 0 and len(data):
            self.failures += 1
            raise OSError(28, os.strerror(28))  # ENOSPC
        return self._pwrite(fd, bytes(data[:room]), offset)


def test_disk_full_stops_the_recording_and_keeps_it_readable(tmp_path, monkeypatch, caplog):
    path = tmp_path / "full.mcap"
    disk = _FullDisk(20_000)
    monkeypatch.setattr(writer.os, "pwrite", disk)
    w = RecordingWriter(path, CONFIG, flush_interval_s=60.0)  # flushes only when the test says
    sent = 0
    on_disk_before_error = 0
    with caplog.at_level("ERROR", logger="visionpos.recording"):
        while w.stats()["error"] is None and sent < 2000:
            on_disk_before_error = sent
            for _ in range(25):
                w.write_packet(sent, _packet(sent), ("127.0.0.1", 4000))
                sent += 1
            w.flush()
        assert w.stats()["error"] is not None, "the disk never filled"
        # the caller goes on: nothing raises, later data is counted, not kept
        for k in range(100):
            w.write_packet(10_000 + k, b"late", ("127.0.0.1", 4000))
        w.write_json("/server/health", 1, {"ok": True})
        w.flush()
        w.close()
        w.close()
    errors = [r for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1
    msg = errors[0].getMessage()
    assert str(path) in msg and "No space left" in msg and f"{on_disk_before_error} messages" in msg
    st = w.stats()
    assert st["dropped"] == (sent - on_disk_before_error) + 101
    assert os.path.getsize(path) == st["bytes"] <= disk.capacity
    expect = [_packet(i) for i in range(on_disk_before_error)]
    with open(path, "rb") as f:  # any MCAP reader, directly
        assert [m.data for _, _, m in make_reader(f).iter_messages()] == expect
    with pytest.warns(RecordingDamagedWarning, match="not closed"):
        r = RecordingReader(path)
        assert [d for _, d in r.packets()] == expect
    assert not r.complete


_CHILD_FSIZE = r"""
import json, resource, signal, struct, sys, time
sys.path.insert(0, sys.argv[2])
from visionpos.recording import RecordingWriter
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG), as on a full disk
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[3]), int(sys.argv[3])))
w = RecordingWriter(sys.argv[1], {"cameras": []}, flush_interval_s=0.01)
i = 0
n_after = 0
while (w.stats()["error"] is None or n_after < 1000) and i < 200_000:
    n_after += w.stats()["error"] is not None
    w.write_packet(i, struct.pack("<I", i) + bytes(i % 50), ("127.0.0.1", 1))
    i += 1
    if i % 50 == 0:
        time.sleep(0.001)  # let the flusher (every 10 ms) write in batches of a few hundred
w.close()
print(json.dumps({"sent": i, **w.stats()}))
"""


def test_file_size_limit_in_a_real_process(tmp_path):
    """The kernel refusing writes (RLIMIT_FSIZE, like a full disk): the writer ends cleanly."""
    import json

    path = tmp_path / "limited.mcap"
    limit = 150_000
    proc = subprocess.run([sys.executable, "-c", _CHILD_FSIZE, str(path), str(ROOT), str(limit)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    with open(path, "rb") as f:
        pk = [m.data for _, _, m in make_reader(f).iter_messages()]
    assert len(pk) > 100
    assert pk == [struct.pack("<I", i) + bytes(i % 50) for i in range(len(pk))]
    st = json.loads(proc.stdout)
    assert st["error"] and st["dropped"] > 0
    assert "recording stopped" in proc.stderr and proc.stderr.count("recording stopped") == 1
    assert os.path.getsize(path) == st["bytes"] <= limit
    assert st["recorded"] == len(pk) and len(pk) + st["dropped"] == st["sent"]


def test_packet_channels_are_bounded(tmp_path):
    """A flood of spoofed source ports: the first MAX_PACKET_SOURCES senders get a channel, the rest share one."""
    n = 1000
    path = tmp_path / "many.mcap"
    with RecordingWriter(path, CONFIG) as w:
        for i in range(n):
            w.write_packet(i, _packet(i), ("10.0.0.9", 10_000 + i))
        for i in range(n):  # the first senders again: still on their own channels
            w.write_packet(n + i, _packet(i % 10), ("10.0.0.9", 10_000 + i % 10))
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    packet_channels = [c for c in summary.channels.values() if c.topic == TOPIC_PACKETS]
    assert len(packet_channels) == MAX_PACKET_SOURCES + 1
    assert summary.statistics.message_count == 2 * n  # nothing refused
    r = RecordingReader(path)
    pk = list(r.packets_with_source())
    assert [d for _, d, _ in pk] == [_packet(i) for i in range(n)] + [_packet(i % 10) for i in range(n)]
    assert [s for _, _, s in pk[:MAX_PACKET_SOURCES]] == [("10.0.0.9", 10_000 + i) for i in range(MAX_PACKET_SOURCES)]
    assert {s for _, _, s in pk[MAX_PACKET_SOURCES:n]} == {None}
    assert [s for _, _, s in pk[n:]] == [("10.0.0.9", 10_000 + i % 10) for i in range(n)]
    end = r.end()
    assert end["packet_sources"] == MAX_PACKET_SOURCES
    assert end["overflow_sources"] == n - MAX_PACKET_SOURCES and end["overflow_packets"] == n - MAX_PACKET_SOURCES
    assert end["messages"] == {TOPIC_PACKETS: 2 * n}


def test_disk_full_at_close_or_at_start(tmp_path, monkeypatch):
    path = tmp_path / "c.mcap"
    disk = _FullDisk(10**9)
    monkeypatch.setattr(writer.os, "pwrite", disk)
    w = RecordingWriter(path, CONFIG, flush_interval_s=60.0)
    for i in range(30):
        w.write_packet(i, _packet(i))
    w.flush()
    disk.capacity = os.path.getsize(path) + 40  # no room for the summary
    w.write_packet(30, _packet(30))
    w.close()  # does not raise
    assert disk.failures == 1 and w.stats()["dropped"] == 1
    with open(path, "rb") as f:
        assert [m.data for _, _, m in make_reader(f).iter_messages()] == [_packet(i) for i in range(30)]
    disk.capacity = 10
    with pytest.raises(RecordingError, match=r"c2\.mcap: cannot write recording: No space left"):
        RecordingWriter(tmp_path / "c2.mcap", CONFIG)


def test_states_recorded_before_update_kind_read_as_none():
    from visionpos.recording import state_from_dict, state_to_dict

    d = state_to_dict(_state(1, np.random.default_rng(2)))
    assert d["update_kind"] == "views"
    del d["update_kind"]  # a recording from before issue 15
    assert state_from_dict(d).update_kind == ""
