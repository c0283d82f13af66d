"""Exact tests of the tracking error measures (rigbuild.eval.tracking)."""

from __future__ import annotations

import numpy as np
import pytest

from rigbuild.eval.tracking import session_tracking_metrics, surface_anchors, tracking_summary


def _mesh():
    V = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0]], float)
    F = np.array([[0, 1, 2], [1, 3, 2]])
    return V, F


def test_vertex_and_correspondence_errors_exact():
    V, F = _mesh()
    truth = np.stack([V, V + [0, 0, 2.0], V + [1.0, 0, 0]])
    # registration slid every vertex by 0.5 mm along x (tangential error), tracking then exact on the surface
    reg = V + np.array([[0.5, 0, 0], [-0.5, 0, 0], [0.5, 0, 0], [-0.5, 0, 0]])  # stays on the surface
    tracked = np.stack([reg, reg + [0, 0, 2.0], reg + [1.0, 0, 0]])
    s = tracking_summary(tracked, truth, F, np.arange(4), reg, V)
    assert s["mean_error_mm"] == pytest.approx(0.5)
    assert s["end_error_mm"] == pytest.approx(0.5)
    assert s["corr_mean_error_mm"] == pytest.approx(0.0, abs=1e-9)
    # now a drift of 0.3 mm in z at the last frame only
    tracked[2] += [0, 0, 0.3]
    s = tracking_summary(tracked, truth, F, np.arange(4), reg, V)
    assert s["corr_end_error_mm"] == pytest.approx(0.3)
    assert s["corr_per_frame_mean_mm"][0] == pytest.approx(0.0, abs=1e-9)
    m = session_tracking_metrics({"a": s, "b": s})
    assert m["end_drift_mm"] == pytest.approx(np.linalg.norm([0.5, 0, 0.3]))
    assert m["corr_end_drift_mm"] == pytest.approx(0.3)


def test_surface_anchors_exact():
    V, F = _mesh()
    tri, bary = surface_anchors(np.array([[2.0, 3.0, 1.0], [9.0, 8.0, -2.0]]), V, F)
    np.testing.assert_allclose(np.einsum("nk,nkd->nd", bary, V[F[tri]]), [[2, 3, 0], [9, 8, 0]], atol=1e-12)


def test_ground_truth_tracking_metrics_from_files_exact(tmp_path):
    """Estimates in a calibrated world rotated 90 deg about z and shifted: mapped back exactly by the
    camera-centre similarity; a 0.2 mm offset of the last frame is the end drift."""
    from rigbuild.camera import Camera, look_at
    from rigbuild.eval.tracking import ground_truth_tracking_metrics
    from rigbuild.io.cameras import write_cameras

    V, F = _mesh()
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    truth_cams = []
    for i, eye in enumerate([[0, 0, 500], [300, 0, 400], [-300, 0, 400], [0, 300, 400]]):
        R, t = look_at(np.array(eye, float), np.zeros(3), np.array([0, 1.0, 0]))
        truth_cams.append(Camera(f"cam{i:02d}", 640, 480, K, np.zeros(5), R, t))
    Rz = np.array([[0, -1.0, 0], [1, 0, 0], [0, 0, 1]])
    shift = np.array([5.0, -3.0, 2.0])  # calibrated world: x_cal = Rz x_gt + shift

    def to_cal(x):
        return x @ Rz.T + shift

    cal_cams = [Camera(c.id, c.width, c.height, c.K, c.dist, c.R @ Rz.T, c.t - c.R @ Rz.T @ shift) for c in truth_cams]
    gt = tmp_path / "ground_truth"
    (gt / "rom").mkdir(parents=True)
    write_cameras(gt / "cameras.json", truth_cams)
    write_cameras(tmp_path / "cameras.json", cal_cams)
    truth = np.stack([V, V + [0, 0, 1.0], V])
    np.savez(gt / "rom" / "rom00.npz", vertices=truth.astype(np.float32), frames=np.array([0, 1, 2]))
    tracked = truth.copy()
    tracked[2] += [0, 0.2, 0]
    values, per = ground_truth_tracking_metrics(gt, tmp_path / "cameras.json", F, np.arange(4), to_cal(V),
                                                ("rom00", 0), {"rom00": (to_cal(tracked), np.array([0, 1, 2]))})
    assert values["neutral_error_mm"] == pytest.approx(0.0, abs=1e-5)
    assert values["mean_error_mm"] == pytest.approx(0.2 / 3, abs=1e-5)
    assert values["end_drift_mm"] == pytest.approx(0.2, abs=1e-5)
    assert per["rom00"]["first_error_mm"] == pytest.approx(0.0, abs=1e-5)
    assert "errors" not in per["rom00"]
    assert values["all_vertices_mean_error_mm"] == pytest.approx(0.2 / 3, abs=1e-5)
    tracked[1, 2] += [0.0, 0.0, 0.9]  # one region vertex, one frame
    neutral = V.copy()
    neutral[2] += [0.0, 0.6, 0.0]  # the region vertex off by 0.6 mm on the registered neutral
    second = tracked.copy()
    second[:, 2] += [0.0, 0.0, 0.3]  # a second sequence: the region vertex off 0.3 mm more in every frame
    np.savez(gt / "rom" / "rom01.npz", vertices=truth.astype(np.float32), frames=np.array([0, 1, 2]))
    values, per = ground_truth_tracking_metrics(gt, tmp_path / "cameras.json", F, np.arange(4), to_cal(neutral),
                                                ("rom00", 0), {"rom00": (to_cal(tracked), np.array([0, 1, 2])),
                                                               "rom01": (to_cal(second), np.array([0, 1, 2]))},
                                                regions={"lips": np.array([2])})
    assert per["rom00"]["lips_mean_error_mm"] == pytest.approx((0.9 + 0.2) / 3, abs=1e-5)
    assert per["rom01"]["lips_mean_error_mm"] == pytest.approx((0.3 + np.hypot(0.2, 0.3) + 1.2) / 3, abs=1e-5)
    assert values["lips_mean_error_mm"] == pytest.approx(
        (per["rom00"]["lips_mean_error_mm"] + per["rom01"]["lips_mean_error_mm"]) / 2, abs=1e-6)
    assert values["neutral_lips_error_mm"] == pytest.approx(0.6, abs=1e-5)
    assert values["neutral_error_mm"] == pytest.approx(0.6 / 4, abs=1e-5)
    with pytest.raises(ValueError, match="no frames"):
        ground_truth_tracking_metrics(gt, tmp_path / "cameras.json", F, np.arange(4), V, ("rom00", 7), {})


