"""Camera planner: how well an arena's cameras see a flight volume, and where one more camera helps most.

Over a grid of the flight volume: how many cameras see a marker (each camera's field of view), the
Cramér–Rao bound of a triangulated marker (geometry/triangulation.py `triangulation_crb`) and of each
body's pose (`pose_crb`, from the markers that two or more cameras see, as the tracker triangulates
them; averaged over yaw, since a drone flies at any heading). Pixel noise is the blob centroid noise
(0.2 px by default: what the detector achieves on well-exposed 4-8 px blobs, docs/benchmarks.md).

The room (`plan:` in the arena file, `Room`): walls, floor and ceiling as a box, obstacles as boxes
that hide what is behind them. The suggestion tries candidate cameras (the arena's first camera's lens)
where a camera can be mounted: on the walls (at the cameras' mean height and under the ceiling), on
the ceiling, and on tripods inside the room outside the flight volume and the obstacles, each aimed at
the volume centre, and ranks them by the fraction of the volume that two or more cameras see, then by
the marker bound over the volume. Without `plan.room` the room is the box around the cameras and the
volume, floor at z = 0. Occlusion by propellers, the body itself or people is not modelled: these are
the bounds of the geometry, which `visionpos bench --only planner` compares with simulated
triangulations.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from visionpos.camera.model import Camera, look_at_rotation
from visionpos.config.arena import ArenaConfig, BodyConfig, ConfigError
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, section
from visionpos.geometry.triangulation import CameraRig, pose_crb, triangulation_crb

YAWS_DEG = (0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0)


@dataclass(frozen=True)
class Volume:
    """An axis-aligned box (m, world frame) and the grid step over it."""

    lo: np.ndarray  # (3,) x, y, z minimum
    hi: np.ndarray  # (3,) maximum
    step_m: float

    def grid(self) -> np.ndarray:
        """(N, 3) grid points, the box's faces included."""
        axes = [np.linspace(a, b, max(2, int(round((b - a) / self.step_m)) + 1)) for a, b in zip(self.lo, self.hi)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _box_spec(path: str, doc: str, *extra: Setting):
    return section(path, doc, *extra,
                   Setting("min_m", "array", doc="the box's minimum corner [x, y, z] (m, world frame)", shape=(3,)),
                   Setting("max_m", "array", doc="the box's maximum corner [x, y, z] (m, world frame)", shape=(3,)))


PLAN = section(
    "plan",
    "The room for `visionpos plan` (analysis/planner.py): where cameras can be mounted and what hides the "
    "volume from them. Boxes are axis-aligned in the world frame.",
    Setting("room", "section", None, "walls, floor and ceiling as one box: suggested cameras sit on its walls, "
            "under its ceiling or on tripods inside it", default_doc="(the box around the cameras and the volume)",
            spec=_box_spec("plan.room", "The room: x and y between its walls, z from floor to ceiling.")),
    Setting("volume", "section", None, "the flight volume (`--volume` wins)", default_doc="(inside the cameras)",
            spec=_box_spec("plan.volume", "The flight volume, inside the room.")),
    Setting("obstacles", "list", [], "boxes that hide what is behind them and where no camera goes (a table, "
            "a pillar, a net's frame)", spec=_box_spec("plan.obstacles[i]", "An obstacle.",
                                                       Setting("name", "text", "", "name in messages"))),
    Setting("mount_offset_m", "number", 0.1, "a camera's centre sits this far from the wall or ceiling it is "
            "mounted on", min=0.0, max=1.0),
    Setting("tripod_height_m", "number", 1.8, "height of a camera on a tripod (m above the floor)",
            min=0.2, max=5.0),
    Setting("tripod_clearance_m", "number", 0.5, "a tripod stays this far outside the flight volume",
            min=0.0, max=5.0),
    Setting("candidate_step_m", "number", 0.5, "spacing of the candidate positions along walls, ceiling "
            "and floor", min=0.05, max=5.0),
    Setting("wall_mounts", "boolean", True, "suggest cameras on the walls"),
    Setting("ceiling_mounts", "boolean", True, "suggest cameras on the ceiling"),
    Setting("tripod_mounts", "boolean", True, "suggest cameras on tripods inside the room"),
)


@dataclass(frozen=True)
class Obstacle:
    name: str
    lo: np.ndarray  # (3,) m
    hi: np.ndarray  # (3,) m
    key: str  # where it is in the arena file, for messages


@dataclass(frozen=True)
class Room:
    """The room the planner mounts cameras in: a box (walls, floor, ceiling) and obstacle boxes."""

    lo: np.ndarray  # (3,) m: the walls at x = lo[0], y = lo[1]; the floor at z = lo[2]
    hi: np.ndarray  # (3,) m: the other walls; the ceiling at z = hi[2]
    obstacles: tuple[Obstacle, ...] = ()
    mount_offset_m: float = 0.1
    tripod_height_m: float = 1.8
    tripod_clearance_m: float = 0.5
    candidate_step_m: float = 0.5
    mounts: tuple[str, ...] = ("wall", "ceiling", "tripod")
    given: bool = True  # False: taken as the box around the cameras and the volume
    volume: "Volume | None" = None  # plan.volume, if given


def _read_box(s, what: str) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = s.array("min_m", (3,)), s.array("max_m", (3,))
    if not (hi > lo).all():
        raise s.error("max_m", f"{what}: every coordinate of max_m must be above min_m's, got min_m "
                      f"{lo.tolist()} and max_m {hi.tolist()}")
    return lo, hi


def parse_plan(arena: ArenaConfig) -> Room:
    """The checked `plan:` section as a Room (room=None in the file: `given` False and the box set by
    `room_around`). ConfigError naming the key: a box with max below min, a volume or a camera outside the
    walls, a camera inside an obstacle."""
    s = PLAN.check(arena.section("plan"))
    v = PLAN.parse(s)
    mounts = tuple(m for m in ("wall", "ceiling", "tripod") if v[f"{m}_mounts"])
    obstacles = []
    for i, o in enumerate(s.items("obstacles")):
        o = PLAN["obstacles"].spec.check(o)
        name = o.string("name", "") or f"obstacles[{i}]"
        obstacles.append(Obstacle(name, *_read_box(o, f"obstacle {name}"), key=f"plan.obstacles[{i}]"))
    volume = None
    if s.data.get("volume") is not None:
        volume = Volume(*_read_box(PLAN["volume"].spec.check(s.sub("volume")), "the flight volume"), 0.25)
    room = Room(np.zeros(3), np.zeros(3), tuple(obstacles), v["mount_offset_m"], v["tripod_height_m"],
                v["tripod_clearance_m"], v["candidate_step_m"], mounts, given=False, volume=volume)
    if s.data.get("room") is not None:
        lo, hi = _read_box(PLAN["room"].spec.check(s.sub("room")), "the room")
        room = Room(lo, hi, **{k: getattr(room, k) for k in ("obstacles", "mount_offset_m", "tripod_height_m",
                                                             "tripod_clearance_m", "candidate_step_m", "mounts",
                                                             "volume")})
        check_room(room, arena.cameras, volume, arena.source, "plan.volume")
    else:
        check_room(room, arena.cameras, None, arena.source, "plan.volume")
    return room


def _inside(p: np.ndarray, lo: np.ndarray, hi: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(N,) bool: points (N, 3) inside the box [lo, hi] grown by margin (m)."""
    return ((p >= lo - margin) & (p <= hi + margin)).all(axis=-1)


def check_room(room: Room, cameras, volume: "Volume | None", source: str, volume_key: str) -> None:
    """ConfigError naming the key where the room contradicts itself: the flight volume reaching outside the
    walls or into an obstacle, a camera outside the walls (by more than 0.5 m: mounts stick out) or inside
    an obstacle. `room.given` False checks only the obstacles."""
    def box(lo, hi):
        return f"x {lo[0]:.2f}..{hi[0]:.2f} y {lo[1]:.2f}..{hi[1]:.2f} z {lo[2]:.2f}..{hi[2]:.2f} m"

    if room.given and volume is not None and not (_inside(volume.lo, room.lo, room.hi, 1e-9)
                                                  and _inside(volume.hi, room.lo, room.hi, 1e-9)):
        raise ConfigError(source, volume_key, f"the flight volume {box(volume.lo, volume.hi)} reaches outside the "
                          f"walls, plan.room is {box(room.lo, room.hi)}; shrink the volume or correct the room")
    for i, c in enumerate(cameras):
        where = f"cameras[{i}].pose.position"
        for o in room.obstacles:
            if _inside(c.center, o.lo, o.hi):
                raise ConfigError(source, where, f"camera {c.name} at {np.round(c.center, 2).tolist()} m is inside "
                                  f"obstacle {o.name} ({o.key}: {box(o.lo, o.hi)}); correct the position or the "
                                  "obstacle")
        if room.given and not _inside(c.center, room.lo, room.hi, 0.5):
            raise ConfigError(source, where, f"camera {c.name} at {np.round(c.center, 2).tolist()} m is outside "
                              f"the walls, plan.room is {box(room.lo, room.hi)}; correct the position or the room")


def room_around(room: Room, cameras, volume: "Volume") -> Room:
    """The room itself if given, else the box around the cameras and the volume (floor at z = 0 or lower):
    cameras are mounted on its walls, so a suggestion stays where the others are."""
    if room.given:
        return room
    C = np.array([c.center for c in cameras])
    lo = np.minimum(C.min(0), volume.lo)
    hi = np.maximum(C.max(0), volume.hi)
    lo[2] = min(lo[2], 0.0)
    return Room(lo, hi, **{k: getattr(room, k) for k in ("obstacles", "mount_offset_m", "tripod_height_m",
                                                         "tripod_clearance_m", "candidate_step_m", "mounts",
                                                         "volume")}, given=False)


register_section("plan", PLAN, parse_plan)


def segment_blocked(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) bool: the segment from a (3,) to each b (N, 3) passes through the box [lo, hi] (slab test)."""
    d = b - a
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - a) / d, (hi - a) / d
    # an axis the segment runs parallel to: inside that slab for all t, or never
    par = np.abs(d) < 1e-12
    inside_slab = (a >= lo) & (a <= hi)
    t_near = np.where(par, np.where(inside_slab, -np.inf, np.inf), np.minimum(t1, t2)).max(axis=1)
    t_far = np.where(par, np.where(inside_slab, np.inf, -np.inf), np.maximum(t1, t2)).min(axis=1)
    return (t_near <= t_far) & (t_far >= 0.0) & (t_near <= 1.0)


def visibility(cameras: list[Camera], points: np.ndarray, obstacles: tuple[Obstacle, ...] = ()) -> np.ndarray:
    """(N, V) bool: each camera's field of view, less the points an obstacle hides from it."""
    vis = np.stack([c.visible(points) for c in cameras], axis=1)
    for v, c in enumerate(cameras):
        for o in obstacles:
            vis[:, v] &= ~segment_blocked(c.center, points, o.lo, o.hi)
    return vis


def default_volume(cameras: tuple[Camera, ...] | list[Camera], step_m: float = 0.25) -> Volume:
    """The box inside the cameras' horizontal footprint (shrunk by 20 % toward its centre) from 0.1 m up to
    two thirds of the lowest camera's height: where a lab flies with wall- or tripod-mounted cameras."""
    C = np.array([c.center for c in cameras])
    mid = 0.5 * (C[:, :2].min(0) + C[:, :2].max(0))
    half = 0.4 * (C[:, :2].max(0) - C[:, :2].min(0))
    top = max(0.5, 2.0 / 3.0 * float(C[:, 2].min()))
    return Volume(np.array([*(mid - half), 0.1]), np.array([*(mid + half), top]), step_m)


@dataclass
class Coverage:
    """Per grid point: cameras seeing it, the marker bound and each body's bounds (NaN where undetermined)."""

    points: np.ndarray  # (N, 3) m
    n_cameras: np.ndarray  # (N,) int
    marker_std_mm: np.ndarray  # (N,) sqrt(trace CRB): the 3-D RMS error of a triangulated marker
    body_position_std_mm: dict[str, np.ndarray] = field(default_factory=dict)  # (N,) 3-D RMS, mean over yaw
    body_rotation_std_deg: dict[str, np.ndarray] = field(default_factory=dict)  # (N,) RMS rotation angle

    def fraction_seen_by(self, k: int) -> float:
        return float(np.mean(self.n_cameras >= k))


def marker_coverage(cameras: list[Camera], points: np.ndarray, sigma_px: float,
                    obstacles: tuple[Obstacle, ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    """(n_cameras (N,), marker_std_mm (N,)) at world points (N, 3); obstacles hide what is behind them."""
    rig = CameraRig(cameras)
    visible = visibility(cameras, points, obstacles)
    crb = triangulation_crb(rig, points, sigma_px, visible)
    return visible.sum(1), np.sqrt(np.trace(crb, axis1=1, axis2=2)) * 1e3


def body_bounds(cameras: list[Camera], body: BodyConfig, origin: np.ndarray, sigma_px: float,
                yaws_deg=YAWS_DEG, obstacles: tuple[Obstacle, ...] = ()) -> tuple[float, float]:
    """(position std mm, rotation std deg) of `body` level at `origin` (3,), the CRB's RMS over the yaws;
    NaN where some yaw leaves the pose undetermined (fewer than 3 markers seen by 2+ cameras)."""
    rig = CameraRig(cameras)
    pos, rot = [], []
    for yaw in np.radians(yaws_deg):
        c, s = np.cos(yaw), np.sin(yaw)
        X = origin + body.markers @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
        visible = visibility(cameras, X, obstacles)
        visible &= (visible.sum(1) >= 2)[:, None]  # the tracker triangulates: single views do not count here
        if visible.any(1).sum() < 3:
            return float("nan"), float("nan")
        C = pose_crb(rig, X, origin, sigma_px, visible)
        pos.append(np.trace(C[:3, :3]))
        rot.append(np.trace(C[3:, 3:]))
    return float(np.sqrt(np.mean(pos)) * 1e3), float(np.degrees(np.sqrt(np.mean(rot))))


def coverage(arena: ArenaConfig, volume: Volume, sigma_px: float = 0.2, with_bodies: bool = True,
             obstacles: tuple[Obstacle, ...] = ()) -> Coverage:
    cams = list(arena.cameras)
    pts = volume.grid()
    n, std = marker_coverage(cams, pts, sigma_px, obstacles)
    cov = Coverage(pts, n, std)
    if with_bodies:
        for b in arena.bodies:
            pb = np.array([body_bounds(cams, b, p, sigma_px, obstacles=obstacles) for p in pts]).reshape(-1, 2)
            cov.body_position_std_mm[b.name] = pb[:, 0]
            cov.body_rotation_std_deg[b.name] = pb[:, 1]
    return cov


@dataclass(frozen=True)
class Suggestion:
    camera: Camera
    seen_by_2: float  # fraction of the volume two or more cameras see, with this camera added
    marker_rms_mm: float  # RMS of the marker bound over the points the current cameras cover (2+), with it
    mount: str = "ring"  # "wall", "ceiling", "tripod" (or "ring": candidate_cameras without a room)
    where: str = ""  # the mount in words ("wall x = 3.00 m")


def _rms(a: np.ndarray) -> float:
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a**2))) if len(a) else float("nan")


