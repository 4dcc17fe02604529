"""Offline calibration: intrinsics, wand extrinsics with bundle adjustment, ground plane.

    from visionpos.calibration import calibrate_wand, calibrate_ground, WandSpec
    cal = calibrate_wand(frames, arena.cameras, WandSpec(0.054, 0.103))   # world = first camera
    g = calibrate_ground(ground_frames, cal.cameras, layout, origin=0, x_marker=1, marker_height=0.007)

`visionpos calibrate intrinsics|wand|ground` (visionpos/cli/calibrate.py; session steps in workflow.py) wraps these.
"""

from visionpos.calibration.bundle import bundle_adjust
from visionpos.calibration.ground import GroundResult, apply_world, calibrate_ground
from visionpos.calibration.intrinsics import BoardSpec, IntrinsicsResult, calibrate_images, calibrate_intrinsics
from visionpos.calibration.pairwise import initial_poses, pair_pose
from visionpos.calibration.wand import CalibrationError, WandData, WandSpec, collect_wand, label_triples
from visionpos.calibration.wand_solve import WandCalibration, calibrate_wand, compare_cameras, wand_lengths

__all__ = [
    "BoardSpec",
    "CalibrationError",
    "GroundResult",
    "IntrinsicsResult",
    "WandCalibration",
    "WandData",
    "WandSpec",
    "apply_world",
    "bundle_adjust",
    "calibrate_ground",
    "calibrate_images",
    "calibrate_intrinsics",
    "calibrate_wand",
    "collect_wand",
    "compare_cameras",
    "initial_poses",
    "label_triples",
    "pair_pose",
    "wand_lengths",
]
