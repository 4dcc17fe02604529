"""A vehicle's vision gap: said loudly (log, status line, health) and to the autopilot (STATUSTEXT), then
"vision resumed"."""

import logging
import time

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from bridge import Bridge
from bridge.fake_autopilot import FakeAutopilot
from bridge.vision_gap import VisionGap
from visionpos.benchmarks.factories import arena_with_vehicles, body_state

MS = 1_000_000


def test_gap_state_machine_on_made_up_times():
    g = VisionGap(500 * MS, repeat_ns=2000 * MS)
    assert g.check(10_000 * MS) is None and g.deadline_ns() is None  # nothing sent yet: nothing to lose
    for t in range(0, 1000, 20):
        assert g.on_sent(t * MS) is None
    assert g.check(1480 * MS) is None  # 500 ms after the last pose (980): not over the threshold yet
    e = g.check(1481 * MS)
    assert (e.kind, round(e.gap_s, 3)) == ("lost", 0.501)
    assert g.check(2000 * MS) is None  # said once; the repeat comes 2 s later
    e = g.check(3481 * MS)
    assert (e.kind, round(e.gap_s, 3)) == ("still", 2.501)
    e = g.on_sent(4000 * MS)
    assert (e.kind, round(e.gap_s, 3)) == ("resumed", 3.02)
    assert g.state(4100 * MS) == {"state": "ok", "since_last_pose_s": 0.1, "gaps": 1, "longest_s": 3.02,
                                  "last_gap_s": 3.02, "threshold_s": 0.5}
    assert g.on_sent(4020 * MS) is None


def test_gap_reaches_the_autopilot_as_statustext_and_resumes(caplog):
    ap = FakeAutopilot("udpin:127.0.0.1:0", sysid=1).start()
    arena = arena_with_vehicles([{"body": "body1", "endpoint": f"udpout:127.0.0.1:{ap.port}", "vision_gap_s": 0.3}])
    bridge = Bridge(arena, {"report_interval_s": 0})
    bridge.start()
    v = bridge.vehicles[0]

    def stream(seconds, tracked=True, until=lambda: False):
        end = time.monotonic() + seconds
        while time.monotonic() < end and not until():
            bridge.publish([body_state("body1", 1, capture_ns=time.monotonic_ns(), tracked=tracked)])
            time.sleep(0.02)

    try:
        with caplog.at_level(logging.WARNING, logger="visionpos.bridge"):
            stream(3.0, until=lambda: v.counters["sent"] >= 10)
            assert v.vision_gap_state()["state"] == "ok"
            stream(0.8, tracked=False)  # the body lost by the cameras: nothing goes for 0.8 s
            h = v.health()["vision_gap"]
            assert h["state"] == "gap" and h["why"] == "the body is not tracked"
            assert "VISION GAP" in bridge.status_line()
            assert bridge.stats()["vehicles"]["body1"]["vision_gap"]["state"] == "gap"
            stream(3.0, until=lambda: len(ap.messages("STATUSTEXT")) >= 2)
        texts = [(m.fields["severity"], m.fields["text"]) for m in ap.messages("STATUSTEXT")]
        assert texts[0][0] == mavlink2.MAV_SEVERITY_WARNING and texts[0][1].startswith("visionpos: NO VISION for 0.")
        assert texts[1][0] == mavlink2.MAV_SEVERITY_NOTICE and texts[1][1].startswith("visionpos: vision resumed")
        h = v.health()["vision_gap"]
        assert h["state"] == "ok" and h["gaps"] == 1 and 0.3 < h["last_gap_s"] < 1.5
        said = [r.getMessage() for r in caplog.records]
        assert sum("VISION LOST: vehicle body1" in t for t in said) == 1
        assert sum("vision resumed: vehicle body1" in t for t in said) == 1
        assert np.all([m.src_component == 197 for m in ap.messages("STATUSTEXT")])
    finally:
        bridge.close()
        ap.close()
