"""Declarations of the arena file's shared parts: the top level, `cameras[i]`, `bodies[i]`, `calibration`.

Stage-owned sections are declared beside their parsers (fusion/settings.py, server/settings.py,
bridge/config.py, sim/scenario.py); config/schema.py assembles the whole file.
"""

from __future__ import annotations

from visionpos.config.settings import Setting, section

CAMERA_POSE = section(
    "cameras[i].pose",
    "Where the camera is and where it looks, in the world frame (m). Give `position` plus one of two "
    "orientation forms:\n\n"
    "- `quaternion_xyzw: [x, y, z, w]`: the camera->world rotation (the camera's axes in world "
    "coordinates; camera frame: x right, y down, z along the optical axis). This is the form "
    "calibration writes (`visionpos calibrate` stores every camera this way).\n"
    "- `look_at: [x, y, z]` (with optional `up`): the optical axis points from `position` at this "
    "world point, with no roll: the image x axis is horizontal (perpendicular to `up`) and image "
    "up (-y) is as close to `up` as possible. Looking straight along `up`, the world y axis "
    "takes its place.\n\n"
    "`quaternion_xyzw` wins when both are given.",
    Setting("position", "array", doc="camera centre in the world frame (m)", shape=(3,)),
    Setting("quaternion_xyzw", "array", None, "camera->world rotation as a quaternion (x, y, z, w); "
            "need not be normalised", shape=(4,), default_doc="(or look_at)"),
    Setting("look_at", "array", None, "world point (m) the optical axis passes through", shape=(3,),
            default_doc="(or quaternion_xyzw)"),
    Setting("up", "array", [0, 0, 1], "world direction that appears up in the image (look_at only)", shape=(3,)),
)

CAMERA = section(
    "cameras[i]",
    "One calibrated camera: intrinsics, distortion, pose and frame rate.\n\n"
    "Lens models (`model`):\n\n"
    "- `pinhole`: OpenCV's pinhole model with its distortion vector in OpenCV's order: "
    "`dist: [k1, k2, p1, p2, k3]` (k1, k2, k3 radial; p1, p2 tangential), optionally followed by "
    "the rational k4, k5, k6; 0, 4, 5 or 8 numbers, missing ones are 0. The same vector "
    "`cv2.calibrateCamera` returns.\n"
    "- `fisheye`: OpenCV's fisheye model (`cv2.fisheye`), the Kannala-Brandt polynomial "
    "theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8) with zero skew: "
    "`dist: [k1, k2, k3, k4]` (0 or 4 numbers).",
    Setting("id", "integer", doc="camera id: the one its station sends in every frame"),
    Setting("name", "text", None, "name in logs and plots", default_doc="cam{id}"),
    Setting("fps", "number", 100.0, "frame rate (Hz); sets the default fusion window and naive grid"),
    Setting("station", "integer", None, "station id expected to send this camera's frames "
            "(others are refused); absent: any station", default_doc="(any)"),
    Setting("model", "text", "pinhole", "lens model", choices=("pinhole", "fisheye")),
    Setting("width", "integer", doc="image width (px)"),
    Setting("height", "integer", doc="image height (px)"),
    Setting("fx", "number", doc="focal length along x (px)"),
    Setting("fy", "number", doc="focal length along y (px)"),
    Setting("cx", "number", doc="principal point x (px)"),
    Setting("cy", "number", doc="principal point y (px)"),
    Setting("dist", "array", [], "distortion coefficients in OpenCV's order (see the lens models)",
            default_doc="[] (none)"),
    Setting("pose", "section", None, "camera position and orientation. Leave it out before the cameras are "
            "calibrated: `visionpos record` records a wand wave without poses and `visionpos calibrate wand` finds "
            "them; fusion, serving and planning need every pose", spec=CAMERA_POSE, default_doc="(not calibrated yet)"),
)

BODY_OCCLUSION = section(
    "bodies[i].occlusion",
    "Simulator only: how this body hides its own markers (overrides `sim.occlusion`).",
    Setting("disc_radius", "number", 0.05, "radius (m) of a disc in the body's x-y plane at its origin "
            "(hub, battery) that hides markers behind it", min=0.0, max=2.0),
    Setting("normal_cutoff_deg", "number", 105.0, "a marker is seen only from directions within this angle "
            "of its normal", min=0.0, max=180.0),
)

