"""The fleet's binding measured on the fleet scenario, offline: `python -m visionpos.benchmarks.fleet_binding [S]`.

The scenario is simulated and replayed through the pipeline (fusion_replay.replay: arrival order, 100 Hz ticks),
and the bridge's binding (bridge/fleet_binding.py) runs on the ticks as the Bridge runs it: each tick's states
and the IdentityBook's states, an evaluation every BIND_EVERY_NS, IdentityBook.bind for each new binding.
Vehicle k is drone k of the scenario (as in `visionpos demo`, whose fake autopilots play their own drone's
truth): its back-channel is that drone's true roll, pitch and body rates, and its accelerometer's specific force
(FRD) with ACCEL_NOISE_M_S2 of noise and a bias of up to ACCEL_BIAS_M_S2 per axis, at TELEMETRY_HZ,
TELEMETRY_LAG_NS late (`--no-accel`: without the accelerations, as before they were used). No network and no
real time: the figures are the binding's own, on the pipeline's real tracks, identity states and losses (a
real-time demo needs the cores to keep 10 cameras at 120 Hz).

Counted: poses that would go to the wrong vehicle (a bound body's pose nearer another drone's truth than its
vehicle's own, or over WRONG_M from it); per vehicle the time from its first motion (a speed over MOVING_M_S or
a body rate over MOVING_RAD_S: its lift-off), and from its first rotation, to its first binding; every dropped
binding of a flying drone and how long until it is bound again.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from bridge.fleet_binding import FleetBinding, optical_attitude
from visionpos.fusion.identity import IdentityState

TELEMETRY_HZ = 50.0
TELEMETRY_LAG_NS = 5_000_000  # the autopilot's message reaches the server this late
WRONG_M = 0.1
MOVING_RAD_S = 0.05  # the first rotation: a body rate over this
MOVING_M_S = 0.02  # the first motion: a speed over this (or the first rotation)
LIFT_M = 0.01
ACCEL_NOISE_M_S2 = 0.02  # the accelerometer's white noise per sample
ACCEL_BIAS_M_S2 = 0.3  # its bias, drawn per vehicle and axis in +-this


LOSS_S = 0.2  # an injected loss: the body untracked this long
SWAP = ("quad1", "quad9")
LIVE_POLL_S = 0.5  # an injected swap: two drones of different cells that fly apart in the huddle leg


def measure(duration_s: float | None = None, scenario: str = "fleet", loss_at_s: tuple[float, ...] = (),
            swap_at_s: float | None = None, use_accel: bool = True, swap: tuple[str, str] = SWAP,
            laps: int = 1) -> dict:
    """The figures (module docstring). loss_at_s: scenario times at which quad3's track is taken away for LOSS_S
    (the bridge sees it untracked, then reacquired); swap_at_s: from then on the states of the SWAP bodies are
    exchanged while the identity book still says continuous (a swap the tracker did not notice); swap: which
    two bodies; laps: the fleet's legs flown this many times (sim/fleet.py), to the last landing unless
    duration_s says otherwise."""
    from visionpos.benchmarks.fusion_replay import replay
    from visionpos.sim import load_scenario, simulate
    from visionpos.sim.fleet import fleet_schedule

    sets = [f"sim.duration={duration_s}"] if duration_s else []
    if laps > 1:
        one = load_scenario(scenario, ["sim.duration=0.1"])
        sets = [f"sim.sessions.{one.session}.{b.name}.laps={laps}" for b in one.bodies] + (sets or [
            f"sim.duration={fleet_schedule(len(one.bodies), laps)['landed'] + 0.5}"])
    sc = load_scenario(scenario, sets)
    sim = simulate(sc)
    names = [b.name for b in sc.bodies]
    vehicles = [f"v{k}" for k in range(len(names))]  # vehicle k flies drone k
    binding = FleetBinding([names], dict(zip(vehicles, names)), dict.fromkeys(vehicles, np.radians(3.0)),
                           dict.fromkeys(vehicles, "continuity"))
    tel_t = np.arange(sc.start_ns, sc.end_ns + 1, int(1e9 / TELEMETRY_HZ), dtype=np.int64)
    tel, acc = {}, {}
    rng = np.random.default_rng(28)
    for k, n in enumerate(names):
        m = sc.motion_at(n, tel_t)
        tel[vehicles[k]] = (tel_t + TELEMETRY_LAG_NS, optical_attitude(m.quaternions, m.angular_velocities))
        f = specific_force_frd(sc, n, tel_t) + rng.uniform(-ACCEL_BIAS_M_S2, ACCEL_BIAS_M_S2, 3)
        acc[vehicles[k]] = (tel_t + TELEMETRY_LAG_NS, f + rng.normal(0.0, ACCEL_NOISE_M_S2, f.shape))
    holder: dict = {}
    log: list[tuple[int, dict[str, str]]] = []  # (tick, bound) after each tick
    sent = {v: [] for v in vehicles}  # (tick ns, position) of every pose a vehicle would get

    injected = {"lost": False}

    def tick_cb(t_ns: int, states) -> None:
        book = holder["pipe"].identity
        identity = {n: s.value for n, s in zip(book.names, book.state)}
        states = _inject(sc, t_ns, list(states), identity, loss_at_s, swap_at_s, swap, injected)
        binding.observe(states, identity)
        if binding.due(t_ns):
            upto = {v: (tt[tt <= t_ns], vals[tt <= t_ns]) for v, (tt, vals) in tel.items()}
            acc_upto = {v: (tt[tt <= t_ns], vals[tt <= t_ns]) for v, (tt, vals) in acc.items()} if use_accel else None
            _, made = binding.evaluate(t_ns, upto, acc_upto)
            for body, _v in made:
                book.bind(book.names.index(body))
                injected["lost"] = injected["lost"] and body != "quad3"
        for st in states:
            v = binding.vehicle_of(st.name)
            if v is not None and st.tracked:
                sent[v].append((t_ns, np.asarray(st.position, float)))
        log.append((t_ns, dict(binding.bound)))

    rep = replay(sc.arena, sim.frames, raw_cb=lambda p: holder.setdefault("pipe", p), tick_cb=tick_cb)
    return _figures(sc, names, vehicles, sent, log, rep)


def specific_force_frd(sc, name: str, times_ns: np.ndarray) -> np.ndarray:
    """What a perfect accelerometer on the drone reads at server times (T,) ns: (T, 3) m/s^2 FRD (its true
    acceleration with gravity added, in the body)."""
    from scipy.spatial.transform import Rotation

    from visionpos.geometry.frames import GRAVITY_M_S2

    traj = sc.body(name).trajectory
    t = (np.asarray(times_ns, np.int64) - np.int64(sc.start_ns)).astype(np.float64) * 1e-9
    a = traj.kinematics(t)[2] + np.array([0.0, 0.0, GRAVITY_M_S2])
    return Rotation.from_quat(sc.motion_at(name, times_ns).quaternions).inv().apply(a) * np.array([1.0, -1.0, -1.0])


def _inject(sc, t_ns: int, states: list, identity: dict, loss_at_s, swap_at_s, swap, injected) -> list:
    """The injected loss and swap (measure's docstring): states and identity changed in place of the tick's."""
    import dataclasses

    t = (t_ns - sc.start_ns) * 1e-9
    if any(a <= t < a + LOSS_S for a in loss_at_s):
        injected["lost"] = True
        states = [dataclasses.replace(s, tracked=False) if s.name == "quad3" else s for s in states]
        identity["quad3"] = IdentityState.LOST.value
    elif injected["lost"]:  # reacquired: not continuous until bound again
        identity["quad3"] = IdentityState.ACQUIRED.value
    if swap_at_s is not None and t >= swap_at_s:
        by = {s.name: s for s in states}
        a, b = swap
        if a in by and b in by:
            states = [dataclasses.replace(by[b], name=a) if s.name == a else
                      dataclasses.replace(by[a], name=b) if s.name == b else s for s in states]
    return states


def _figures(sc, names, vehicles, sent, log, rep) -> dict:
    wrong, total = 0, 0
    for k, v in enumerate(vehicles):
        if not sent[v]:
            continue
        t = np.array([s[0] for s in sent[v]], np.int64)
        p = np.array([s[1] for s in sent[v]])
        d = np.stack([np.linalg.norm(p - sc.truth_at(n, t)[0], axis=1) for n in names])
        total += len(t)
        wrong += int(np.sum((np.argmin(d, axis=0) != k) | (d[k] > WRONG_M)))
    ts = rep.times_ns
    rows = []
    for k, (n, v) in enumerate(zip(names, vehicles)):
        m = sc.motion_at(n, ts)
        rotating = np.linalg.norm(m.angular_velocities, axis=1) > MOVING_RAD_S
        rot = ts[np.argmax(rotating)]
        moved = ts[np.argmax(rotating | (np.linalg.norm(m.velocities, axis=1) > MOVING_M_S))]
        lift = ts[np.argmax(m.positions[:, 2] > m.positions[0, 2] + LIFT_M)]
        first = next((t for t, b in log if v in b.values()), None)
        drops = []
        was, since = False, 0
        for t, b in log:
            on = v in b.values()
            if was and not on:
                since = t
            if on and not was and since:
                drops.append(((since - sc.start_ns) * 1e-9, (t - since) * 1e-9))
            was = on
        rows.append({"vehicle": v, "drone": n, "lift_off_s": (lift - sc.start_ns) * 1e-9,
                     "first_rotation_s": (rot - sc.start_ns) * 1e-9, "first_motion_s": (moved - sc.start_ns) * 1e-9,
                     "bound_after_motion_s": None if first is None else (first - moved) * 1e-9,
                     "bound_after_rotation_s": None if first is None else (first - rot) * 1e-9,
                     "bound_after_lift_off_s": None if first is None else (first - lift) * 1e-9,
                     "rebinds": drops, "final": binding_state(log, v)})
    book = rep.pipeline.identity
    return {"poses": total, "wrong_vehicle": wrong, "rows": rows, "ambiguities": book.swaps_suspected,
            "identity_end": [s.value for s in book.state], "continuity": IdentityState.CONTINUITY.value}


class _PosesAtAutopilot:
    """Every pose a fake autopilot of the live demo received inside its scored window, with the truths of all
    its fleet (the demo's AutopilotPoses, keeping (stamp ns, position m world) too: measure_live)."""

    def __init__(self, base: type) -> None:
        self.base, self.tallies = base, []
        self.details: list[tuple[int, int, float, float]] = []  # wrong poses: (vehicle, stamp ns, m off its own
        # drone, m off the nearest other)

    def make(self, *args, **kwargs):
        outer = self

        class Tally(self.base):
            def __init__(self, *a, **k) -> None:
                super().__init__(*a, **k)
                self.got: list[tuple[int, np.ndarray]] = []
                outer.tallies.append(self)

            def on_pose(self, r) -> None:
                super().on_pose(r)
                if self._window is None or not self.boot_stamps:
                    return
                from bridge.fake_autopilot import decode_pose

                pose = decode_pose(r)
                stamp_ns = int(pose["usec"]) * 1000
                if self._window[0] <= stamp_ns <= self._window[1]:
                    self.got.append((stamp_ns, np.asarray(pose["position_ned"], float) * np.array([1.0, -1.0, -1.0])))

        return Tally(*args, **kwargs)

    def wrong(self) -> tuple[int, int, list[int], int]:
        """(poses scored, poses nearer another drone's truth than the vehicle's own or over WRONG_M from it, per
        vehicle the wrong ones, of them the ones nearer another drone's truth)."""
        truths = [t._truth for t in self.tallies if t._truth is not None]
        total, per, nearer = 0, [], 0
        for k, t in enumerate(x for x in self.tallies if x._truth is not None):
            if not t.got:
                per.append(0)
                continue
            ts = np.array([g[0] for g in t.got], np.int64)
            p = np.array([g[1] for g in t.got])
            d = np.stack([np.linalg.norm(p - f(ts), axis=1) for f in truths])
            total += len(ts)
            bad = (np.argmin(d, axis=0) != k) | (d[k] > WRONG_M)
            per.append(int(np.sum(bad)))
            others = np.delete(d, k, axis=0).min(axis=0) if len(d) > 1 else np.full(len(ts), np.inf)
            self.details += [(k, int(ts[i]), float(d[k, i]), float(others[i])) for i in np.nonzero(bad)[0]]
            nearer += int(np.sum(np.argmin(d, axis=0) != k))
        return total, sum(per), per, nearer


def measure_live(duration_s: float | None = None, fps: float = 30.0, scenario: str = "fleet",
                 cameras: int | None = None) -> dict:
    """The goal's own place, in real time: `visionpos demo --scenario SCENARIO` with every camera at `fps`
    (`--set cameras.N.fps=FPS`: this host's cores cannot fuse ten cameras at 120 Hz in real time) and one fake
    autopilot per vehicle playing its own drone's truth as its telemetry (bridge/fake_autopilot.py); at each
    autopilot, the poses it received that came from another drone's body (nearer another drone's truth than
    its own at the pose's stamp, or over WRONG_M from its own); cameras: only the scenario's first this many
    (None: all). Returns those counts with the server's shed
    frames and late ticks, the output rate, per vehicle how long it was bound (the bridge's binding sampled every
    LIVE_POLL_S) and its binding at the end."""
    import asyncio
    import tempfile

    import yaml

    from visionpos.app import demo
    from visionpos.config.arena import load_yaml, resolve_config_path

    data = load_yaml(resolve_config_path(scenario))
    data["cameras"] = data["cameras"][:cameras]
    for c in data["cameras"]:
        c["fps"] = fps
    duration = duration_s or float(data["sim"]["duration"])
    with tempfile.TemporaryDirectory() as tmp:
        path = f"{tmp}/{scenario}.yaml"
        with open(path, "w") as f:
            yaml.safe_dump(data, f, sort_keys=False)
        arena = demo.demo_arena(path, duration, None, [])
    tally = _PosesAtAutopilot(demo.AutopilotPoses)
    seen: dict[str, dict] = {}  # vehicle: the bridge's binding, sampled every LIVE_POLL_S
    bound_s: dict[str, float] = {}  # vehicle: seconds of the run it was bound

    async def watch(ctx) -> None:
        t0 = time.monotonic()
        while time.monotonic() - t0 < duration:
            for v in ctx.bridge.vehicles:
                seen[v.cfg.name] = ctx.bridge.identity(v.cfg.name)
                if seen[v.cfg.name].get("identity_binding") == "bound":
                    bound_s[v.cfg.name] = bound_s.get(v.cfg.name, 0.0) + LIVE_POLL_S
            await asyncio.sleep(LIVE_POLL_S)

    demo.AutopilotPoses = tally.make  # read-only: the summary's tallies, each also keeping its poses
    try:
        summary = asyncio.run(demo.run_demo(arena, duration, None, during=watch))
    finally:
        demo.AutopilotPoses = tally.base
    total, wrong, per, nearer = tally.wrong()
    return {"fps": fps, "cameras": len(arena.cameras), "duration_s": summary["duration_s"], "poses": total,
            "wrong_vehicle": wrong, "wrong_per_vehicle": per, "nearer_another_drone": nearer,
            "frames_shed": summary["server"]["frames_shed"],
            "frames_accepted": summary["server"]["frames_accepted"], "late_ticks": summary["late_ticks"],
            "output_rate_hz": summary["output_rate_hz"], "kernels": summary["kernels"],
            "tick_cost_max_ms": summary["server"]["tick_cost_max_ms"],
            "binding": seen, "bound_s": bound_s, "wrong_poses": tally.details[:50],
            "mavlink_messages": {b["name"]: b.get("mavlink_messages") for b in summary["bodies"]}}


def binding_state(log, v: str) -> str | None:
    """The body vehicle v is bound to at the end, or None."""
    return next((b for b, x in log[-1][1].items() if x == v), None) if log else None


def _main(argv: list[str]) -> None:
    flags = [a for a in argv if a.startswith("--")]
    args = [float(a) for a in argv if not a.startswith("--")]
    if "--live" in flags:
        # python -m visionpos.benchmarks.fleet_binding --live [DURATION [FPS [CAMERAS]]] (0: the scenario's)
        out = measure_live(args[0] if args and args[0] else None, args[1] if len(args) > 1 else 30.0,
                           cameras=int(args[2]) if len(args) > 2 and args[2] else None)
        print(f"live demo, {out['cameras']} cameras at {out['fps']:g} Hz, {out['duration_s']:.1f} s: poses at the "
              f"autopilots {out['poses']}, wrong {out['wrong_vehicle']} {out['wrong_per_vehicle']} (nearer another "
              f"drone {out['nearer_another_drone']}); "
              f"frames shed {out['frames_shed']} of {out['frames_accepted']} accepted, late ticks {out['late_ticks']}, "
              f"output {out['output_rate_hz']:.0f} Hz; kernels {out['kernels']}")
        for name, b in out["binding"].items():
            print(f"{name}: bound {out['bound_s'].get(name, 0.0):.1f} s; at the end {b.get('identity_binding')} "
                  f"({b.get('identity_reason')})")
        return
    # python -m visionpos.benchmarks.fleet_binding [--no-accel] [--fleet20] [--laps=N]
    #     [DURATION [SWAP_AT [LOSS_AT ...]]] (0: none)
    # --laps=N: the fleet's crossings flown N times (29 laps of the fleet: 10 minutes)
    laps = next((int(f.split("=", 1)[1]) for f in flags if f.startswith("--laps=")), 1)
    out = measure(args[0] if args and args[0] else None, "fleet20" if "--fleet20" in flags else "fleet",
                  tuple(args[2:]), args[1] if len(args) > 1 and args[1] else None, use_accel="--no-accel" not in flags,
                  laps=laps)
    print(f"poses to vehicles {out['poses']}, to the wrong vehicle {out['wrong_vehicle']}; "
          f"ambiguities {out['ambiguities']}")
    for r in out["rows"]:
        rm, ra = r["bound_after_motion_s"], r["bound_after_rotation_s"]
        when = "never" if rm is None else f"{rm:.2f} s after it ({ra:.2f} s after its first rotation)"
        print(f"{r['vehicle']} ({r['drone']}): first motion {r['first_motion_s']:.2f} s, first rotation "
              f"{r['first_rotation_s']:.2f} s, bound {when}; re-binds (at s, after s) "
              f"{[(round(a, 2), round(b, 2)) for a, b in r['rebinds']]}; at the end {r['final']}")
    done = [r["bound_after_motion_s"] for r in out["rows"]]
    print("first motion to binding: worst " + ("never" if None in done else f"{max(done):.2f} s"))


if __name__ == "__main__":
    _main(sys.argv[1:])