def candidate_cameras(cameras: list[Camera], volume: Volume, n_azimuths: int = 16) -> list[Camera]:
    """Cameras with the first camera's lens on a ring around the volume at the cameras' mean height
    (radius: the cameras' mean horizontal distance from the volume centre), aimed at the volume centre.
    Knows no walls: `mount_candidates` is what `suggest_camera` uses."""
    centre = 0.5 * (volume.lo + volume.hi)
    C = np.array([c.center for c in cameras])
    radius = float(np.mean(np.linalg.norm(C[:, :2] - centre[:2], axis=1)))
    height = float(np.mean(C[:, 2]))
    next_id = max(c.id for c in cameras) + 1
    out = []
    for k in range(n_azimuths):
        a = 2 * np.pi * k / n_azimuths
        pos = np.array([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a), height])
        R = look_at_rotation(pos, centre)
        out.append(Camera(next_id, f"suggested{k}", cameras[0].model, R, -R @ pos, cameras[0].fps))
    return out


def _ticks(a: float, b: float, step: float) -> np.ndarray:
    """Positions from a to b (both included) about `step` apart."""
    return np.linspace(a, b, max(2, int(round((b - a) / step)) + 1)) if b > a else np.array([0.5 * (a + b)])


def mount_positions(room: Room, volume: Volume, height_m: float) -> list[tuple[np.ndarray, str, str]]:
    """(position (3,) m, mount, where in words) of every place a camera can go: on the four walls at
    `height_m` and just under the ceiling, on the ceiling, on tripods (room.tripod_height_m) inside the room
    at least tripod_clearance_m outside the flight volume; every one mount_offset_m off its wall or ceiling
    and outside the obstacles (grown by the same offset)."""
    off, step = room.mount_offset_m, room.candidate_step_m
    lo, hi = room.lo + off, room.hi - off
    xs, ys = _ticks(lo[0], hi[0], step), _ticks(lo[1], hi[1], step)
    out: list[tuple[np.ndarray, str, str]] = []
    if "wall" in room.mounts:
        for z in sorted({round(float(np.clip(height_m, room.lo[2] + 0.3, hi[2])), 6), round(float(hi[2]), 6)}):
            for axis, ticks in ((0, ys), (1, xs)):
                for side, wall in ((lo[axis], room.lo[axis]), (hi[axis], room.hi[axis])):
                    for u in ticks:
                        p = np.array([side, u, z]) if axis == 0 else np.array([u, side, z])
                        out.append((p, "wall", f"wall {'xy'[axis]} = {wall:.2f} m"))
    if "ceiling" in room.mounts:
        out += [(np.array([x, y, hi[2]]), "ceiling", f"ceiling z = {room.hi[2]:.2f} m") for x in xs for y in ys]
    if "tripod" in room.mounts and room.lo[2] + room.tripod_height_m <= hi[2]:
        z = room.lo[2] + room.tripod_height_m
        for x in xs:
            for y in ys:
                p = np.array([x, y, z])
                if not _inside(p, volume.lo, volume.hi, room.tripod_clearance_m):
                    out.append((p, "tripod", f"tripod {room.tripod_height_m:.2f} m high"))
    seen: set[tuple[float, ...]] = set()  # a wall's top row is also the ceiling's edge: listed once, as a wall
    kept = []
    for m in out:
        key = tuple(np.round(m[0], 6))
        if key not in seen and not any(_inside(m[0], o.lo, o.hi, off) for o in room.obstacles):
            seen.add(key)
            kept.append(m)
    return kept


