"""The fleet's binding of optical bodies to vehicles (bridge/fleet_binding.py) on made-up telemetry."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bridge.fleet_binding import (
    BOUND,
    QUALITY_SPREAD,
    RATE_PER_ATT_S,
    STOPPED,
    UNKNOWN,
    UNRESOLVED,
    FleetBinding,
    attitude_sigma_rad,
    optical_attitude,
    optical_rate_noise,
    pair_costs,
)

STEP_NS = 10_000_000  # output ticks, 100 Hz
TEL_NS = 20_000_000  # telemetry, 50 Hz


class State(NamedTuple):
    name: str
    time_ns: int
    quaternion: np.ndarray
    angular_velocity: np.ndarray
    tracked: bool = True
    position: np.ndarray = np.zeros(3)
    covariance: np.ndarray = np.diag([1e-6] * 3 + [math.radians(0.25) ** 2 / 3] * 3)  # attitude sigma 0.25 deg


def test_optical_attitude_is_what_an_autopilot_reports():
    q = Rotation.from_euler("xy", [10, 20], degrees=True).as_quat()  # body FLU -> world z-up
    got = optical_attitude(q[None], np.array([[0.1, 0.2, 0.3]]))[0]
    # FLU -> FRD: a roll right is the same, a pitch about y-left by +20 deg is nose down: -20 deg up
    assert np.degrees(got[0]) == pytest.approx(10.0, abs=1e-9)
    assert np.degrees(got[1]) == pytest.approx(-20.0 * math.cos(math.radians(10)) / math.cos(math.radians(10)),
                                               abs=1e-9)
    assert got[2:] == pytest.approx([0.1, -0.2, -0.3])


def test_pair_costs_sum_the_normalised_squares():
    opt = np.zeros((2, 3, 5))
    tel = np.zeros((1, 3, 5))
    opt[1, :, 4] = 0.2  # body 1 yaws at 0.2 rad/s: rate sigma 0.1 + 0.1 * 0.2 = 0.12
    tel[0, :, 0] = math.radians(1.0)  # the vehicle reports 1 deg of roll: 1/2 sigma at 2 deg
    c = pair_costs(opt, tel, np.array([math.radians(2.0)]))
    assert c[0, 0] == pytest.approx(3 * 0.25)
    assert c[1, 0] == pytest.approx(3 * (0.25 + (0.2 / 0.12) ** 2))


def test_the_optical_rates_noise_grows_with_the_attitudes_uncertainty_over_its_usual():
    assert attitude_sigma_rad(np.diag([9.0, 9.0, 9.0, 0.01, 0.02, 0.06])) == pytest.approx(0.3)
    usual = np.radians([0.25, 0.5])
    s = np.radians([[0.25] * 9, [0.5] * 9])
    s[0, 4] = math.radians(1.25)  # one glitch of body 0: 1 deg over its usual
    s[1, 0] = math.radians(0.3)  # under body 1's usual: no extra
    got = optical_rate_noise(s, usual)
    want = np.zeros((2, 9))
    want[0, 4 - QUALITY_SPREAD:4 + QUALITY_SPREAD + 1] = RATE_PER_ATT_S * math.radians(1.0)
    assert got == pytest.approx(want)
    opt, tel = np.zeros((1, 1, 5)), np.zeros((1, 1, 5))
    opt[0, 0, 2] = 1.0  # a roll rate of 1 rad/s the vehicle does not report: sigma 0.1 + 0.4 + 0.1 * 1
    assert pair_costs(opt, tel, np.array([1.0]), np.array([[0.4]]))[0, 0] == pytest.approx((1.0 / 0.6) ** 2)


class Fleet:
    """Drones on the floor; optical body i is drone perm[i]; vehicle 'v{k}' is drone k. yaw_rate[k](t s) rad/s."""

    def __init__(self, perm=(2, 0, 1), policy="continuity", pads=None, positions=None, yaw_offset_deg=0.0):
        self.perm = list(perm)
        n = len(self.perm)
        self.bodies = [f"quad{i + 1}" for i in range(n)]
        self.names = [f"v{k}" for k in range(n)]
        self.binding = FleetBinding([self.bodies], dict(zip(self.names, self.bodies)),
                                    dict.fromkeys(self.names, math.radians(3.0)), dict.fromkeys(self.names, policy),
                                    pads=pads, yaw_offset_rad=dict.fromkeys(self.names, math.radians(yaw_offset_deg)))
        self.positions = [np.zeros(3)] * n if positions is None else [np.asarray(p, float) for p in positions]
        self.yaw_offset_deg = yaw_offset_deg
        self.ekf_error: dict[str, np.ndarray] | None = None  # vehicle: its EKF's error (m world); None: no positions
        self.rates = [lambda t: 0.0] * n
        self.yaw = [0.0] * n
        self.tel = {n: ([], []) for n in self.names}
        self.t_ns = 0
        self.silent: set[str] = set()
        self.lost: set[str] = set()
        self.identity = None  # None: from the tracked flags
        self.made: list[tuple[int, str, str]] = []
        self.stopped: list[tuple[int, str]] = []
        self.glitch: dict[str, np.ndarray] = {}  # body: an error of its optical rates (rad/s FLU)
        self.sigma_deg: dict[str, float] = {}  # body: its attitude's sigma (default 0.25 deg)

    def step(self, seconds: float) -> None:
        rng = np.random.default_rng(self.t_ns)
        for _ in range(int(round(seconds * 1e9 / STEP_NS))):
            self.t_ns += STEP_NS
            t = self.t_ns * 1e-9
            r = [f(t) for f in self.rates]
            self.yaw = [y + ri * STEP_NS * 1e-9 for y, ri in zip(self.yaw, r)]
            states = [State(b, self.t_ns, Rotation.from_euler("z", self.yaw[d]).as_quat(),
                            np.array([0.0, 0.0, r[d]]) + rng.normal(0, 0.01, 3) + self.glitch.get(b, 0.0),
                            b not in self.lost, self.positions[d],
                            np.diag([1e-6] * 3 + [math.radians(self.sigma_deg.get(b, 0.25)) ** 2 / 3] * 3))
                      for b, d in zip(self.bodies, self.perm)]
            stop = self.binding.observe(states, self.identity)
            if self.t_ns % TEL_NS == 0:
                for k, n in enumerate(self.names):
                    if n not in self.silent:
                        self.tel[n][0].append(self.t_ns)
                        self.tel[n][1].append([0.0, 0.0, 0.0, 0.0, -r[k]])  # FRD: yaw rate right is -z FLU
            if self.binding.due(self.t_ns):
                tel = {n: (np.array(ts, np.int64), np.array(v).reshape(-1, 5)) for n, (ts, v) in self.tel.items()}
                more, made = self.binding.evaluate(self.t_ns, tel, None, self.ekf_positions())
                stop += more
                self.made += [(self.t_ns, b, v) for b, v in made]
                if self.identity is not None:  # the bridge tells the identity book (IdentityBook.bind)
                    self.identity.update({b: "tracked-by-continuity" for b, _ in made})
            self.stopped += [(self.t_ns, v) for v in stop]

    def ekf_positions(self) -> dict | None:
        """Each vehicle's LOCAL_POSITION_NED as its autopilot sends it: its drone's true position plus its EKF's
        error, in NED (N = x, E = -y, D = -z) turned by the yaw offset (heading of world +x), written out here."""
        if self.ekf_error is None:
            return None
        c, s = math.cos(math.radians(self.yaw_offset_deg)), math.sin(math.radians(self.yaw_offset_deg))
        out = {}
        for k, n in enumerate(self.names):
            x, y, z = self.positions[k] + self.ekf_error.get(n, np.zeros(3))
            north, east = x, -y
            out[n] = (self.t_ns, (c * north - s * east, s * north + c * east, -z))
        return out

    def truth_vehicle(self, body: str) -> str:
        return self.names[self.perm[self.bodies.index(body)]]


def hand_yaw(start_s: float, turn_deg: float = 45.0, span_s: float = 1.0):
    """A yaw by hand: a sine-squared rate bump turning turn_deg in span_s from start_s (rad/s)."""
    peak = math.radians(turn_deg) * 2 / span_s

    def rate(t: float) -> float:
        u = (t - start_s) / span_s
        return peak * math.sin(math.pi * u) ** 2 if 0 <= u <= 1 else 0.0

    return rate


def test_still_vehicles_are_not_bound_and_say_why():
    f = Fleet()
    f.step(3.0)
    assert f.made == []
    for v in f.names:
        st = f.binding.vehicles[v]
        assert st.state == UNRESOLVED and st.body is None
        assert "no motion yet" in st.reason
    assert all(f.binding.vehicle_of(b) is None for b in f.bodies)


def test_a_yaw_by_hand_binds_the_moved_body_to_its_vehicle_only():
    f = Fleet()
    f.rates[0] = hand_yaw(2.0)  # drone 0 (optical quad2) is turned by hand from t = 2 s
    f.step(4.0)
    assert [(b, v) for _, b, v in f.made] == [("quad2", "v0")]
    t_bind = f.made[0][0] * 1e-9
    assert 2.0 < t_bind <= 3.0  # within a second of the first motion
    assert f.binding.vehicle_of("quad2") == "v0"
    assert f.binding.vehicles["v0"].state == BOUND
    # the two still ones: unresolved between themselves, and nothing goes to them
    for v in ("v1", "v2"):
        assert f.binding.vehicles[v].state == UNRESOLVED
        assert "two candidates" in f.binding.vehicles[v].reason
    # then the others, one at a time: each to its own vehicle
    f.rates[1] = hand_yaw(4.5)
    f.step(2.0)
    assert {b: v for _, b, v in f.made} == {b: f.truth_vehicle(b) for b in f.bodies}


def test_a_loss_drops_the_binding_at_once_and_it_is_made_again():
    f = Fleet()
    f.rates[0] = hand_yaw(1.0, 90.0, 4.0)
    f.step(2.5)
    assert f.binding.vehicle_of("quad2") == "v0"
    f.lost.add("quad2")
    f.step(0.01)
    assert f.stopped[-1] == (f.t_ns, "v0")
    assert f.binding.vehicle_of("quad2") is None
    assert "track lost" in f.binding.vehicles["v0"].reason
    f.lost.clear()
    t_back = f.t_ns
    f.step(1.5)
    assert f.made[-1][1:] == ("quad2", "v0")
    assert (f.made[-1][0] - t_back) * 1e-9 <= 1.0


def test_a_binding_that_disagrees_stops_first_then_binds_again():
    f = Fleet()
    f.rates[0] = hand_yaw(1.0, 360.0, 8.0)
    f.rates[1] = hand_yaw(1.0, -360.0, 8.0)
    f.step(2.5)
    assert f.binding.vehicle_of("quad2") == "v0" and f.binding.vehicle_of("quad3") == "v1"
    f.perm = [2, 1, 0]  # the tracks of drones 0 and 1 swap unnoticed by the tracker
    f.step(1.0)
    stops = [v for _, v in f.stopped]
    assert "v0" in stops and "v1" in stops
    assert f.binding.disagreements >= 1
    first_stop = min(t for t, v in f.stopped if v in ("v0", "v1"))
    rebound = [(t, b, v) for t, b, v in f.made if t >= first_stop]
    assert all(f.truth_vehicle(b) == v for _, b, v in rebound)  # never the wrong one
    f.step(1.0)
    assert f.binding.vehicle_of("quad3") == "v0" and f.binding.vehicle_of("quad2") == "v1"
    assert f.binding.vehicles["v0"].state == BOUND


@pytest.mark.parametrize("sigma_deg", [1.0, 0.25])
def test_optical_rates_that_err_while_the_attitude_is_uncertain_do_not_stop_a_right_binding(sigma_deg):
    # fleet20's crossing: markers of two bodies merge in some cameras, the body's attitude is less certain
    # (its covariance says so) and its filtered rates err by 1.3 rad/s; the same error with a certain attitude
    # is a disagreement
    f = Fleet()
    f.rates[0] = hand_yaw(1.0, 360.0, 8.0)
    f.step(2.5)
    assert f.binding.vehicle_of("quad2") == "v0"
    f.glitch["quad2"], f.sigma_deg["quad2"] = np.array([1.3, -1.3, 0.0]), sigma_deg
    f.step(0.6)
    f.glitch.clear(), f.sigma_deg.clear()
    f.step(1.0)
    if sigma_deg > 0.25:
        assert f.stopped == [] and f.binding.vehicle_of("quad2") == "v0"
    else:
        assert [v for _, v in f.stopped] == ["v0"]


def test_a_swap_whose_one_side_is_uncertain_stops_both_at_once():
    f = Fleet()
    f.rates[0] = hand_yaw(1.0, 360.0, 8.0)
    f.rates[1] = hand_yaw(1.0, -360.0, 8.0)
    f.step(2.5)
    assert f.binding.vehicle_of("quad2") == "v0" and f.binding.vehicle_of("quad3") == "v1"
    f.perm = [2, 1, 0]  # swapped unnoticed; quad3 (now drone 0) is the one whose optical attitude is uncertain
    f.sigma_deg["quad3"] = 2.0
    f.step(0.3)
    stops = dict((v, t) for t, v in reversed(f.stopped))
    assert set(stops) == {"v0", "v1"} and stops["v0"] == stops["v1"]
    why = f.binding.vehicles["v1"].reason
    assert "binding in doubt: quad2's binding disagreed and quad3's attitude is uncertain" in why


def test_a_disagreeing_binding_says_stopped():
    f = Fleet()
    f.rates[0] = hand_yaw(1.0, 360.0, 8.0)
    f.step(2.5)
    f.perm = [2, 1, 0]  # quad2 now follows the still drone 1
    f.step(0.6)
    st = f.binding.vehicles["v0"]
    assert ("v0" in [v for _, v in f.stopped]) and (st.state in (STOPPED, UNRESOLVED))
    assert f.binding.vehicle_of("quad2") != "v0"


@pytest.mark.parametrize("policy", ["continuity", "stop"])
def test_a_silent_back_channel_turns_the_identity_unknown_and_follows_the_policy(policy):
    f = Fleet(policy=policy)
    f.rates[0] = hand_yaw(1.0, 90.0, 2.0)
    f.step(2.5)
    assert f.binding.vehicle_of("quad2") == "v0"
    f.silent.add("v0")
    f.step(2.5)
    st = f.binding.vehicles["v0"]
    assert st.state == UNKNOWN and "silent" in st.reason
    if policy == "continuity":
        assert f.binding.vehicle_of("quad2") == "v0" and "go on" in st.reason
        f.lost.add("quad2")  # any loss: stopped, and nothing to bind it again with
        f.step(0.5)
        f.lost.clear()
        f.step(2.0)
        assert f.binding.vehicle_of("quad2") is None
    else:
        assert f.binding.vehicle_of("quad2") is None and "stopped" in st.reason


def test_ten_on_the_floor_turned_by_hand_one_at_a_time_the_last_by_elimination():
    perm = [3, 7, 0, 9, 5, 1, 8, 2, 6, 4]  # the tracker's names say nothing about which drone is which
    f = Fleet(perm)
    order = [0, 1, 2, 3, 4, 5, 6, 7, 8]  # drone k turned 30 deg over 1 s at 1.5 k s; drone 9 never moves
    for k in order:
        f.rates[k] = hand_yaw(1.0 + 1.5 * k, 30.0, 1.0)
    f.step(1.0 + 1.5 * len(order) + 1.0)
    assert {b: v for _, b, v in f.made} == {b: f.truth_vehicle(b) for b in f.bodies}
    bound_at = {v: t * 1e-9 for t, _, v in f.made}
    for k in order:  # each within a second of its turn's start
        assert 0 < bound_at[f"v{k}"] - (1.0 + 1.5 * k) <= 1.0
    assert f.binding.binds == 10 and f.stopped == []


class Book:
    """The pipeline's IdentityBook as the bridge reads it: names, state, bind."""

    def __init__(self, names):
        from visionpos.fusion.identity import IdentityState

        self.names, self.state, self.bound = list(names), [IdentityState.ACQUIRED] * len(names), []
        self.S = IdentityState

    def bind(self, b: int) -> bool:
        self.bound.append(self.names[b])
        self.state[b] = self.S.CONTINUITY
        return True


