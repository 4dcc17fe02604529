"""Single-marker (point) bodies in the bridge: the config refuses attitude options, the vehicle gets position-only
messages (the fake ArduPilot and the fake PX4 read them), and a fleet of them is bound by accelerations
(bridge/point_binding.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bridge import Bridge
from bridge.config import parse_vehicles
from bridge.fake_autopilot import FakeAutopilot
from bridge.fleet_binding import FleetBinding
from bridge.point_binding import level_from_imu, level_from_optical
from tests.bridge.test_mavlink import KEY, feed, key_file
from visionpos.app.ports import free_port
from visionpos.benchmarks.factories import body_state
from visionpos.config.arena import ConfigError, parse_arena

G = 9.80665
NAN4 = (float("nan"),) * 4


def _arena(**vehicle):
    v = {"body": "dot", "endpoint": "udpin:127.0.0.1:1", "autopilot_address": "127.0.0.1:2", **vehicle}
    return parse_arena({"bodies": [{"name": "dot", "id": 1, "markers": [[0, 0, 0]]}], "vehicles": [v]}, "a.yaml")


@pytest.mark.parametrize("key, value", [("pivot_offset", [0.0, 0.0, 0.05]), ("identity_check", "warn"),
                                        ("identity_tolerance_deg", 5.0), ("message", "odometry")])
def test_attitude_options_of_a_point_body_vehicle_are_refused_with_their_key(key, value):
    with pytest.raises(ConfigError, match=rf"vehicles\[0\]\.{key}: its body is a single-marker point body"):
        parse_vehicles(_arena(**{key: value}))
    v = parse_vehicles(_arena())[0]
    assert v.position_only and v.identity_check == "off"
    assert parse_vehicles(_arena(message="odometry", autopilot="px4"))[0].message == "odometry"


def _point_state(**kw):
    C = np.full((6, 6), np.nan)
    C[:3, :3] = np.diag([1e-6, 2e-6, 3e-6])
    return body_state(name="dot", position=(1, 2, 3), quaternion=NAN4, velocity=(0.5, 0, 0),
                      angular_velocity=(np.nan,) * 3, covariance=C, n_markers=1, **kw)


def _pair(fake, **vehicle):
    port = free_port()
    v = {"body": "dot", "sysid": 1, "endpoint": f"udpin:127.0.0.1:{port}", "max_age_ms": 10000,
         "signing": {"key_file": key_file()}, **vehicle}
    arena = parse_arena({"bodies": [{"name": "dot", "id": 1, "markers": [[0, 0, 0]]}], "vehicles": [v]}, "a.yaml")
    bridge = Bridge(arena, {"report_interval_s": 0})
    bridge.start()
    ap = FakeAutopilot(f"udpout:127.0.0.1:{port}", sysid=1, signing_key=KEY, autopilot=fake).start()
    assert ap.wait_for("HEARTBEAT", 1, 5.0)
    return bridge, ap


def test_ardupilot_gets_the_position_with_a_zero_attitude_and_an_unknown_covariance():
    bridge, ap = _pair("ardupilot")
    try:
        feed(bridge, [_point_state()])
        assert ap.wait_for("VISION_POSITION_ESTIMATE", 1)
        f = ap.messages("VISION_POSITION_ESTIMATE")[0].fields
        assert (f["x"], f["y"], f["z"]) == pytest.approx((1, -2, -3), abs=1e-6)  # world z-up -> NED
        assert (f["roll"], f["pitch"], f["yaw"]) == (0.0, 0.0, 0.0)  # ignored unless EK3_SRC1_YAW = 6
        assert math.isnan(f["covariance"][0])  # unknown: VISO_POS_M_NSE applies
    finally:
        bridge.close()
        ap.close()


def test_px4_gets_odometry_with_a_nan_quaternion_and_fuses_the_position():
    bridge, ap = _pair("px4", message="odometry", autopilot="px4")
    try:
        feed(bridge, [_point_state()])
        assert ap.wait_for("ODOMETRY", 1)
        f = ap.messages("ODOMETRY")[0].fields
        assert (f["x"], f["y"], f["z"]) == pytest.approx((1, -2, -3), abs=1e-6)
        assert math.isnan(f["q"][0])  # MAVLink: attitude unknown
        assert all(math.isnan(f[k]) for k in ("vx", "vy", "vz", "rollspeed", "pitchspeed", "yawspeed"))
        pc = f["pose_covariance"]
        assert (pc[0], pc[6], pc[11]) == pytest.approx((1e-6, 2e-6, 3e-6))  # x, y, z: the filter's (NED: same axes)
        assert math.isnan(pc[15]) and math.isnan(pc[20])  # roll, yaw variances unknown
        assert math.isnan(f["velocity_covariance"][0])
        assert not ap.dropped_poses
    finally:
        bridge.close()
        ap.close()


def test_the_level_specific_force_is_free_of_heading():
    # a vehicle rolled 20 deg right, pitched 10 deg up, accelerating 2 m/s^2 north and 1 up (world z-up: +x, +z)
    a_world = np.array([[2.0, 0.0, 1.0]])
    rot = Rotation.from_euler("ZYX", [0.7, math.radians(10), math.radians(20)])  # body FRD -> NED, any yaw
    f_ned = np.array([2.0, 0.0, -1.0]) - np.array([0.0, 0.0, G])  # specific force: a - g, g down +z in NED
    f_frd = rot.inv().apply(f_ned)[None]
    got = level_from_imu(f_frd, np.array([math.radians(20)]), np.array([math.radians(10)]))
    assert got[0] == pytest.approx([-(1.0 + G), 2.0])
    assert level_from_optical(a_world)[0] == pytest.approx([-(1.0 + G), 2.0])


def _ring_state(name, t_ns, p):
    return body_state(name=name, capture_ns=t_ns, position=p, quaternion=NAN4, angular_velocity=(np.nan,) * 3)


def test_a_fleet_of_point_bodies_is_bound_by_its_accelerations():
    """Two point bodies bob up and down at different rates; body 'dot1' is vehicle b's drone, 'dot2' vehicle a's.
    Each vehicle reports its roll/pitch (level) and the specific force of its own drone: the binding pairs them."""
    bodies, vehicles = ["dot1", "dot2"], ["a", "b"]
    fb = FleetBinding([bodies], {"a": "dot1", "b": "dot2"}, dict.fromkeys(vehicles, 0.05),
                      dict.fromkeys(vehicles, "continuity"), frozenset(bodies))
    omega = {"dot1": 2 * math.pi * 1.0, "dot2": 2 * math.pi * 1.7}
    drone_of = {"b": "dot1", "a": "dot2"}
    amp = 0.1  # m: 4 and 11 m/s^2 peak
    made = []
    t_all = np.arange(0, 2_000_000_000, 10_000_000, dtype=np.int64)
    for i, t in enumerate(t_all):
        s = t * 1e-9
        fb.observe([_ring_state(b, int(t), (0.0, 0.0, 1.0 + amp * math.sin(omega[b] * s))) for b in bodies], None)
        if fb.due(int(t)) and i > 0:
            ts = t_all[: i + 1]
            tel = {v: (ts, np.zeros((len(ts), 5))) for v in vehicles}
            w = {v: omega[drone_of[v]] for v in vehicles}  # up: a = -amp w^2 sin(w t); FRD z reads -(a + g)
            acc = {v: (ts, np.column_stack([np.zeros(len(ts)), np.zeros(len(ts)),
                                            -(G - amp * w[v] ** 2 * np.sin(w[v] * ts * 1e-9))])) for v in vehicles}
            made += fb.evaluate(int(t), tel, acc)[1]
    assert sorted(made) == [("dot1", "b"), ("dot2", "a")]


def test_the_outputs_never_send_an_attitude_for_a_point_body():
    import json
    import time

    from bridge.pose_stream import _json_line
    from bridge.vrpn import encode_reports
    from tests.bridge.test_natnet import server

    st = _point_state()
    line = json.loads(_json_line(st, 0))  # pose stream: the position, the attitude null (JSON has no NaN)
    assert line["tracked"] and line["position"] == pytest.approx([1, 2, 3]) and line["quaternion"] == [None] * 4
    assert line["angular_velocity"] == [None] * 3 and line["velocity"] == pytest.approx([0.5, 0, 0])
    cov = line["covariance"]  # upper triangle of [x y z rx ry rz]: (0,0) (1,1) known, (3,3) (5,5) not
    assert cov[0] == pytest.approx(1e-6) and cov[6] == pytest.approx(2e-6) and cov[15] is None and cov[20] is None
    assert encode_reports(st, 0, time.time_ns(), 0) is None  # VRPN: Pos_Quat needs an attitude: nothing sent
    srv = server(transmission="unicast")
    try:  # NatNet: a rigid body not valid, at the origin with the identity (as an untracked one)
        f = srv.build_frame([body_state("cf1", 7, position=(1, 2, 3), quaternion=NAN4)], None, time.monotonic_ns())
        assert [(i, tuple(p), tuple(q), ok) for i, p, q, _, ok in f.bodies] == [(7, (0, 0, 0), (0, 0, 0, 1), False)]
    finally:
        srv.close()


def test_natnetsdk_reads_a_point_body_as_not_valid_and_never_a_made_up_attitude():
    """OptiTrack's own client (natnetsdk) decodes what our NatNet server sends for a body without an attitude."""
    import time

    from tests.bridge.test_natnet import natnet_client, server, shutdown, wait_for

    srv = server(transmission="unicast")
    c, got = natnet_client(srv)
    try:
        assert c.run()
        q = Rotation.from_euler("z", 0.3).as_quat()
        for _ in range(30):  # cf1 has no attitude (a point body's state), drone_b a full pose
            srv.publish([body_state("cf1", 7, position=(1, 2, 3), quaternion=NAN4),
                         body_state("drone_b", 12, position=(-1, 0.5, 1), quaternion=q)])
            time.sleep(0.01)
        assert wait_for(lambda: len(got["frames"]) >= 5)
        rb = {r.id_num: r for r in got["frames"][-1][1].rigid_body_data.rigid_body_list}
        assert not rb[7].tracking_valid and tuple(rb[7].pos) == (0.0, 0.0, 0.0)
        assert all(math.isfinite(x) for x in rb[7].rot)
        assert rb[12].tracking_valid
    finally:
        shutdown(c)
        srv.close()
