"""The accelerometer half of the autopilot's IMU messages (bridge/telemetry.py imu_sample, bridge/imu_samples.py)
and the back-channel's hook."""

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from bridge.backchannel import Backchannel
from bridge.config import parse_vehicles
from bridge.imu_samples import AccelSamples
from bridge.telemetry import imu_sample
from visionpos.benchmarks.factories import arena_with_vehicles

G = 9.80665


def _highres(t_us, acc):
    return mavlink2.MAVLink_highres_imu_message(t_us, *acc, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)


def _raw(t_us, acc):
    return mavlink2.MAVLink_raw_imu_message(t_us, *acc, 0, 0, 0, 0, 0, 0)


def _accel(m, autopilot):
    s = imu_sample(m, autopilot)
    return None if s is None else tuple(s[1])


def test_units_per_message():
    assert _accel(_highres(0, (0.5, -0.25, -9.0)), "px4") == pytest.approx((0.5, -0.25, -9.0))
    # ArduPilot's RAW_IMU and SCALED_IMU: milli-g, 1000 of them one g
    assert _accel(_raw(0, (0, 500, -1000)), "ardupilot") == pytest.approx((0.0, G / 2, -G))
    assert _accel(_raw(0, (0, 0, -1000)), "px4") is None  # raw counts: units unknown
    assert _accel(_highres(0, (float("nan"), 0, 0)), "px4") is None
    s = AccelSamples()
    s.add(0, (1e6, 0, 0))  # beyond any IMU's range: dropped
    assert len(s) == 0


def test_samples_restart_on_a_reboot_and_map_onto_the_server_clock():
    s = AccelSamples()
    for k in range(3):
        s.add(5_000_000_000 + k * 20_000_000, (k, 0, -G))
    assert s.on_server_clock(lambda t: None) is None  # the clocks are not mapped yet
    t, a = s.on_server_clock(lambda t: (t - 4_000_000_000.0).astype(np.int64))
    assert t.tolist() == [1_000_000_000, 1_020_000_000, 1_040_000_000]
    assert a[:, 0].tolist() == [0.0, 1.0, 2.0]
    s.add(1_000_000, (9, 0, -G))  # the autopilot rebooted: a new clock
    assert len(s) == 1


def test_the_back_channel_keeps_the_accelerometer_of_each_imu_message():
    cfg = parse_vehicles(arena_with_vehicles([{"body": "body1", "endpoint": "udpout:127.0.0.1:9"}]))[0]
    bc = Backchannel(cfg, lambda: 0, mavlink2.MAVLink(None, 1, 197), lambda m: True, lambda *a: None)
    bc.handle(mavlink2.MAVLink_heartbeat_message(2, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 3, 3), 1, 0)
    for k in range(4):
        bc.handle(_raw(7_000_000 + k * 20_000, (0, 0, -1000 - k)), 1, 10_000_000 + k * 20_000_000)
    assert len(bc.gyro) == 4 and len(bc.accel) == 4
    t, a = bc.accel.on_server_clock(bc.ap_to_server_ns)
    assert a[:, 2] == pytest.approx([-G * (1000 + k) / 1000 for k in range(4)])
    assert np.all(np.diff(t) == 20_000_000)


def test_the_fleet_gets_each_vehicles_accelerometer_on_the_server_clock():
    from bridge import Bridge
    from visionpos.config.arena import parse_arena

    layout = [[0.1, 0, 0], [0, 0.1, 0], [-0.1, 0, 0], [0, -0.12, 0.02]]
    arena = parse_arena({"bodies": [{"name": "quadA", "id": 1, "markers": layout},
                                    {"name": "quadB", "id": 2, "markers": layout}],
                         "vehicles": [{"body": "quadA", "endpoint": "udpout:127.0.0.1:9"},
                                      {"body": "quadB", "endpoint": "udpout:127.0.0.1:10"}]}, "fleet-test.yaml")
    bridge = Bridge(arena, {"clock_ns": lambda: 10**12, "report_interval_s": 0, "pose_stream": False})
    a, b = bridge.vehicle("quadA").bc, bridge.vehicle("quadB").bc
    a.clock_offsets.add(10**12, (-(10**12 - 3_000_000_000),))  # quadA's autopilot clock: 3 s since its boot
    for k in range(3):
        a.accel.add(3_000_000_000 + k * 20_000_000, (0, 0, -G - k))
    got = bridge.fleet.accel_telemetry(bridge._by_name)
    t, acc = got["quadA"]
    assert t.tolist() == [10**12, 10**12 + 20_000_000, 10**12 + 40_000_000]
    assert acc[:, 2] == pytest.approx([-G, -G - 1, -G - 2])
    assert got["quadB"] is None and len(b.accel) == 0  # nothing heard from it: its clock is not mapped
