"""Fusion benchmark: realistic flights (issue 15 item 2).

Two indoor-MAV flights on the thesis arena (sessions `slalom` and `dash`,
visionpos/sim/trajectories.py: up to 2 m/s, 180 deg/s of yaw, the roll/pitch
flicks a multirotor makes to accelerate at several m/s^2), run through
FusionPipeline as the server runs it, against four goals per flight:

- position RMSE <= 1.2 x and rotation RMSE <= 1.0 x the body's single-snapshot
  Cramer-Rao bound along the path. Judged on the pose at its newest frame's
  capture time, the instant the snapshot bound speaks of, made the way the
  MAVLink bridge, VRPN and NatNet make what they send: the output tick's state
  moved back to that time (bridge.convert.pose_at; the bridge stamps each pose
  with its capture time, or a point of its 1/rate_hz grid just before it, so the
  autopilot's EKF, told the latency, fuses it at that instant; VRPN's report
  time and NatNet's CameraMidExposureTimestamp are that capture time). The
  outputs predicted on to the tick (6-8 ms past the newest capture here: 4 ms of
  transport and the tick's phase; what the pose stream sends, its time_ns the
  tick) are reported beside it: their excess is the price of extrapolating the
  motion, which no causal estimator avoids. The bound
  is evaluated at the true pose of every 5th output tick (enough for a smooth
  path) with the cameras that see each marker then (simulator truth); the RMSE
  is a root mean square over ticks, so the bound it is held against is the root
  mean square of the per-tick bounds, sqrt(mean_t trace CRB(t)) (the RMSE an
  efficient estimator of each snapshot alone would have);
- maximum position error <= 4 mm (of the same poses);
- no gap between accepted filter measurements longer than 2 frame periods
  while 2 or more cameras see 3 or more of the body's markers (the output
  stall of issue 15: measurements refused while the body is plainly seen).

Called from benchmarks/fusion.py (`visionpos bench --only fusion`).
"""

from __future__ import annotations

import copy

import numpy as np
from scipy.spatial.transform import Rotation

from bridge.config import IMU_RATE_WITH_FUSION_HZ
from bridge.convert import pose_at
from visionpos.benchmarks import BenchResult

# (session of the thesis arena, what it flies). Issue 15's envelope is 2 m/s and 180 deg/s: slalom and dash fly
# within it and have its goals; dash_sharp tilts twice as fast and has issue 29's only (benchmarks/__init__.py)
FLIGHTS = (
    ("slalom", "weaving along x at 2 m/s, roll reversals of +-34 deg, yaw swinging at up to 180 deg/s"),
    ("dash", "waypoint dashes at 2 m/s, 4.5 m/s^2 reached in 0.35 s (27 deg pitch/roll flicks at up to 174 "
             "deg/s), 180 deg yaw turns at up to 180 deg/s"),
    ("dash_sharp", "beyond the envelope: the dash with 5 m/s^2 reached in 0.2 s (tilting at up to 340 deg/s, "
                   "6000 deg/s^2), issue 29's goals only"),
)
# other fusion settings on the flights and the static body, what each trades (reported, no goals; the
# defaults are the rows above): the defaults before issue 15's per-view updates, with and without the
# angular-acceleration state
ALTERNATIVES = (
    ("pose", "fusion.single_view.mode occlusion (the motion-compensated pose), kalman.angular_jerk_psd 0, "
     "max_noise_scale 10000, gate_retest off: the defaults before",
     {"single_view": {"mode": "occlusion"},
      "kalman": {"angular_jerk_psd": 0.0, "max_noise_scale": 1e4, "gate_retest": False}}),
    ("pose_ang_acc", "fusion.single_view.mode occlusion, the angular-acceleration state as the defaults",
     {"single_view": {"mode": "occlusion"}}),
    ("no_floors", "kalman.tilt_jerk_ms 0 and angular_accel_hold_ms 0: the defaults without the multirotor floors "
     "(before issue 29's)", {"kalman": {"tilt_jerk_ms": 0.0, "angular_accel_hold_ms": 0.0}}),
)
# the fake autopilot's IMU for the IMU rows (issue 29 item 2): a MEMS IMU streamed at 200 Hz (imu_rate_hz's
# default), stamped on the vehicle's clock and delay-corrected (bridge/imu_feed.py), arriving 3 ms after its sample;
# noise per sample and biases drawn per flight from its seed (std per axis)
IMU_FAKE = {"rate_hz": IMU_RATE_WITH_FUSION_HZ, "delay_ms": 3.0, "accel_noise_m_s2": 0.03, "accel_bias_m_s2": 0.1,
            "gyro_noise_rad_s": 0.002, "gyro_bias_rad_s": 0.005}