def mount_candidates(cameras: list[Camera], room: Room, volume: Volume) -> list[tuple[Camera, str, str]]:
    """(camera, mount, where) at every mount position, the first camera's lens, aimed at the volume centre."""
    centre = 0.5 * (volume.lo + volume.hi)
    height = float(np.mean([c.center[2] for c in cameras]))
    next_id = max(c.id for c in cameras) + 1
    out = []
    for k, (pos, mount, where) in enumerate(mount_positions(room, volume, height)):
        R = look_at_rotation(pos, centre)
        out.append((Camera(next_id, f"suggested{k}", cameras[0].model, R, -R @ pos, cameras[0].fps), mount, where))
    return out


def suggest_camera(arena: ArenaConfig, volume: Volume, sigma_px: float = 0.2, top: int = 3,
                   room: Room | None = None) -> list[Suggestion]:
    """The `top` mountable candidate cameras (`mount_candidates` in `room`, default: the box around the
    cameras and the volume) that most improve the volume's coverage, then its marker bound."""
    cams = list(arena.cameras)
    room = room_around(room or Room(np.zeros(3), np.zeros(3), given=False), cams, volume)
    pts = volume.grid()
    n0, _ = marker_coverage(cams, pts, sigma_px, room.obstacles)
    covered = n0 >= 2
    scored = []
    for cand, mount, where in mount_candidates(cams, room, volume):
        n, std = marker_coverage([*cams, cand], pts, sigma_px, room.obstacles)
        scored.append(Suggestion(cand, float(np.mean(n >= 2)), _rms(std[covered]) if covered.any() else float("nan"),
                                 mount, where))
    scored.sort(key=lambda s: (-round(s.seen_by_2, 3), s.marker_rms_mm))
    return scored[:top]