def test_the_bridge_sends_a_fleet_body_to_the_vehicle_it_is_bound_to_only():
    from bridge import Bridge
    from visionpos.benchmarks.factories import body_state
    from visionpos.config.arena import parse_arena

    layout = [[0.1, 0, 0], [0, 0.1, 0], [-0.1, 0, 0], [0, -0.12, 0.02]]
    arena = parse_arena({"bodies": [{"name": "quadA", "id": 1, "markers": layout},
                                    {"name": "quadB", "id": 2, "markers": layout}],
                         "vehicles": [{"body": "quadA", "endpoint": "udpout:127.0.0.1:9"},
                                      {"body": "quadB", "endpoint": "udpout:127.0.0.1:10"}]}, "fleet-test.yaml")
    clock = [10**12]
    bridge = Bridge(arena, {"clock_ns": lambda: clock[0], "report_interval_s": 0, "pose_stream": False})
    book = Book(["quadA", "quadB"])
    bridge.use_identity(book)
    v_a, v_b = bridge.vehicle("quadA"), bridge.vehicle("quadB")
    turn = hand_yaw(1.0, 45.0, 1.0)  # quadA is vehicle quadB's drone: its autopilot turns, quadA's body too
    yaw = 0.0
    for i in range(250):
        clock[0] += STEP_NS
        t = (clock[0] - 10**12) * 1e-9
        r = turn(t)
        yaw += r * STEP_NS * 1e-9
        if i % 2 == 0:
            for v, rate in ((v_b, r), (v_a, 0.0)):
                v.bc.att.add(clock[0], (0.0, 0.0, 0.0, 0.0, -rate))
                v.bc.clock_offsets.add(clock[0], (0,))
        q = Rotation.from_euler("z", yaw).as_quat()
        bridge.publish([body_state("quadA", 1, capture_ns=clock[0], quaternion=q, angular_velocity=(0, 0, r)),
                        body_state("quadB", 2, capture_ns=clock[0])])
        if i == 50:
            assert v_a._slot is None and v_b._slot is None  # unbound: nothing offered
            assert "no motion yet" in bridge.health()["quadA"]["identity_reason"]
            assert "identity unresolved" in bridge.status_line()
            # a vision-gap warning says why nothing goes: its identity, not "the body is not tracked"
            assert v_a.not_sent_why.startswith("identity unresolved: no motion yet"), v_a.not_sent_why
    assert book.bound == ["quadA", "quadB"]  # quadA by its turn, then quadB by elimination
    assert v_b._slot.name == "quadA" and v_a._slot.name == "quadB"
    assert bridge.stats()["vehicles"]["quadB"]["bound_body"] == "quadA"
    book.state[0] = book.S.LOST  # its track breaks: its vehicle stops at once, its mailbox emptied
    v_b._slot = None
    bridge.publish([body_state("quadA", 1, capture_ns=clock[0] + STEP_NS, tracked=False),
                    body_state("quadB", 2, capture_ns=clock[0] + STEP_NS)])
    assert v_b._slot is None and bridge.health()["quadB"]["identity_binding"] == "unresolved"
    assert "track lost" in bridge.health()["quadB"]["identity_reason"]
    assert v_b.not_sent_why.startswith("identity unresolved: track lost"), v_b.not_sent_why
    assert v_a._slot.name == "quadB"


