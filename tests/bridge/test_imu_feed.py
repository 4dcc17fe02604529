"""bridge/imu_feed.py: the autopilot's IMU messages as the fusion's samples (its clock, its body frame, SI units),
and the mailbox that hands them to the pipeline. Expected values are written out from the MAVLink units."""

import time

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from scipy.spatial.transform import Rotation

from bridge.imu_feed import ImuFeed, to_fusion
from bridge.telemetry import imu_sample

MAV = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)


def _decoded(msg):
    return MAV.decode(bytearray(msg.pack(MAV)))


HIGHRES = _decoded(MAV.highres_imu_encode(2_000_000, 0.5, -0.25, -9.75, 0.01, -0.02, 0.03, 0, 0, 0, 1013, 0, 0, 20,
                                          0x3F))
RAW = _decoded(MAV.raw_imu_encode(3_000_000, 100, -50, -1000, 10, -20, 30, 0, 0, 0))
SCALED = _decoded(MAV.scaled_imu_encode(4000, 100, -50, -1000, 10, -20, 30, 0, 0, 0))


def test_each_imu_message_reads_in_si_units_on_the_autopilot_clock():
    t, a, w = imu_sample(HIGHRES, "px4")
    assert t == 2_000_000_000
    np.testing.assert_allclose(a, [0.5, -0.25, -9.75], rtol=1e-6)
    np.testing.assert_allclose(w, [0.01, -0.02, 0.03], rtol=1e-6)
    t, a, w = imu_sample(RAW, "ardupilot")  # ArduPilot's mG and mrad/s
    assert t == 3_000_000_000
    np.testing.assert_allclose(a, [0.980665, -0.4903325, -9.80665])
    np.testing.assert_allclose(w, [0.01, -0.02, 0.03])
    t, _, w = imu_sample(SCALED, "px4")
    assert t == 4_000_000_000
    np.testing.assert_allclose(w, [0.01, -0.02, 0.03])
    assert imu_sample(RAW, "px4") is None  # another autopilot's raw sensor units: unknown


def test_to_fusion_moves_the_sample_onto_the_capture_clock_and_into_the_body_frame():
    t, a, w = to_fusion(5_000_000_000, np.array([1.0, 2.0, -9.8]), np.array([0.1, 0.2, 0.3]), 1_250_000.0)
    assert t == 4_998_750_000
    np.testing.assert_allclose(a, [1.0, -2.0, 9.8])  # FRD -> FLU: at rest the body reads +g up
    np.testing.assert_allclose(w, [0.1, -0.2, -0.3])


class _Bc:
    autopilot = "ardupilot"
    clock_lag_ns: float | None = None
    filter_lag: float | None = 11_300_000.0

    def gyro_lag_ns(self):
        return self.filter_lag

    def imu_clock_lag_ns(self, t_ap_ns):
        return self.clock_lag_ns


def test_the_feed_waits_for_the_clocks_then_hands_over_the_samples_with_the_filter_lag_taken_off():
    feed, bc = ImuFeed(), _Bc()
    raw = imu_sample(RAW, "ardupilot")
    assert not feed.offer(*raw, bc) and feed.unmapped == 1  # the vehicle's clock not measured yet
    bc.clock_lag_ns = 1_000_000.0
    assert feed.offer(*raw, bc)
    assert imu_sample(_decoded(MAV.heartbeat_encode(2, 3, 0, 0, 0)), "ardupilot") is None  # not an IMU message
    got = []
    assert feed.drain(lambda *s: got.append(s) or True, "quad", np.zeros(3)) == 1
    body, t, a, w, arm = got[0]
    assert body == "quad" and t == 3_000_000_000 - 1_000_000 - 11_300_000
    np.testing.assert_allclose(a, [0.980665, 0.4903325, 9.80665])
    assert not feed.queue
    feed.offer(*raw, bc)
    assert feed.drain(lambda *s: True, None, np.zeros(3)) == 0 and not feed.queue  # bound to no body: dropped


