"""`visionpos calibrate intrinsics|wand|ground` (solvers in visionpos.calibration, steps in its workflow.py).

    visionpos calibrate intrinsics --images DIR --board chessboard --inner-corners 9x6 --square 0.025 \
        --model pinhole --out cam.yaml [--plot cov.png] [--rescale 640x480]
    visionpos calibrate wand session.mcap --config arena.yaml --out arena_calibrated.yaml [--report wand.png]
    visionpos calibrate wand --sim thesis --out arena_calibrated.yaml
    visionpos calibrate ground ground.mcap --config arena_calibrated.yaml --out arena_final.yaml
    visionpos calibrate ground --sim thesis --config arena_calibrated.yaml --out arena_final.yaml
"""

from __future__ import annotations

import argparse
from pathlib import Path

import yaml

from visionpos.calibration.workflow import capture_frames, ground_layout, wand_section, wand_settings, write_arena
from visionpos.errors import UsageError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="step", metavar="STEP", required=True)

    p = sub.add_parser("intrinsics", help="camera intrinsics from chessboard/ChArUco images",
                       description="Camera intrinsics from 15-40 images of a flat board held at different places, "
                       "distances and tilts, covering the whole image (docs/calibration.md).")
    p.add_argument("--images", required=True, help="folder of board images of one camera in one capture mode")
    p.add_argument("--board", choices=("chessboard", "charuco"), default="chessboard",
                   help="board type (default chessboard)")
    size = p.add_mutually_exclusive_group(required=True)
    size.add_argument("--inner-corners", metavar="NxM", type=_pair,
                      help="chessboard inner corners across x down, where four squares meet: OpenCV's pattern size "
                           "(a board of 10x7 squares has 9x6)")
    size.add_argument("--squares", metavar="NxM", type=_pair, help="board squares across x down (ChArUco's size)")
    size.add_argument("--cols", type=int, help=argparse.SUPPRESS)  # squares across: before --squares; still read
    p.add_argument("--rows", type=int, help=argparse.SUPPRESS)
    p.add_argument("--square", type=float, required=True, help="side of one printed square (m), measured on the print")
    p.add_argument("--marker", type=float, default=None, help="ChArUco: side of one ArUco marker (m)")
    p.add_argument("--dict", default="DICT_4X4_50", help="ChArUco: the ArUco dictionary (cv2.aruco name, default "
                   "DICT_4X4_50)")
    p.add_argument("--model", choices=("pinhole", "fisheye"), default="pinhole",
                   help="lens model: pinhole (with radial-tangential distortion, lenses up to about 100 deg) or "
                        "fisheye (equidistant, wider lenses); default pinhole")
    p.add_argument("--max-views", type=int, default=40, help="most views kept after dropping near-duplicates "
                   "(default 40)")
    p.add_argument("--free-k3", action="store_true", help="estimate the pinhole k3 too (strong distortion only: "
                   "it trades off against the focal length)")
    p.add_argument("--rescale", action="append", default=[], metavar="WxH[+UxV]",
                   help="also write the intrinsics for another capture mode of the same sensor: WxH pixels after "
                        "resizing, with the centred crop that keeps the aspect ratio, or an explicit total crop "
                        "UxV (e.g. 640x360 from 1280x960 images crops 0x120); repeatable")
    p.add_argument("--out", required=True, help="output YAML (intrinsics keys of an arena camera entry)")
    p.add_argument("--plot", default=None, help="PNG of the corners' coverage and residuals")
    p.add_argument("--no-progress", action="store_true", help="no progress output")

    for name, text in (("wand", "camera poses from a waved 3-marker wand"),
                       ("ground", "world frame from a static L-frame/triangle on the floor")):
        q = sub.add_parser(name, help=text)
        q.add_argument("recording", nargs="?", default=None, help="MCAP recording of the capture")
        q.add_argument("--sim", default=None, metavar="SCENARIO",
                       help="simulate the capture instead ('thesis', 'arena8' or an arena YAML)")
        q.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                       help="override a scenario key for --sim (e.g. sim.duration=30)")
        q.add_argument("--config", default=None,
                       help="arena YAML with the cameras' intrinsics" + (" and wand poses" if name == "ground" else "")
                       + " (default: the recording's or the scenario's)")
        q.add_argument("--out", required=True, help="output arena YAML")
        q.add_argument("--no-progress", action="store_true", help="no progress bars")
    w = sub.choices["wand"]
    w.add_argument("--ab", type=float, default=None, help="wand A-B distance (m) [0.054 or calibration.wand.ab]")
    w.add_argument("--bc", type=float, default=None, help="wand B-C distance (m) [0.103 or calibration.wand.bc]")
    w.add_argument("--known", choices=("ab", "bc", "ac"), default=None,
                   help="the wand segment measured most precisely; it sets the scale and the others are checked "
                   "against it [ac or calibration.wand.known]")
    w.add_argument("--max-clock-offset-ms", type=float, default=None,
                   help="largest clock offset of a camera to search for; 0 trusts the stamps "
                   "[60 or calibration.wand.max_clock_offset_ms]")
    w.add_argument("--rate", type=float, default=50.0, help="common time grid (Hz) the cameras are interpolated to")
    w.add_argument("--align", choices=("interpolate", "nearest"), default="interpolate",
                   help="bring asynchronous cameras to common times by interpolation or nearest frame (<= 2 ms)")
    w.add_argument("--ref", type=int, default=None, help="id of the camera that defines the frame [first]")
    w.add_argument("--refine-intrinsics", action="store_true",
                   help="also refine fx, fy, cx, cy per camera; refused (with the reason) where the wand data cannot "
                   "determine them")
    w.add_argument("--max-frames", type=int, default=None, help="use at most this many time steps")
    w.add_argument("--report", default=None, help="PNG report (camera poses, residuals, wand lengths)")
    g = sub.choices["ground"]
    g.add_argument("--frame", default=None,
                   help="name of the ground frame in the config's bodies or sim.props [lframe/ground/triangle]")
    g.add_argument("--markers", default=None, metavar="X,Y,Z;X,Y,Z;...",
                   help="ground frame marker layout (m, frame x-y plane on the floor) instead of --frame")
    g.add_argument("--origin", type=int, default=0, help="marker index at the world origin")
    g.add_argument("--x-marker", type=int, default=None, help="marker index the world x axis points to [1]")
    g.add_argument("--marker-height", type=float, default=None,
                   help="height of the marker centres above the floor (m) [marker_diameter/2]")
    g.add_argument("--tolerance-sigma", type=float, default=4.0,
                   help="a measured distance matches the frame's when they differ by less than this many standard "
                        "deviations of the difference (from the measured triangulation noise; default 4)")
    g.add_argument("--frame-accuracy-mm", type=float, default=1.0,
                   help="how well the frame's marker distances are known (mm, 1 sigma; default 1: a frame built "
                        "with a ruler)")
    g.add_argument("--plot", default=None, help="PNG of the cameras, the static points and the frame, from above and "
                   "from the side")