def test_silent_backchannel_is_checked():
    from bridge.config import parse_vehicles
    from visionpos.benchmarks.factories import arena_with_vehicles
    from visionpos.config.arena import ConfigError

    with pytest.raises(ConfigError, match=r"vehicles\[0\]\.silent_backchannel"):
        parse_vehicles(arena_with_vehicles([{"body": "body1", "endpoint": "udpout:127.0.0.1:9",
                                             "silent_backchannel": "sometimes"}]))


def test_the_server_hands_the_identity_book_to_its_outputs():
    from visionpos.server.service import FusionServer, load_config_with_overrides
    from visionpos.server.sinks import Sink

    class Pipeline:
        identity = object()

    class Out(Sink):
        got = None

        def use_identity(self, book):
            self.got = book

    out = Out()
    arena = load_config_with_overrides("thesis", ["server.insecure=true"])
    FusionServer(arena, sinks=[out], pipeline=Pipeline())
    assert out.got is Pipeline.identity


def test_another_body_starts_the_vehicles_own_identity_check_afresh():
    from bridge.backchannel import Backchannel
    from bridge.config import parse_vehicles
    from visionpos.benchmarks.factories import arena_with_vehicles

    cfg = parse_vehicles(arena_with_vehicles([{"body": "body1", "endpoint": "udpout:127.0.0.1:9"}]))[0]
    bc = Backchannel(cfg, lambda: 0, None, lambda m: True, lambda *a: None)
    for k in range(5):
        bc.on_optical(k * 10**7, 0.1, 0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    bc.identity_tripped, bc.identity = True, "mismatch"  # tripped against the body it got until now
    bc.optical_epoch += 1  # the bridge bound it to another body
    bc.on_optical(10**8, 0.0, 0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    assert len(bc.opt) == 1 and not bc.identity_tripped and bc.identity == "unknown"


def _climb(t: np.ndarray, start_s: float, height_m: float = 1.0, span_s: float = 1.5):
    """A vertical take-off at start_s: height (T,) m and vertical acceleration (T,) m/s^2 of a septic step (rest
    to rest in span_s)."""
    u = np.clip((t - start_s) / span_s, 0.0, 1.0)
    z = height_m * u**4 * (35 - 84 * u + 70 * u**2 - 20 * u**3)
    a = height_m * 420 * u**2 * (1 - u) ** 2 * (1 - 2 * u) / span_s**2
    return z, a


@pytest.mark.parametrize("with_accel", [True, False])
def test_drones_taking_off_in_turn_are_told_apart_by_their_accelerometers(with_accel):
    """Four level drones, no rates: they take off straight up 0.3 s apart. Their accelerometers (a bias each)
    bind each to its own body within 2 s of its lift-off; without them nothing is bound."""
    perm = [2, 0, 3, 1]  # optical body i is drone perm[i]
    bodies, names = [f"quad{i + 1}" for i in range(4)], [f"v{k}" for k in range(4)]
    binding = FleetBinding([bodies], dict(zip(names, bodies)), dict.fromkeys(names, math.radians(3.0)),
                           dict.fromkeys(names, "continuity"))
    rng = np.random.default_rng(5)
    lift_s = [1.0 + 0.3 * k for k in range(4)]
    bias = rng.uniform(-0.3, 0.3, (4, 3))
    t_tel = np.arange(0, 4.0, TEL_NS * 1e-9)
    tel = {n: (np.round(t_tel * 1e9).astype(np.int64), np.zeros((len(t_tel), 5))) for n in names}
    acc = {}
    for k, n in enumerate(names):
        f = np.zeros((len(t_tel), 3)) + bias[k] + rng.normal(0, 0.02, (len(t_tel), 3))
        f[:, 2] -= 9.80665 + _climb(t_tel, lift_s[k])[1]  # FRD: up is -z
        acc[n] = (tel[n][0], f)
    made = {}
    level = np.array([0.0, 0.0, 0.0, 1.0])
    for i in range(1, 400):
        t_ns = i * STEP_NS
        states = [State(b, t_ns, level, rng.normal(0, 0.01, 3),
                        position=np.array([0.5 * d, 0.0, _climb(np.array([t_ns * 1e-9]), lift_s[d])[0][0]])
                        + rng.normal(0, 3e-4, 3)) for b, d in zip(bodies, perm)]
        binding.observe(states, None)
        if binding.due(t_ns):
            upto = {n: (t[t <= t_ns], v[t <= t_ns]) for n, (t, v) in tel.items()}
            a_upto = {n: (t[t <= t_ns], v[t <= t_ns]) for n, (t, v) in acc.items()} if with_accel else None
            for b, v in binding.evaluate(t_ns, upto, a_upto)[1]:
                made[b] = (v, t_ns * 1e-9)
    if not with_accel:
        assert made == {}
        assert all("no motion yet" in binding.vehicles[n].reason for n in names)
        return
    assert {b: v for b, (v, _) in made.items()} == {b: names[d] for b, d in zip(bodies, perm)}
    for b, (v, t) in made.items():
        k = names.index(v)
        assert t - lift_s[k] <= 2.0
        assert t - lift_s[k] > 0 or k == 3  # the last one may be bound by elimination, before it moves


def test_a_binding_dropped_for_disagreeing_is_not_made_again_by_the_same_evaluation():
    """Both held pairs cost 50 under the reject (100), but each body fits the other vehicle at 20: both stop.
    The evaluation's own assignment held them (each body free only to keep its vehicle or none, by a margin of
    50): it must not bind them again; only fresh samples may."""
    from visionpos.analysis.autopilot import assign_identities

    b = FleetBinding([["quadA", "quadB"]], {"v0": "quadA", "v1": "quadB"}, dict.fromkeys(["v0", "v1"], 0.05),
                     dict.fromkeys(["v0", "v1"], "continuity"))
    b.bound = {"quadA": "v0", "quadB": "v1"}
    b.identity = dict.fromkeys(["quadA", "quadB"], "tracked-by-continuity")
    cost = np.array([[50.0, 20.0], [20.0, 50.0]])
    held = np.array([[50.0, np.nan], [np.nan, 50.0]])
    dropped, made = b._apply(["quadA", "quadB"], ["v0", "v1"], cost, 100.0, assign_identities(held, 100.0, 13.8),
                             False, assign_identities(cost, 100.0, 13.8))
    assert sorted(dropped) == ["v0", "v1"] and made == []
    assert b.bound == {} and b.vehicles["v0"].state == STOPPED


def test_the_live_bench_counts_poses_from_another_drones_body_at_each_autopilot():
    from visionpos.app.demo_summary import AutopilotPoses
    from visionpos.benchmarks.fleet_binding import _PosesAtAutopilot

    tally = _PosesAtAutopilot(AutopilotPoses)
    a, b = tally.make(boot_stamps=True), tally.make(boot_stamps=True)
    a.score(0, 10, lambda t: np.zeros((len(t), 3)))  # drone a hovers at the origin, drone b 1 m along x
    b.score(0, 10, lambda t: np.tile([1.0, 0.0, 0.0], (len(t), 1)))
    a.got = [(1, np.array([0.01, 0.0, 0.0])), (2, np.array([0.98, 0.0, 0.0]))]  # the second is b's
    b.got = [(1, np.array([1.0, 0.0, 0.0])), (2, np.array([1.2, 0.0, 0.0]))]  # the second 0.2 m off: not its own
    assert tally.wrong() == (4, 2, [1, 1], 1)


PADS = {"v0": (0.0, 0.0), "v1": (1.0, 0.0), "v2": (2.0, 0.0)}


def test_still_vehicles_standing_on_their_pads_are_bound_before_they_move():
    """vehicles[].pad: drone k stands on v{k}'s pad; each still body is bound to the vehicle whose pad it stands on
    (within 10 cm), none by elimination or by motion."""
    f = Fleet(pads=PADS, positions=[(0.03, -0.04, 0.02), (1.0, 0.05, 0.0), (1.95, 0.0, 0.01)])
    f.step(1.5)
    assert {b: v for _, b, v in f.made} == {b: f.truth_vehicle(b) for b in f.bodies}
    for v in f.names:
        st = f.binding.vehicles[v]
        assert st.state == BOUND and "standing on its pad" in st.reason
    assert f.stopped == []


def test_a_body_off_its_pad_or_in_the_air_is_not_bound_by_the_pad():
    # drone 1 stands 12 cm from its pad, drone 2 is held 0.5 m up above its pad: only drone 0 is bound
    f = Fleet(pads=PADS, positions=[(0.0, 0.0, 0.0), (1.12, 0.0, 0.0), (2.0, 0.0, 0.5)])
    f.step(1.5)
    assert [(b, v) for _, b, v in f.made] == [("quad2", "v0")]
    assert f.binding.vehicles["v1"].state == UNRESOLVED and "no motion yet" in f.binding.vehicles["v1"].reason


def test_drones_parked_on_each_others_pads_are_stopped_at_their_first_motion_and_bound_right():
    """Drones 0 and 1 parked on each other's pads: the pads bind them wrongly; the first motion (drone 0 turned)
    stops both bindings within a second and binds them by motion, each to its own vehicle."""
    f = Fleet(pads=PADS, positions=[(1.0, 0.0, 0.0), (0.0, 0.0, 0.0), (2.0, 0.0, 0.0)])
    f.step(1.5)
    wrong = {b: v for _, b, v in f.made}
    assert wrong["quad2"] == "v1" and wrong["quad3"] == "v0"  # quad2 is drone 0, on v1's pad
    f.rates[0] = hand_yaw(2.0, 90.0, 2.0)
    f.step(2.0)
    stops = [(t * 1e-9, v) for t, v in f.stopped]
    assert {"v0", "v1"} <= {v for _, v in stops} and max(t for t, _ in stops) <= 3.0
    assert f.binding.vehicles["v2"].state == BOUND and not any(v == "v2" for _, v in stops)
    f.step(2.0)
    assert f.binding.vehicle_of("quad2") == "v0" and f.binding.vehicle_of("quad3") == "v1"
    # their pads were wrong: no pad binds them again (a lost track is bound by motion only), v2's still does
    assert f.binding.pad_refuted == {"v0", "v1"}
    f.lost.update(["quad2", "quad3"])
    f.step(0.3)
    f.lost.clear()
    f.rates[0] = lambda t: 0.0
    f.step(1.5)
    assert f.binding.vehicle_of("quad2") is None and f.binding.vehicle_of("quad3") is None


def test_pads_closer_than_twice_the_radius_are_refused():
    from bridge.config import parse_vehicles
    from bridge.fleet_binding import PAD_RADIUS_M
    from visionpos.benchmarks.factories import arena_with_vehicles
    from visionpos.config.arena import ConfigError

    assert PAD_RADIUS_M == 0.10  # the docs' "within 10 cm"
    vs = [{"body": "body1", "sysid": 1, "endpoint": "udpout:127.0.0.1:14551", "pad": [0.0, 0.0]},
          {"body": "body2", "sysid": 2, "endpoint": "udpout:127.0.0.1:14552", "pad": [0.15, 0.0]}]
    with pytest.raises(ConfigError, match=r"vehicles\[1\]\.pad.*at least 0.2 m apart"):
        parse_vehicles(arena_with_vehicles(vs))
    vs[1]["pad"] = [0.25, 0.0]
    assert [v.pad for v in parse_vehicles(arena_with_vehicles(vs))] == [(0.0, 0.0), (0.25, 0.0)]


def test_a_vehicle_bound_again_to_another_body_gets_a_reset():
    """A re-binding to another optical body (a drone on the wrong pad, found at its first motion) jumps the
    poses: the reset counter tells the autopilot's EKF to take the new position, not to reject it."""
    from bridge import Bridge
    from visionpos.benchmarks.factories import body_state
    from visionpos.config.arena import parse_arena

    layout = [[0.1, 0, 0], [0, 0.1, 0], [-0.1, 0, 0], [0, -0.12, 0.02]]
    arena = parse_arena({"bodies": [{"name": "quadA", "id": 1, "markers": layout},
                                    {"name": "quadB", "id": 2, "markers": layout}],
                         "vehicles": [{"body": "quadA", "endpoint": "udpout:127.0.0.1:9"},
                                      {"body": "quadB", "endpoint": "udpout:127.0.0.1:10"}]}, "fleet-test.yaml")
    bridge = Bridge(arena, {"report_interval_s": 0, "pose_stream": False})
    results = iter([([], [("quadB", "quadA")]), (["quadA"], []), ([], [("quadB", "quadA")]),
                    (["quadA"], []), ([], [("quadA", "quadA")])])
    bridge.fleet.due = lambda now: True
    bridge.fleet.evaluate = lambda now, tel, acc=None, pos=None: next(results)
    v = bridge.vehicle("quadA")
    resets = []
    for _ in range(5):
        bridge.publish([body_state("quadA", 1), body_state("quadB", 2)])
        resets.append(v.local_resets)
    # bound to quadB, dropped, bound to quadB again (the same body: no reset), dropped, bound to quadA: a reset
    assert resets == [0, 0, 0, 0, 1]


def test_the_docs_say_what_a_pad_does():
    from pathlib import Path

    from bridge.fleet_binding import PAD_MAX_HEIGHT_M, PAD_RADIUS_M

    doc = " ".join((Path(__file__).resolve().parents[2] / "docs" / "autopilot-setup.md").read_text().split())
    assert (f"standing within {PAD_RADIUS_M * 100:.0f} cm of the pad (horizontally, below {PAD_MAX_HEIGHT_M:g} m, "
            "on no other vehicle's pad)") in doc
    assert f"Pads closer than {2 * PAD_RADIUS_M:g} m are refused at start" in doc
    assert "increments the pose's reset counter" in doc  # test_a_vehicle_bound_again_to_another_body_gets_a_reset


def test_an_armed_vehicle_moving_on_an_unconfirmed_pad_binding_gets_nothing_until_its_motion_confirms_it():
    """Once armed and moving (its own IMU or rates), a vehicle bound only by its pad is held: an EKF fed another
    drone's still pose through its climb learns a wrong climb (measured with ArduPilot SITL: a fly-away). On the
    ground, or once its motion confirmed the binding, its body's states go to it."""
    from bridge import Bridge
    from bridge.fleet_binding import VehicleIdentity
    from visionpos.benchmarks.factories import body_state
    from visionpos.config.arena import parse_arena
    from visionpos.fusion.identity import IdentityState

    layout = [[0.1, 0, 0], [0, 0.1, 0], [-0.1, 0, 0], [0, -0.12, 0.02]]
    arena = parse_arena({"bodies": [{"name": "quadA", "id": 1, "markers": layout},
                                    {"name": "quadB", "id": 2, "markers": layout}],
                         "vehicles": [{"body": "quadA", "endpoint": "udpout:127.0.0.1:9", "pad": [0, 0]},
                                      {"body": "quadB", "endpoint": "udpout:127.0.0.1:10", "pad": [1, 0]}]},
                        "fleet-test.yaml")
    bridge = Bridge(arena, {"report_interval_s": 0, "pose_stream": False})
    fleet, v = bridge.fleet, bridge.vehicle("quadA")
    fleet.due = lambda now: False
    fleet.bound["quadA"] = "quadA"
    fleet.identity["quadA"] = IdentityState.CONTINUITY.value  # as a binding made by evaluate leaves it
    fleet.vehicles["quadA"] = VehicleIdentity(BOUND, "bound to quadA: standing on its pad", "quadA", on_pad=True)

    def offered(armed: bool, accel_z: float) -> bool:
        v._slot = None
        v.bc.armed = armed
        v.bc.accel.add(v.bc.accel.last_t() + 1 if v.bc.accel.d else 1, (0.0, 0.0, -accel_z))
        bridge.publish([body_state("quadA", 1), body_state("quadB", 2)])
        return v._slot is not None

    assert offered(False, 9.81)  # on the ground, disarmed: the pad's binding feeds it
    assert offered(True, 9.81)  # armed, still: still fed (ArduPilot arms only on fresh vision)
    assert not offered(True, 12.5)  # it climbs: held, and said why
    assert v.held_unconfirmed == 1 and "until its motion confirms it" in v.not_sent_why
    assert not offered(True, 9.81)  # a steady climb still holds until the binding is confirmed
    fleet.vehicles["quadA"] = VehicleIdentity(BOUND, "bound to quadA: on its pad, confirmed by its motion", "quadA")
    assert offered(True, 9.81)


def test_the_docs_say_when_a_pad_binding_is_held():
    from pathlib import Path

    from bridge.backchannel import MOTION_ACCEL_M_S2, MOTION_RATE_RAD_S, MOTION_SAMPLES

    doc = " ".join((Path(__file__).resolve().parents[2] / "docs" / "autopilot-setup.md").read_text().split())
    assert (f"specific force more than {MOTION_ACCEL_M_S2:g} m/s^2 off 1 g, or a body rate over "
            f"{MOTION_RATE_RAD_S:g} rad/s, in its newest {MOTION_SAMPLES} samples") in doc
    assert '"held: it moves on its pad\'s binding, until its motion confirms it"' in doc


ROW_IN_AIR = [(0.0, -1.2, 1.0), (0.0, 0.0, 1.0), (0.0, 1.2, 1.0)]


def _bound_hovering_row(**kw) -> Fleet:
    """Three identical drones hovering 1.2 m apart, each bound by a yaw (the last by elimination), then still."""
    f = Fleet(positions=ROW_IN_AIR, **kw)
    f.rates[0], f.rates[1] = hand_yaw(1.0), hand_yaw(2.5)
    f.step(4.5)
    assert {b: v for _, b, v in f.made} == {b: f.truth_vehicle(b) for b in f.bodies}
    return f


def _stall(f: Fleet) -> int:
    """Every track lost for 50 ms at once (a host stall), then tracked again; returns when they came back."""
    f.lost.update(f.bodies)
    f.step(0.05)
    assert sorted(v for _, v in f.stopped[-3:]) == f.names and all(f.binding.vehicle_of(b) is None for b in f.bodies)
    f.lost.clear()
    return f.t_ns


@pytest.mark.parametrize("yaw_offset_deg", [0.0, 30.0])
def test_hovering_drones_lost_at_once_are_bound_again_where_their_own_ekfs_say_they_are(yaw_offset_deg):
    """After a loss of every track, still drones give no motion to bind by: each is bound again to the body
    reacquired where its own EKF (LOCAL_POSITION_NED, in its vision frame) says it is, within 1 s."""
    f = _bound_hovering_row(yaw_offset_deg=yaw_offset_deg)
    f.ekf_error = {"v0": np.array([0.08, 0.0, 0.0]), "v1": np.array([0.0, -0.05, 0.03])}  # dead reckoning's drift
    back = _stall(f)
    n_made = len(f.made)
    f.step(1.0)
    again = f.made[n_made:]
    assert {b: v for _, b, v in again} == {b: f.truth_vehicle(b) for b in f.bodies}
    assert all((t - back) * 1e-9 <= 1.0 for t, _, _ in again)
    for v in f.names:
        st = f.binding.vehicles[v]
        assert st.state == BOUND and "from where its EKF says it is" in st.reason, st.reason


def test_without_positions_still_drones_stay_unbound_after_a_loss():
    """The same stall where the autopilots send no position: nothing binds still drones again (the case the
    positions are for)."""
    f = _bound_hovering_row()
    _stall(f)
    n_made = len(f.made)
    f.step(2.0)
    assert f.made[n_made:] == []


@pytest.mark.parametrize("case", ["drifted", "another body near", "another vehicle near", "lost long ago"])
def test_a_position_that_could_be_another_drones_binds_nothing(case):
    """Where the vehicle says it is must pick one body, and nothing else may be near: an EKF drifted 0.2 m, a
    body of the layout 0.4 m from it, another vehicle saying it is 0.4 m from the body, or a loss 3.5 s ago."""
    f = _bound_hovering_row()
    f.ekf_error = {}
    if case == "drifted":
        f.ekf_error["v1"] = np.array([0.2, 0.0, 0.0])
    elif case == "another body near":
        f.positions[2] = np.array([0.0, 0.4, 1.0])  # drone 2 hovers 0.4 m from drone 1
    elif case == "another vehicle near":
        f.ekf_error["v2"] = np.array([0.0, -0.8, 0.0])  # v2 says it is 0.4 m from drone 1
    _stall(f)
    if case == "lost long ago":
        f.ekf_error = None  # no positions until 3.5 s after the loss
        f.step(3.5)
        f.ekf_error = {}
    n_made = len(f.made)
    f.step(1.0)
    # v1 is not bound by its position (with the other two bound by theirs, it may be by elimination: rightly)
    assert "EKF says" not in f.binding.vehicles["v1"].reason
    assert all(v == f.truth_vehicle(b) for _, b, v in f.made[n_made:])
    if case != "drifted":
        assert f.binding.vehicles["v1"].state == UNRESOLVED


def test_the_docs_say_when_a_vehicle_is_bound_again_by_its_position():
    from pathlib import Path

    from bridge import position_binding as P

    doc = " ".join((Path(__file__).resolve().parents[2] / "docs" / "autopilot-setup.md").read_text().split())
    assert (f"a vehicle whose binding a track loss dropped at most {P.REBIND_WITHIN_NS * 1e-9:g} s ago is bound again "
            f"to the one body reacquired within {P.NEAR_M:g} m of its LOCAL_POSITION_NED (at most "
            f"{P.POSITION_STALE_NS * 1e-9:g} s old") in doc
    assert (f"no other body of its layout is within {P.CLEAR_M:g} m of that position and no other vehicle says it is "
            f"within {P.CLEAR_M:g} m of that body") in doc
    assert "binding dropped, binding again when it moves or where its EKF says it is" in doc


def test_a_track_lost_and_acquired_between_two_ticks_is_a_loss_too():
    """The identity book may mark a track lost and acquire it again within one tick: the bridge then sees it go
    from tracked-by-continuity to acquired. That drops the binding as a loss, and the position binds it again."""
    f = _bound_hovering_row()
    f.ekf_error = {}
    f.identity = {b: "tracked-by-continuity" for b in f.bodies}
    f.step(0.05)
    f.identity = {b: "unresolved: acquired" for b in f.bodies}
    n_made, n_stopped = len(f.made), len(f.stopped)
    f.step(1.0)
    assert sorted(v for _, v in f.stopped[n_stopped:]) == f.names
    assert {b: v for _, b, v in f.made[n_made:]} == {b: f.truth_vehicle(b) for b in f.bodies}
    assert all("from where its EKF says it is" in f.binding.vehicles[v].reason for v in f.names)


def test_a_binding_dropped_for_an_ambiguity_is_not_made_again_by_position():
    """Two vehicles lost, bound again by their motion, then dropped for an ambiguous encounter: their earlier
    losses do not let their positions bind them (the drones were close); still, they stay unresolved."""
    f = _bound_hovering_row()
    f.ekf_error = {}
    f.binding._lost_ns.update(v0=f.t_ns, v1=f.t_ns)  # as if lost just before their motion bound them
    f.identity = {b: "tracked-by-continuity" for b in f.bodies}
    f.step(0.05)
    pair = [f.bodies[f.perm.index(k)] for k in (0, 1)]
    f.identity.update(dict.fromkeys(pair, "unresolved: two candidates"))
    f.step(0.05)
    assert all(f.binding.vehicle_of(b) is None for b in pair)
    n_made = len(f.made)
    f.step(1.0)
    assert [v for _, _, v in f.made[n_made:]] == []
    assert all("EKF says" not in f.binding.vehicles[v].reason for v in ("v0", "v1"))
