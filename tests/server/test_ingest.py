"""Ingest: registration, sync, heartbeats, HMAC, sequence and clock checks, bad packets.

Driven through Ingest.handle() with chosen receive times (no sockets, no sleeps);
the loopback UDP path is covered in test_service.py. `_send` plays a well-behaved
station: it answers the HELLO cookie challenge and numbers control messages; the
attack tests at the end build their packets by hand.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import random
import time

import numpy as np
import pytest

from visionpos import protocol as P
from visionpos.config.arena import ConfigError, load_arena, load_yaml, parse_arena, resolve_config_path
from visionpos.messages import FLAG_RESYNC, BlobFrame
from visionpos.server.ingest import ClockJump, Ingest, IngestEvent
from visionpos.server.settings import ServerSettings, parse_server

ADDR = ("127.0.0.1", 40000)
MS = 1_000_000
T0 = 10_000 * MS  # a receive-time origin far from 0


class Collector:
    """Records what ingest hands the pipeline (ingest's output, not a fusion stand-in)."""

    def __init__(self):
        self.frames: list[BlobFrame] = []
        self.removed: list[int] = []
        self.pauses: list[tuple[int, bool]] = []

    def push(self, frame):
        self.frames.append(frame)

    def remove_camera(self, camera_id):
        self.removed.append(camera_id)

    def pause_view_updates(self, paused):
        self.pauses.append((len(self.frames), paused))  # before which frame
        return paused


class Clock:
    def __init__(self, t):
        self.t = t

    def __call__(self):
        return self.t


def _arena(server: dict | None = None, tmp_path=None):
    data = load_yaml(resolve_config_path("thesis"))
    if server is not None:
        data["server"] = server
    if isinstance(data.get("server"), dict) and "key_file" not in data["server"]:
        data["server"] = {"insecure": True, **data["server"]}  # unsigned test packets, said explicitly
    src = str(tmp_path / "arena.yaml") if tmp_path is not None else str(resolve_config_path("thesis"))
    return parse_arena(data, src)


def _ingest(server=None, tmp_path=None, t=T0):
    clock = Clock(t)
    pipe = Collector()
    ing = Ingest(_arena(server, tmp_path), pipeline=pipe, clock=clock)
    return ing, pipe, clock


def _frame(cam: int, seq: int, capture_ns: int, station: int = None, flags: int = 0, n: int = 3,
           session: int = 7) -> BlobFrame:
    blobs = np.arange(n * 4, dtype=np.float32).reshape(n, 4) + seq
    return BlobFrame(cam, seq, capture_ns, blobs, cam if station is None else station, flags, 0, session)


def _hello(cam, session=7, station=None, w=960, h=640, timebase=P.Timebase.SERVER, counter=0, cookie=P.NO_COOKIE):
    return P.Hello(cam if station is None else station, cam, session, w, h, 100.0, "fisheye", f"pi{cam}", "test",
                   timebase, counter, cookie)


def _send(ing, msg, recv_ns, key=None, addr=ADDR):
    """Send like a station: control messages without a counter get the next one; a HELLO without a
    cookie that is challenged is sent again with the cookie (the replies to that one are returned)."""
    if isinstance(msg, (P.Hello, P.Heartbeat, P.SyncRequest, P.Bye)):
        last = getattr(ing, "_test_counter", 0)
        if msg.counter == 0:
            msg = dataclasses.replace(msg, counter=last + 1)
        ing._test_counter = max(last, msg.counter)
    replies = [P.decode(r, key) for r in ing.handle(P.encode(msg, key), addr, recv_ns)]
    if (isinstance(msg, P.Hello) and msg.cookie == P.NO_COOKIE
            and [r.status for r in replies] == [P.AckStatus.CHALLENGE]):
        return _send(ing, dataclasses.replace(msg, counter=0, cookie=replies[0].cookie), recv_ns, key, addr)
    return replies


def test_registration_and_trigger_time():
    ing, _, clock = _ingest({"start_delay_s": 2.0})
    assert ing.start_ns == T0 + 2_000 * MS
    (ack,) = _send(ing, _hello(1), T0)
    assert isinstance(ack, P.HelloAck)
    assert (ack.status, ack.session, ack.camera_id, ack.start_ns, ack.server_ns) == (P.AckStatus.OK, 7, 1,
                                                                                     T0 + 2000 * MS, T0)
    h = ing.health()["cameras"][1]
    assert h["registered"] and h["station_id"] == 1 and h["addr"] == "127.0.0.1:40000"
    # resolution that does not match the calibration: refused with the reason
    (ack,) = _send(ing, _hello(2, w=640, h=480), T0)
    assert ack.status == P.AckStatus.REJECTED
    assert not ing.health()["cameras"][2]["registered"]


def test_frames_before_trigger_are_dropped():
    ing, pipe, _ = _ingest({"start_delay_s": 1.0})
    _send(ing, _hello(1), T0)
    _send(ing, _frame(1, 0, T0 + 500 * MS), T0 + 503 * MS)
    _send(ing, _frame(1, 1, T0 + 1000 * MS), T0 + 1003 * MS)
    assert [f.seq for f in pipe.frames] == [1]
    assert ing.health()["cameras"][1]["before_start"] == 1


def test_unknown_station_refused_and_logged_once(caplog):
    ing, pipe, _ = _ingest()
    with caplog.at_level(logging.WARNING, logger="visionpos.server.ingest"):
        for i in range(5):
            (ack,) = _send(ing, _hello(9), T0 + i)
            assert ack.status == P.AckStatus.REJECTED
        for i in range(5):
            assert _send(ing, _frame(9, i, T0 + i * 10 * MS), T0 + i * 10 * MS + 3 * MS) == []
        assert _send(ing, P.SyncRequest(9, 9, 123, 1), T0) == []
    assert pipe.frames == []
    h = ing.health()
    assert h["unknown"] == 11 and h["unknown_sources"] == {"9/9": 11}
    lines = [r.getMessage() for r in caplog.records if "camera 9" in r.getMessage()]
    assert len(lines) == 1 and "not in the arena config" in lines[0]


def test_station_id_pinned_in_config():
    data = load_yaml(resolve_config_path("thesis"))
    data["cameras"][0]["station"] = 11
    data["server"]["insecure"] = True
    ing = Ingest(parse_arena(data, "a.yaml"), pipeline=Collector(), clock=Clock(T0))
    (ack,) = _send(ing, _hello(1, station=12), T0)
    assert ack.status == P.AckStatus.REJECTED
    (ack,) = _send(ing, _hello(1, station=11), T0)
    assert ack.status == P.AckStatus.OK


def test_clock_sync_reply_stamps():
    ing, _, clock = _ingest()
    _send(ing, _hello(1), T0)
    clock.t = T0 + 250_000  # the reply is built 0.25 ms after the datagram arrived
    (rep,) = _send(ing, P.SyncRequest(1, 1, t1_ns=-55_555, counter=42, session=7), T0)
    assert isinstance(rep, P.SyncReply)
    assert (rep.t1_ns, rep.t2_ns, rep.t3_ns, rep.echo, rep.session) == (-55_555, T0, T0 + 250_000, 42, 7)


def test_heartbeat_records_station_clock():
    ing, _, _ = _ingest()
    hb = P.Heartbeat(1, 1, 0, session=7, status=P.HeartbeatStatus.CLOCK_SYNCED, frames_captured=500, frames_dropped=2,
                     clock_offset_ns=-1_234_567, clock_uncertainty_ns=40_000, drift_ppb=-15000, temperature_c=51.5)
    (ack,) = _send(ing, hb, T0)
    assert ack.status == P.AckStatus.UNKNOWN_SESSION  # not registered yet: register again
    _send(ing, _hello(1), T0)
    (ack,) = _send(ing, hb, T0 + MS)
    assert ack.status == P.AckStatus.OK and ack.session == 7
    h = ing.health()["cameras"][1]
    assert h["clock_offset_ms"] == pytest.approx(-1.234567)
    assert h["clock_uncertainty_us"] == pytest.approx(40.0)
    assert h["drift_ppb"] == -15000 and h["temperature_c"] == 51.5 and h["station_frames_dropped"] == 2


def test_hmac_wrong_key_and_unsigned_dropped(tmp_path, caplog):
    (tmp_path / "key.bin").write_bytes(b"the right key 0123456789")
    ing, pipe, _ = _ingest({"key_file": "key.bin"}, tmp_path)  # relative to the arena file
    good, bad = b"the right key 0123456789", b"the wrong key 0123456789"
    with caplog.at_level(logging.WARNING, logger="visionpos.server.ingest"):
        assert _send(ing, _hello(1), T0, key=bad) == []
        assert ing.handle(P.encode(_frame(1, 0, T0), bad), ADDR, T0 + 3 * MS) == []
        assert ing.handle(P.encode(_frame(1, 1, T0), None), ADDR, T0 + 3 * MS) == []
    assert pipe.frames == [] and ing.health()["auth_failed"] == 3
    assert any("authentication" in r.getMessage() for r in caplog.records)
    (ack,) = _send(ing, _hello(1), T0, key=good)  # replies are signed with the key
    assert ack.status == P.AckStatus.OK
    with pytest.raises(P.ProtocolError):
        P.decode(ing.handle(P.encode(_hello(1), good), ADDR, T0)[0], bad)
    _send(ing, _frame(1, 2, T0 + 10 * MS), T0 + 13 * MS, key=good)
    assert [f.seq for f in pipe.frames] == [2]


def test_sequence_loss_duplicates_reordering_replay():
    ing, pipe, _ = _ingest()
    _send(ing, _hello(1), T0)
    seqs = [100, 101, 102, 105, 105, 103, 106, 107] + list(range(108, 300)) + [150, 20, 300]
    for i, s in enumerate(seqs):
        t = T0 + i * 10 * MS
        _send(ing, _frame(1, s, t), t + 4 * MS)
    got = [f.seq for f in pipe.frames]
    assert got == [100, 101, 102, 105, 106, 107] + list(range(108, 301))
    h = ing.health()["cameras"][1]
    assert h["duplicates"] == 1
    assert h["reordered"] == 1  # 103 came late: dropped
    assert h["lost"] == 2  # 103 and 104 were never accepted (loss counts what was accepted)
    assert h["replayed"] == 2  # 150 and 20 are far older than 299
    assert h["frames"] == len(got)
    assert all(f.recv_ns == T0 + i * 10 * MS + 4 * MS for i, f in zip(range(3), pipe.frames))
    # sequence wraps at 2^32 without counting a loss
    _send(ing, _hello(2), T0)
    for i, s in enumerate([2**32 - 2, 2**32 - 1, 0, 1]):
        t = T0 + i * 10 * MS
        _send(ing, _frame(2, s, t), t + 4 * MS)
    assert ing.health()["cameras"][2]["lost"] == 0 and ing.health()["cameras"][2]["frames"] == 4


def test_replayed_frames_inside_the_reorder_window_do_not_hide_loss():
    # an attacker resends frames it saw, a few seqs old: refused as reordered, and `lost` does not move
    ing, pipe, _ = _ingest()
    _send(ing, _hello(1), T0)
    sent = {}
    for i, s in enumerate([10, 11, 12, 20]):  # 13..19 lost on the network: 7 frames
        t = T0 + i * 10 * MS
        sent[s] = P.encode(_frame(1, s, t))
        ing.handle(sent[s], ADDR, t + 4 * MS)
    assert ing.health()["cameras"][1]["lost"] == 7
    for k, s in enumerate([10, 11, 12, 12, 11, 10] * 3):  # inside the 64-frame window
        ing.handle(sent[s], ADDR, T0 + 40 * MS + k * MS)
    h = ing.health()["cameras"][1]
    assert h["reordered"] + h["duplicates"] == 18 and h["lost"] == 7
    # real loss after the replays is still counted: 21 accepted, 22..24 lost
    for i, s in enumerate([21, 25]):
        t = T0 + 100 * MS + i * 10 * MS
        ing.handle(P.encode(_frame(1, s, t)), ADDR, t + 4 * MS)
    h = ing.health()["cameras"][1]
    assert h["lost"] == 10 and h["frames"] == 6 and [f.seq for f in pipe.frames] == [10, 11, 12, 20, 21, 25]
    assert h["loss"] == pytest.approx(10 / 16)


def test_new_session_restarts_sequence():
    ing, pipe, _ = _ingest()
    _send(ing, _hello(1, session=1), T0)
    _send(ing, _frame(1, 500, T0, session=1), T0 + 3 * MS)
    _send(ing, _hello(1, session=2), T0 + 5 * MS)  # station restarted: seq starts over
    _send(ing, _frame(1, 0, T0 + 10 * MS, session=2), T0 + 13 * MS)
    _send(ing, _frame(1, 501, T0 + 20 * MS, session=1), T0 + 23 * MS)  # the old session's frames: refused
    assert [f.seq for f in pipe.frames] == [500, 0]
    assert ing.health()["cameras"][1]["wrong_session"] == 1


def test_frames_that_queued_too_long_are_shed_not_fused():
    """Load shedding: a frame that waited in the server's receive queue longer than
    shed_backlog_ms is checked and counted, not fused; fresh frames are fused. A station's
    own steady latency (here 45 ms, longer than the shedding threshold) never sheds."""
    ing, pipe, clock = _ingest({"shed_backlog_ms": 30})
    _send(ing, _hello(1), T0)
    for seq, backlog_ms in enumerate([0, 2, 55, 31, 29, 0], start=1):
        t = T0 + 100 * MS + seq * 10 * MS  # captures after the trigger time
        clock.t = t
        frame = P.encode(_frame(1, seq, t - 45 * MS), None)
        ing.handle(frame, ADDR, t, backlog_ms * MS)
    assert [f.seq for f in pipe.frames] == [1, 2, 5, 6]
    h = ing.health()
    assert h["frames_shed"] == 2 and h["cameras"][1]["shed"] == 2 and h["frames_accepted"] == 6
    assert h["cameras"][1]["clock_jumps"] == 0
    off, off_pipe, _ = _ingest({"shed_backlog_ms": 0})  # 0 = off
    _send(off, _hello(1), T0)
    off.handle(P.encode(_frame(1, 1, T0 + 5 * MS), None), ADDR, T0 + 10 * MS, 10_000 * MS)
    assert len(off_pipe.frames) == 1


def test_a_queue_behind_pauses_the_view_updates_until_it_drains():
    """Load relief (server/load.py): a frame that waited over pause_views_backlog_ms pauses the per-frame view
    updates; frames are still fused; they resume once a frame waits under a fifth of it (2 ms of 10), not
    before; counted in frames_without_view_updates. 0 = off."""
    ing, pipe, clock = _ingest({"pause_views_backlog_ms": 10, "shed_backlog_ms": 30})
    _send(ing, _hello(1), T0)
    waits_ms = [0, 3, 12, 25, 5, 2.5, 1.5, 0, 11]
    for seq, backlog_ms in enumerate(waits_ms, start=1):
        t = T0 + 100 * MS + seq * 10 * MS
        clock.t = t
        ing.handle(P.encode(_frame(1, seq, t - 4 * MS), None), ADDR, t, int(backlog_ms * MS))
    assert [f.seq for f in pipe.frames] == list(range(1, 10))  # every frame fused
    # paused before frame 3 (12 ms), resumed before frame 7 (1.5 ms < 2), paused again before frame 9
    assert pipe.pauses == [(2, True), (6, False), (8, True)]
    assert ing.health()["frames_without_view_updates"] == 5  # frames 3, 4, 5, 6 and 9
    off, off_pipe, _ = _ingest({"pause_views_backlog_ms": 0})
    _send(off, _hello(1), T0)
    off.handle(P.encode(_frame(1, 1, T0 + 5 * MS), None), ADDR, T0 + 10 * MS, 14 * MS)
    assert off_pipe.pauses == [] and off.health()["frames_without_view_updates"] == 0


def test_clock_jumps_dropped_then_resync():
    ing, pipe, clock = _ingest({"resync_after": 5, "max_future_ms": 20, "max_age_ms": 300})
    _send(ing, _hello(1), T0)
    t = T0
    seq = 0

    def send(capture_offset_ms, flags=0):
        nonlocal t, seq
        t += 10 * MS
        seq += 1
        clock.t = t
        return _send(ing, _frame(1, seq, t - 3 * MS + capture_offset_ms * MS, flags=flags), t)

    send(0)
    send(0)
    assert len(pipe.frames) == 2
    assert send(+500) == []  # capture 0.5 s in the future
    assert send(-900) == []  # capture 0.9 s old: clock stepped back (or a delayed replay)
    send(0)
    assert send(-15) == []  # 15 ms earlier than the previous frame: time going backwards
    send(0)
    h = ing.health()["cameras"][1]
    assert (h["clock_jumps_future"], h["clock_jumps_stale"], h["clock_jumps_backwards"]) == (1, 1, 1)
    assert len(pipe.frames) == 4
    # a station whose clock stays 2 s off: frames dropped (never answered), then the server asks it to
    # resync in the answer to its next heartbeat
    assert [send(+2000) for _ in range(5)] == [[]] * 5
    h = ing.health()["cameras"][1]
    assert h["resync_requests"] == 1 and h["registered"]
    assert len(pipe.frames) == 4
    (ack,) = _send(ing, P.Heartbeat(1, 1, 0, session=7), t)
    assert ack.status == P.AckStatus.RESYNC and ack.session == 7
    (ack,) = _send(ing, P.Heartbeat(1, 1, 0, session=7), t)
    assert ack.status == P.AckStatus.OK  # asked once
    # the station resyncs; one that flags its own resync may step back a little
    assert send(0) == []
    assert send(-8, flags=FLAG_RESYNC) == []
    assert len(pipe.frames) == 6 and pipe.frames[-1].flags & FLAG_RESYNC


def test_realtime_timebase_converted():
    ing, pipe, _ = _ingest()
    _send(ing, _hello(1, timebase=P.Timebase.REALTIME), T0)
    mono, real = time.monotonic_ns(), time.time_ns()
    ing.handle(P.encode(_frame(1, 0, real - 4 * MS)), ADDR, mono)
    (f,) = pipe.frames
    assert abs((mono - f.capture_ns) - 4 * MS) < 2 * MS  # only the two clock reads apart
    assert f.recv_ns == mono
    # replay: the offset comes from the recording, not from today's clocks
    ing.realtime_minus_monotonic_ns = 1_700_000_000 * 10**9
    _send(ing, _hello(1, session=8, timebase=P.Timebase.REALTIME), T0)  # a new run on another clock
    ing.handle(P.encode(_frame(1, 1, 1_700_000_000 * 10**9 + T0 + 20 * MS, session=8)), ADDR, T0 + 25 * MS)
    assert pipe.frames[-1].capture_ns == T0 + 20 * MS


def test_vanish_and_return_and_bye():
    ing, pipe, clock = _ingest({"vanish_periods": 10, "vanish_min_s": 0.0})
    for cam in (1, 2):
        _send(ing, _hello(cam), T0)
    for i in range(20):
        t = T0 + i * 10 * MS
        for cam in (1, 2):
            _send(ing, _frame(cam, i, t), t + 3 * MS)
    last = T0 + 19 * 10 * MS + 3 * MS
    assert ing.check_vanished(last + 99 * MS) == []  # 10 periods of 100 Hz = 100 ms
    for i in range(20, 40):  # camera 2 goes on, camera 1 is silent
        t = T0 + i * 10 * MS
        _send(ing, _frame(2, i, t), t + 3 * MS)
        ing.check_vanished(t + 3 * MS)
    assert pipe.removed == [1]
    h = ing.health()["cameras"]
    assert not h[1]["online"] and h[1]["vanished"] == 1 and h[2]["online"]
    t = T0 + 41 * 10 * MS
    _send(ing, _frame(1, 41, t), t + 3 * MS)  # back, with a gap in seq
    assert ing.health()["cameras"][1]["online"] and ing.health()["cameras"][1]["lost"] == 21
    _send(ing, P.Bye(2, 2, 7), t + 5 * MS)
    assert pipe.removed == [1, 2]
    assert not ing.health()["cameras"][2]["registered"]


def test_garbage_and_truncated_packets_never_raise():
    ing, pipe, _ = _ingest()
    rng = random.Random(5)
    _send(ing, _hello(1), T0)
    valid = [P.encode(_hello(1)), P.encode(_frame(1, 1, T0, n=5)), P.encode(P.SyncRequest(1, 1, 5, 1, 7)),
             P.encode(P.Heartbeat(1, 1, 1, session=7)), P.encode(P.HelloAck(1, 1, 7, 0, 0)),
             P.encode(_frame(2, 1, T0, n=0), b"k")]
    n_bad = 0
    for v in valid:
        for cut in range(len(v)):  # every truncation
            assert ing.handle(v[:cut], ADDR, T0 + 3 * MS) == []
            n_bad += 1
    for _ in range(2000):  # random bytes, and valid packets with random bytes flipped
        if rng.random() < 0.5:
            data = bytes(rng.getrandbits(8) for _ in range(rng.randrange(0, 1600)))
        else:
            data = bytearray(rng.choice(valid))
            for _ in range(rng.randrange(1, 4)):
                data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
            data = bytes(data)
        ing.handle(data, ADDR, T0 + 3 * MS)
    h = ing.health()
    assert h["malformed"] >= n_bad
    assert h["packets"] == n_bad + 2000 + 2
    # every frame that got through decoded to exactly what a valid frame carries
    for f in pipe.frames:
        assert f.blobs.shape[1] == 4
    # the server still works afterwards
    _send(ing, _hello(3), T0)
    _send(ing, _frame(3, 1, T0 + 10 * MS), T0 + 13 * MS)
    assert pipe.frames[-1].camera_id == 3 and pipe.frames[-1].seq == 1


def test_malformed_logged_rate_limited_per_reason_with_a_count(caplog):
    ing, _, _ = _ingest()
    now = [100.0]
    ing.rlog.clock = lambda: now[0]
    with caplog.at_level(logging.WARNING, logger="visionpos.server.ingest"):
        for i in range(50):
            ing.handle(b"GET / HTTP/1.1\r\n\r\n", ("10.0.0.1", 1000 + i), T0)  # 50 senders, one reason
        now[0] += 11.0
        ing.handle(b"GET / HTTP/1.1\r\n\r\n", ADDR, T0)
    msgs = [r.getMessage() for r in caplog.records]
    assert len(msgs) == 2 and all("bad magic" in m for m in msgs) and "10.0.0.1:1000" in msgs[0]
    assert "127.0.0.1:40000" in msgs[1] and "49 more like this" in msgs[1]
    assert ing.health()["malformed_reasons"] == {"bad magic": 51}


class Rec:
    def __init__(self):
        self.got = []

    def write_packet(self, recv_ns, data, source=None):
        self.got.append((recv_ns, data, source))


def test_recorder_gets_only_accepted_packets():
    """Nothing undecodable, unauthenticated, of an unknown camera or refused is recorded; it is counted."""
    rec = Rec()
    ing = Ingest(_arena(), pipeline=None, recorder=rec, clock=Clock(T0))
    src = ("10.0.0.5", 5000)
    challenge = ing.handle(P.encode(_hello(1)), src, T0)  # no cookie: challenged, not recorded
    (ack,) = [P.decode(r) for r in challenge]
    hello = P.encode(_hello(1, counter=1, cookie=ack.cookie))
    good_frame = P.encode(_frame(1, 1, T0 + MS))
    pkts = [hello, b"junk" * 100, P.encode(_frame(9, 1, T0)), P.encode(_frame(1, 1, T0, session=8)),
            good_frame, P.encode(_frame(1, 1, T0 + MS)), P.encode(_frame(2, 1, T0 + MS))]
    for p in pkts:
        ing.handle(p, src, T0 + 3 * MS)
    assert rec.got == [(T0 + 3 * MS, hello, src), (T0 + 3 * MS, good_frame, src)]
    assert ing.health()["not_recorded"] == {"no valid cookie": 1, "undecodable": 1, "unknown camera": 1,
                                            "wrong session": 1, "duplicate seq": 1, "not registered": 1}


@pytest.mark.parametrize("server, key, what", [
    ({"port": "abc"}, "server.port", "expected an integer"),
    ({"port": 70000}, "server.port", "<= 65535"),
    ({"output_rate_hz": 0}, "server.output_rate_hz", ">= 1"),
    ({"outptu_rate_hz": 50}, "server.outptu_rate_hz", "unknown key"),
    ({"key_file": "missing.key"}, "server.key_file", "cannot read"),
    ([1, 2], "server", "expected a mapping"),
])
def test_config_errors_name_the_key(server, key, what, tmp_path):
    with pytest.raises(ConfigError) as ei:
        parse_server(_arena(server, tmp_path))
    assert ei.value.key == key and what in str(ei.value) and "arena.yaml" in str(ei.value)


def test_empty_key_file_refused(tmp_path):
    (tmp_path / "k").write_bytes(b"")
    with pytest.raises(ConfigError, match="server.key_file.*empty"):
        parse_server(_arena({"key_file": "k"}, tmp_path))


def test_builtin_config_defaults():
    s = ServerSettings.for_replay(load_arena("thesis"))
    assert s.port == P.DEFAULT_PORT and s.output_rate_hz == 100.0 and s.key is None and s.bind == "127.0.0.1"


def test_station_vanishes_mid_flight_tracking_continues():
    """Deterministic: simulated stations' packets through handle() on the simulation's clock,
    the real FusionPipeline, 100 Hz ticks; camera 2 stops sending half-way."""
    sim = pytest.importorskip("visionpos.sim")
    from visionpos.fusion.pipeline import FusionPipeline

    sc = sim.load_scenario("thesis", ["sim.duration=2.5", "server.insecure=true"])
    frames = sim.simulate(sc).frames_by_recv()
    cut = sc.start_ns + 1_200 * MS
    arena = sc.arena
    pipe = FusionPipeline(arena, arena.raw.get("fusion"))
    clock = Clock(frames[0].recv_ns)
    ing = Ingest(arena, pipeline=pipe, clock=clock)
    ing.set_start(sc.start_ns)
    for cam in arena.cameras:
        _send(ing, _hello(cam.id, station=cam.id), frames[0].recv_ns, addr=("127.0.0.1", 6000 + cam.id))
    states, lost_at = [], None
    tick = frames[0].recv_ns
    for f in frames:
        while tick <= f.recv_ns:
            clock.t = tick
            if ing.check_vanished(tick) == [2]:
                lost_at = tick
            states += pipe.tick(tick)
            tick += 10 * MS
        if f.camera_id == 2 and f.capture_ns >= cut:
            continue
        clock.t = f.recv_ns
        f = dataclasses.replace(f, station_id=f.camera_id, session=7)
        ing.handle(P.encode_frame(f), ("127.0.0.1", 6000 + f.camera_id), f.recv_ns)
    h = ing.health()
    assert h["frames_accepted"] == len([f for f in frames if not (f.camera_id == 2 and f.capture_ns >= cut)])
    # lost after its vanish timeout (10 frame periods = 100 ms), not before, and only camera 2
    assert lost_at is not None and cut + 100 * MS <= lost_at <= cut + 130 * MS
    assert [c for c, v in h["cameras"].items() if v["vanished"]] == [2]
    assert pipe.stats()["removed_camera"] == 1
    after = [s for s in states if s.time_ns > lost_at + 50 * MS]
    assert len(after) > 50 and all(s.tracked and s.n_cameras == 3 for s in after)
    truth, _ = sc.truth_at("quad", np.array([s.time_ns for s in after], dtype=np.int64))
    err = np.linalg.norm(np.array([s.position for s in after]) - truth, axis=1)
    assert np.median(err) < 0.002 and err.max() < 0.005  # 3 cameras still give millimetres


def test_clock_jump_kinds_are_the_logged_words_and_health_counters(caplog):
    ing, _, clock = _ingest({"max_future_ms": 20, "max_age_ms": 300})
    _send(ing, _hello(1), T0)
    counters = {ClockJump.FUTURE: "clock_jumps_future", ClockJump.STALE: "clock_jumps_stale",
                ClockJump.BACKWARDS: "clock_jumps_backwards"}
    with caplog.at_level(logging.WARNING, logger="visionpos.server.ingest"):
        t = T0 + 10 * MS
        _send(ing, _frame(1, 1, t - 3 * MS), t)
        for seq, (kind, offset_ms) in enumerate([(ClockJump.FUTURE, +500), (ClockJump.STALE, -900),
                                                 (ClockJump.BACKWARDS, -40)], start=2):
            t += 10 * MS
            clock.t = t
            assert _send(ing, _frame(1, seq, t - 3 * MS + offset_ms * MS), t) == []
            assert f"clock jump ({kind.value})" in caplog.records[-1].getMessage()
            assert ing.health()["cameras"][1][counters[kind]] == 1
    assert [k.value for k in ClockJump] == ["in the future", "too old", "going backwards"]


def test_far_ahead_frame_log_says_what_was_refused_and_later_frames_are_fused(caplog):
    # one signed frame far in the future (an attacker's, or one bad clock read): it alone is refused, and
    # the log says so with a count; the station's genuine frames after it are accepted, and the log says that
    ing, pipe, clock = _ingest({"max_future_ms": 20, "max_age_ms": 300})
    _send(ing, _hello(1), T0)
    with caplog.at_level(logging.INFO, logger="visionpos.server.ingest"):
        t = T0 + 10 * MS
        _send(ing, _frame(1, 1, t - 3 * MS), t)
        t += 10 * MS
        assert _send(ing, _frame(1, 2, t + 3_600_000 * MS), t) == []
        warned = caplog.records[-1].getMessage()
        for k in range(3, 6):
            t += 10 * MS
            _send(ing, _frame(1, k, t - 3 * MS), t)
    assert [f.seq for f in pipe.frames] == [1, 3, 4, 5]
    assert "frame refused (1 refused since its last accepted frame, 1 since start" in warned
    assert "until" not in warned and "dropping its frames" not in warned
    assert any("frames accepted again after 1 refused for a clock jump" in r.getMessage() for r in caplog.records)


def test_event_kinds_are_the_recorded_strings():
    recorded = []  # what the service writes on /server/events: JSON with "kind"
    clock = Clock(T0)
    ing = Ingest(_arena({"vanish_periods": 10, "vanish_min_s": 0.0, "resync_after": 2}), pipeline=Collector(),
                 clock=clock, events=lambda kind, info: recorded.append(json.loads(json.dumps({"kind": kind}))["kind"]))
    _send(ing, _hello(1), T0)
    _send(ing, _frame(1, 1, T0), T0 + 3 * MS)
    ing.check_vanished(T0 + 500 * MS)
    _send(ing, _frame(1, 2, T0 + 600 * MS), T0 + 603 * MS)
    for seq in (3, 4):
        _send(ing, _frame(1, seq, T0 + 5000 * MS), T0 + 610 * MS)  # 4.4 s in the future, twice: resync
    assert recorded == ["registered", "camera_lost", "camera_back", "resync_request"]
    assert [e.value for e in IngestEvent] == recorded


# ---------------------------------------------------------------- attacks of issue 14 (each passed on v1's ingest)


def _streaming(ing, pipe, cam=1, n=3, t0=T0):
    """Register camera `cam` and accept n frames; returns the time of the last one."""
    _send(ing, _hello(cam), t0)
    t = t0
    for seq in range(n):
        t = t0 + (seq + 1) * 10 * MS
        _send(ing, _frame(cam, seq, t - 3 * MS), t)
    return t


def test_a_refused_frame_with_a_far_ahead_seq_does_not_blind_the_camera():
    """v1 stored the seq before checking the time: one forged or replayed frame blinded a camera."""
    ing, pipe, _ = _ingest()
    t = _streaming(ing, pipe)
    before = ing.health()["cameras"][1]
    _send(ing, _frame(1, 1_000_000, t - 10**12), t + MS)  # seq far ahead, capture 1000 s old
    _send(ing, _frame(1, 2_000_000, t + 10**12), t + MS)  # ... and 1000 s in the future
    after = ing.health()["cameras"][1]
    changed = {k for k in before if before[k] != after[k]}
    assert changed <= {"clock_jumps", "clock_jumps_stale", "clock_jumps_future", "last_drop_reason",
                       "last_seen_s_ago"}, changed
    assert after["last_seen_s_ago"] == before["last_seen_s_ago"]  # refused: not "seen"
    _send(ing, _frame(1, 3, t + 7 * MS), t + 10 * MS)  # the genuine next frame
    assert [f.seq for f in pipe.frames] == [0, 1, 2, 3]
    assert ing.health()["cameras"][1]["lost"] == 0


def test_frames_of_a_camera_that_never_registered_are_not_fused_and_not_answered():
    ing, pipe, _ = _ingest()
    for seq in range(3):
        assert ing.handle(P.encode(_frame(2, seq, T0 + seq * MS)), ADDR, T0 + seq * MS + 3 * MS) == []
    assert pipe.frames == []
    cam = ing.health()["cameras"][2]
    assert cam["unregistered"] == 3 and cam["frames"] == 0 and not cam["registered"]


def test_frames_only_from_the_registered_session_and_address():
    ing, pipe, _ = _ingest()
    t = _streaming(ing, pipe)
    forger = ("127.0.0.1", 40666)
    assert ing.handle(P.encode(_frame(1, 3, t + 2 * MS)), forger, t + 5 * MS) == []  # right session, wrong address
    assert ing.handle(P.encode(_frame(1, 3, t + 2 * MS, session=8)), ADDR, t + 5 * MS) == []  # wrong session
    assert ing.handle(P.encode(_frame(1, 3, t + 2 * MS, station=9)), ADDR, t + 5 * MS) == []  # other station
    assert [f.seq for f in pipe.frames] == [0, 1, 2]
    cam = ing.health()["cameras"][1]
    assert (cam["wrong_address"], cam["wrong_session"]) == (1, 2)
    _send(ing, _frame(1, 3, t + 7 * MS), t + 10 * MS)
    assert [f.seq for f in pipe.frames] == [0, 1, 2, 3]


def test_hello_needs_the_cookie_of_its_own_address_and_time():
    ing, pipe, _ = _ingest()
    (ch,) = [P.decode(r) for r in ing.handle(P.encode(_hello(1, counter=1)), ADDR, T0)]
    assert ch.status == P.AckStatus.CHALLENGE and ch.echo == 1 and ch.cookie != P.NO_COOKIE
    assert not ing.health()["cameras"][1]["registered"]  # a challenge changes no state
    wrong_addr = ing.handle(P.encode(_hello(1, counter=2, cookie=ch.cookie)), ("127.0.0.1", 40001), T0)
    assert P.decode(wrong_addr[0]).status == P.AckStatus.CHALLENGE  # the cookie was for another source port
    late = ing.handle(P.encode(_hello(1, counter=2, cookie=ch.cookie)), ADDR, T0 + 20_001 * MS)
    assert P.decode(late[0]).status == P.AckStatus.CHALLENGE  # two 10 s buckets later: expired
    assert not ing.health()["cameras"][1]["registered"]
    ok = ing.handle(P.encode(_hello(1, counter=2, cookie=ch.cookie)), ADDR, T0 + 9_000 * MS)
    assert P.decode(ok[0]).status == P.AckStatus.OK and ing.health()["cameras"][1]["registered"]


def test_replayed_signed_hello_and_heartbeat_change_nothing(tmp_path):
    """v1: an old signed HELLO replayed once a second re-registered the station each time."""
    key = b"the right key 0123456789"
    (tmp_path / "key.bin").write_bytes(key)
    ing, pipe, _ = _ingest({"key_file": "key.bin"}, tmp_path)
    (ch,) = [P.decode(r, key) for r in ing.handle(P.encode(_hello(1, session=1, counter=1), key), ADDR, T0)]
    old_hello = P.encode(_hello(1, session=1, counter=2, cookie=ch.cookie), key)  # what an attacker captures
    assert P.decode(ing.handle(old_hello, ADDR, T0)[0], key).status == P.AckStatus.OK
    hb = P.encode(P.Heartbeat(1, 1, 3, session=1, clock_offset_ns=5), key)
    assert P.decode(ing.handle(hb, ADDR, T0 + MS)[0], key).status == P.AckStatus.OK
    # replays of the current session: stale counters, no answer, no state change
    assert ing.handle(old_hello, ADDR, T0 + 2 * MS) == []
    assert ing.handle(hb, ADDR, T0 + 2 * MS) == []
    assert ing.health()["cameras"][1]["stale_control"] == 2
    # the station restarts (session 2); the old session's HELLO, replayed with its still-valid cookie, is refused
    _send(ing, _hello(1, session=2, counter=1), T0 + 3 * MS, key=key)
    _send(ing, _frame(1, 0, T0 + 4 * MS, session=2), T0 + 6 * MS, key=key)
    assert ing.handle(old_hello, ADDR, T0 + 7 * MS) == []
    cam = ing.health()["cameras"][1]
    assert cam["registered"] and ing.cameras[1].session == 2
    _send(ing, _frame(1, 1, T0 + 8 * MS, session=2), T0 + 10 * MS, key=key)
    assert [f.seq for f in pipe.frames] == [0, 1]  # the sequence state was not reset by the replay
    # a replayed BYE of the old session does not unregister the new one
    assert ing.handle(P.encode(P.Bye(1, 1, 1, 99), key), ADDR, T0 + 11 * MS) == []
    assert ing.health()["cameras"][1]["registered"]


def test_resync_is_asked_in_the_next_heartbeat_reply_never_in_answer_to_frames():
    ing, pipe, clock = _ingest({"resync_after": 3})
    t = _streaming(ing, pipe)
    replies = [ing.handle(P.encode(_frame(1, seq, t + 5_000 * MS)), ADDR, t + seq * MS) for seq in range(3, 9)]
    assert replies == [[]] * 6
    assert ing.health()["cameras"][1]["resync_requests"] == 1  # once pending, not asked again per frame
    (ack,) = _send(ing, P.Heartbeat(1, 1, 0, session=7), t + 10 * MS)
    assert ack.status == P.AckStatus.RESYNC
    assert ing.health()["cameras"][1]["registered"]  # the station keeps its registration and seq


def test_a_camera_whose_frames_are_dropped_shows_dropping_with_the_reason_never_gone():
    ing, pipe, clock = _ingest({"vanish_periods": 10, "vanish_min_s": 0.0, "max_age_ms": 300})
    t = _streaming(ing, pipe, cam=2)
    for k in range(1, 40):  # the station streams on, its clock 2 s behind: every frame refused
        now = t + k * 10 * MS
        clock.t = now
        ing.handle(P.encode(_frame(2, 2 + k, now - 2_000 * MS)), ADDR, now)
        ing.check_vanished(now)
    h = ing.health(clock.t)["cameras"][2]
    assert not h["online"] and h["state"] == "dropping" and h["dropping"] == "clock jump: too old"
    assert "2:dropping(clock jump: too old)" in ing.status_line(clock.t)
    assert "2:gone" not in ing.status_line(clock.t)
    # a station that stops altogether is gone once its last frame is older than the vanish timeout
    assert "2:gone" in ing.status_line(clock.t + 200 * MS)
    # frames of another session: the reason says so
    ing.handle(P.encode(_frame(2, 50, clock.t, session=99)), ADDR, clock.t + 3 * MS)
    assert "2:dropping(wrong session)" in ing.status_line(clock.t + 3 * MS)


def test_per_sender_tables_and_logs_are_bounded(caplog):
    ing, _, _ = _ingest()
    with caplog.at_level(logging.WARNING, logger="visionpos.server.ingest"):
        for i in range(1000):  # 1000 made-up station/camera pairs
            ing.handle(P.encode(_frame(100 + i, 1, T0)), ("10.9.0.1", 1000 + i), T0)
    h = ing.health()
    assert len(h["unknown_sources"]) == 64 and h["unknown_sources_evicted"] == 1000 - 64
    assert h["unknown"] == 1000
    assert "1099/1099" in h["unknown_sources"] and "100/100" not in h["unknown_sources"]  # the newest kept
    assert len([r for r in caplog.records if "not in the arena config" in r.getMessage()]) == 1
    assert len(ing.rlog) <= 2


def test_taps_get_the_accepted_packets_only_and_a_failing_tap_changes_nothing():
    """Live outputs' taps see each accepted packet (hello and frames), never a refused one; a tap that
    raises is counted, and the frame is still fused."""
    seen: list[tuple[int, bytes]] = []

    def broken(recv_ns, data):
        raise RuntimeError("output bug")

    pipe = Collector()
    ing = Ingest(_arena({"start_delay_s": 0.0}), pipeline=pipe, clock=Clock(T0),
                 taps=[lambda t, d: seen.append((t, d)), broken])
    _send(ing, _hello(1), T0)
    good = P.encode_frame(_frame(1, 1, T0 + 10 * MS))
    ing.handle(good, ADDR, T0 + 12 * MS)
    ing.handle(P.encode_frame(_frame(1, 2, T0 + 9 * MS)), ADDR, T0 + 13 * MS)  # older than seq 1: refused
    ing.handle(P.encode_frame(_frame(3, 1, T0 + 10 * MS)), ADDR, T0 + 14 * MS)  # camera 3 not registered
    assert [f.seq for f in pipe.frames] == [1]
    types = [d[5] for _, d in seen]
    assert types == [P.MsgType.HELLO, P.MsgType.FRAME] and seen[-1] == (T0 + 12 * MS, good)
    assert ing.health()["tap_errors"] == 2  # the hello and the frame


def test_the_docs_say_when_the_view_updates_pause():
    from pathlib import Path

    from visionpos.server.load import RESUME_FRACTION
    from visionpos.server.settings import SERVER

    doc = " ".join((Path(__file__).resolve().parents[2] / "docs" / "architecture.md").read_text().split())
    pause = SERVER["pause_views_backlog_ms"].field_default
    assert (f"a frame that queued longer than `pause_views_backlog_ms` ({pause:g}) pauses the per-frame "
            "single-view updates of triangulated bodies until a frame queues less than a fifth of it") in doc
    assert RESUME_FRACTION == 1 / 5
    assert "`frames_without_view_updates`" in doc and "frames_without_view_updates" in _ingest()[0].health()
