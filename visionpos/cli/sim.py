"""`visionpos sim`: simulate a scenario and write a recording (visionpos.sim.write)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from visionpos.errors import UsageError
from visionpos.sim.write import write_recording


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default="thesis",
                   help="arena with a sim section: thesis, arena8, fleet (10 identical quads), fleet20 or a YAML "
                        "path (default thesis)")
    p.add_argument("--session", default=None,
                   help="entry of sim.sessions to run (e.g. flight, hover, wand, ground; fleet)")
    p.add_argument("--duration", type=float, default=None, help="seconds to simulate (default sim.duration)")
    p.add_argument("--seed", type=int, default=None, help="random seed (default sim.seed)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config key, e.g. sim.centroid_noise_px=0.5 (repeatable)")
    p.add_argument("--key", default=None,
                   help="HMAC key (text) to sign packets with, as stations configured with one do")
    p.add_argument("--frame-truth", action="store_true", help="also record every frame's blob labels and true pixels")
    p.add_argument("--out", required=True, help="MCAP file to write")


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if out.parent and not out.parent.exists():
        raise UsageError(f"--out {out}: folder {out.parent} does not exist")
    rec = write_recording(args.scenario, out, duration_s=args.duration, seed=args.seed, session=args.session,
                          overrides=args.set, key=args.key.encode() if args.key else None,
                          frame_truth=args.frame_truth)
    sc = rec.scenario
    print(f"wrote {out}: {sc.duration_s:g} s of '{sc.session}' on {rec.config_path.name} (seed {sc.seed}) "
          f"in {rec.wall_s:.1f} s")
    print(f"bodies: {', '.join(b.name + ('' if b.tracked else ' (prop)') for b in sc.bodies)}")
    print(f"{'camera':>8} {'fps':>6} {'frames':>7} {'blobs':>8} {'per frame':>9} {'spurious':>8}")
    for t in sc.timings:
        c = rec.per_camera[t.camera_id]
        per = c["blobs"] / max(c["frames"], 1)
        print(f"{t.camera_id:>8} {t.fps:>6g} {c['frames']:>7} {c['blobs']:>8} {per:>9.2f} {c['spurious']:>8}")
    total_f = sum(c["frames"] for c in rec.per_camera.values())
    total_b = sum(c["blobs"] for c in rec.per_camera.values())
    print(f"{'total':>8} {'':>6} {total_f:>7} {total_b:>8}")
    sys.stdout.flush()
    return 0