SKIP_S = 0.5  # acquisition and the filter's first convergence are not judged
CRB_EVERY = 5  # evaluate the bound at every 5th output tick


def seeing_cameras(frames, frame_truth, body_index: int, times_ns: np.ndarray, min_markers: int = 3) -> np.ndarray:
    """How many cameras see at least min_markers markers of body `body_index` at each time (T,).

    A camera sees what its newest frame captured at or before t shows (simulator truth,
    counting each marker blob once), for one frame period after its capture; a dropped
    frame is a camera that does not see.
    """
    per_cam: dict[int, tuple[list[int], list[int]]] = {}
    for f, tr in zip(frames, frame_truth):
        caps, counts = per_cam.setdefault(int(f.camera_id), ([], []))
        caps.append(int(f.capture_ns))
        counts.append(len(set(tr.marker[tr.body == body_index].tolist())))
    out = np.zeros(len(times_ns), dtype=np.int64)
    for caps_l, counts_l in per_cam.values():
        order = np.argsort(caps_l)
        caps, counts = np.asarray(caps_l, np.int64)[order], np.asarray(counts_l)[order]
        period = int(np.median(np.diff(caps))) if len(caps) > 1 else 0
        k = np.searchsorted(caps, times_ns, side="right") - 1
        ok = k >= 0
        kk = np.maximum(k, 0)
        out += ok & (counts[kk] >= min_markers) & (times_ns - caps[kk] < 1.5 * period)
    return out


def longest_stall_ns(accepted_ns: np.ndarray, seen: np.ndarray, times_ns: np.ndarray) -> int:
    """The longest time (ns) without an accepted measurement while `seen` (T,) holds
    continuously on the grid times_ns (T,): at each grid time t where it holds, the time
    since the later of the last accepted measurement and the start of the current stretch."""
    acc = np.sort(np.asarray(accepted_ns, np.int64))
    k = np.searchsorted(acc, times_ns, side="right") - 1
    last = np.where(k >= 0, acc[np.maximum(k, 0)], np.iinfo(np.int64).min)
    worst = 0
    start = None
    for i in range(len(times_ns)):
        if not seen[i]:
            start = None
            continue
        if start is None:
            start = times_ns[i]
        worst = max(worst, int(times_ns[i] - max(last[i], start)))
    return worst


def path_crb(sc, sim, body_name: str, times_ns: np.ndarray) -> tuple[float, float]:
    """RMS over times_ns of the single-snapshot Cramer-Rao bound of the body's pose: position (mm), rotation (deg).

    At each time: the true pose, and which camera sees which marker in its newest frame (simulator truth).
    """
    from visionpos.geometry.triangulation import pose_crb

    b = [x.name for x in sc.bodies].index(body_name)
    body = sc.body(body_name)
    cam_ids = [c.id for c in sc.cameras]
    caps = {c: [] for c in cam_ids}
    seen: dict[int, list[np.ndarray]] = {c: [] for c in cam_ids}
    for f, tr in zip(sim.frames, sim.frame_truth):
        caps[f.camera_id].append(int(f.capture_ns))
        seen[f.camera_id].append(np.unique(tr.marker[tr.body == b]))
    caps_a = {c: np.asarray(v, np.int64) for c, v in caps.items()}
    p_true, q_true = sc.truth_at(body_name, times_ns)
    pos_var, rot_var = [], []
    for t, p, q in zip(times_ns, p_true, q_true):
        visible = np.zeros((len(body.markers), len(cam_ids)), bool)
        for v, c in enumerate(cam_ids):
            k = int(np.searchsorted(caps_a[c], t, side="right")) - 1
            if k >= 0:
                visible[seen[c][k], v] = True
        if (visible.sum(1) >= 2).sum() < 3:
            continue  # no pose from this snapshot: no bound either
        mw = Rotation.from_quat(q).apply(body.markers) + p
        # the bound of the triangulated pose: markers that two or more cameras see
        crb = pose_crb(sc.cameras, mw, p, sc.centroid_noise_px, visible & (visible.sum(1) >= 2)[:, None])
        pos_var.append(np.trace(crb[:3, :3]))
        rot_var.append(np.trace(crb[3:, 3:]))
    return float(np.sqrt(np.mean(pos_var)) * 1e3), float(np.degrees(np.sqrt(np.mean(rot_var))))


