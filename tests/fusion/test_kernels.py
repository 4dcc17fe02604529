"""The fusion kernels' packed layouts (layout.py) against the code that builds and reads them."""

import numpy as np

from visionpos.fusion import layout as L
from visionpos.fusion.body_filter import FilterBank
from visionpos.fusion.kernels import _pack_states, _tracked_motion
from visionpos.fusion.matching import Projector
from visionpos.fusion.settings import KalmanSettings
from visionpos.fusion.tracks import PX_VAR_PRIOR, Track, new_track_rows
from visionpos.sim import load_scenario


def test_projector_packs_the_camera_as_the_layout_names_it():
    cam = load_scenario("thesis", session="hover", duration=0.1).arena.cameras[0]
    proj = Projector(cam)
    packed = proj.packed
    assert packed.shape == (L.N_CAMERA,)
    assert np.array_equal(packed[L.CAMERA_R].reshape(3, 3), proj.R)
    assert np.array_equal(packed[L.CAMERA_T], proj.t)
    assert np.array_equal(packed[L.CAMERA_INTRINSICS], proj.intrinsics)
    assert packed[L.CAMERA_INTRINSICS][L.INTRINSICS_FX] == cam.model.fx
    assert packed[L.CAMERA_INTRINSICS][L.INTRINSICS_FY] == cam.model.fy
    assert np.array_equal(packed[L.CAMERA_DIST], proj.dist)
    assert packed[L.CAMERA_COS_MAX] == proj.cos_max and packed[L.CAMERA_FISHEYE] == float(proj.fisheye)


def test_filter_bank_arrays_are_in_filter_arrays_order():
    bank = FilterBank(2, KalmanSettings())
    assert len(bank.arrays) == len(L.FilterArrays._fields)
    for field, array in zip(L.FilterArrays._fields, bank.arrays):
        assert array is getattr(bank, field)
    assert bank.adapt.shape == (2, L.N_ADAPT) and bank.clock.shape == (2, L.N_CLOCK)
    assert bank.params.shape == (L.N_KALMAN_PARAMS,) and bank.params[L.KALMAN_GATE_CHI2] == KalmanSettings().gate_chi2


def test_verdict_enum_and_kernel_constants_agree():
    assert [int(v) for v in L.Verdict] == [L.VERDICT_TOO_FEW, L.VERDICT_FIT_REJECTED, L.VERDICT_ACCEPTED,
                                           L.VERDICT_GATED, L.VERDICT_RESET, L.VERDICT_VIEWS,
                                           L.VERDICT_VIEWS_UNCONSTRAINED, L.VERDICT_VIEWS_GATED]
    assert [int(v) for v in L.UpdateKind] == [L.UPDATE_NONE, L.UPDATE_POSE, L.UPDATE_VIEWS]
    assert L.Verdict.ACCEPTED < L.Verdict.GATED < L.Verdict.RESET  # the pipeline counts v >= ACCEPTED as measured


def test_track_views_read_and_write_the_packed_rows():
    rows = new_track_rows(2)
    assert rows.ints.shape == (2, L.N_TRACK_INTS) and rows.floats.shape == (2, L.N_TRACK_FLOATS)
    track = Track(None, rows.ints[1], rows.floats[1])
    assert track.first_reject_ns is None and track.px_var == PX_VAR_PRIOR and np.isnan(track.residual_mm)
    track.tracked, track.n_markers, track.first_reject_ns, track.marker_var = True, 4, 123, 2e-8
    assert rows.ints[1, L.TRACK_TRACKED] == 1 and rows.ints[1, L.TRACK_N_MARKERS] == 4
    assert rows.ints[1, L.TRACK_FIRST_REJECT_NS] == 123 and rows.floats[1, L.TRACK_MARKER_VAR] == 2e-8
    assert rows.ints[0, L.TRACK_TRACKED] == 0 and rows.ints[0, L.TRACK_FIRST_REJECT_NS] == L.NO_TIME  # untouched


def test_packed_states_and_marker_motion_of_a_moving_body():
    bank = FilterBank(2, KalmanSettings())
    b = 1
    bank.x[b, L.X_POS] = [1.0, 2.0, 3.0]
    bank.x[b, L.X_VEL] = [0.5, 0.0, 0.0]
    bank.P[b, L.VEL0 + 1, L.VEL0 + 1] = 0.3  # mean velocity variance (1 + 0.3 + 1) / 3
    bank.clock[b, L.CLOCK_T_NS] = 1_000_000_000
    bodies = np.array([b], dtype=np.int64)
    states = _pack_states(bank.arrays, bodies, 1_100_000_000)
    assert states.shape == (1, L.N_STATE_COLS)
    assert np.array_equal(states[0, L.STATE_X], bank.x[b])
    assert np.array_equal(states[0, L.STATE_R_NOM].reshape(3, 3), bank.R_nom[b])
    assert np.isclose(states[0, L.STATE_DT_S], 0.1)
    assert np.isclose(states[0, L.STATE_VEL_VAR], 2.3 / 3) and states[0, L.STATE_RATE_VAR] == 1.0
    local = np.array([[0.1, 0.0, 0.0], [0.0, 0.2, 0.0]])
    tracked = tuple(L.TrackedSet(bodies, np.array([4, 5]), np.array([2]), np.array([0, 0]), local))
    t_c, motion = _tracked_motion(bank.arrays, tracked)
    assert t_c == 1_000_000_000 and motion.shape == (3, 2, 3)
    assert np.allclose(motion[L.MOTION_POS], [[1.1, 2.0, 3.0], [1.0, 2.2, 3.0]])
    assert np.allclose(motion[L.MOTION_VEL], [[0.5, 0.0, 0.0]] * 2) and not motion[L.MOTION_ACC].any()
