"""Rigid-body identification (visionpos/fusion/rigidbody.py); the Kabsch kernels are in
tests/geometry/test_alignment.py."""

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos.config.arena import load_arena
from visionpos.fusion.rigidbody import BodyModel, identify, layout_ambiguities
from visionpos.geometry.alignment import kabsch_horn_batch


def _models(name="arena8"):
    return [BodyModel(b.name, b.id, b.markers) for b in load_arena(name).bodies]


def test_identify_several_bodies_among_clutter():
    models = _models()
    rng = np.random.default_rng(3)
    pts, truth = [], []
    poses = []
    for bi, m in enumerate(models):
        R = Rotation.random(random_state=10 + bi).as_matrix()
        t = np.array([-1.0 + bi, 0.3 * bi, 1.0])
        poses.append((R, t))
        p = m.markers @ R.T + t + rng.normal(0, 0.0005, m.markers.shape)
        pts.append(p)
        truth += [(bi, k) for k in range(len(p))]
    clutter = rng.uniform([-1.5, -1.5, 0.5], [1.5, 1.5, 1.5], (6, 3))
    pts.append(clutter)
    truth += [(-1, -1)] * len(clutter)
    P = np.vstack(pts)
    order = rng.permutation(len(P))
    P = P[order]
    truth = [truth[i] for i in order]
    found = identify(P, models, tolerance=0.008)
    assert sorted(f.body for f in found) == [0, 1, 2]
    for f in found:
        for m, q in enumerate(f.point_index):
            assert truth[q] == (f.body, m)
        R, t = poses[f.body]
        assert np.linalg.norm(f.t - t) < 0.002
        assert np.degrees(Rotation.from_matrix(f.R @ R.T).magnitude()) < 1.0


def test_identify_with_three_of_four_markers():
    models = _models()
    R = Rotation.from_euler("zyx", [40, 10, -5], degrees=True).as_matrix()
    t = np.array([0.5, -0.2, 1.2])
    p = models[0].markers @ R.T + t
    found = identify(p[[0, 2, 3]], models, tolerance=0.008)
    assert len(found) == 1 and found[0].body == 0
    assert found[0].point_index.tolist() == [0, -1, 1, 2]
    assert np.linalg.norm(found[0].t - t) < 1e-6


def test_identify_rejects_too_few_and_unrelated_points():
    models = _models()
    assert identify(np.zeros((2, 3)), models) == []
    rng = np.random.default_rng(5)
    assert identify(rng.uniform(-2, 2, (4, 3)), models, tolerance=0.003) == []


def test_layout_ambiguities():
    assert layout_ambiguities(_models("arena8"), 0.005) == []
    assert layout_ambiguities(_models("thesis"), 0.005) == []
    square = BodyModel("square", 9, np.array([[0.1, 0, 0], [0, 0.1, 0], [-0.1, 0, 0], [0, -0.1, 0]]))
    msgs = layout_ambiguities([square], 0.005)
    assert any("symmetric" in s for s in msgs)
    twin = BodyModel("twin", 10, _models()[0].markers + 0.5)
    assert any("swapped" in s for s in layout_ambiguities([_models()[0], twin], 0.005))


def test_pose_measurement_covariance_matches_monte_carlo():
    from visionpos.fusion.measurements import pose_measurement_cov

    m = _models()[2].markers  # five markers
    R0 = Rotation.from_euler("zyx", [30, 20, -10], degrees=True).as_matrix()
    t0 = np.array([0.3, -0.2, 1.1])
    mw = m @ R0.T + t0
    sigma = 0.001
    rng = np.random.default_rng(7)
    N = 4000
    dst = mw[None] + rng.normal(0, sigma, (N, len(m), 3))
    R, t = kabsch_horn_batch(np.broadcast_to(m, dst.shape), dst, np.ones((N, len(m))))
    rv = Rotation.from_matrix(R @ R0.T).as_rotvec()
    emp = np.cov(np.hstack([t - t0, rv]).T)
    pred = pose_measurement_cov(mw, t0, sigma**2)
    # same covariance within Monte-Carlo scatter (diagonals within 10 %, correlations within 0.1)
    assert np.allclose(np.diag(emp), np.diag(pred), rtol=0.1)
    d = np.sqrt(np.diag(pred))
    assert np.abs(emp / np.outer(d, d) - pred / np.outer(d, d)).max() < 0.1
