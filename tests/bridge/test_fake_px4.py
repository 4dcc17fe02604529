"""The fake autopilot as PX4 (bridge/fake_px4.py) and the bridge's output and back-channel against it."""

import socket
import struct
import time

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from bridge.fake_autopilot import FakeAutopilot, trajectory_truth
from tests.bridge.test_backchannel import FIG8, _pairs, _stream


def _client(port):
    """A raw MAVLink2 sender/receiver to the fake's udpin port, as a GCS (sysid 255)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.05)
    mav = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
    rx = mavlink2.MAVLink(None)

    def send(msg):
        sock.sendto(msg.pack(mav), ("127.0.0.1", port))

    def recv(kind, timeout_s=2.0, cond=lambda m: True):
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            try:
                data = sock.recv(65535)
            except socket.timeout:
                continue
            for m in rx.parse_buffer(data) or []:
                if m.get_type() == kind and cond(m):
                    return m
        return None

    return sock, mav, send, recv


def test_fake_px4_drops_mocap_and_foreign_frames_and_fuses_vision():
    ap = FakeAutopilot("udpin:127.0.0.1:0", sysid=1, autopilot="px4").start()
    sock, mav, send, recv = _client(ap.port)
    try:
        def odo(frame, est, usec):
            return mav.odometry_encode(usec, frame, 12, 0, 0, -1, [1, 0, 0, 0], 0, 0, 0, 0, 0, 0, [float("nan")] * 21,
                                       [float("nan")] * 21, 0, est, 100)

        send(odo(1, 6, 1000))  # MOCAP
        send(odo(8, 2, 2000))  # MAV_FRAME_BODY_NED: not a frame PX4 takes the position in
        assert ap.wait_for("ODOMETRY", 2, 2.0)
        time.sleep(0.05)
        assert len(ap.dropped_poses) == 2 and "estimator_type 6" in ap.dropped_poses[0]
        assert "frame_id 8" in ap.dropped_poses[1] and not ap.ev_fused(time.monotonic_ns())
        send(odo(1, 2, 3000))  # LOCAL_NED, VISION
        assert ap.wait_for("ODOMETRY", 3, 2.0)
        time.sleep(0.05)
        assert len(ap.dropped_poses) == 2 and ap.ev_fused(time.monotonic_ns())
    finally:
        sock.close()
        ap.close()


def test_fake_px4_arms_only_with_gcs_manual_control_position_mode_and_vision():
    ap = FakeAutopilot("udpin:127.0.0.1:0", sysid=1, autopilot="px4", heartbeat_hz=10).start()
    sock, mav, send, recv = _client(ap.port)
    arm = mav.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    vpe = lambda: mav.vision_position_estimate_encode(time.monotonic_ns() // 1000, 0, 0, -1, 0, 0, 0)  # noqa: E731
    try:
        send(vpe())
        send(arm)
        assert recv("STATUSTEXT").text.endswith("no GCS heartbeat")  # said before the COMMAND_ACK
        assert recv("COMMAND_ACK", cond=lambda m: m.command == 400).result == mavlink2.MAV_RESULT_DENIED
        for _ in range(3):
            send(mav.heartbeat_encode(mavlink2.MAV_TYPE_GCS, 8, 0, 0, 4))
            send(mav.manual_control_encode(1, 0, 0, 500, 0, 0))
            send(vpe())
        send(arm)
        assert recv("STATUSTEXT", cond=lambda m: "Arming" in m.text).text.endswith("not in Position mode")
        send(mav.command_long_encode(1, 1, 176, 0, 1, 3, 0, 0, 0, 0, 0))  # MAV_CMD_DO_SET_MODE custom, POSCTL
        assert recv("COMMAND_ACK", cond=lambda m: m.command == 176).result == mavlink2.MAV_RESULT_ACCEPTED
        send(mav.manual_control_encode(1, 0, 0, 500, 0, 0))
        send(vpe())
        send(arm)
        assert recv("COMMAND_ACK", cond=lambda m: m.command == 400).result == mavlink2.MAV_RESULT_ACCEPTED
        hb = recv("HEARTBEAT", cond=lambda m: m.base_mode & 128)
        assert hb is not None and hb.custom_mode == 3 << 16 and hb.autopilot == mavlink2.MAV_AUTOPILOT_PX4
        # Offboard, then the sticks go quiet: PX4 (COM_RCL_EXCEPT 0) fails safe into AUTO.LAND after 0.5 s
        send(mav.command_long_encode(1, 1, 176, 0, 1, 6, 0, 0, 0, 0, 0))
        assert recv("COMMAND_ACK", cond=lambda m: m.command == 176).result == mavlink2.MAV_RESULT_ACCEPTED
        assert recv("HEARTBEAT", cond=lambda m: m.custom_mode == 6 << 16) is not None
        assert recv("STATUSTEXT", 2.0, cond=lambda m: m.text == "Failsafe activated") is not None
        hb = recv("HEARTBEAT")
        assert hb.custom_mode == (4 << 16) | (6 << 24) and hb.base_mode & 128  # still armed, landing
    finally:
        sock.close()
        ap.close()


def test_fake_px4_answers_its_parameters_only():
    ap = FakeAutopilot("udpin:127.0.0.1:0", sysid=1, autopilot="px4", reject_params=("EKF2_EV_NOISE_MD",)).start()
    sock, mav, send, recv = _client(ap.port)
    try:
        # PX4 carries an INT32 parameter's bytes in the float field (PARAM_ENCODE_BYTEWISE): 3 is 3 * 2**-149
        three = struct.unpack("<f", struct.pack("<i", 3))[0]
        assert three == 3 * 2.0 ** -149
        send(mav.param_set_encode(1, 1, b"EKF2_HGT_REF", three, mavlink2.MAV_PARAM_TYPE_INT32))
        m = recv("PARAM_VALUE")
        assert m.param_id == "EKF2_HGT_REF" and m.param_type == mavlink2.MAV_PARAM_TYPE_INT32
        assert m.param_value == three and ap.params["EKF2_HGT_REF"] == 3
        send(mav.param_request_read_encode(1, 1, b"EKF2_EV_DELAY", -1))  # a REAL32 one: the float itself
        m = recv("PARAM_VALUE")
        assert m.param_type == mavlink2.MAV_PARAM_TYPE_REAL32 and m.param_value == 0.0
        for name in (b"EKF2_EV_NOISE_MD", b"VISO_TYPE"):  # rejected here; ArduPilot's, not PX4's
            send(mav.param_set_encode(1, 1, name, 1, mavlink2.MAV_PARAM_TYPE_INT32))
            assert recv("PARAM_VALUE", 0.3) is None
        assert "VISO_TYPE" not in ap.params
    finally:
        sock.close()
        ap.close()


def test_bridge_to_px4_sends_local_ned_vision_and_reads_estimator_status():
    """ODOMETRY to PX4 goes as LOCAL_NED (north-aligned: PX4 aligns its heading and can arm), estimator_type VISION;
    the back-channel asks for ESTIMATOR_STATUS and HIGHRES_IMU and says EKF2 fuses the vision."""
    t0 = time.monotonic_ns()
    ap = FakeAutopilot("udpin:127.0.0.1:0", sysid=1, autopilot="px4", truth=trajectory_truth(FIG8, t0))
    bridge = _pairs([{"message": "odometry"}], [ap])
    v = bridge.vehicles[0]
    try:
        # the frame follows the HEARTBEAT: the poses from a little after the bridge heard PX4's
        after = lambda: [m for m in ap.messages("ODOMETRY") if v.bc.first_heard_ns  # noqa: E731
                         and m.recv_ns > v.bc.first_heard_ns + 200_000_000]
        _stream(bridge, [FIG8], t0, 8.0, until=lambda: v.health()["ekf"]["state"] == "using vision"
                and v.bc.identity == "consistent" and len(after()) >= 20)
        odo = after()
        assert odo and {(m.fields["frame_id"], m.fields["estimator_type"]) for m in odo} == {(1, 2)}
        assert not ap.dropped_poses
        assert 230 in ap.intervals_ns and 105 in ap.intervals_ns and 193 not in ap.intervals_ns
        h = v.health()
        assert h["ekf"]["state"] == "using vision" and "EKF2 fuses the vision" in h["ekf"]["detail"]
        assert v.bc.identity == "consistent" and v.bc.gyro_source == "HIGHRES_IMU"
    finally:
        bridge.close()
        ap.close()


def test_the_autopilot_setting_decides_before_any_heartbeat():
    """`autopilot: px4` sends LOCAL_NED from the first pose; `auto` follows the HEARTBEAT (None before it)."""
    from bridge.config import parse_vehicles
    from bridge.vehicle_link import VehicleLink
    from visionpos.benchmarks.factories import arena_with_vehicles

    for setting, expected in (("px4", "px4"), ("ardupilot", "ardupilot"), ("auto", None)):
        cfg = parse_vehicles(arena_with_vehicles([{"body": "body1", "endpoint": "udpout:127.0.0.1:9",
                                                   "autopilot": setting}]))[0]
        link = VehicleLink(cfg)
        try:
            assert link.estimator() == expected
            link.bc.autopilot = "px4"  # as its HEARTBEAT would say
            assert link.estimator() == (expected or "px4")
        finally:
            link.close()


def test_the_fake_autopilots_clock_never_reads_before_its_boot():
    """reboot() runs on the test's thread while the fake's loop may hold a `now` taken just before it: that moment,
    before the new boot, reads 0 (a negative time_boot_ms cannot be packed and killed the loop, so a reboot test
    saw one vehicle never reboot)."""
    ap = FakeAutopilot("udpin:127.0.0.1:0", sysid=1)
    ap.reboot()
    assert ap.boot_time_ns(ap.boot_ns - 5_000_000) == 0
    assert ap.boot_time_ns(ap.boot_ns + 7) == 7
    ap.mav.attitude_encode(ap.boot_time_ns(ap.boot_ns - 5_000_000) // 1_000_000, 0, 0, 0, 0, 0, 0).pack(ap.mav)