def summary_lines(arena: ArenaConfig, volume: Volume, cov: Coverage, suggestions: list[Suggestion],
                  sigma_px: float, room: Room | None = None) -> list[str]:
    """The planner's printed report."""
    lines = []
    if room is not None:
        r = room_around(room, arena.cameras, volume)
        lines.append(f"room{'' if r.given else ' (plan.room not given: the box around the cameras and the volume)'}"
                     f": x {r.lo[0]:.2f}..{r.hi[0]:.2f}  y {r.lo[1]:.2f}..{r.hi[1]:.2f}  z {r.lo[2]:.2f}..{r.hi[2]:.2f}"
                     f" m; {len(r.obstacles)} obstacle(s); mounts: {', '.join(r.mounts) or 'none'}")
    lines += [
        f"volume x {volume.lo[0]:.2f}..{volume.hi[0]:.2f}  y {volume.lo[1]:.2f}..{volume.hi[1]:.2f}  "
        f"z {volume.lo[2]:.2f}..{volume.hi[2]:.2f} m, {len(cov.points)} points every {volume.step_m:g} m; "
        f"{len(arena.cameras)} cameras; centroid noise {sigma_px:g} px",
        "cameras seeing a point: " + ", ".join(
            f">={k}: {100 * cov.fraction_seen_by(k):.0f} %" for k in range(1, min(len(arena.cameras), 4) + 1)),
    ]
    ok = np.isfinite(cov.marker_std_mm)
    if ok.any():
        m = cov.marker_std_mm[ok]
        lines.append(f"marker 3-D RMS bound (where 2+ cameras see it): median {np.median(m):.3f} mm, "
                     f"90th percentile {np.percentile(m, 90):.3f} mm, worst {m.max():.3f} mm")
    for name, pos in cov.body_position_std_mm.items():
        rot = cov.body_rotation_std_deg[name]
        good = np.isfinite(pos)
        if good.any():
            lines.append(f"body {name}: pose determined at {100 * good.mean():.0f} % of the volume; position bound "
                         f"median {np.median(pos[good]):.3f} mm (90th pct {np.percentile(pos[good], 90):.3f}), "
                         f"rotation median {np.median(rot[good]):.3f} deg "
                         f"(90th pct {np.percentile(rot[good], 90):.3f})")
        else:
            lines.append(f"body {name}: no point of the volume where 3 of its markers are seen by 2+ cameras")
    base2 = cov.fraction_seen_by(2)
    base_rms = _rms(cov.marker_std_mm)
    centre = 0.5 * (volume.lo + volume.hi)
    if suggestions:
        lines.append("suggestions, each one camera added: the share of the volume 2+ cameras see (now -> with it) "
                     "and the marker 3-D RMS bound's RMS over the points 2+ cameras see now (mm, now -> with it)")
    for i, s in enumerate(suggestions):
        c = s.camera.center
        lines.append(f"suggestion {i + 1}: a camera on the {s.where or s.mount} at ({c[0]:.2f}, {c[1]:.2f}, "
                     f"{c[2]:.2f}) m aimed at the volume centre ({centre[0]:.2f}, {centre[1]:.2f}, {centre[2]:.2f}) "
                     f"m: seen by 2+ {100 * base2:.0f} % -> {100 * s.seen_by_2:.0f} %, marker 3-D RMS bound (RMS "
                     f"over the points 2+ cameras see now) {base_rms:.3f} -> {s.marker_rms_mm:.3f} mm")
    return lines