def test_a_fake_autopilots_imu_reaches_the_pipelines_push_live():
    """The whole way over loopback: the fake autopilot's RAW_IMU (its truth plus a drawn accelerometer bias), the
    back-channel, the feed, the bridge's drain into push_imu: times on the server clock, FLU, SI units."""
    from bridge import Bridge
    from bridge.fake_autopilot import FakeAutopilot, imu_from_truth, trajectory_truth
    from bridge.imu_feed import FRD_TO_FLU
    from visionpos.benchmarks.factories import arena_with_vehicles
    from visionpos.sim import trajectories as T

    t0 = time.monotonic_ns()
    truth = trajectory_truth(T.Aggressive(np.array([0.0, 0.0, 1.5])), t0)
    ap = FakeAutopilot("udpin:127.0.0.1:0", sysid=1, truth=truth, boot_ns=t0, accel_bias_m_s2=0.2, seed=4).start()
    bridge = Bridge(arena_with_vehicles([{"sysid": 1, "body": "body1", "endpoint": f"udpout:127.0.0.1:{ap.port}",
                                          "telemetry_rate_hz": 200.0}]), {"report_interval_s": 0})
    (drain,) = bridge.imu_sources()
    bridge.start()
    got = []
    try:
        bc = bridge.vehicles[0].bc
        bc.clock_lag_ns = float(-t0)  # as measured: its boot clock is the server's less t0 (exact here)
        end = time.monotonic() + 5.0
        while len(got) < 200 and time.monotonic() < end:
            time.sleep(0.05)
            drain(lambda *s: got.append(s) or True)
    finally:
        bridge.close()
        ap.close()
    assert len(got) >= 200, f"{len(got)} samples"
    assert {s[0] for s in got} == {"body1"}
    t = np.array([s[1] for s in got], np.int64)
    gyro_frd, acc_frd = imu_from_truth(truth(t))
    acc = np.array([s[2] for s in got])
    # RAW_IMU carries whole mG: resolution 0.01 m/s^2, noise 0.02 m/s^2; the mean offset is the drawn bias
    np.testing.assert_allclose((acc - acc_frd * FRD_TO_FLU).mean(0), ap.accel_bias * FRD_TO_FLU, atol=0.01)
    np.testing.assert_allclose(np.array([s[3] for s in got]), gyro_frd * FRD_TO_FLU, atol=0.05)


def test_the_imu_stream_is_asked_for_at_its_own_rate_200_hz_where_the_filter_takes_it():
    import pytest

    from bridge.backchannel import Backchannel
    from bridge.config import parse_vehicles
    from visionpos.config.arena import ConfigError, parse_arena

    def vehicle(imu_on=None, **kw):
        raw = {"bodies": [{"name": "body1", "id": 1, "markers": [[0, 0, 0], [0.1, 0, 0], [0, 0.12, 0], [0, 0, 0.05]]}],
               "vehicles": [{"body": "body1", "endpoint": "udpout:127.0.0.1:9", **kw}]}
        if imu_on is not None:
            raw["fusion"] = {"imu": {"enabled": imu_on}}
        return parse_vehicles(parse_arena(raw, "a.yaml"))[0]

    assert vehicle(True).imu_rate_hz == 200.0 and vehicle(True, imu_rate_hz=400).imu_rate_hz == 400.0  # fusion.imu on
    assert vehicle().imu_rate_hz == 50.0  # off by default
    assert vehicle(False).imu_rate_hz == 50.0 and vehicle(False, telemetry_rate_hz=20).imu_rate_hz == 20.0
    with pytest.raises(ConfigError, match=r"a\.yaml: vehicles\[0\]\.imu_rate_hz: .*<= 1000"):
        vehicle(imu_rate_hz=2000)
    sent = []
    bc = Backchannel(vehicle(True, telemetry_rate_hz=40), lambda: 100 * 10**9, mavlink2.MAVLink(None, 1, 197),
                     lambda m: sent.append(m) or True, lambda *a: None)
    bc.handle(mavlink2.MAVLink_heartbeat_message(2, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 3, 3), 1, 0)
    bc.service(100 * 10**9)
    asked = {int(m.param1): m.param2 for m in sent
             if m.get_type() == "COMMAND_LONG" and m.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL}
    assert asked[mavlink2.MAVLINK_MSG_ID_ATTITUDE] == 25_000  # us: 40 Hz
    assert asked[mavlink2.MAVLINK_MSG_ID_RAW_IMU] == 5_000  # 200 Hz


def test_the_optical_rate_is_the_central_difference_of_the_triangulated_rotations():
    from bridge.imu_feed import optical_rate_body

    w = np.array([0.3, -1.2, 2.0])  # rad/s, body frame, constant
    R0 = Rotation.from_euler("xyz", [0.2, -0.1, 1.0])
    t = np.array([0, 7_000_000, 20_000_000])  # uneven spacing
    R = np.stack([(R0 * Rotation.from_rotvec(w * s * 1e-9)).as_matrix() for s in t])
    np.testing.assert_allclose(optical_rate_body(t, R), w, atol=1e-9)


