"""Mapping estimates from the calibrated world (reference camera frame) into the ground-truth world."""

from __future__ import annotations

import numpy as np

from rigbuild.camera import Camera, look_at
from rigbuild.eval.frames import calibrated_to_ground_truth, points_to_ground_truth, vectors_to_ground_truth
from rigbuild.geometry.rigid import apply_rigid
from rigbuild.io.cameras import write_cameras


def test_calibrated_world_maps_onto_ground_truth_world(tmp_path):
    K = [[800, 0, 320], [0, 800, 240], [0, 0, 1]]
    truth = [Camera(f"c{i}", 640, 480, K, np.zeros(5), *look_at(c, [0, 0, 0]))
             for i, c in enumerate([[400, 0, 300], [-400, 50, 300], [0, 300, 400], [0, -200, 450]])]
    # the calibrated world is the first camera's frame: x_cal = R0 x_gt + t0
    R0, t0 = truth[0].R, truth[0].t
    est = [Camera(c.id, 640, 480, K, np.zeros(5), c.R @ R0.T, c.t - c.R @ R0.T @ t0) for c in truth]
    write_cameras(tmp_path / "gt" / "cameras.json", truth)
    sim = calibrated_to_ground_truth(tmp_path / "gt", est)
    X = np.random.default_rng(0).normal(scale=50, size=(20, 3))
    X_cal = apply_rigid(X, R0, t0)
    assert np.allclose(points_to_ground_truth(X_cal, sim), X, atol=1e-9)
    d = np.random.default_rng(1).normal(size=(5, 20, 3))
    assert np.allclose(vectors_to_ground_truth(d @ R0.T, sim), d, atol=1e-9)
    assert abs(sim[0] - 1.0) < 1e-12