def test_ground_truth_tracking_metrics_evaluate_the_observed_face(tmp_path):
    """A face-region triangle that faces away from every camera counts in the headline errors (the whole face
    mask) and is left out of the visible_* errors (no camera measures it); vertex counts and fractions exact,
    per session and per sequence."""
    from rigbuild.camera import Camera, look_at
    from rigbuild.eval.tracking import ground_truth_tracking_metrics, observed_face_vertices
    from rigbuild.io.cameras import write_cameras

    V, F = _mesh()
    back = np.array([[0, 0, -5], [0, 10, -5], [10, 0, -5]], float)  # wound so its normal is -z
    V = np.vstack([V, back])
    F = np.vstack([F, [[4, 5, 6]]])
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    cams = []
    for i, eye in enumerate([[0, 0, 500], [300, 0, 400], [-300, 0, 400]]):
        R, t = look_at(np.array(eye, float), np.zeros(3), np.array([0, 1.0, 0]))
        cams.append(Camera(f"cam{i:02d}", 640, 480, K, np.zeros(5), R, t))
    np.testing.assert_array_equal(observed_face_vertices(V, F, cams, np.arange(7)), [0, 1, 2, 3])
    assert observed_face_vertices(V, F, cams, np.arange(7), min_cameras=4).size == 0
    gt = tmp_path / "ground_truth"
    (gt / "rom").mkdir(parents=True)
    write_cameras(gt / "cameras.json", cams)
    write_cameras(tmp_path / "cameras.json", cams)
    truth = np.stack([V, V])
    np.savez(gt / "rom" / "rom00.npz", vertices=truth.astype(np.float32), frames=np.array([0, 1]))
    tracked = truth.copy()
    tracked[:, 4:] += [0, 0, 0.7]  # the unseen triangle is off by 0.7 mm, the seen square exact
    values, per = ground_truth_tracking_metrics(gt, tmp_path / "cameras.json", F, np.arange(7), tracked[0],
                                              ("rom00", 0), {"rom00": (tracked, np.array([0, 1]))})
    assert values["observed_face_vertices"] == 4
    assert values["observed_face_fraction"] == pytest.approx(4 / 7)
    # whole mask: 3 of the 7 vertices off by 0.7 mm in every frame
    for key in ("mean_error_mm", "p95_error_mm", "end_drift_mm", "neutral_error_mm"):
        expected = 0.7 if key == "p95_error_mm" else 0.3
        assert values[key] == pytest.approx(expected, abs=1e-5), key
        assert values[f"visible_{key}"] == pytest.approx(0.0, abs=1e-5), key
    assert values["corr_mean_error_mm"] > 0.2 and values["visible_corr_mean_error_mm"] == pytest.approx(0.0, abs=1e-5)
    assert not any(k.startswith("mask_") for k in values)
    seq = per["rom00"]
    assert seq["mean_error_mm"] == pytest.approx(0.3, abs=1e-5) and seq["end_error_mm"] == pytest.approx(0.3, abs=1e-5)
    assert seq["visible_mean_error_mm"] == pytest.approx(0.0, abs=1e-5)
    assert seq["visible_end_error_mm"] == pytest.approx(0.0, abs=1e-5)
    assert seq["per_frame_mean_mm"] == pytest.approx([0.3, 0.3], abs=1e-5)


def test_contour_regions_are_the_vertices_near_the_lip_and_eyelid_loops():
    from rigbuild.eval.tracking import contour_regions

    # 68 landmarks: lips on a 20 mm circle at the origin, eyes on 8 mm circles at (+-30, 40); the rest far away
    L = np.full((68, 3), 500.0)
    a = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    L[48:60] = np.c_[20 * np.cos(a), 20 * np.sin(a), np.zeros(12)]
    L[60:68] = np.c_[10 * np.cos(a[:8] * 1.5), 10 * np.sin(a[:8] * 1.5), np.zeros(8)]
    for k, cx in ((36, -30.0), (42, 30.0)):
        b = np.linspace(0, 2 * np.pi, 6, endpoint=False)
        L[k:k + 6] = np.c_[cx + 8 * np.cos(b), 40 + 8 * np.sin(b), np.zeros(6)]
    probes = np.array([[0, 20.5, 0], [0, 0, 0], [0, 27, 0], [-30, 47.5, 0], [-30, 40, 0], [100, 0, 0]], float)
    V = np.vstack([L, probes])
    r = contour_regions(V, np.arange(68), np.arange(68, 74), lip_mm=6.0, eyelid_mm=4.0)
    assert r["lips"].tolist() == [68]  # 0.5 mm off the outer loop; the centre (10 mm) and 7 mm out are not
    assert r["eyelids"].tolist() == [71]
    assert contour_regions(V, None, np.arange(68, 74)) == {}
