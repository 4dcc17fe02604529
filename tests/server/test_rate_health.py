"""Per-camera frame-rate health (issue 15): a station that delivers fewer frames than configured is
reported in health() (structured), in the status line and in the log, once."""

from __future__ import annotations

import logging

from visionpos.server.ingest import LOW_RATE_AFTER_S, Ingest

from .test_ingest import MS, T0, Clock, Collector, _arena, _frame, _hello, _send


def _stream(ing, cam, fps, t_start, seconds, seq0=0, check_vanished=False):
    """Frames of `cam` at `fps` for `seconds` (capture 3 ms before receive); returns (next seq, end time)."""
    period = int(1e9 / fps)
    n = int(seconds * fps)
    t = t_start
    for k in range(n):
        t = t_start + k * period
        _send(ing, _frame(cam, seq0 + k, t - 3 * MS), t)
        if check_vanished:
            assert ing.check_vanished(t + period - MS) == []  # just before its next frame
    return seq0 + n, t


def test_station_delivering_fewer_frames_than_configured_is_reported_once(caplog):
    ing = Ingest(_arena(), pipeline=Collector(), clock=Clock(T0))
    _send(ing, _hello(2), T0)  # announces 100 fps, as configured
    with caplog.at_level(logging.INFO, logger="visionpos.server.ingest"):
        seq, t = _stream(ing, 2, 15.0, T0 + 10 * MS, LOW_RATE_AFTER_S - 1.2)
        cam = ing.health(t)["cameras"][2]
        assert cam["warnings"] == [] and not cam["low_frame_rate"]  # not yet: a second or two may be a hiccup
        seq, t = _stream(ing, 2, 15.0, t + 66 * MS, 4.0, seq)
        cam = ing.health(t)["cameras"][2]
        assert cam["low_frame_rate"] and cam["fps_configured"] == 100.0 and 13.0 < cam["fps"] < 17.0
        (w,) = cam["warnings"]
        assert w["kind"] == "low_frame_rate" and w["configured_fps"] == 100.0 and 13.0 < w["measured_fps"] < 17.0
        for words in ("camera 2", "pi2", "15 fps", "cameras[1].fps", "100", "lower", "load"):
            assert words in w["message"], words
        assert "2:15fps(LOW, configured 100)" in ing.status_line(t)
        warned = [r for r in caplog.records if r.levelno == logging.WARNING and "delivers" in r.getMessage()]
        assert len(warned) == 1 and warned[0].getMessage() == w["message"]
        # back at the configured rate: the warning goes, and the log says so
        seq, t = _stream(ing, 2, 100.0, t + 66 * MS, 2.5, seq)
        cam = ing.health(t)["cameras"][2]
        assert cam["warnings"] == [] and not cam["low_frame_rate"] and "LOW" not in ing.status_line(t)
        assert any("delivers 100 fps again" in r.getMessage() for r in caplog.records)
    assert len([r for r in caplog.records if r.levelno == logging.WARNING and "delivers" in r.getMessage()]) == 1


def test_slow_station_is_not_taken_for_a_vanished_one():
    # announced 100 fps (vanish after 10 periods = 100 ms), delivering 8 fps (125 ms apart): once its
    # rate is measured, its silence between frames is its frame interval, not a lost camera
    pipe = Collector()
    ing = Ingest(_arena(), pipeline=pipe, clock=Clock(T0))
    _send(ing, _hello(1), T0)
    seq, t = _stream(ing, 1, 8.0, T0 + 10 * MS, 2.0)
    seq, t = _stream(ing, 1, 8.0, t + 125 * MS, 3.0, seq, check_vanished=True)
    assert pipe.removed == [] and ing.health(t)["cameras"][1]["vanished"] == 0


def test_rate_after_an_outage_is_measured_only_while_the_camera_streams(caplog):
    # a camera at its configured 100 fps, off for 10 s (a reboot), back at 100 fps: no low-rate warning,
    # and the rate it reports after the reboot is its streaming rate, not frames / (a span with the outage)
    ing = Ingest(_arena(), pipeline=Collector(), clock=Clock(T0))
    _send(ing, _hello(1), T0)
    with caplog.at_level(logging.WARNING, logger="visionpos.server.ingest"):
        seq, t = _stream(ing, 1, 100.0, T0 + 10 * MS, 1.5)
        ing.check_vanished(t + 10_000 * MS)  # the outage: the camera is lost
        seq, t = _stream(ing, 1, 100.0, t + 10_000 * MS, 1.5, seq)
        cam = ing.health(t)["cameras"][1]
    assert 95.0 < cam["fps"] < 105.0 and not cam["low_frame_rate"] and cam["warnings"] == []
    assert not [r for r in caplog.records if "delivers" in r.getMessage()]


def test_outage_without_a_vanish_check_is_no_rate_either(caplog):
    # a replay or a stalled server may not run check_vanished during the gap: the gap itself restarts it
    ing = Ingest(_arena(), pipeline=Collector(), clock=Clock(T0))
    _send(ing, _hello(1), T0)
    with caplog.at_level(logging.WARNING, logger="visionpos.server.ingest"):
        seq, t = _stream(ing, 1, 100.0, T0 + 10 * MS, 1.5)
        seq, t = _stream(ing, 1, 100.0, t + 10_000 * MS, 0.5, seq)
        cam = ing.health(t)["cameras"][1]
    assert not [r for r in caplog.records if "delivers" in r.getMessage()]
    assert not cam["low_frame_rate"] and cam["fps"] > 95.0