BODY = section(
    "bodies[i]",
    "A rigid body fusion tracks: its markers in the body frame (m; x forward, y left, z up).",
    Setting("name", "text", doc="unique name (vehicles and the pose stream refer to it)"),
    Setting(
        "id", "integer", None, "body id in outputs (1..255)", min=1, max=255, default_doc="position in the list + 1"
    ),
    Setting("markers", "array", doc="marker centres (M, 3) in m, at least 3, no two closer than 10 mm; or one "
            "marker at the origin, [[0, 0, 0]]: a point body, tracked for its position only",
            shape=(None, 3)),
    Setting("marker_diameter", "number", 0.014, "marker sphere diameter (m)", min=0.001),
    Setting("occlusion", "section", doc="simulator self-occlusion of this body", spec=BODY_OCCLUSION),
)

WAND = section(
    "calibration.wand",
    "The calibration wand: three collinear markers A, B, C, marker centre to centre, B off-centre "
    "(AB clearly shorter than BC, e.g. 1:2, so A and C can be told apart); `visionpos calibrate wand`'s "
    "--ab/--bc/--known/--max-clock-offset-ms win. See docs/calibration.md for building one.",
    Setting("ab", "number", 0.054, "distance A-B (m)", min=0.005),
    Setting("bc", "number", 0.103, "distance B-C (m)", min=0.005),
    Setting("known", "text", "ac", "the segment measured most precisely: it sets the scale, the other two are "
            "measured against it and a mismatch is reported", choices=("ab", "bc", "ac")),
    Setting("max_clock_offset_ms", "number", 60.0, "largest clock offset of a camera the wand step searches for "
            "(0: trust the stamps)", min=0.0, max=500.0),
)

LFRAME = section(
    "calibration.lframe",
    "The ground frame lying on the floor for `visionpos calibrate ground` (an L-frame or triangle): its "
    "markers in its own frame, x-y plane on the floor. Used when --frame/--markers are not given; "
    "otherwise a body or sim prop named lframe/ground/triangle/ground_frame.",
    Setting("markers", "array", doc="marker centres (M, 3) in m, at least 3; legs of clearly different "
            "lengths so the frame's orientation is unambiguous", shape=(None, 3)),
    Setting("marker_diameter", "number", 0.014, "marker sphere diameter (m); the centres sit one radius above "
            "the floor", min=0.001),
)

CALIBRATION = section(
    "calibration",
    "Calibration inputs, and the reports `visionpos calibrate` writes back into the arena it produces.",
    Setting("wand", "section", {}, "the wand's geometry", spec=WAND),
    Setting("lframe", "section", None, "the ground frame's geometry", spec=LFRAME, default_doc="(bodies/props)"),
    Setting("extrinsics", "any", None, "report written by `calibrate extrinsics` (reference camera, "
            "residuals); read by nobody", default_doc="(written)"),
    Setting("ground", "any", None, "report written by `calibrate ground` (marker choice, fit residual); "
            "read by nobody", default_doc="(written)"),
)

# the stage-owned sections get their specs in config/schema.py
TOP = section(
    "(top level)",
    "The sections of an arena file. Only `cameras` and `bodies` are needed; every other section is optional.",
    Setting("cameras", "list", [], "the cameras", spec=CAMERA),
    Setting("bodies", "list", [], "the rigid bodies to track", spec=BODY),
    Setting("fusion", "section", {}, "fusion: time alignment, matching, tracking"),
    Setting("camera_monitor", "section", {}, "continuous calibration: moved cameras flagged and corrected"),
    Setting("server", "section", {}, "the fusion server's network and timing"),
    Setting("vehicles", "list", [], "autopilots the MAVLink bridge feeds"),
    Setting("pose_stream", "section", None, "UDP pose stream", default_doc="(off)"),
    Setting("vrpn", "section", None, "VRPN server", default_doc="(off)"),
    Setting("natnet", "section", None, "NatNet server for OptiTrack clients", default_doc="(off)"),
    Setting("foxglove", "section", None, "Foxglove WebSocket server (the [foxglove] extra)", default_doc="(off)"),
    Setting("sim", "section", {}, "the simulator's scenario"),
    Setting("sitl", "section", {}, "ArduPilot SITL for `visionpos sitl`"),
    Setting("console", "section", {}, "the operator console (web page)"),
    Setting("calibration", "section", {}, "calibration wand, ground frame and reports", spec=CALIBRATION),
    Setting("plan", "section", {}, "the room for `visionpos plan`: walls, ceiling, obstacles, flight volume"),
)
