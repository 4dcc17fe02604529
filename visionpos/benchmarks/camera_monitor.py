"""Continuous calibration benchmarks (issue 30.1): a knocked camera is flagged, left out and corrected while
tracking goes on.

    visionpos bench --only camera_monitor [--quick]

The thesis arena's test flight (0.5 m square at 0.8 m), simulated; at 5 s camera 2 is knocked (its true pose
turns by 0.5, 2 or 5 deg, or its centre moves by 5 cm) while the arena file keeps the old pose. The fusion
pipeline runs with the camera monitor as the server runs it (benchmarks.fusion_replay.replay: the monitor fed
each frame and each tick's states, its exclusion and corrections applied), on the simulated clock. Measured
per knock: seconds from the knock to the flag (the camera left out of the fusion from then on), to its first
correction and to "agrees again" (corrected and back in the fusion); the pose the pipeline is left with against
the camera's true one (deg, and px: RMS over a 1 m cube around the flight); the largest position error between
the knock and the flag (how far the one wrong camera pushed the pose before it was excluded) against the largest
before the knock; the position RMS / max over the 10 s from the knock. A flight without a knock (60 s, 30 s with
--quick) must flag no camera. Two cameras knocked at once (2 by 2 deg, 3 by 1 deg): both must be found and
corrected.

Goals (issue 30), over the worst knock: flagged within 3 s, corrected (agrees again) within 10 s, the pose left
within 0.3 px of the truth (the calibration's own accuracy: the wand calibration's 0.27 px RMS on real data), no
other camera flagged, no camera flagged when none moved.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos.benchmarks import BenchResult

BUMP_AT_S = 5.0
AFTER_S = 11.0  # the flight goes on this long after the knock
CAMERA = 2
# name -> (label, the knock's override)
KNOCKS = {
    "rot0p5": ("0.5 deg", "bump_rotation_deg=[0.3, 0.4, 0.0]"),
    "rot0p5z": ("0.5 deg about the optical axis", "bump_rotation_deg=[0.0, 0.0, 0.5]"),
    "rot2": ("2 deg", "bump_rotation_deg=[1.2, 1.6, 0.0]"),
    "rot5": ("5 deg", "bump_rotation_deg=[3.0, 4.0, 0.0]"),
    "shift5cm": ("5 cm", "bump_shift_m=[0.03, 0.04, 0.0]"),
}


def _flight(overrides: list[str], duration_s: float, seed: int):
    from visionpos.benchmarks.fusion_replay import replay
    from visionpos.fusion.camera_monitor import CameraMonitor
    from visionpos.sim import load_scenario, simulate

    sc = load_scenario("thesis", overrides, session="flight", duration=duration_s, seed=seed)
    sim = simulate(sc)
    flags: list[tuple[int, int]] = []  # (camera id, flagged at ns): each flag once

    class Watch(CameraMonitor):  # notes when each camera is flagged, on the simulated clock
        def step(self, now_ns):
            out = super().step(now_ns)
            for cid, w in self.cams.items():
                if w.flagged and (cid, w.flagged_since_ns) not in flags:
                    flags.append((cid, w.flagged_since_ns))
            return out

    mon = Watch(sc.arena)
    rep = replay(sc.arena, sim.frames, monitor=mon)
    return sc, rep, mon, flags


def position_errors_mm(sc, rep, a_ns: int, b_ns: int) -> np.ndarray:
    """The tracked outputs' position errors (mm) against the truth over ticks in [a_ns, b_ns)."""
    name = sc.arena.bodies[0].name
    sel = (rep.times_ns >= a_ns) & (rep.times_ns < b_ns) & rep.tracked[name]
    if not sel.any():
        return np.zeros(0)
    p, _ = sc.truth_at(name, rep.times_ns[sel])
    return np.linalg.norm(rep.positions[name][sel] - p, axis=1) * 1e3