# -------------------------------------------------------------------- steps
def _pair(text: str) -> tuple[int, int]:
    try:
        a, b = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected NxM, e.g. 9x6; got {text!r}") from None
    return a, b


def _board_squares(args) -> tuple[int, int]:
    """(squares across, squares down) from --inner-corners, --squares or the older --cols/--rows (squares)."""
    if args.inner_corners is not None:
        if args.board == "charuco":
            raise UsageError("--inner-corners is for chessboards; give a ChArUco board's size with --squares")
        return args.inner_corners[0] + 1, args.inner_corners[1] + 1
    if args.squares is not None:
        return args.squares
    if args.rows is None:
        raise UsageError("--cols needs --rows (both count squares); better: --inner-corners NxM or --squares NxM")
    return args.cols, args.rows


def _run_intrinsics(args) -> int:
    from visionpos.calibration.intrinsics import (
        BoardSpec,
        calibrate_images,
        capture_mode,
        load_images,
        model_warnings,
    )
    from visionpos.calibration.report import intrinsics_report, plot_intrinsics, progress_printer

    # everything that can be wrong with the options is found before the (slow) corner search and solve
    if args.board == "charuco" and args.marker is None:
        raise UsageError("--board charuco needs --marker (the ArUco marker side in m)")
    cols, rows = _board_squares(args)
    board = BoardSpec(args.board, cols, rows, args.square, args.marker or 0.0, args.dict)
    if args.max_views < 8:
        raise UsageError(f"--max-views {args.max_views}: a calibration needs at least 8 distinct views")
    images = load_images(args.images)
    h, w = images[0][1].shape[:2]
    modes = [capture_mode(spec, (w, h)) for spec in args.rescale]
    if args.plot:
        from visionpos.analysis.plots import _pyplot

        _pyplot()  # matplotlib missing: say so now, not after the solve
    res = calibrate_images(images, board, args.model, args.max_views, progress_printer(not args.no_progress),
                           fix_k3=not args.free_k3)
    print(intrinsics_report(res))
    for warning in model_warnings(res):
        print(f"warning: {warning}")
    d = res.model.to_dict()
    d["rms_px"] = round(res.rms_px, 4)
    d["views"] = len(res.views)
    if modes:
        d["modes"] = [m.apply(res.model).to_dict() for m in modes]
    Path(args.out).write_text(yaml.safe_dump(d, sort_keys=False))
    print(f"wrote {args.out}")
    if args.plot:
        plot_intrinsics(res, args.plot)
        print(f"wrote {args.plot}")
    return 0


