"""Cameras: one lens model per kind, and the calibrated camera built on them.

- pinhole.py  OpenCV rational + tangential distortion (cv2.projectPoints)
- fisheye.py  Kannala-Brandt (cv2.fisheye)
  each: distort, its Jacobian and undistort, vectorised numpy and compiled per-point forms
- lens.py     the one dispatch over them: lens_module, and compiled per point distort, undistort,
              pixel_from_normalized and project_with_jacobian (the fusion hot path's projection)
- model.py    CameraModel (intrinsics, capture modes, YAML), Camera (pose), look_at_rotation,
              and the compiled pixel undistortion of the fusion hot path
"""
