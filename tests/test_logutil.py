"""RateLimitedLog: first line per key at once, then one per interval with the suppressed count; bounded keys."""

from __future__ import annotations

import logging

from visionpos.logutil import RateLimitedLog


def test_first_line_then_one_per_interval_with_a_count(caplog):
    now = [0.0]
    rl = RateLimitedLog(logging.getLogger("t.rl"), interval_s=10.0, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, logger="t.rl"):
        for i in range(108):  # the 108 re-sync warnings in 20 s
            now[0] = i * 20.0 / 108
            rl.log(("resync", 2), logging.WARNING, "camera %d: resync", 2)
    msgs = [r.getMessage() for r in caplog.records]
    assert msgs[0] == "camera 2: resync"
    assert len(msgs) == 2 and "more like this in the last 10 s" in msgs[1]
    # lines 1..53 fall within 10 s of the first (i * 20 / 108 < 10); line 54 is logged with their count
    assert rl.suppressed == 106 and int(msgs[1].split("(")[1].split()[0]) == 53


def test_key_table_is_an_lru_with_an_eviction_count():
    rl = RateLimitedLog(logging.getLogger("t.rl2"), max_keys=4, clock=lambda: 0.0)
    for k in range(10):
        rl.log(k, logging.DEBUG, "k")
    assert len(rl) == 4 and rl.evicted == 6
    assert not rl.log(9, logging.DEBUG, "k")  # still known: suppressed
    assert rl.log(0, logging.DEBUG, "k")  # evicted: logged again


def test_warning_is_log_at_warning_level_under_the_same_limit(caplog):
    now = [0.0]
    rl = RateLimitedLog(logging.getLogger("t.rl3"), interval_s=10.0, clock=lambda: now[0])
    with caplog.at_level(logging.DEBUG, logger="t.rl3"):
        assert rl.warning("stale", "vehicle %s: stale", "v1")
        now[0] = 9.9
        assert not rl.warning("stale", "vehicle %s: stale", "v1")
        now[0] = 10.0
        assert rl.warning("stale", "vehicle %s: stale", "v1")
    assert [r.levelno for r in caplog.records] == [logging.WARNING, logging.WARNING]
    assert caplog.records[1].getMessage() == "vehicle v1: stale (1 more like this in the last 10 s)"