def pose_left(used, true, centre_m: np.ndarray, half_m: float = 0.5) -> tuple[float, float]:
    """(deg, px) between the camera the pipeline uses and the true one: the angle between their orientations,
    and the RMS distance of their projections of a 5x5x5 grid over a cube of side 2 half_m around centre_m (the
    points both see)."""
    g = np.linspace(-half_m, half_m, 5)
    X = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3) + centre_m
    a, b = used.project(X), true.project(X)
    ok = np.isfinite(a).all(1) & np.isfinite(b).all(1) & used.model.in_image(a) & true.model.in_image(b)
    px = float(np.sqrt(np.mean(np.sum((a[ok] - b[ok]) ** 2, axis=1)))) if ok.any() else float("nan")
    return float(np.degrees(Rotation.from_matrix(used.R @ true.R.T).magnitude())), px


def knock(kind: str, seed: int = 3) -> dict[str, float]:
    """One knock of camera CAMERA at BUMP_AT_S: the figures of the module docstring (s from the knock, inf: never)."""
    _, override = KNOCKS[kind]
    sc, rep, mon, flags = _flight([f"sim.cameras.{CAMERA}.bump_at_s={BUMP_AT_S}",
                                   f"sim.cameras.{CAMERA}.{override}"], BUMP_AT_S + AFTER_S, seed=seed)
    bump_ns = sc.start_ns + sc.bumps[CAMERA][0]
    w = mon.cams[CAMERA]
    mine = [t for c, t in flags if c == CAMERA and t >= bump_ns]
    flag_ns = mine[0] if mine else None
    fixed = [a["time_ns"] for a in w.applied if a["time_ns"] >= bump_ns]
    agreed = w.agreed_again_ns if w.agreed_again_ns is not None and not w.flagged else None
    name = sc.arena.bodies[0].name
    ok = rep.tracked[name]
    centre = sc.truth_at(name, rep.times_ns[ok])[0].mean(axis=0)
    deg, px = pose_left(rep.pipeline.cameras[CAMERA], sc.bumps[CAMERA][1], centre)
    before = position_errors_mm(sc, rep, sc.start_ns + int(1e9), bump_ns)
    push = position_errors_mm(sc, rep, bump_ns, flag_ns if flag_ns is not None else rep.times_ns[-1] + 1)
    after = position_errors_mm(sc, rep, bump_ns, bump_ns + int(10e9))

    def s(t):
        return (t - bump_ns) * 1e-9 if t is not None else float("inf")

    return {"flag_s": s(flag_ns), "first_correction_s": s(fixed[0] if fixed else None), "corrected_s": s(agreed),
            "corrections": float(w.corrections),
            "other_cameras_flagged": float(len({c for c, _ in flags if c != CAMERA})),
            "pose_left_deg": deg, "pose_left_px": px,
            "push_max_mm": float(push.max()) if len(push) else 0.0,
            "before_max_mm": float(before.max()), "before_rms_mm": float(np.sqrt(np.mean(before**2))),
            "after_rms_mm": float(np.sqrt(np.mean(after**2))), "after_max_mm": float(after.max()),
            "tracked_after": float(ok[(rep.times_ns >= bump_ns)].mean())}


def two_knocks(seed: int = 3) -> dict[str, float]:
    """Cameras 2 (2 deg) and 3 (1 deg) knocked at the same moment (BUMP_AT_S): the worst of the two's times
    from the knock to the flag and to "agrees again", the worst pose left (px), cameras flagged that did not
    move, and the position RMS / max over the 10 s from the knock."""
    knocks = [f"sim.cameras.2.bump_at_s={BUMP_AT_S}", "sim.cameras.2.bump_rotation_deg=[1.2, 1.6, 0]",
              f"sim.cameras.3.bump_at_s={BUMP_AT_S}", "sim.cameras.3.bump_rotation_deg=[0.6, -0.8, 0]"]
    sc, rep, mon, flags = _flight(knocks, BUMP_AT_S + AFTER_S, seed=seed)
    bump_ns = sc.start_ns + sc.bumps[2][0]
    name = sc.arena.bodies[0].name
    centre = sc.truth_at(name, rep.times_ns[rep.tracked[name]])[0].mean(axis=0)
    out = {"flag_s_max": 0.0, "corrected_s_max": 0.0, "pose_left_px_max": 0.0}
    for cid in (2, 3):
        w = mon.cams[cid]
        mine = [t for c, t in flags if c == cid and t >= bump_ns]
        agreed = w.agreed_again_ns if w.agreed_again_ns is not None and not w.flagged else None
        out["flag_s_max"] = max(out["flag_s_max"], (mine[0] - bump_ns) * 1e-9 if mine else float("inf"))
        out["corrected_s_max"] = max(out["corrected_s_max"],
                                     (agreed - bump_ns) * 1e-9 if agreed is not None else float("inf"))
        out["pose_left_px_max"] = max(out["pose_left_px_max"],
                                      pose_left(rep.pipeline.cameras[cid], sc.bumps[cid][1], centre)[1])
    after = position_errors_mm(sc, rep, bump_ns, bump_ns + int(10e9))
    out.update({"other_cameras_flagged": float(len({c for c, _ in flags if c not in (2, 3)})),
                "after_rms_mm": float(np.sqrt(np.mean(after**2))), "after_max_mm": float(after.max())})
    return out


