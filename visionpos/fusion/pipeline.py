"""Fusion pipeline: camera frames in, one filtered pose per body out. Pure, no I/O.

    pipe = FusionPipeline(arena, settings)
    pipe.push(frame)            # every BlobFrame, in arrival order
    states = pipe.tick(now_ns)  # one BodyState per configured body, predicted to now_ns

Deterministic: the same frames in the same order and the same tick times
give identical outputs (replay depends on it). Only frame.capture_ns is
used as time; tick() changes the filter state only to fuse a frame the rate
limit deferred (TimeAligner.take_deferred), at the tick's place in the input.

Per frame: undistort its blobs, associate them with the markers of tracked
bodies (prediction at the frame's capture time, see matching.py), then fuse
the newest frame of every camera in the time-alignment group (timealign.py)
at the reference time: motion-compensated triangulation of every tracked
marker, a weighted Kabsch pose per body, a gated Kalman update
(tracking.py). Leftover blobs go to acquisition: cross-view matching,
identification of lost bodies by marker geometry (rigidbody.py) and the
loose points, in steps of fusion.acquire_step_ms of work (fusion/steps.py).

Occlusion: a tracked body with fewer than min_markers markers triangulated in a
fusion is updated instead from the 2-D markers each of the fusion's frames sees
(kernels._single_views, tracking.filter_update_view: a reprojection measurement
at the frame's own capture time, each frame used once, NIS-gated, only
unambiguous associations). The track is kept only while the recent views' pose
information bounds the pose; single views never acquire or re-identify, and a new or
reacquired track takes none until a triangulated pose has told it its velocity
(kernels._velocity_known).
BodyState.update_kind says which kind of update last kept a body.

Measurement covariance: from the rigid-body fit itself. The Kabsch residual
gives the per-marker noise (sigma^2 = sum |r|^2 / (3n - 6), averaged per body
over recent fusions, floored by `marker_sigma_m`); with the marker layout it
gives the pose covariance (rotation: sigma^2 (sum |r_i|^2 I - r_i r_i^T)^-1,
position: sigma^2 / n plus the lever arm of the body origin). So the filter
weighs measurements by what they are actually worth in this arena, with
these cameras, at this noise level, without per-arena tuning.

Measurement reuse: in motion-compensated mode one camera frame takes part
in about as many fusions as there are cameras in the group (its own and one
per other camera until it is replaced; fewer under the rate limit). The
filter is told so: each fused pose's measurement covariance is multiplied by
that count, which splits each frame's information over the fusions that
reuse it instead of counting it several times (an overconfident filter
would smooth too little and gate wrongly).

Motion compensation and its feedback loop: the offsets come from the
filter, so a wrong velocity would bias the measurement towards itself. Until
the filter's velocity std is below 0.3 m/s (a new or reacquired track) the
views are fused uncompensated and the motion between them is added to the
measurement covariance (|v|^2 + var v) * mean(dt^2), and the per-marker
residual gate and the rigid-fit tolerance are widened by the motion the
views may disagree by (so a body reacquired at 3 m/s is not refused); once
compensating, only the velocity's own uncertainty is added. The naive mode
gets the same treatment, so the comparison is with a fair baseline.

Outputs: tick() predicts each tracked body to now_ns (latency cancelled)
with its covariance; a body not updated for max_prediction_ms or lost is
tracked=False with a NaN pose (a stale pose is never sent). Both timeouts are
at least 2 and 3 measured frame intervals of the slowest live camera
(timealign.py measures them), so stations slower than configured still track.
reset_counter increments only when a tracked filter is restarted at a
measurement it kept rejecting (a jump), not on a dropout or reacquisition.

Every `fusion:` key (and `fusion.kalman:`) with its unit, default and bounds is in
docs/configuration.md, generated from the declarations in fusion/settings.py.
The output rate is the server's (tick() is called by it).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from visionpos.camera.model import Camera
from visionpos.config.arena import ArenaConfig, ConfigError
from visionpos.fusion.acquisition import match_unlabeled, match_unlabeled_steps, still_seen
from visionpos.fusion.body_filter import FilterBank
from visionpos.fusion.identity import IdentityBook
from visionpos.fusion.imu import ImuInputs
from visionpos.fusion.kernels import _finite_rows, _fuse_tracked, _observe_frame, _tracked_motion
from visionpos.fusion.layout import (
    MEAS_POS,
    MEAS_ROT,
    PARAM_SV_ENABLED,
    SV_PARAM_ALWAYS,
    SV_PARAM_OCCLUSION,
    TRACK_LAST_CAPTURE_NS,
    TRACK_LAST_UPDATE_NS,
    TRACK_N_CAMERAS,
    TRACK_N_MARKERS,
    TRACK_RESETS,
    TRACK_RESIDUAL_MM,
    TRACK_TRACKED,
    TRACK_UPDATE_KIND,
    X_POS,
    X_VEL,
    TrackedSet,
    UpdateKind,
    Verdict,
    ViewSet,
)
from visionpos.fusion.matching import Projector
from visionpos.fusion.measurements import pose_measurement_cov
from visionpos.fusion.point_tracks import PointTracks
from visionpos.fusion.rigidbody import BodyModel, Identification, identify_steps, layout_ambiguities
from visionpos.fusion.settings import FUSION_PARAMS, pack_params, parse_fusion
from visionpos.fusion.snapshot import CameraFrame, FusionSnapshot
from visionpos.fusion.steps import Steps, advance, finish
from visionpos.fusion.timealign import Group, TimeAligner, TimeAlignment
from visionpos.fusion.tracks import Observation, Track, new_track_rows
from visionpos.fusion.warmup import warm_up_once
from visionpos.messages import BlobFrame, BodyState, LoosePoints

# the image-space manoeuvre detector samples at most this often (capture clock)
_IMAGE_NIS_INTERVAL_NS = 2_000_000

# acquisition in steps (fusion/steps.py): the estimated work of starting a found body's track and of checking
# it is still there (twenty: about 7 and 2 ms); a body that moved more than _STILL_PX in the images since its
# frames is found again from the newest, and later acquisitions run at once (a parked one moves less: blob noise
# is about 0.1-0.2 px)
_START_TRACK_NS, _MOVED_CHECK_NS, _STILL_PX = 350_000, 100_000, 0.5

# the output and lost timeouts are at least this many measured frame intervals of the slowest live camera
# (max_prediction_ms and lost_timeout_ms are for cameras at their configured rate)
_PREDICTION_PERIODS = 2
_LOST_PERIODS = 3

# per fusion verdict, the stats counters it increments, and the verdicts with a fitted pose (last_raw);
# tables, because reading an enum member off its class costs ~0.15 us in the per-fusion loop
_VERDICT_COUNTERS = {
    Verdict.TOO_FEW: (),
    Verdict.FIT_REJECTED: ("rejected_fit",),
    Verdict.ACCEPTED: ("measurements",),
    Verdict.GATED: ("rejected_gate",),
    Verdict.RESET: ("rejected_gate", "measurements", "filter_resets"),
    Verdict.VIEWS: ("view_updates",),
    Verdict.VIEWS_UNCONSTRAINED: ("view_updates_unconstrained",),
    Verdict.VIEWS_GATED: ("rejected_view_gate",),
}
_POSE_FITTED = frozenset((Verdict.ACCEPTED, Verdict.GATED, Verdict.RESET))
# BodyState.update_kind by layout.UpdateKind
_UPDATE_NAMES = {int(UpdateKind.NONE): "", int(UpdateKind.POSE): "pose", int(UpdateKind.VIEWS): "views"}
# why a tracked body was lost, from its last fusion's verdict (the console's health view)
_LOST_WHY = {
    Verdict.TOO_FEW: "not seen by enough cameras: too few of its markers in two views",
    Verdict.FIT_REJECTED: "its markers did not fit its layout (rigid-fit residual too large)",
    Verdict.GATED: "measurements gated: they disagreed with the filter's prediction",
}


class FusionPipeline:
    """Asynchronous multi-camera fusion into filtered rigid-body poses (see module docstring)."""

    def __init__(self, arena: ArenaConfig, settings: dict[str, Any] | None = None, warm_up: bool = True):
        self.arena = arena
        arena.require_poses("fusion")
        if len(arena.cameras) < 2:
            raise ConfigError(arena.source, "cameras", f"fusion needs at least 2 cameras, the arena has "
                              f"{len(arena.cameras)}; add the calibrated cameras "
                              "(`visionpos calibrate wand` writes them)")
        self.settings = parse_fusion(arena, settings)
        st = self.settings
        self.models = [BodyModel(b.name, b.id, np.asarray(b.markers, float)) for b in arena.bodies]
        # single-marker bodies: position-only tracks by continuity (point_tracks.py), apart from the rigid ones
        self._point_bodies = [b for b, m in enumerate(self.models) if len(m.markers) == 1]
        self._point_row = {b: k for k, b in enumerate(self._point_bodies)}
        self._n_rigid = len(self.models) - len(self._point_bodies)
        self._point_names = frozenset(self.models[b].name for b in self._point_bodies)
        self.points = PointTracks(self._point_bodies, st.kalman.marker_sigma_m) if self._point_bodies else None
        # layouts the geometry cannot tell apart would be swapped or flipped: refuse them
        problems = layout_ambiguities([m for m in self.models if len(m.markers) > 1], 0.5 * st.identify_tolerance_m)
        if problems:
            raise ConfigError(
                arena.source,
                "bodies",
                "; ".join(problems) + ". Move a marker so every body's distances differ by > 1 cm.",
            )
        sizes = [len(m.markers) for m in self.models]
        self._marker_start = np.concatenate([[0], np.cumsum(sizes)]).astype(int)  # body b: rows start[b]:start[b + 1]
        self.n_markers = int(self._marker_start[-1])  # of all bodies
        self._marker_body = np.repeat(np.arange(len(self.models)), sizes)
        self._marker_local = np.concatenate([m.markers for m in self.models]) if self.models else np.zeros((0, 3))
        # cameras: stacked poses, indexed by the kernels
        self.cameras = {c.id: c for c in arena.cameras}
        self._cam_index = {c.id: i for i, c in enumerate(arena.cameras)}
        self._R = np.array([c.R for c in arena.cameras]).reshape(-1, 3, 3)
        self._t = np.array([c.t for c in arena.cameras]).reshape(-1, 3)
        self._focal_px = np.array([np.sqrt(c.model.fx * c.model.fy) for c in arena.cameras])
        self._proj = {c.id: Projector(c) for c in arena.cameras}
        # bodies sharing a layout: which is which, by continuity (identity.py)
        self.identity = IdentityBook(self.models, np.array([c.center for c in arena.cameras]), self._focal_px,
                                     st.match_gate_px)
        self._layout_cache: dict[tuple[int, ...], TrackedSet] = {}
        self._gate_px = float(st.match_gate_px)
        self._unique_sigmas = float(st.single_view.unique_sigmas)
        self._kernel_params = pack_params(FUSION_PARAMS, st)  # the fusion kernels' settings (fusion/settings.py)
        self._kernel_params_sv = float(self._kernel_params[PARAM_SV_ENABLED])  # as configured (pause_view_updates)
        self._view_cache: dict[tuple[int, ...], tuple] = {}  # ViewSets as plain tuples
        self.aligner = TimeAligner(
            st.time_alignment,
            st.window_ns,
            st.grid_ns,
            st.max_clock_lead_ns,
            periods_ns={c.id: int(1e9 / c.fps) for c in arena.cameras if c.fps > 0},
            min_interval_ns=st.min_fusion_interval_ns,
            auto_window=st.auto_window,
        )
        self._compensating = self.aligner.mode == TimeAlignment.MOTION_COMPENSATED
        self.obs: dict[int, Observation] = {}
        # each camera's newest observation of every marker (NaN = none); Observation.marker_xn is its row,
        # so a fusion reads its views without stacking them
        self._marker_xn = np.full((len(arena.cameras), self.n_markers, 2), np.nan)
        # ... and whether that association is unambiguous (the single-view path uses only those)
        self._marker_ok = np.zeros((len(arena.cameras), self.n_markers), dtype=np.bool_)
        self._camera_packed = np.array([self._proj[c.id].packed for c in arena.cameras])
        self._capture_ns = np.zeros(len(arena.cameras), dtype=np.int64)  # each camera's newest frame
        # per-body state in arrays the kernels update in place; tracks[b] is a view of row b
        self.bank = FilterBank(len(self.models), st.kalman)
        self._track_rows = new_track_rows(len(self.models), len(arena.cameras))
        self._track_ints, self._track_floats, self._track_view_ns, self._track_info = self._track_rows
        self._track_rows_arg = tuple(self._track_rows)  # the kernels take argument groups as plain tuples
        self.tracks = [Track(fl, self._track_ints[b], self._track_floats[b]) for b, fl in enumerate(self.bank.filters)]
        self._motion: tuple[int, np.ndarray] | None = None  # see _motion_cache
        # the vehicles' IMU samples (push_imu) in the prediction, when fusion.imu.enabled (fusion/imu.py)
        self.imu = ImuInputs(st.imu, [m.name for m in self.models], st.kalman) if st.imu.enabled else None
        self._imu_sources: list = []
        self._pose_taps: list = []  # the IMU sources' optical_pose (add_imu_source)
        # tap(log_ns, body, t_ns, accel, gyro, lever_arm, at) sees every sample the sources hand over, before the
        # pipeline takes it (the recording: RecordingWriter.write_imu; None: not recording)
        self.imu_tap = None
        self._tracking_changed()
        self.loose_points: LoosePoints | None = None
        self._last_acquire_ns = -(1 << 62)
        # an acquisition under way (_acquire's steps, fusion/steps.py) and the reference time of its last step
        self._acquiring: Steps[None] | None = None
        self._acquire_began_ns = self._acquire_step_ns = 0
        self._acquire_at_once = False  # from now on in one step: bodies moved while one went on in steps
        self._was_tracked = np.zeros(len(self.models), dtype=bool)  # a re-acquisition runs at once
        self._last_img_ns = -(1 << 62)
        # a frame takes part in about (frame period / fusion spacing) fusions at most
        self._max_reuse = max(1.0, (st.window_ns / 1.2) / max(st.min_fusion_interval_ns, 1))
        # body -> (ref_ns, position, R) of the last Kabsch pose
        self.last_raw: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}
        self._stats: dict[str, int] = {
            "frames": 0,
            "fusions": 0,
            "deferred": 0,
            "fused_at_tick": 0,  # deferred fusions that the output tick did (their burst's next frame was late)
            "measurements": 0,
            "rejected_gate": 0,
            "rejected_residual": 0,
            "rejected_fit": 0,
            "unknown_camera": 0,
            "malformed": 0,
            "clock_jump": 0,
            "late": 0,
            "reordered": 0,
            "removed_camera": 0,
            "acquisitions": 0,
            "lost": 0,
            "filter_resets": 0,
            "view_updates": 0,
            "view_updates_unconstrained": 0,
            "rejected_view_gate": 0,
        }
        self._per_camera: dict[int, int] = {}
        # for the operator console (read, never used by fusion): each camera's newest blobs in pixels, its
        # rows as obs[cam].label's; each body's last fusion verdict (Verdict, -1 = none yet); and why each
        # untracked body is not tracked, in words (set where acquisition decides, a few times a second)
        self.last_px: dict[int, np.ndarray] = {}
        self.last_verdict = [-1] * len(self.models)
        self.untracked_why: dict[int, str] = {}
        if warm_up:
            warm_up_once(arena, settings)

    # ------------------------------------------------------------------ input
    def push(self, frame: BlobFrame) -> None:
        """Take one camera frame (arrival order) and do the fusion work it enables."""
        if self._imu_sources and self.imu is not None:
            self._drain_imu(int(frame.recv_ns), "frame")
        self._stats["frames"] += 1
        cam = int(frame.camera_id)
        if cam not in self.cameras:
            self._stats["unknown_camera"] += 1
            return
        self._per_camera[cam] = self._per_camera.get(cam, 0) + 1
        blobs = np.asarray(frame.blobs)
        if blobs.ndim != 2 or (blobs.shape[0] and blobs.shape[1] < 2):
            self._stats["malformed"] += 1
            return
        px = _finite_rows(blobs[:, :2].astype(np.float64))
        t = int(frame.capture_ns)
        why = self.aligner.admit(cam, t)
        if why is not None:
            self._stats[why] += 1
            return
        before, after = self.aligner.add(cam, t)
        if self._compensating and not after:
            self._stats["deferred"] += 1
        for g in before:
            self._fuse(g)
        self.last_px[cam] = px
        self.obs[cam] = self._observe(cam, t, px)
        for g in after:
            self._fuse(g)

    def push_imu(self, body: str, t_ns: int, accel_body: np.ndarray, gyro_body: np.ndarray,
                 lever_arm_m: np.ndarray | None = None) -> bool:
        """One IMU sample of the vehicle bound to `body` (fusion/imu.py): t_ns on the capture clock, specific
        force (3,) m/s^2 and rate (3,) rad/s in the body's frame, from an IMU lever_arm_m (3,) from the body's
        origin (None: at it). False (nothing changes) when fusion.imu is off, the body unknown or the sample
        refused (ImuInput.push); a single-marker body's IMU is not used (its filter has no attitude to turn it)."""
        if self.imu is None or body in self._point_names:
            return False
        return self.imu.push(body, t_ns, accel_body, gyro_body, lever_arm_m)

    def pause_view_updates(self, paused: bool) -> bool:
        """While paused, triangulated bodies take no single-view updates (fusion.single_view.mode `always` acts
        as `occlusion`; occluded bodies still do): the server's load relief before it sheds frames
        (server/load.py). Returns whether anything is paused (False where the mode is `occlusion` already)."""
        if self._kernel_params_sv != SV_PARAM_ALWAYS:
            return False
        self._kernel_params[PARAM_SV_ENABLED] = SV_PARAM_OCCLUSION if paused else SV_PARAM_ALWAYS
        return paused

    def add_imu_source(self, drain) -> None:
        """drain(push_imu) is called before every frame and tick, on the pipeline's thread: it hands over the
        IMU samples that arrived (bridge/imu_feed.py). Nothing is drained while fusion.imu is off. A source with
        an optical_pose(body, t_ns, R) method gets, while samples are in the filters, each fusion's triangulated
        rotation R (3, 3) body->world of every tracked body at its reference time t_ns: the optical-only
        attitude (the back-channel's identity check and delay measurement compare it with the autopilot's)."""
        self._imu_sources.append(drain)
        if callable(getattr(drain, "optical_pose", None)):
            self._pose_taps.append(drain.optical_pose)

    def _drain_imu(self, log_ns: int, at: str) -> None:
        """The sources' samples into push_imu, each shown first to imu_tap with the input's time and kind: a
        frame's receive time ("frame": before that frame) or the tick's time ("tick")."""
        tap = self.imu_tap
        push = self.push_imu
        if tap is not None:
            def push(body, t_ns, accel, gyro, lever_arm_m=None):
                tap(log_ns, body, t_ns, accel, gyro, lever_arm_m, at)
                return self.push_imu(body, t_ns, accel, gyro, lever_arm_m)
        for drain in self._imu_sources:
            drain(push)

    def remove_camera(self, camera_id: int) -> None:
        """A station vanished: stop using and waiting for its frames."""
        if camera_id in self.obs or camera_id in self.aligner.latest:
            self._stats["removed_camera"] += 1
        self.obs.pop(camera_id, None)
        self.aligner.remove(camera_id)

    # ------------------------------------------------------------ association
    def _tracking_changed(self) -> None:
        """Refresh the tracked-body set after a body was acquired or lost."""
        self._tracked = tuple(int(b) for b in np.flatnonzero(self._track_ints[:, TRACK_TRACKED]))
        self._tracked_set = tuple(self._layout(self._tracked)) if self._tracked else ()  # the kernels' argument
        # by blob label: free for acquisition unless a marker of a tracked body (label -1: the last entry)
        self._label_free = np.append(self._track_ints[self._marker_body, TRACK_TRACKED] == 0, True)
        if self.points is not None:  # a tracked point body's blob (labelled by _track_points) is not free
            self._label_free[self._marker_start[self._point_bodies]] = ~self.points.tracked
        self._motion = None

    def _motion_cache(self) -> tuple[int, np.ndarray]:
        """(t_c, motion (3, sum M_b, 3)): the tracked bodies' marker positions, velocities and
        accelerations at t_c, the newest filter time.

        The filters change only in fusions, and each fusion with tracked bodies
        leaves this for the next frames (_fuse_tracked), so each frame only
        evaluates X0 + dt V + dt^2 / 2 A (error ~ r (w dt)^3 / 6, micrometres).
        It is computed here after the tracked set changed.
        """
        if self._motion is None:
            t_c, motion = _tracked_motion(self.bank.arrays, self._tracked_set)
            self._motion = (int(t_c), motion)
        return self._motion

    def _observe(self, cam: int, t_ns: int, px: np.ndarray) -> Observation:
        proj = self._proj[cam]
        v = self._cam_index[cam]
        self._capture_ns[v] = t_ns
        marker_xn = self._marker_xn[v]  # this camera's row of the shared array
        if not self._tracked or not len(px):
            marker_xn[:] = np.nan
            self._marker_ok[v] = False
            return Observation(t_ns, proj.undistort(px), np.full(len(px), -1, dtype=np.int64), marker_xn)
        t_c, motion = self._motion_cache()
        # the image-space manoeuvre detector: plenty often for a detector, and saves CPU
        image_nis = abs(t_ns - self._last_img_ns) >= _IMAGE_NIS_INTERVAL_NS
        if image_nis:
            self._last_img_ns = t_ns
        xn, label, pred_px = _observe_frame(px, (t_ns - t_c) * 1e-9, motion, self._tracked_set, marker_xn,
                                            self._marker_ok[v], proj.packed, self._gate_px, self._unique_sigmas,
                                            image_nis, t_ns, self.bank.arrays, self._track_floats)
        return Observation(t_ns, xn, label, marker_xn, pred_px, self._tracked_set[1])

    # ----------------------------------------------------------------- fusion
    def _views(self, cams: tuple[int, ...]) -> tuple:
        """The ViewSet of `cams`: camera indices (V,), R (V, 3, 3), t (V, 3), focal_px (V,), packed cameras
        (V, N_CAMERA), as the plain tuple the kernels take (cached per set)."""
        views = self._view_cache.get(cams)
        if views is None:
            index = np.array([self._cam_index[c] for c in cams], dtype=np.int64)
            views = tuple(ViewSet(index, self._R[index], self._t[index], self._focal_px[index],
                                  self._camera_packed[index]))
            self._view_cache[cams] = views
        return views

    def _fuse(self, g: Group) -> None:
        obs = self.obs
        cams = g.cameras
        if not all(c in obs for c in cams):
            cams = tuple(c for c in cams if c in obs)
            if not cams:
                return
        st = self.settings
        ref = g.ref_ns
        self._stats["fusions"] += 1
        views = self._views(cams)
        if self._tracked:
            imu = self.imu if self.imu is not None and self.imu.live else None
            if imu is not None:
                imu.before_fusion(self._tracked, self.bank.filters, ref)
            self._update_tracked(views, ref, g.compensate)
            if imu is not None:
                imu.after_fusion(self._tracked, self.last_raw, ref)
                for tap in self._pose_taps:  # the optical-only attitude, while the IMU is in the filters
                    for b in self._tracked:
                        raw = self.last_raw.get(b)
                        if raw is not None and raw[0] == ref:
                            tap(self.models[b].name, ref, raw[2])
        if self.points is not None and self.points.due(ref):
            self._track_points([obs[c] for c in cams], views, ref)
        # acquisition is for lost bodies; with all tracked it only refreshes the loose points
        lost = len(self._tracked) < self._n_rigid
        interval = st.acquire_interval_ns if lost else st.loose_points_interval_ns
        lost_ns = max(st.kalman.lost_timeout_ns, _LOST_PERIODS * self.aligner.slowest_period_ns())
        if self._acquiring is not None:
            if ref - self._acquire_step_ns >= st.acquire_interval_ns or ref < self._acquire_step_ns:
                self._acquire_step(ref, lost_ns)
        elif (lost or st.loose_points) and (ref - self._last_acquire_ns >= interval or ref < self._last_acquire_ns):
            cam_index, R, t, focal_px, _ = views
            self._acquiring = self._acquire([obs[c] for c in cams], cam_index, R, t, focal_px, ref)
            self._acquire_began_ns = ref
            self._acquire_step(ref, lost_ns)
        # lost-track bookkeeping on the capture clock
        track_ints = self._track_ints
        gone = [b for b in self._tracked if ref - track_ints[b, TRACK_LAST_UPDATE_NS] > lost_ns]
        if self.identity.shared and self.points is None:
            self.identity.after_fusion(ref, self._tracked, self.bank.x, self.bank.P)
        elif self.identity.shared:
            self._identity_with_points(ref)
        if gone:
            track_ints[gone, TRACK_TRACKED] = 0
            self._stats["lost"] += len(gone)
            for b in gone:
                self.untracked_why[b] = _LOST_WHY.get(self.last_verdict[b],
                                                      "no new measurement: its cameras sent no frames")
            self._tracking_changed()

    def _layout(self, tracked: tuple[int, ...]) -> TrackedSet:
        """The TrackedSet of a non-empty set of tracked bodies (cached): the bodies (B,), their global
        marker rows (M,), marker counts (B,), for each row the index of its body in `tracked` (M,),
        and the body-frame markers of the rows (M, 3)."""
        key = tuple(tracked)
        lay = self._layout_cache.get(key)
        if lay is None:
            sizes = np.array([self._marker_start[b + 1] - self._marker_start[b] for b in tracked], dtype=np.int64)
            rows = np.concatenate([np.arange(self._marker_start[b], self._marker_start[b + 1]) for b in tracked])
            lay = TrackedSet(np.array(tracked, dtype=np.int64), rows, sizes, np.repeat(np.arange(len(tracked)), sizes),
                             self._marker_local[rows])
            self._layout_cache[key] = lay
        return lay

    def _update_tracked(self, views: tuple, ref: int, compensate: bool) -> None:
        """One fusion of the tracked bodies (_fuse_tracked) from the ViewSet `views` at ref (ns)."""
        tracked = self._tracked
        cameras, _, _, _, _ = views
        reuse = min(len(cameras), self._max_reuse) if compensate else 1.0
        verdict, meas, refused, t_c, motion = _fuse_tracked(
            self._marker_xn, self._marker_ok, self._capture_ns, views, ref, self._tracked_set, self._kernel_params,
            bool(compensate), float(reuse), self.bank.arrays, self._track_rows_arg,
        )
        # the filters moved: the next frames predict their markers from this fusion
        self._motion = (int(t_c), motion)
        stats = self._stats
        stats["rejected_residual"] += int(refused)
        last_verdict = self.last_verdict
        # Python ints: numpy compares its scalars with an IntEnum member slowly (microseconds)
        for i, (b, v) in enumerate(zip(tracked, verdict.tolist())):
            last_verdict[b] = v
            for counter in _VERDICT_COUNTERS[v]:
                stats[counter] += 1
            if v in _POSE_FITTED:
                m = meas[i]
                self.last_raw[b] = (ref, m[MEAS_POS], m[MEAS_ROT].reshape(3, 3))

    def _acquire_step(self, ref: int, lost_ns: int) -> None:
        """One step (fusion.acquire_step_ms) of the acquisition under way at the fusion at ref (ns); the rest at
        once where it began 2/3 of the lost timeout ago (its bodies start from its frames) or the clock went back."""
        st = self.settings
        late = ref - self._acquire_began_ns > 2 * lost_ns // 3 or ref < self._acquire_step_ns
        at_once = late or self._acquire_at_once or st.acquire_step_ns <= 0
        self._acquire_step_ns = ref
        done, _ = advance(self._acquiring, float("inf") if at_once else st.acquire_step_ns)
        if done:  # the next one acquire_interval_ms after this one ended: its frames are new ones
            self._acquiring = None
            self._last_acquire_ns = ref

    def _acquire(self, obs: list[Observation], cam_index: np.ndarray, R: np.ndarray, t: np.ndarray,
                 focal_px: np.ndarray, ref: int) -> Steps[None]:
        """Match leftover blobs across views (cam_index (V,): their cameras' indices); identify lost bodies; report
        loose points. In steps (fusion/steps.py); the bodies it finds start at ref, from these frames."""
        st = self.settings
        lost = [b for b in range(len(self.tracks)) if b not in self._tracked and b not in self._point_row]
        if not lost and not st.loose_points:
            return
        free = [np.flatnonzero(self._label_free[o.label]) for o in obs]
        seeing = sum(len(fr) > 0 for fr in free)
        if seeing < 2:
            for b in lost:
                self.untracked_why[b] = (f"not seen by enough cameras: {seeing} of {len(obs)} see blobs no "
                                         "tracked body explains (2 needed)")
            self.loose_points = LoosePoints(ref, np.zeros((0, 3)), np.zeros(0))
            return
        xs = [o.xn[fr] for o, fr in zip(obs, free)]
        # a body lost after it was tracked is most likely flying: it would have moved before the last step
        again = bool(self._was_tracked[lost].any())
        steps = match_unlabeled_steps(xs, R, t, focal_px, st.acquire_ray_gate_px, st.max_residual_px)
        pts, idx, rms = finish(steps) if again else (yield from steps)
        if not lost or len(pts) < 3:
            for b in lost:
                self.untracked_why[b] = (f"not seen by enough cameras: {len(pts)} marker(s) seen by two cameras "
                                         "or more (3 needed)")
            self.loose_points = LoosePoints(ref, pts, rms)
            return
        left = np.ones(len(pts), dtype=bool)
        ambiguous: set[int] = set()
        steps = identify_steps(pts, self.models, st.identify_tolerance_m, st.min_markers, lost, ambiguous)
        found = finish(steps) if again else (yield from steps)
        if self._acquire_step_ns != ref:
            yield len(found) * _MOVED_CHECK_NS  # the check below, before it runs
        moved = self._moved_since(found, ref) if self._acquire_step_ns != ref else set()
        if moved:  # a track must not start from frames its body has left: acquisition at once from now on
            found = [ident for ident in found if ident.body not in moved]
            self._acquire_at_once = True
        found = self.identity.acquired(found, lost)
        for b in set(lost) - {ident.body for ident in found}:
            self.untracked_why[b] = (
                "it moved while acquisition ran over several frames: acquired again from the newest" if b in moved
                else "identification ambiguous: its visible markers fit another body as well" if b in ambiguous
                else f"{len(pts)} markers triangulated, none fits its layout within "
                     f"{st.identify_tolerance_m * 1e3:.0f} mm")
        for n_found, ident in enumerate(found):
            if n_found and not again:
                yield _START_TRACK_NS
            b = ident.body
            self._was_tracked[b] = True
            tr = self.tracks[b]
            matched = ident.point_index >= 0
            n_id = int(matched.sum())
            tr.marker_var = max(ident.rms**2 * n_id / max(n_id - 2, 1), st.kalman.marker_sigma_m**2)
            tr.filter.initialize(
                ref, ident.t, ident.R, pose_measurement_cov(pts[ident.point_index[matched]], ident.t, tr.marker_var)
            )
            tr.tracked = True
            tr.update_kind = UpdateKind.POSE
            self._track_info[b] = 0.0
            # the frames that identified it are in the filter: the single-view path must not count them again
            self._track_view_ns[b, cam_index] = np.maximum(self._track_view_ns[b, cam_index],
                                                           [o.capture_ns for o in obs])
            self.untracked_why.pop(b, None)
            tr.first_reject_ns = None
            tr.last_update_ns = ref
            tr.last_capture_ns = max(o.capture_ns for o in obs)
            tr.n_markers = ident.n_markers
            tr.residual_mm = ident.rms * 1e3
            self._stats["acquisitions"] += 1
            # label the blobs that made the body in the stored frames, so the
            # next fusions see it in every camera at once
            for m, q in enumerate(ident.point_index):
                if q < 0:
                    continue
                left[q] = False
                for v, o in enumerate(obs):
                    j = idx[q, v]
                    if j >= 0:
                        blob = free[v][j]
                        o.label[blob] = self._marker_start[b] + m
                        o.marker_xn[self._marker_start[b] + m] = o.xn[blob]
            first, end = self._marker_start[b], self._marker_start[b + 1]
            tr.n_cameras = int(sum((o.label >= first).any() and (o.label < end).any() for o in obs))
            self._tracking_changed()
        self.loose_points = LoosePoints(ref, pts[left], rms[left])

    def _moved_since(self, found: list[Identification], ref: int) -> set[int]:
        """The bodies of `found` (identified in frames up to ref ns) that the frames taken since do not show
        where they were (acquisition.still_seen within _STILL_PX in two of the cameras with a newer frame)."""
        newer = [c for c in sorted(self.obs) if self.obs[c].capture_ns > ref]
        index = np.array([self._cam_index[c] for c in newer], dtype=np.int64)
        seen = still_seen([self.models[f.body].markers[f.point_index >= 0] @ f.R.T + f.t for f in found],
                          [self.obs[c].xn[self._label_free[self.obs[c].label]] for c in newer], self._R[index],
                          self._t[index], self._focal_px[index], _STILL_PX, self.settings.min_markers)
        return {f.body for f, ok in zip(found, seen) if not ok}

    # ----------------------------------------------------------- point bodies
    def _track_points(self, obs: list[Observation], views: tuple, ref: int) -> None:
        """One point fusion (point_tracks.py) at ref (ns) from the blobs no tracked body took in obs (the fusion's
        frames, cameras `views`): triangulate them, update the point tracks, label the blobs they took, lose the
        stale ones, and acquire lost point bodies from confirmed new points, named as the identity book names
        bodies of a shared layout."""
        st, pt = self.settings, self.points
        cam_index, R, t, focal_px, _ = views
        free = [np.flatnonzero(self._label_free[o.label]) for o in obs]
        pts, idx, rms = match_unlabeled([o.xn[fr] for o, fr in zip(obs, free)], R, t, focal_px,
                                        st.acquire_ray_gate_px, st.max_residual_px)
        n_views = (idx >= 0).sum(axis=1)
        # per axis: the reprojection residual (at least 0.2 px) at the farthest camera's range, over the views
        centres = -np.einsum("vji,vj->vi", R, t)
        far_m = np.sqrt(((pts[:, None] - centres[None]) ** 2).sum(-1)).max(axis=1) if len(pts) else np.zeros(0)
        var = (np.maximum(rms, 0.2) * far_m / float(np.min(focal_px))) ** 2 / np.maximum(n_views, 1)
        capture = max(o.capture_ns for o in obs)
        seen = idx >= 0
        t_obs = np.array([o.capture_ns for o in obs], dtype=np.int64)
        t_meas = ((seen * (t_obs - capture)).sum(axis=1) // np.maximum(n_views, 1) + capture).astype(np.int64)
        used = pt.step(ref, pts, var, n_views, t_meas, capture)
        for q in np.flatnonzero(used >= 0).tolist():
            row = int(self._marker_start[self._point_bodies[used[q]]])
            pt.residual_px[used[q]] = rms[q]
            for v, o in enumerate(obs):
                if idx[q, v] >= 0:
                    o.label[free[v][idx[q, v]]] = row
        lost_ns = max(st.kalman.lost_timeout_ns, _LOST_PERIODS * self.aligner.slowest_period_ns())
        changed = False
        for k in np.flatnonzero(pt.tracked & (ref - pt.last_update_ns > lost_ns)).tolist():
            pt.tracked[k], changed = False, True
            self._stats["lost"] += 1
            self.untracked_why[self._point_bodies[k]] = "its marker was not seen by two cameras near its prediction"
        lost = [b for k, b in enumerate(self._point_bodies) if not pt.tracked[k]]
        if lost:
            confirmed = pt.candidates(pts[used < 0], n_views[used < 0])
            for b in lost:
                self.untracked_why[b] = "no new point seen by three cameras for a while"
            found = [Identification(lost[0], np.zeros(1, np.int64), np.eye(3), p, 0.0) for p in confirmed[:len(lost)]]
            for f in self.identity.acquired(found, lost):
                k = self._point_row[f.body]
                near = int(np.argmin(((pts - f.t) ** 2).sum(-1)))
                pt.start(k, ref, f.t, float(var[near]), capture)
                self.untracked_why.pop(f.body, None)
                self._stats["acquisitions"] += 1
                changed = True
        else:
            pt.cand, pt.hits = pt.cand[:0], pt.hits[:0]  # candidates are for lost bodies, fresh each time
        if changed:
            self._tracking_changed()

    def _identity_with_points(self, ref: int) -> None:
        """IdentityBook.after_fusion over the rigid and the point tracks (the point filters' positions and
        velocities in the rigid states' places)."""
        pt = self.points
        x, P = self.bank.x.copy(), self.bank.P.copy()
        rows = np.array(self._point_bodies)
        x[rows, X_POS], x[rows, X_VEL] = pt.x[:, :3], pt.x[:, 3:6]
        P[rows, X_POS, X_POS] = pt.P[:, :3, :3]
        tracked = tuple(sorted(self._tracked + tuple(rows[pt.tracked].tolist())))
        self.identity.after_fusion(ref, tracked, x, P)

    def _is_tracked(self, b: int) -> bool:
        k = self._point_row.get(b)
        return bool(self.tracks[b].tracked) if k is None else bool(self.points.tracked[k])

    def _point_state(self, b: int, now_ns: int, max_prediction_ns: int, lost_ns: int) -> BodyState:
        """A point body's BodyState at now_ns: position and velocity with their covariances; no attitude (NaN
        quaternion, body rates and rotation covariance: a point has none), n_markers 1."""
        pt, k, model = self.points, self._point_row[b], self.models[b]
        age = now_ns - int(pt.last_update_ns[k])
        nan3 = np.full(3, np.nan)
        cov = np.full((6, 6), np.nan)
        if pt.tracked[k] and age <= max_prediction_ns and age <= lost_ns:
            p, v, Pp, Pv = pt.output_at(k, now_ns)
            cov[:3, :3] = Pp
            return BodyState(name=model.name, body_id=model.id, time_ns=int(now_ns),
                             capture_ns=int(pt.last_capture_ns[k]), position=p, quaternion=np.full(4, np.nan),
                             velocity=v, angular_velocity=nan3, covariance=cov, velocity_covariance=Pv, tracked=True,
                             n_markers=1, n_cameras=int(pt.n_cameras[k]),
                             residual_mm=float("nan"), update_kind="position")
        return BodyState(name=model.name, body_id=model.id, time_ns=int(now_ns),
                         capture_ns=int(pt.last_capture_ns[k]), position=nan3, quaternion=np.full(4, np.nan),
                         velocity=nan3.copy(), angular_velocity=nan3.copy(), covariance=cov,
                         velocity_covariance=np.full((3, 3), np.nan), tracked=False)

    # ----------------------------------------------------------------- output
    def tick(self, now_ns: int) -> list[BodyState]:
        """One BodyState per configured body, predicted to now_ns.

        First the fusion the rate limit deferred, if no later frame took it (TimeAligner.take_deferred): every
        frame admitted before a tick is in its output, even when the frame that would end its burst is lost
        or late. Otherwise the filters do not change. A body not updated within max_prediction (or lost) is
        reported with tracked=False and NaN pose: a stale pose is never re-sent.
        """
        if self._imu_sources and self.imu is not None:
            self._drain_imu(int(now_ns), "tick")
        pending = self.aligner.take_deferred()
        if pending is not None:
            self._stats["fused_at_tick"] += 1
            self._fuse(pending)
        st = self.settings
        out = []
        # stations slower than configured: a body is updated about once per frame interval
        slowest = self.aligner.slowest_period_ns()
        max_prediction_ns = max(st.kalman.max_prediction_ns, _PREDICTION_PERIODS * slowest)
        lost_ns = max(st.kalman.lost_timeout_ns, _LOST_PERIODS * slowest)
        for b, (model, tr) in enumerate(zip(self.models, self.tracks)):
            if b in self._point_row:
                out.append(self._point_state(b, now_ns, max_prediction_ns, lost_ns))
                continue
            row = self._track_ints[b].tolist()  # Python ints, read once
            age = now_ns - row[TRACK_LAST_UPDATE_NS]
            if row[TRACK_TRACKED] and age <= max_prediction_ns and age <= lost_ns:
                p, q, v, w_body, cov, vcov, acc = (tr.filter.output_at(now_ns) if self.imu is None or not self.imu.live
                                                   else self.imu.output_at(b, tr.filter, now_ns))
                out.append(
                    BodyState(
                        name=model.name,
                        body_id=model.id,
                        time_ns=int(now_ns),
                        capture_ns=row[TRACK_LAST_CAPTURE_NS],
                        position=p,
                        quaternion=q,
                        velocity=v,
                        angular_velocity=w_body,
                        covariance=cov,
                        velocity_covariance=vcov,
                        tracked=True,
                        n_markers=row[TRACK_N_MARKERS],
                        n_cameras=row[TRACK_N_CAMERAS],
                        residual_mm=float(self._track_floats[b, TRACK_RESIDUAL_MM]),
                        reset_counter=row[TRACK_RESETS],
                        update_kind=_UPDATE_NAMES[row[TRACK_UPDATE_KIND]], acceleration=acc,
                    )
                )
            else:
                nan3 = np.full(3, np.nan)
                out.append(
                    BodyState(
                        name=model.name,
                        body_id=model.id,
                        time_ns=int(now_ns),
                        capture_ns=int(tr.last_capture_ns),
                        position=nan3,
                        quaternion=np.full(4, np.nan),
                        velocity=nan3.copy(),
                        angular_velocity=nan3.copy(),
                        covariance=np.full((6, 6), np.nan),
                        velocity_covariance=np.full((3, 3), np.nan),
                        tracked=False,
                        n_markers=0,
                        n_cameras=0,
                        reset_counter=tr.reset_counter,
                    )
                )
        return out

    def set_camera_pose(self, camera_id: int, camera: Camera) -> None:
        """Replace a camera's pose while tracking goes on (the continuous calibration's correction,
        fusion/camera_monitor.py): every array and cache that holds it is updated; the next frame uses it."""
        i = self._cam_index[camera_id]
        self.cameras[camera_id] = camera
        self._R[i], self._t[i] = camera.R, camera.t
        self._proj[camera_id] = Projector(camera)
        self._camera_packed[i] = self._proj[camera_id].packed
        self._view_cache.clear()
        self.arena = self.arena.with_cameras([self.cameras[c.id] for c in self.arena.cameras])

    def snapshot(self) -> FusionSnapshot:
        """What the operator console shows (fusion/snapshot.py); references to this pipeline's arrays, no copies."""
        cams = {cid: CameraFrame(o.capture_ns, self.last_px[cid], o.xn, o.label, o.pred_px, o.pred_rows)
                for cid, o in self.obs.items() if cid in self.last_px}
        tracked = tuple(self._is_tracked(b) for b in range(len(self.tracks)))
        return FusionSnapshot(cams, tracked, dict(self.untracked_why), self.loose_points, self.identity.states())

    def stats(self) -> dict[str, Any]:
        """Counters: frames, fusions, measurements, rejections by reason, per-camera frames, per-body state."""
        d: dict[str, Any] = dict(self._stats)
        d["per_camera_frames"] = dict(sorted(self._per_camera.items()))
        d["bodies"] = {
            m.name: {"tracked": self._is_tracked(b), "reset_counter": tr.reset_counter,
                     "n_markers": tr.n_markers if b not in self._point_row else int(self._is_tracked(b)),
                     "identity": self.identity.state[b].value}
            for b, (m, tr) in enumerate(zip(self.models, self.tracks))
        }
        d["time_alignment"] = self.settings.time_alignment
        if self.imu is not None:  # per body: samples pushed, used, refused, late, invalid; dropped; bias fits
            d["imu"] = {m.name: {**i.stats, "dropped": i.dropped, "bias_fits": i.bias_fits}
                        for m, i in zip(self.models, self.imu.bodies)}
        return d
