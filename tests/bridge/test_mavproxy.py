"""Integration: MAVProxy receives and forwards the bridge's messages.

MAVProxy is not in the [test] extra: its declared dependencies pull vtk, opencv-python (beside
our opencv-python-headless) and matplotlib for its GUI and 3-D modules, none of which the
non-interactive mavproxy.py run here needs. .ci/run installs it on its own with
`pip install --no-deps MAVProxy` and its small runtime dependencies, and sets
VISIONPOS_REQUIRE_MAVPROXY=1 so that a failed install fails instead of skipping.

bridge --udpout--> MAVProxy (--master=udpin) --out udpout--> fake autopilot (udpin)
MAVProxy also writes a telemetry log, read back with pymavlink.
"""

import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pymavlink import mavutil

from bridge import Bridge
from bridge.fake_autopilot import FakeAutopilot
from visionpos.app.ports import free_port
from visionpos.benchmarks.factories import arena_with_vehicles, body_state

S45 = math.sqrt(0.5)


def mavproxy_path() -> str | None:
    local = Path(sys.executable).with_name("mavproxy.py")
    return str(local) if local.exists() else shutil.which("mavproxy.py")


def tlog_count(path: Path) -> int:
    """VISION_POSITION_ESTIMATE messages in a (possibly still growing) MAVProxy telemetry log."""
    if not path.exists():
        return 0
    log = mavutil.mavlink_connection(str(path))
    n = 0
    while log.recv_match(type="VISION_POSITION_ESTIMATE") is not None:
        n += 1
    log.close()
    return n


NOT_INSTALLED = ("MAVProxy not installed (not in the [test] extra: its dependencies are heavy); "
                 "install it as .ci/run does: pip install --no-deps MAVProxy && pip install defusedxml pynmeagps")


def test_mavproxy_receives_vision_position_estimate(tmp_path):
    if mavproxy_path() is None:
        if os.environ.get("VISIONPOS_REQUIRE_MAVPROXY"):
            pytest.fail(NOT_INSTALLED)
        pytest.skip(NOT_INSTALLED)
    master_port = free_port()
    out = FakeAutopilot("udpin:127.0.0.1:0", sysid=1, heartbeat_hz=0, timesync_hz=0).start()
    tlog = tmp_path / "mavproxy.tlog"
    proc = subprocess.Popen(
        [sys.executable, mavproxy_path(), f"--master=udpin:127.0.0.1:{master_port}",
         f"--out=udpout:127.0.0.1:{out.port}", "--daemon", "--non-interactive", "--default-modules=",
         f"--state-basedir={tmp_path}", f"--logfile={tlog}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=tmp_path, env=dict(os.environ, MAVLINK20="1"),
    )
    bridge = Bridge(arena_with_vehicles([{"body": "body1", "sysid": 1, "endpoint": f"udpout:127.0.0.1:{master_port}"}]),
                    {"report_interval_s": 0})
    bridge.start()
    try:
        deadline = time.monotonic() + 30  # MAVProxy start-up on a loaded machine
        # MAVProxy writes its telemetry log from a thread of its own: keep sending until the
        # forwarded messages and the log both hold them, so terminating it loses nothing
        while (len(out.messages("VISION_POSITION_ESTIMATE")) < 5 or tlog_count(tlog) < 5) \
                and time.monotonic() < deadline:
            assert proc.poll() is None, proc.stdout.read().decode(errors="replace")
            bridge.publish([body_state(position=(1, 2, 3), quaternion=(0, 0, S45, S45))])
            time.sleep(0.02)
    finally:
        bridge.close()
        proc.terminate()
        try:
            log_text = proc.communicate(timeout=10)[0].decode(errors="replace")
        except subprocess.TimeoutExpired:
            proc.kill()
            log_text = proc.communicate()[0].decode(errors="replace")
        out.close()
    poses = out.messages("VISION_POSITION_ESTIMATE")
    assert len(poses) >= 5, log_text
    m = poses[-1]
    assert (m.src_system, m.src_component) == (1, 197)
    assert (m.fields["x"], m.fields["y"], m.fields["z"]) == pytest.approx((1, -2, -3), abs=1e-6)
    assert m.fields["yaw"] == pytest.approx(-math.pi / 2, abs=1e-6)
    # MAVProxy's own telemetry log has them too
    log = mavutil.mavlink_connection(str(tlog))
    n = 0
    while (msg := log.recv_match(type="VISION_POSITION_ESTIMATE")) is not None:
        n += 1
        assert (msg.get_srcSystem(), msg.get_srcComponent()) == (1, 197)
    assert n >= 5
