"""Unit tests of the shared contracts: Rig, Camera, rigid fits, atomic I/O, metrics, rig I/O."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rigbuild.camera import Camera, look_at
from rigbuild.errors import InputError
from rigbuild.geometry import apply_rigid, fit_rigid_motion, fit_similarity, rotation_angle_deg
from rigbuild.io.atomic import atomic_path, write_json
from rigbuild.io.metrics import flatten_metrics, gather_metrics, read_metrics, write_metrics_fragment
from rigbuild.io.rigs import read_rig_npz, write_obj_folder_rig, write_rig_npz, read_obj_folder_rig
from rigbuild.rig import Rig


def _tetra_rig():
    neutral = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    deltas = np.zeros((2, 4, 3))
    deltas[0, 3, 2] = 1.0
    deltas[1, 1, 0] = -0.5
    return Rig(neutral, deltas, ["a", "b"], faces, units="cm", name="tetra",
               marker_names=["m0", "m1"], marker_vertices=[3, 1])


def test_rig_evaluate_exact():
    rig = _tetra_rig()
    v = rig.evaluate([2.0, 1.0])
    assert v[3, 2] == 3.0 and v[1, 0] == 0.5
    vb = rig.evaluate(np.array([[0, 0], [1, 0]]))
    assert vb.shape == (2, 4, 3) and np.array_equal(vb[0], rig.neutral)
    assert np.array_equal(rig.markers(), rig.neutral[[3, 1]])


def test_rig_units_and_validation():
    rig = _tetra_rig().to_units("mm")
    assert rig.neutral[1, 0] == 10.0 and rig.deltas[0, 3, 2] == 10.0
    with pytest.raises(InputError, match="no shape 'zz'"):
        rig.shape_index("zz")
    with pytest.raises(InputError, match="deltas must be"):
        Rig(np.zeros((4, 3)), np.zeros((1, 3, 3)), ["a"], np.array([[0, 1, 2]]))
    with pytest.raises(InputError, match="duplicate shape"):
        Rig(np.zeros((4, 3)), np.zeros((2, 4, 3)), ["a", "a"], np.array([[0, 1, 2]]))


def test_rig_npz_and_obj_roundtrip(tmp_path):
    rig = _tetra_rig()
    write_rig_npz(tmp_path / "r.npz", rig)
    back = read_rig_npz(tmp_path / "r.npz")
    assert back.shape_names == rig.shape_names and back.units == "cm"
    assert np.allclose(back.deltas, rig.deltas) and back.marker_names == ["m0", "m1"]
    write_obj_folder_rig(rig, tmp_path / "objs")
    back = read_obj_folder_rig(tmp_path / "objs")
    assert back.shape_names == ["a", "b"] and np.allclose(back.deltas, rig.deltas, atol=1e-6)
    assert np.array_equal(back.faces, rig.faces) and back.marker_names == ["m0", "m1"]


def test_obj_folder_topology_mismatch_names_file(tmp_path):
    rig = _tetra_rig()
    write_obj_folder_rig(rig, tmp_path)
    (tmp_path / "b.obj").write_text("v 0 0 0\nv 1 0 0\nf 1 2 1\n")
    with pytest.raises(InputError, match=r"b\.obj.*topology differs"):
        read_obj_folder_rig(tmp_path)


def test_fit_similarity_recovers_exact_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    ang = 0.7
    R = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    dst = apply_rigid(src, R, [1, 2, 3], s=2.5)
    s, R2, t2 = fit_similarity(src, dst)
    assert s == pytest.approx(2.5) and np.allclose(R2, R) and np.allclose(t2, [1, 2, 3])
    R3, t3 = fit_rigid_motion(src, apply_rigid(src, R, [0, 0, 1]), weights=rng.uniform(0.1, 1, 20))
    assert np.allclose(R3, R) and np.allclose(t3, [0, 0, 1])
    assert rotation_angle_deg(R) == pytest.approx(np.degrees(0.7))


def test_camera_projection_matches_opencv():
    import cv2

    R, t = look_at([100, 50, 600], [0, 0, 0])
    cam = Camera("c0", 640, 480, [[800, 0, 320], [0, 810, 240], [0, 0, 1]], [-0.1, 0.05, 1e-3, -2e-3, 0.01], R, t)
    assert np.allclose(cam.center, [100, 50, 600])
    X = np.random.default_rng(1).uniform(-50, 50, (30, 3))
    ref, _ = cv2.projectPoints(X, cam.rvec, cam.t, cam.K, cam.dist)
    assert np.allclose(cam.project(X), ref.reshape(-1, 2), atol=1e-9)
    # rays through the projections pass through the points
    d = cam.rays(cam.project(X))
    v = X - cam.center
    cross = np.linalg.norm(np.cross(d, v), axis=1)
    assert cross.max() < 1e-6 * np.linalg.norm(v, axis=1).max()
    # the image y axis points down the world up axis
    assert cam.project(np.array([[0, 10, 0]]))[0, 1] < cam.project(np.array([[0, 0, 0]]))[0, 1]


def test_atomic_path_leaves_nothing_on_error(tmp_path):
    target = tmp_path / "out.json"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("partial")
            raise RuntimeError("crash")
    assert list(tmp_path.iterdir()) == []
    write_json(target, {"a": np.float32(1.5), "b": np.arange(2)})
    assert json.loads(target.read_text()) == {"a": 1.5, "b": [0, 1]}


def test_metrics_fragments_gather_into_one_file(tmp_path):
    a, b, c = tmp_path / "a.json", tmp_path / "b.json", tmp_path / "c.json"
    write_metrics_fragment(a, "calibration", {"rms_px": np.float64(0.1), "bad": float("nan")})
    write_metrics_fragment(b, "calibration", {"focal_error_pct": 0.01, "per": {"cam0": 1}})
    write_metrics_fragment(c, "tracking", {"mean_error_mm": 0.3})
    m = gather_metrics([a, b, c])
    assert m["calibration"] == {"rms_px": 0.1, "bad": None, "focal_error_pct": 0.01, "per": {"cam0": 1}}
    assert flatten_metrics(m)["tracking.mean_error_mm"] == 0.3
    assert flatten_metrics(m)["calibration.per.cam0"] == 1
    write_json(tmp_path / "metrics.json", m)
    assert read_metrics(tmp_path / "metrics.json") == m


def test_a_metric_written_twice_with_two_values_is_an_error_naming_both_files(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    write_metrics_fragment(a, "tracking", {"sequences": {"rom00": {"lost_frames": 1}}})
    write_metrics_fragment(b, "tracking", {"sequences": {"rom00": {"lost_frames": 2}}})
    with pytest.raises(ValueError, match=r"tracking\.sequences\.rom00\.lost_frames.*a\.json.*b\.json"):
        gather_metrics([a, b])
    write_metrics_fragment(b, "tracking", {"sequences": 3})
    with pytest.raises(ValueError, match=r"tracking\.sequences.* and 3 in"):
        gather_metrics([a, b])
    assert gather_metrics([a, a]) == gather_metrics([a])  # the same value twice is fine


def test_metrics_are_scalars(tmp_path):
    with pytest.raises(TypeError, match="tracking.curve"):
        write_metrics_fragment(tmp_path / "x.json", "tracking", {"curve": [1.0, 2.0]})
    assert not (tmp_path / "x.json").exists()


def test_ict_loader_reads_shared_folder(ict_rig):
    assert ict_rig.n_vertices == 26719 and ict_rig.n_shapes == 53
    assert ict_rig.units == "mm" and ict_rig.landmarks.shape == (68,)
    width = np.ptp(ict_rig.neutral[ict_rig.face_vertices, 0])
    assert 150 < width < 250  # head about 18-25 cm wide, now in mm
    assert "jawOpen" in ict_rig.shape_names and np.abs(ict_rig.deltas[ict_rig.shape_index("jawOpen")]).max() > 10