def run(quick: bool = False) -> BenchResult:
    res = BenchResult()
    rows = ["| knock of camera 2 | flagged (s) | first correction (s) | agrees again (s) | corrections "
            "| other cameras flagged | pose left (deg, px) | max error knock-flag (mm; before the knock) "
            "| 10 s from the knock: RMS / max (mm) | tracked |", "|---|---|---|---|---|---|---|---|---|---|"]
    runs = {}
    for kind, (label, _) in KNOCKS.items():
        runs[kind] = k = knock(kind)
        for key, v in k.items():
            res.metrics[f"monitor_{kind}_{key}"] = v
        rows.append(f"| {label} | {k['flag_s']:.1f} | {k['first_correction_s']:.1f} | {k['corrected_s']:.1f} "
                    f"| {k['corrections']:.0f} | {k['other_cameras_flagged']:.0f} | {k['pose_left_deg']:.3f}, "
                    f"{k['pose_left_px']:.2f} | {k['push_max_mm']:.2f} ({k['before_max_mm']:.2f}) "
                    f"| {k['after_rms_mm']:.2f} / {k['after_max_mm']:.2f} | {100 * k['tracked_after']:.1f} % |")
    for key in ("flag_s", "corrected_s", "pose_left_px", "pose_left_deg", "push_max_mm"):  # the worst knock
        res.metrics[f"monitor_{key}_max"] = float(max(k[key] for k in runs.values()))
    res.metrics["monitor_other_cameras_flagged"] = float(sum(k["other_cameras_flagged"] for k in runs.values()))
    two = two_knocks()
    res.metrics.update({f"monitor_two_{k}": v for k, v in two.items()})
    rows.append(f"| 2 deg and, on camera 3, 1 deg at once | {two['flag_s_max']:.1f} (the later) | - "
                f"| {two['corrected_s_max']:.1f} (the later) | - | {two['other_cameras_flagged']:.0f} "
                f"| -, {two['pose_left_px_max']:.2f} (the worse) | - | {two['after_rms_mm']:.2f} / "
                f"{two['after_max_mm']:.2f} | - |")
    still_s = 30.0 if quick else 60.0
    sc, rep, mon, flags = _flight([], still_s, seed=5)
    res.metrics["monitor_unmoved_flags"] = float(len(flags))
    res.metrics["monitor_unmoved_s"] = still_s
    largest = max((w.last.get("disp_px", 0.0) for w in mon.cams.values()), default=0.0)
    err = position_errors_mm(sc, rep, sc.start_ns + int(1e9), rep.times_ns[-1] + 1)
    rows.append(f"| none, {still_s:.0f} s | - | - | - | {sum(w.corrections for w in mon.cams.values())} "
                f"| {len(flags)} | - | - | {np.sqrt(np.mean(err**2)):.2f} / {err.max():.2f} | - |")
    res.tables[f"Camera monitor: thesis test flight, camera 2 knocked at {BUMP_AT_S:g} s (its arena-file pose "
               "unchanged); times from the knock"] = "\n".join(rows)
    res.notes.append(f"Camera monitor: the unmoved flight's last fitted correction moved a camera's markers by "
                     f"{largest:.2f} px at most (flag threshold camera_monitor.flag_px, default 0.5 px). "
                     "'max error knock-flag' is how far the one wrong camera pushed the pose before it was left "
                     "out of the fusion.")
    return res
