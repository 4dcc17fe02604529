"""`visionpos-station --config station.yaml`: run one camera station."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path

from visionpos.config.arena import ConfigError


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="visionpos-station",
        description="Capture IR frames, detect marker blobs and stream them to the visionpos server "
        "(protocol: docs/protocol.md, set-up: docs/stations.md).",
    )
    p.add_argument("--config", "-c", required=True, help="station YAML file")
    p.add_argument("--check", action="store_true", help="validate the config and open the camera once, then exit")
    p.add_argument("--frames", type=int, default=None, help="stop after this many captured frames")
    p.add_argument("--snapshot", metavar="DIR", default=None,
                   help="save camera frames into DIR for `visionpos calibrate intrinsics --images DIR` instead of "
                        "streaming (the server is not contacted)")
    p.add_argument("--count", type=int, default=30, help="with --snapshot: frames to save (default 30)")
    p.add_argument("--interval-s", type=float, default=1.0,
                   help="with --snapshot: at least this long between saved frames (default 1 s)")
    p.add_argument("--chessboard", metavar="NxM", default=None,
                   help="with --snapshot: keep only frames showing this chessboard (inner corners, OpenCV's pattern "
                        "size) from a new place or angle, and report the image coverage")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    log = logging.getLogger("visionpos.station")
    from stations.agent import StationAgent
    from stations.config import load_station
    from stations.sources import SourceError

    try:
        cfg = load_station(args.config)
    except ConfigError as e:
        print(f"visionpos-station: config error: {e}", file=sys.stderr)
        return 2
    if cfg.key is None:
        log.warning("INSECURE: insecure is true (%s), so packets are neither signed nor checked; anyone on the "
                    "network can pose as this station or its server. Copy the server's key (`visionpos keygen`) "
                    "here and remove `insecure` (docs/security.md)", args.config)
    if args.snapshot is not None:
        return _snapshot(args, cfg)
    try:
        agent = StationAgent(cfg)
    except OSError as e:
        print(f"visionpos-station: cannot reach server {cfg.server_host}:{cfg.server_port}: {e}", file=sys.stderr)
        return 2
    if args.check:
        try:
            agent.source.open()
            img, _ = agent.source.read()
            agent.source.close()
        except (SourceError, ConfigError) as e:
            print(f"visionpos-station: camera check failed: {e}", file=sys.stderr)
            return 1
        print(f"config OK: station {cfg.station_id} camera {cfg.camera_id} -> {cfg.server_host}:{cfg.server_port}, "
              f"source {agent.source.name} {img.shape[1]}x{img.shape[0]}")
        return 0

    def _stop(signum, _frame):
        log.info("signal %d: stopping", signum)
        agent.stop()

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    log.info("station %d camera %d -> %s:%d (%s clock%s)", cfg.station_id, cfg.camera_id, cfg.server_host,
             cfg.server_port, "built-in sync" if cfg.clock_sync else "external PTP/chrony",
             ", HMAC" if cfg.key else "")
    try:
        return agent.run(max_frames=args.frames)
    except ConfigError as e:
        print(f"visionpos-station: config error: {e}", file=sys.stderr)
        return 2


def _snapshot(args, cfg) -> int:
    from stations.snapshot import snapshot
    from stations.sources import SourceError, make_source

    pattern = None
    if args.chessboard is not None:
        try:
            pattern = tuple(int(v) for v in args.chessboard.lower().split("x"))
            if len(pattern) != 2 or min(pattern) < 2:
                raise ValueError
        except ValueError:
            print(f"visionpos-station: --chessboard {args.chessboard!r}: expected inner corners NxM, e.g. 9x6",
                  file=sys.stderr)
            return 2
    if args.count < 1 or args.interval_s < 0:
        print("visionpos-station: --count must be >= 1 and --interval-s >= 0", file=sys.stderr)
        return 2
    source = make_source(cfg.source, camera_id=cfg.camera_id)
    try:
        source.open()
        files = snapshot(source, args.snapshot, args.count, args.interval_s, pattern, prefix=f"cam{cfg.camera_id}")
    except (SourceError, OSError) as e:
        print(f"visionpos-station: snapshot failed: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # Ctrl-C ends a snapshot session early; what was saved stays
        files = sorted(Path(args.snapshot).glob(f"cam{cfg.camera_id}_*.png"))
    finally:
        source.close()
    print(f"{len(files)} frames in {args.snapshot}; next: visionpos calibrate intrinsics --images {args.snapshot} ...")
    return 0 if files else 1


if __name__ == "__main__":
    sys.exit(main())