def _run_wand(args) -> int:
    from visionpos.calibration.report import plot_wand, progress_printer, wand_report
    from visionpos.calibration.wand_solve import calibrate_wand, compare_cameras

    frames, arena, truth = capture_frames(args.recording, args.sim, "wand", args.set, args.config)
    if args.max_clock_offset_ms is not None and not 0 <= args.max_clock_offset_ms <= 500:
        raise UsageError(f"--max-clock-offset-ms {args.max_clock_offset_ms}: expected 0 to 500")
    spec, max_offset_ms = wand_settings(arena, args.ab, args.bc, args.known, args.max_clock_offset_ms)
    cams = list(arena.cameras)
    ref = 0
    if args.ref is not None:
        ids = [c.id for c in cams]
        if args.ref not in ids:
            raise UsageError(f"--ref {args.ref}: no such camera id (cameras: {ids})")
        ref = ids.index(args.ref)
    cal = calibrate_wand(
        frames, cams, spec, ref=ref, rate_hz=args.rate, refine_intrinsics=args.refine_intrinsics,
        max_frames=args.max_frames, progress=progress_printer(not args.no_progress), align=args.align,
        max_offset_ms=max_offset_ms,
    )
    print(wand_report(cal))
    if truth is not None:
        ce, re, s = compare_cameras(cal.cameras, truth)
        print(f"\nagainst the simulator's cameras (after a similarity alignment, scale {s:.5f}): "
              f"centre error max {ce.max() * 1000:.2f} mm, orientation error max {re.max():.4f} deg")
    write_arena(arena, cal.cameras, args.out, wand_section(cal, max_offset_ms, ref))
    print(f"wrote {args.out} (world = camera {cal.cameras[ref].name}; run `visionpos calibrate ground` next)")
    if args.report:
        plot_wand(cal, args.report)
        print(f"wrote {args.report}")
    return 0


def _run_ground(args) -> int:
    from visionpos.calibration.ground import calibrate_ground
    from visionpos.calibration.wand_solve import compare_cameras

    if args.config is None:
        raise UsageError("ground needs --config: the arena YAML written by `visionpos calibrate wand`")
    frames, arena, truth = capture_frames(args.recording, args.sim, "ground", args.set, args.config)
    arena.require_poses("the ground step")
    layout, height = ground_layout(arena, args.frame, args.markers, args.marker_height)
    x_marker = args.x_marker if args.x_marker is not None else 1
    if not args.tolerance_sigma > 0 or not args.frame_accuracy_mm >= 0:
        raise UsageError("--tolerance-sigma must be > 0 and --frame-accuracy-mm >= 0")
    if args.plot:
        from visionpos.analysis.plots import _pyplot

        _pyplot()  # matplotlib missing: say so before the work
    g = calibrate_ground(frames, list(arena.cameras), layout, args.origin, x_marker, height,
                         n_sigma=args.tolerance_sigma, layout_std=args.frame_accuracy_mm * 1e-3)
    print(f"ground frame: {len(layout)} markers found among {g.n_static} static points, layout fit RMS "
          f"{g.fit_rms * 1000:.2f} mm (markers measured to {1000 * float(g.marker_std.max()):.2f} mm, effective "
          f"pixel error {g.sigma_px:.2f} px)")
    for c in g.cameras:
        C = c.center
        print(f"  {c.name:>10}: position {C[0]:+.4f} {C[1]:+.4f} {C[2]:+.4f} m")
    if truth is not None:
        ce, re, _ = compare_cameras(g.cameras, truth, similarity=False)
        print(f"against the simulator's cameras (no alignment): centre error max {ce.max() * 1000:.2f} mm, "
              f"orientation error max {re.max():.4f} deg")
    write_arena(arena, g.cameras, args.out, {
        "ground": {"origin_marker": args.origin, "x_marker": x_marker, "marker_height": height,
                   "fit_rms_mm": round(g.fit_rms * 1000, 4)},
    })
    print(f"wrote {args.out}")
    if args.plot:
        from visionpos.calibration.report import plot_ground

        plot_ground(g, layout, args.plot)
        print(f"wrote {args.plot}")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.step == "intrinsics":
        return _run_intrinsics(args)
    if args.step == "wand":
        return _run_wand(args)
    return _run_ground(args)