def _pose_errors(sc, name: str, times_ns: np.ndarray, positions: np.ndarray,
                 quaternions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (T,) m and rotation (T,) rad errors of poses (T, 3), (T, 4) xyzw against the truth at times_ns (T,)."""
    p_true, q_true = sc.truth_at(name, times_ns)
    dr = (Rotation.from_quat(quaternions) * Rotation.from_quat(q_true).inv()).magnitude()
    return np.linalg.norm(positions - p_true, axis=1), dr


def fake_imu(sc, name: str, seed: int, imu: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """The fake autopilot's IMU over the flight (imu: IMU_FAKE's keys): sample times (N,) ns on the capture
    clock, specific force (N, 3) m/s^2 and rates (N, 3) rad/s in the body's frame (as bridge/imu_feed.py
    hands them to the core), and the drawn biases (FLU)."""
    from bridge.fake_autopilot import imu_from_truth, imu_reading, trajectory_truth
    from bridge.imu_feed import FRD_TO_FLU

    rng = np.random.default_rng(1000 + seed)
    gyro_bias = rng.normal(0.0, imu["gyro_bias_rad_s"], 3)
    accel_bias = rng.normal(0.0, imu["accel_bias_m_s2"], 3)
    t = np.arange(sc.start_ns, sc.end_ns, int(1e9 / imu["rate_hz"]), dtype=np.int64)
    gyro, acc = imu_from_truth(trajectory_truth(sc.body(name).trajectory, sc.start_ns)(t))
    gyro, acc = imu_reading(gyro, acc, gyro_bias, accel_bias, imu["gyro_noise_rad_s"], imu["accel_noise_m_s2"], rng)
    return t, acc * FRD_TO_FLU, gyro * FRD_TO_FLU, {"accel": accel_bias * FRD_TO_FLU, "gyro": gyro_bias * FRD_TO_FLU}


def imu_feeder(sc, name: str, seed: int, imu: dict):
    """fake_imu's samples as replay's feed_cb (each pushed once it arrived, delay_ms after its time), the time
    of the newest one pushed (a function) and the drawn biases."""
    t_imu, acc, gyro, bias = fake_imu(sc, name, seed, imu)
    arrive = t_imu + int(imu["delay_ms"] * 1e6)
    k = [0]

    def feed(pipe, t_ns):
        while k[0] < len(t_imu) and arrive[k[0]] <= t_ns:
            pipe.push_imu(name, int(t_imu[k[0]]), acc[k[0]], gyro[k[0]])
            k[0] += 1

    return feed, lambda: int(t_imu[k[0] - 1]) if k[0] else -(1 << 62), bias


def static_imu_jitter(static: tuple, imu: dict, settings: dict | None = None) -> tuple[float, float]:
    """(raw, output) position jitter (mm per axis) of the static body (static_flight's scenario and simulation)
    with the fake IMU fed (fusion.imu on), as benchmarks.fusion_replay.static_jitter measures it."""
    from visionpos.analysis.metrics import position_jitter
    from visionpos.benchmarks.fusion_replay import replay

    sc, sim = static
    feed, _, _ = imu_feeder(sc, "quad", 1, imu)
    raws: dict[int, tuple] = {}

    def cb(p):
        r = p.last_raw.get(0)
        if r is not None:
            raws[r[0]] = r

    st = {"time_alignment": "motion_compensated", **copy.deepcopy(settings or {}),
          "imu": {"enabled": True, **imu.get("fusion", {})}}
    rep = replay(sc.arena, sim.frames, st, raw_cb=cb, feed_cb=feed)
    t = np.array(sorted(raws))
    t = t[t >= t[0] + 500_000_000]
    P = np.array([raws[k][1] for k in t])
    ok = rep.tracked["quad"] & (rep.times_ns >= t[0])
    return position_jitter(t, P) * 1e3, position_jitter(rep.times_ns[ok], rep.positions["quad"][ok]) * 1e3


def fly(session: str, duration_s: float, seed: int, settings: dict | None = None,
        overrides: list[str] | None = None, imu: dict | None = None, told=None) -> dict[str, float]:
    """One flight of the thesis arena's `session` through the pipeline: errors, bound, stall (see the module).

    settings: fusion settings for the pipeline; overrides: `--set` style changes of the arena file; imu:
    the fake autopilot's IMU (IMU_FAKE) fed to the pipeline as each sample arrives (fusion.imu on); told:
    told(scenario) gives a function called with the pipeline after every frame (told_the_manoeuvre)."""
    from visionpos.benchmarks.fusion_replay import replay
    from visionpos.sim import load_scenario, simulate

    sc = load_scenario("thesis", overrides, session=session, duration=duration_s, seed=seed)
    sim = simulate(sc)
    name = sc.arena.bodies[0].name
    accepted: list[int] = []
    after_frame = told(sc) if told is not None else None

    def watch(pipe):  # after every frame: the reference time of the body's last accepted measurement
        tr = pipe.tracks[0]
        if tr.tracked and (not accepted or tr.last_update_ns != accepted[-1]):
            accepted.append(tr.last_update_ns)
        if after_frame is not None:
            after_frame(pipe)

    sent: list[tuple] = []  # per tracked tick: (tick ns, capture ns, position, quaternion) as MAVLink sends it

    def at_capture(tick_ns, states):
        st = states[0]
        if st.tracked:
            p, q = pose_at(st, st.capture_ns)
            sent.append((tick_ns, st.capture_ns, p, q))

    feed, age_ns = None, []
    if imu is not None:
        settings = {**(settings or {}), "imu": {"enabled": True, **imu.get("fusion", {})}}
        feed, newest_sample_ns, bias = imu_feeder(sc, name, seed, imu)

    def at_tick(tick_ns, states):  # the newest information in the output: frame capture or IMU sample
        at_capture(tick_ns, states)
        if states[0].tracked:
            newest = states[0].capture_ns
            if imu is not None:
                newest = max(newest, newest_sample_ns())
            age_ns.append((tick_ns, tick_ns - newest))

    rep = replay(sc.arena, sim.frames, settings, raw_cb=watch, tick_cb=at_tick, feed_cb=feed)
    t = rep.times_ns
    judged_from_ns = sc.start_ns + int(SKIP_S * 1e9)
    keep = t >= judged_from_ns
    ok = rep.tracked[name] & keep
    dp_tick, dr_tick = _pose_errors(sc, name, t[ok], rep.positions[name][ok], rep.quaternions[name][ok])
    sent = [x for x in sent if x[0] >= judged_from_ns]
    dp, dr = _pose_errors(sc, name, np.array([x[1] for x in sent], np.int64), np.array([x[2] for x in sent]),
                          np.array([x[3] for x in sent]))
    crb_pos_mm, crb_rot_deg = path_crb(sc, sim, name, t[keep][::CRB_EVERY])
    period_ns = int(1e9 / min(c.fps for c in sc.arena.cameras))
    grid = np.arange(judged_from_ns, int(t[-1]), 250_000, dtype=np.int64)
    seen = seeing_cameras(sim.frames, sim.frame_truth, 0, grid) >= 2
    stall_ns = longest_stall_ns(np.asarray(accepted, np.int64), seen, grid)
    ages = np.array([a for tk, a in age_ns if tk >= judged_from_ns], float)
    out = {}
    if imu is not None:
        est = rep.pipeline.imu.bodies[0]
        out = {"accel_bias_err_m_s2": float(np.linalg.norm(est.accel_bias - bias["accel"])),
               "accel_bias_m_s2": float(np.linalg.norm(bias["accel"])),
               "gyro_bias_err_rad_s": float(np.linalg.norm(est.gyro_bias - bias["gyro"])),
               "gyro_bias_rad_s": float(np.linalg.norm(bias["gyro"])),
               "imu_refused": float(est.stats["refused"]), "imu_dropped": float(est.dropped)}
    return out | {
        "newest_age_ms": float(ages.mean() / 1e6) if len(ages) else float("nan"),
        "pos_rmse_mm": float(np.sqrt((dp**2).mean()) * 1e3),
        "rot_rmse_deg": float(np.degrees(np.sqrt((dr**2).mean()))),
        "max_err_mm": float(dp.max() * 1e3),
        "tick_pos_rmse_mm": float(np.sqrt((dp_tick**2).mean()) * 1e3),
        "tick_rot_rmse_deg": float(np.degrees(np.sqrt((dr_tick**2).mean()))),
        "tick_max_err_mm": float(dp_tick.max() * 1e3),
        "crb_pos_mm": crb_pos_mm,
        "crb_rot_deg": crb_rot_deg,
        "max_gap_ms": stall_ns / 1e6,
        "max_gap_periods": stall_ns / period_ns,
        "tracked_fraction": float(ok.sum() / keep.sum()),
        "gated": float(rep.pipeline.stats()["rejected_gate"]),
    }


# the reference told the manoeuvre: the rotation-noise scale after every frame from the simulator's true angular
# jerk j (rad/s^3), its square averaged over TOLD_WINDOW_S around TOLD_LEAD_S past the filter's time, as a white
# angular-jerk density |j|^2 x TOLD_WINDOW_S x k over the floor; the best k of TOLD_GAINS is reported
TOLD_WINDOW_S, TOLD_LEAD_S, TOLD_GAINS = 0.03, 0.005, (0.01, 0.03, 0.1, 0.3)


def told_the_manoeuvre(gain: float):
    """told= for fly(): a function of the scenario giving the after-frame hook that sets body 0's rotation-noise
    scale from the true angular jerk (TOLD_*): a filter that knows when and how hard the vehicle manoeuvres."""

    def make(sc):
        name = sc.arena.bodies[0].name
        step_ns = 1_000_000
        t = np.arange(sc.start_ns, sc.end_ns, step_ns, dtype=np.int64)
        rot = Rotation.from_quat(sc.truth_at(name, t)[1])
        rate = (rot[1:] * rot[:-1].inv()).as_rotvec() / (step_ns * 1e-9)  # world rate at the midpoints
        jerk = np.gradient(np.gradient(rate, step_ns * 1e-9, axis=0), step_ns * 1e-9, axis=0)
        n = max(1, int(round(TOLD_WINDOW_S / (step_ns * 1e-9))))
        jerk2 = np.convolve((jerk**2).sum(1), np.ones(n) / n, mode="same")
        t_mid = t[:-1] + step_ns // 2

        def after_frame(pipe):
            tr = pipe.tracks[0]
            if tr.tracked:
                f = tr.filter
                i = min(int(np.searchsorted(t_mid, f.t_ns + int(TOLD_LEAD_S * 1e9))), len(t_mid) - 1)
                f.scale_r = float(np.clip(gain * jerk2[i] * TOLD_WINDOW_S / f.s.angular_jerk_psd, 1.0, 1e4))

        return after_frame

    return make


def _flights(session: str, dur: float, seeds: list[int], settings: dict | None = None,
             imu: dict | None = None, told=None) -> dict[str, float]:
    """fly() over seeds, combined: RMSEs and bounds as root mean squares, the worst max error, stall and tracking
    (and with imu: the mean age of the newest information, the worst bias errors, the samples refused)."""
    runs = [fly(session, dur, s, copy.deepcopy(settings), imu=imu, told=told) for s in seeds]

    def rms(key):
        return float(np.sqrt(np.mean([r[key] ** 2 for r in runs])))

    m = {
        "pos_rmse_mm": rms("pos_rmse_mm"),
        "rot_rmse_deg": rms("rot_rmse_deg"),
        "tick_pos_rmse_mm": rms("tick_pos_rmse_mm"),
        "tick_rot_rmse_deg": rms("tick_rot_rmse_deg"),
        "crb_pos_mm": rms("crb_pos_mm"),
        "crb_rot_deg": rms("crb_rot_deg"),
        "max_err_mm": max(r["max_err_mm"] for r in runs),
        "tick_max_err_mm": max(r["tick_max_err_mm"] for r in runs),
        "max_gap_periods": max(r["max_gap_periods"] for r in runs),
        "tracked_fraction": min(r["tracked_fraction"] for r in runs),
        "gated": sum(r["gated"] for r in runs),
        "newest_age_ms": float(np.mean([r["newest_age_ms"] for r in runs])),
    }
    if imu is not None:
        for k in ("accel_bias_err_m_s2", "accel_bias_m_s2", "gyro_bias_err_rad_s", "gyro_bias_rad_s"):
            m[k] = max(r[k] for r in runs)
        m["imu_refused"] = sum(r["imu_refused"] for r in runs)
        m["imu_dropped"] = max(r["imu_dropped"] for r in runs)
    m["pos_over_crb"] = m["pos_rmse_mm"] / m["crb_pos_mm"]
    m["rot_over_crb"] = m["rot_rmse_deg"] / m["crb_rot_deg"]
    m["tick_pos_over_crb"] = m["tick_pos_rmse_mm"] / m["crb_pos_mm"]
    m["tick_rot_over_crb"] = m["tick_rot_rmse_deg"] / m["crb_rot_deg"]
    return m


def run_alternatives(quick: bool, res: BenchResult, static: tuple) -> None:
    """The ALTERNATIVES on the slalom, the dash and the static body (static: benchmarks.fusion_replay.static_flight's
    scenario and simulation): metrics fusion_alt_<name>_*."""
    from visionpos.benchmarks.fusion_replay import static_jitter, static_poses

    dur = 4.0 if quick else 10.0
    seeds = [1] if quick else [1, 2]
    sc, sim = static
    tbl = [
        "| settings | slalom position / rotation (x bound) | dash position / rotation (x bound) | the same at the "
        "output ticks | max error (mm) | gated | static body: output jitter / raw |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, what, settings in ALTERNATIVES:
        sl, da = (_flights(s, dur, seeds, settings) for s in ("slalom", "dash"))
        t, P, _, rep = static_poses(sc, sim, {"time_alignment": "motion_compensated", **copy.deepcopy(settings)})
        raw_jit, out_jit = static_jitter(t, P, rep)
        m = {"slalom_pos_over_crb": sl["pos_over_crb"], "slalom_rot_over_crb": sl["rot_over_crb"],
             "dash_pos_over_crb": da["pos_over_crb"], "dash_rot_over_crb": da["rot_over_crb"],
             "slalom_tick_pos_over_crb": sl["tick_pos_over_crb"], "slalom_tick_rot_over_crb": sl["tick_rot_over_crb"],
             "dash_tick_pos_over_crb": da["tick_pos_over_crb"], "dash_tick_rot_over_crb": da["tick_rot_over_crb"],
             "max_err_mm": max(sl["max_err_mm"], da["max_err_mm"]), "gated": sl["gated"] + da["gated"],
             "static_jitter_filtered_over_raw": out_jit / raw_jit}
        for k, v in m.items():
            res.metrics[f"fusion_alt_{name}_{k}"] = v
        tbl.append(f"| {what} | {m['slalom_pos_over_crb']:.2f} / {m['slalom_rot_over_crb']:.2f} | "
                   f"{m['dash_pos_over_crb']:.2f} / {m['dash_rot_over_crb']:.2f} | "
                   f"{m['slalom_tick_pos_over_crb']:.2f} / {m['slalom_tick_rot_over_crb']:.2f}, "
                   f"{m['dash_tick_pos_over_crb']:.2f} / {m['dash_tick_rot_over_crb']:.2f} | {m['max_err_mm']:.2f} | "
                   f"{m['gated']:.0f} | {m['static_jitter_filtered_over_raw']:.2f} |")
    tbl += [
        "",
        "The defaults are the realistic flights' table above and the static body's (jitter / raw goal 0.5). Each "
        "camera frame's markers at its own capture time (the default single_view.mode always) leave out the motion "
        "compensation's error, which the fused pose carries into the filter; the process noise follows the "
        "fused pose's NIS in both.",
    ]
    res.tables[
        f"Fusion: other filter settings on the flights (slalom and dash: {len(seeds)} seed(s) x {dur:.0f} s; "
        "the static body as above)"
    ] = "\n".join(tbl)


def run(quick: bool, res: BenchResult) -> None:
    """The realistic-flights section of the fusion group: metrics fusion_flights_<session>_*, then the
    ALTERNATIVES (fusion_alt_*)."""
    dur = 4.0 if quick else 10.0
    seeds = [1] if quick else [1, 2]
    tbl = [
        "| flight | position RMSE (mm) | bound (mm) | RMSE / bound | rotation RMSE (deg) | bound (deg) "
        "| RMSE / bound | max error (mm) | at the output ticks: position / rotation RMSE / bound, max error (mm) "
        "| longest stall (frame periods) | gated | tracked |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    optical = {}
    for session, what in FLIGHTS:
        m = optical[session] = _flights(session, dur, seeds)
        for k, v in m.items():
            res.metrics[f"fusion_flights_{session}_{k}"] = v
        tbl.append(
            f"| {session}: {what} | {m['pos_rmse_mm']:.2f} | {m['crb_pos_mm']:.2f} | {m['pos_over_crb']:.2f} | "
            f"{m['rot_rmse_deg']:.3f} | {m['crb_rot_deg']:.3f} | {m['rot_over_crb']:.2f} | {m['max_err_mm']:.2f} | "
            f"{m['tick_pos_over_crb']:.2f} / {m['tick_rot_over_crb']:.2f}, {m['tick_max_err_mm']:.2f} | "
            f"{m['max_gap_periods']:.2f} | {m['gated']:.0f} | {100 * m['tracked_fraction']:.1f} % |"
        )
    told = {session: min((_flights(session, dur, seeds, told=told_the_manoeuvre(k))["tick_rot_over_crb"]
                          for k in TOLD_GAINS)) for session, _ in FLIGHTS}
    for session, v in told.items():
        res.metrics[f"fusion_flights_{session}_told_tick_rot_over_crb"] = v
    tbl += [
        "",
        "Reference for the rotation at the output ticks, told the manoeuvre: the same filter with its rotation-noise "
        "scale set after every frame from the simulator's true angular jerk (its square averaged over "
        f"{TOLD_WINDOW_S * 1e3:.0f} ms around {TOLD_LEAD_S * 1e3:.0f} ms ahead, as a white angular-jerk density, "
        f"the best of {len(TOLD_GAINS)} gains): "
        + ", ".join(f"{session} {v:.2f}" for session, v in told.items())
        + " x the bound, against the filter's own in the table: the difference is what finding each manoeuvre in "
        "the frames costs. A reference, not a bound: a filter told more (its angular acceleration too) could do "
        "better.",
        "",
        "Errors: the pose MAVLink, VRPN and NatNet send, stamped with its newest frame's capture time (the output "
        "tick's state moved back to it with the filter's velocities and acceleration), against the truth then; at "
        "the output ticks: the state predicted to the tick (6-8 ms past the newest capture: what the pose stream "
        "sends, its time_ns the tick). "
        "Bound: the single-snapshot Cramer-Rao bound of the pose (0.2 px centroid noise, the cameras that see each "
        "marker) at the true pose of every 5th output tick, root mean square over the path. Longest stall: the "
        "longest time without an accepted filter measurement while 2 or more cameras see 3 or more markers, in "
        "frame periods (10 ms). Gated: measurements the filter's innovation gate refused.",
    ]
    res.tables[
        f"Fusion: realistic flights (thesis arena, 4 cameras at 100 Hz; {len(seeds)} seed(s) x {dur:.0f} s each, "
        f"outputs at 100 Hz vs truth, first {SKIP_S} s not judged)"
    ] = "\n".join(tbl)
    run_imu(quick, res, optical)


IMU_COST_RUNS = 3


def imu_cpu_cost(quick: bool) -> dict[str, float]:
    """What the IMU costs the fusion thread: CPU time (time.thread_time) of the slalom replayed with IMU_FAKE
    fed less without it, per sample the filter used (best of IMU_COST_RUNS each), and the longest bias-window
    fit (ImuInput._fit_window, ms): metrics cpu_us_per_sample, bias_fit_ms."""
    import time

    from visionpos.benchmarks.fusion_replay import replay
    from visionpos.fusion.imu import ImuInput
    from visionpos.sim import load_scenario, simulate

    sc = load_scenario("thesis", None, session="slalom", duration=3.0 if quick else 6.0, seed=1)
    sim = simulate(sc)
    name = sc.arena.bodies[0].name
    fits_ms: list[float] = []
    fit_window = ImuInput._fit_window

    def timed_fit(self):
        t0 = time.thread_time_ns()
        fit_window(self)
        fits_ms.append((time.thread_time_ns() - t0) / 1e6)

    def cpu_s(with_imu: bool) -> tuple[float, int]:
        feed, settings = None, {}
        if with_imu:
            feed, _, _ = imu_feeder(sc, name, 1, IMU_FAKE)
            settings = {"imu": {"enabled": True}}
        t0 = time.thread_time()
        rep = replay(sc.arena, sim.frames, settings, feed_cb=feed)
        return time.thread_time() - t0, rep.pipeline.imu.bodies[0].stats["used"] if with_imu else 0

    off, on, used = [], [], 0
    ImuInput._fit_window = timed_fit
    try:
        for _ in range(IMU_COST_RUNS):
            off.append(cpu_s(False)[0])
            t_on, used = cpu_s(True)
            on.append(t_on)
    finally:
        ImuInput._fit_window = fit_window
    return {"cpu_us_per_sample": (min(on) - min(off)) / max(used, 1) * 1e6, "bias_fit_ms": max(fits_ms)}


def run_imu(quick: bool, res: BenchResult, optical: dict[str, dict[str, float]]) -> None:
    """The flights with the fake autopilot's IMU in the prediction (fusion.imu, IMU_FAKE at the vehicles' default
    imu_rate_hz, 200 Hz, and at 50 Hz, the default telemetry_rate_hz) against without (`optical`: run's metrics
    per session), and the static body's jitter with it: metrics fusion_imu_*."""
    from visionpos.benchmarks.fusion_replay import static_flight

    dur = 4.0 if quick else 10.0
    seeds = [1] if quick else [1, 2]
    tbl = [
        "| flight | IMU | position / rotation RMSE / bound | at the output ticks | max error (mm), at the ticks "
        "| newest information at the ticks (ms) | accelerometer bias error / drawn (m/s^2) | gyro bias error / "
        "drawn (rad/s) | samples refused |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def row(session, label, m, bias):
        tbl.append(f"| {session} | {label} | {m['pos_over_crb']:.2f} / {m['rot_over_crb']:.2f} | "
                   f"{m['tick_pos_over_crb']:.2f} / {m['tick_rot_over_crb']:.2f} | {m['max_err_mm']:.2f}, "
                   f"{m['tick_max_err_mm']:.2f} | {m['newest_age_ms']:.1f} | {bias} |")

    for session, _ in FLIGHTS:
        row(session, "none", optical[session], "- | - | -")
        for rate in (IMU_FAKE["rate_hz"], 50.0):
            m = _flights(session, dur, seeds, imu={**IMU_FAKE, "rate_hz": rate})
            for k, v in m.items():
                res.metrics[f"fusion_imu_{session}_{rate:.0f}hz_{k}"] = v
            row(session, f"{rate:.0f} Hz", m, f"{m['accel_bias_err_m_s2']:.3f} / {m['accel_bias_m_s2']:.3f} | "
                f"{m['gyro_bias_err_rad_s']:.4f} / {m['gyro_bias_rad_s']:.4f} | {m['imu_refused']:.0f}")
    raw_jit, out_jit = static_imu_jitter(static_flight(quick), IMU_FAKE)
    res.metrics["fusion_imu_static_jitter_filtered_over_raw"] = out_jit / raw_jit
    cost = imu_cpu_cost(quick)
    res.metrics.update({f"fusion_imu_{k}": v for k, v in cost.items()})
    tbl += [
        "",
        f"The fake autopilot's IMU (bridge/fake_autopilot.py imu_reading): accelerometer noise "
        f"{IMU_FAKE['accel_noise_m_s2']} m/s^2 per sample and bias drawn with std {IMU_FAKE['accel_bias_m_s2']} "
        f"m/s^2 per axis, gyro noise {IMU_FAKE['gyro_noise_rad_s']} rad/s and bias std {IMU_FAKE['gyro_bias_rad_s']} "
        f"rad/s, each sample arriving {IMU_FAKE['delay_ms']:.0f} ms after its time (delay-corrected). Bias error: the "
        "estimate at the flight's end against the drawn bias (the worst seed). Newest information: the tick less "
        "the newest frame's capture or IMU sample in its output, mean. The static body with the IMU at "
        f"{IMU_FAKE['rate_hz']:.0f} Hz: output jitter / raw {out_jit / raw_jit:.2f}. Cost on the fusion thread "
        f"(CPU time, the slalom replayed with the IMU at {IMU_FAKE['rate_hz']:.0f} Hz less without, best of "
        f"{IMU_COST_RUNS}): {cost['cpu_us_per_sample']:.0f} µs per sample, everything included; of it the bias "
        f"window's fit, once per window: {cost['bias_fit_ms']:.2f} ms (the longest).",
    ]
    res.tables[
        f"Fusion: the vehicle's IMU in the prediction (fusion.imu; thesis arena, {len(seeds)} seed(s) x {dur:.0f} s "
        "each; position and rotation as RMSE / bound)"
    ] = "\n".join(tbl)