def _wired_wrong(seconds, optical_only, opt_traj):
    """A vehicle whose autopilot flies AGGRESSIVE while the body it gets is opt_traj, its IMU in the filter, so the
    filter's attitude and rates (its poses, on_optical) follow that autopilot's gyro; optical_only: the fusions'
    triangulated attitudes of the body go to BridgeImu.optical_pose. The identity check's verdicts (simulated
    clock, 100 Hz poses, 50 Hz telemetry)."""
    from bridge import Bridge
    from visionpos.benchmarks.factories import arena_with_vehicles
    from visionpos.geometry.frames import euler_ned_frd, flu_to_frd, quat_world_body_to_ned_frd
    from visionpos.sim import trajectories as T

    ap_traj = T.Aggressive(np.array([0.0, 0.0, 1.5]))
    bridge = Bridge(arena_with_vehicles([{"sysid": 1, "body": "body1", "endpoint": "udpout:127.0.0.1:9"}]),
                    {"report_interval_s": 0})
    (imu,) = bridge.imu_sources()
    v = bridge.vehicles[0]
    bc = v.bc
    ts = np.arange(0, int(seconds * 1e9), 10_000_000)
    ma, mo = ap_traj(ts * 1e-9), opt_traj(ts * 1e-9)
    e_ap, g_ap, q_ap = euler_ned_frd(ma.quaternions), flu_to_frd(ma.angular_velocities), \
        quat_world_body_to_ned_frd(ma.quaternions)
    noise = Rotation.from_rotvec(np.random.default_rng(3).normal(0, 0.0005, (len(ts), 3)))  # Kabsch's, 0.03 deg
    R_opt = (Rotation.from_quat(mo.quaternions) * noise).as_matrix()
    off, verdicts = 7_000_000_000, []
    for i, t in enumerate(ts):
        t = int(t)
        bc.imu_feed.queue.append((t, np.zeros(3), np.zeros(3)))
        imu(lambda *s: True)  # the pipeline takes the vehicle's sample: its IMU is in the filter
        if optical_only:
            imu.optical_pose("body1", t, R_opt[i])
        bc.on_optical(t, e_ap[i, 0], e_ap[i, 1], g_ap[i], q_ap[i])  # the filter's pose: the autopilot's gyro
        if i % 2 == 0:
            bc.handle(mavlink2.MAVLink_attitude_message((t + off) // 1_000_000, *e_ap[i], *g_ap[i]), 1, t + 1_000_000)
        if i % 50 == 0:
            bc._ts_pending[t] = t
            bc.on_timesync_reply(t, t + off + 2_000_000, t + 3_000_000)
        if i % 25 == 0:
            verdicts.append(bc.check_identity(t + 3_000_000))
    return verdicts


def test_a_wrong_vehicles_imu_in_the_filter_is_still_caught_by_the_identity_check():
    from visionpos.sim import trajectories as T

    fig8, aggressive = T.Figure8(np.array([0.0, 0.0, 1.0])), T.Aggressive(np.array([0.0, 0.0, 1.5]))
    # the filter's poses carry the wrong autopilot's gyro: compared with them, the check would pass it
    assert _wired_wrong(3.0, False, fig8)[2:] == ["consistent"] * 10
    assert _wired_wrong(3.0, True, fig8)[2:] == ["mismatch"] * 10  # against the optical-only attitudes: caught
    assert _wired_wrong(3.0, True, aggressive)[2:] == ["consistent"] * 10  # the right vehicle: no false alarm


def test_the_imu_stream_outgrows_a_57600_baud_radio_as_the_setup_guide_says():
    """docs/autopilot-setup.md keeps fusion.imu off by default for the link: 200 Hz of signed RAW_IMU (54-byte
    MAVLink 2 frames) is 10.8 kB/s, more than a 57600-baud radio's 5.8 kB/s (8N1: 10 bits a byte)."""
    from pathlib import Path

    from bridge.config import IMU_RATE_WITH_FUSION_HZ

    mav = mavlink2.MAVLink(None, 1, 1)
    mav.signing.secret_key = bytes(range(32))
    mav.signing.link_id, mav.signing.sign_outgoing = 0, True
    # ArduPilot's in flight: 1 g on z down, some rate, the magnetometer (mgauss), IMU 0 at 45 degC (cdegC)
    packed = mavlink2.MAVLink_raw_imu_message(123_456_789, 35, -12, -1003, 21, -7, 4, 220, -30, 410, 0,
                                              4500).pack(mav)
    assert len(packed) == 54 and IMU_RATE_WITH_FUSION_HZ == 200
    assert IMU_RATE_WITH_FUSION_HZ * len(packed) == 10_800 and round(57_600 / 10 / 100) / 10 == 5.8
    text = " ".join((Path(__file__).parents[2] / "docs" / "autopilot-setup.md").read_text().split())
    assert "200 Hz of signed RAW_IMU is more than a 57600-baud telemetry radio carries (below)" in text
    assert ("200 Hz of signed RAW_IMU is up to 10.8 kB/s (54-byte MAVLink2 frames), more than a 57600-baud "
            "telemetry radio carries (5.8 kB/s)") in text
