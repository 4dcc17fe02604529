"""Multi-view geometry as pure functions on numpy arrays, one module per idea.

- rotations.py      rotation vectors, matrices, quaternions, ZYX Euler angles; skew; rotation mean
                    (compiled kernels for the Kalman filter next to numpy forms)
- frames.py         world z-up <-> NED, body FLU <-> FRD, attitudes for the MAVLink edge
- alignment.py      the Kabsch family: SVD (Kabsch, Umeyama) and Horn's compiled quaternion method
- triangulation.py  N-view triangulation (DLT + Levenberg-Marquardt) through the lens models,
                    CameraRig, Cramer-Rao bound
- epipolar.py       essential matrix (8-point, RANSAC) and its decomposition

The lens models are in visionpos/camera (pinhole.py, fisheye.py). Import from the
submodules; this package exports nothing itself.

Conventions: a camera pose (R, t) maps world to camera, x_cam = R @ x_world + t;
normalised image coordinates are (x/z, y/z); missing observations are NaN.
"""
