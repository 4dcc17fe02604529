"""`visionpos plan`: coverage and Cramér–Rao bounds of an arena's cameras over a flight volume, and where
one more camera would help most (visionpos.analysis.planner)."""

from __future__ import annotations

import argparse
import json

import numpy as np

from visionpos.errors import UsageError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="arena YAML (cameras with poses and intrinsics, bodies; the room in its `plan:` "
                   "section) or a built-in arena name")
    p.add_argument("--volume", type=float, nargs=6, metavar=("XMIN", "XMAX", "YMIN", "YMAX", "ZMIN", "ZMAX"),
                   help="flight volume in metres, world frame (default: plan.volume, else inside the cameras' "
                        "footprint, shrunk by 20 %%, from 0.1 m to 2/3 of the lowest camera's height)")
    p.add_argument("--step-m", type=float, default=0.25, help="grid step over the volume (m); default 0.25")
    p.add_argument("--noise-px", type=float, default=0.2,
                   help="blob centroid noise per axis (px, 1 sigma); default 0.2 (well-exposed 4-8 px blobs)")
    p.add_argument("--suggest", type=int, default=3, help="how many added-camera positions to print; 0: none")
    p.add_argument("--no-bodies", action="store_true", help="skip the per-body pose bounds (faster)")
    p.add_argument("--out", metavar="DIR", help="write plan.json (every grid point's results) and plan.png (slices "
                   "of camera count and marker bound; needs matplotlib) into DIR")


def run(args: argparse.Namespace) -> int:
    from visionpos.analysis.planner import (
        Volume,
        check_room,
        coverage,
        default_volume,
        parse_plan,
        plot_coverage,
        suggest_camera,
        summary_lines,
    )
    from visionpos.config.arena import load_arena

    if not args.step_m > 0:
        raise UsageError(f"--step-m {args.step_m}: must be > 0")
    if not args.noise_px > 0:
        raise UsageError(f"--noise-px {args.noise_px}: must be > 0")
    arena = load_arena(args.config)
    arena.require_poses("the planner")
    if len(arena.cameras) < 2:
        raise UsageError(f"{arena.source}: the planner needs at least 2 cameras, the file has {len(arena.cameras)}")
    room = parse_plan(arena)
    if args.volume is not None:
        v = np.array(args.volume, float)
        lo, hi = v[0::2], v[1::2]
        if not (hi > lo).all():
            raise UsageError("--volume: give XMIN XMAX YMIN YMAX ZMIN ZMAX with each maximum above its minimum")
        volume = Volume(lo, hi, args.step_m)
        check_room(room, arena.cameras, volume, arena.source, "--volume")
    elif room.volume is not None:
        volume = Volume(room.volume.lo, room.volume.hi, args.step_m)
    else:
        volume = default_volume(arena.cameras, args.step_m)
        if room.given:  # the cameras' footprint may reach past the walls: the room's part of it
            volume = Volume(np.clip(volume.lo, room.lo, room.hi), np.clip(volume.hi, room.lo, room.hi), args.step_m)
    n_points = len(volume.grid())
    if n_points > 20000:
        raise UsageError(f"--volume with --step-m {args.step_m:g} gives {n_points} points; use a coarser step")
    cov = coverage(arena, volume, args.noise_px, with_bodies=not args.no_bodies, obstacles=room.obstacles)
    suggestions = suggest_camera(arena, volume, args.noise_px, args.suggest, room) if args.suggest > 0 else []
    for line in summary_lines(arena, volume, cov, suggestions, args.noise_px, room):
        print(line)
    if args.out:
        from pathlib import Path

        from visionpos.analysis.plots import PlotsUnavailable

        out_dir = Path(args.out)
        out_dir.mkdir(parents=True, exist_ok=True)

        def num(a):
            return [None if not np.isfinite(x) else round(float(x), 6) for x in a]

        out = {"volume": {"lo": volume.lo.tolist(), "hi": volume.hi.tolist(), "step_m": volume.step_m},
               "noise_px": args.noise_px, "points": cov.points.round(4).tolist(), "n_cameras": cov.n_cameras.tolist(),
               "marker_std_mm": num(cov.marker_std_mm),
               "bodies": {k: {"position_std_mm": num(v), "rotation_std_deg": num(cov.body_rotation_std_deg[k])}
                          for k, v in cov.body_position_std_mm.items()},
               "suggestions": [{"position": s.camera.center.round(4).tolist(), "mount": s.mount, "where": s.where,
                                "look_at": (0.5 * (volume.lo + volume.hi)).round(4).tolist(),
                                "seen_by_2": s.seen_by_2, "marker_rms_mm": s.marker_rms_mm} for s in suggestions]}
        (out_dir / "plan.json").write_text(json.dumps(out))
        print(f"wrote {out_dir / 'plan.json'}")
        try:
            plot_coverage(out_dir / "plan.png", arena, volume, cov, suggestions)
            print(f"wrote {out_dir / 'plan.png'}")
        except PlotsUnavailable as e:
            print(f"no plot: {e}")
    return 0