def plot_coverage(path, arena: ArenaConfig, volume: Volume, cov: Coverage, suggestions: list[Suggestion]) -> None:
    """PNG: for three heights, the number of cameras seeing each point and the marker bound (mm), with the
    cameras (black) and the first suggestion (red) from above."""
    from visionpos.analysis.plots import _pyplot

    plt = _pyplot()
    zs = np.unique(cov.points[:, 2])
    levels = zs[np.unique(np.linspace(0, len(zs) - 1, min(3, len(zs))).round().astype(int))]
    fig, axes = plt.subplots(len(levels), 2, figsize=(10, 4 * len(levels)), squeeze=False)
    C = np.array([c.center for c in arena.cameras] + [s.camera.center for s in suggestions[:1]])
    xs, ys = np.unique(cov.points[:, 0]), np.unique(cov.points[:, 1])
    extent = (xs[0], xs[-1], ys[0], ys[-1])
    for row, z in zip(axes, levels):
        sel = cov.points[:, 2] == z
        count = cov.n_cameras[sel].reshape(len(xs), len(ys)).T
        std = cov.marker_std_mm[sel].reshape(len(xs), len(ys)).T
        for ax, img, title, cmap in ((row[0], count, "cameras seeing", "viridis"),
                                     (row[1], std, "marker bound (mm, 3-D RMS)", "magma")):
            im = ax.imshow(img, origin="lower", extent=extent, cmap=cmap, aspect="equal")
            fig.colorbar(im, ax=ax)
            ax.scatter(C[:len(arena.cameras), 0], C[:len(arena.cameras), 1], c="k", marker="^", label="cameras")
            if suggestions:
                s = suggestions[0].camera.center
                ax.scatter([s[0]], [s[1]], c="r", marker="*", s=120, label="suggested")
            ax.set_title(f"{title} at z = {z:.2f} m")
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
            pad = 0.3
            ax.set_xlim(min(xs[0], C[:, 0].min()) - pad, max(xs[-1], C[:, 0].max()) + pad)
            ax.set_ylim(min(ys[0], C[:, 1].min()) - pad, max(ys[-1], C[:, 1].max()) + pad)
        row[0].legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
