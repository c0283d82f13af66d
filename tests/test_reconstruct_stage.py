"""Stage test: a textured sphere session on disk (ray-cast ground truth) through the reconstruct stage.

Checks the outputs (depth/points/mesh/coverage per frame, recon_metrics.json, metrics.json), accuracy against
the analytic sphere, depth_at through the written depth file, and bad-input handling (skip / fail / cameras
that do not match the session).
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from recon_scene import camera_arc, render, sphere_scene
from rigbuild.errors import InputError

RADIUS = 60.0
CENTERS = {0: np.zeros(3), 1: np.array([2.0, -1.0, 1.5]), 2: np.zeros(3)}


@pytest.fixture(scope="module")
def sphere_session(tmp_path_factory):
    from rigbuild.io.cameras import write_cameras
    from rigbuild.session import write_session

    root = tmp_path_factory.mktemp("sphere_session")
    cams = camera_arc(5, 640, 480, 1400, 450, target=(0, 0, 0), yaw_span_deg=80, dist=(-0.08, 0.03, 0, 0, 0))
    for f, c in CENTERS.items():
        scene = sphere_scene(RADIUS, center=c, texture_size=512)
        for k, cam in enumerate(cams):
            img = render(scene, cam, noise_sigma=1.0 / 255, seed=10 * f + k)["image"]
            if f == 2 and k == 3:
                img[:] = 0  # a dead camera on frame 2
            p = root / "rom" / "seq" / cam.id / f"{f:06d}.png"
            p.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(p), img)
    write_session({"name": "sphere", "cameras": [c.id for c in cams], "image_size": [640, 480],
                   "board": {"type": "charuco", "squares_x": 7, "squares_y": 5, "square_size_mm": 24.0,
                             "marker_size_mm": 18.0, "dictionary": "DICT_5X5_100"},
                   "rom": [{"name": "seq", "frames": [0, 2], "neutral_frame": 0}]}, root)
    write_cameras(root / "cameras.json", cams)
    return root, cams


@pytest.fixture(scope="module")
def stage_run(sphere_session, tmp_path_factory):
    from rigbuild.reconstruct.sequence import run_frame_job, run_sequence_summary

    root, cams = sphere_session
    out = tmp_path_factory.mktemp("results") / "seq"
    metrics = out.parent / "metrics.json"
    logs = []
    records = run_frame_job(root, "seq", [0, 1, 2], root / "cameras.json", {"on_bad_frame": "skip"}, out,
                            log=logs.append)
    summary = run_sequence_summary(root, "seq", [out / "frames" / f"{f:06d}.json" for f in (0, 1, 2)], out, metrics)
    return out, metrics, records, summary, logs


def test_outputs_exist_and_bad_frame_is_reported(stage_run):
    out, metrics, records, summary, logs = stage_run
    for f in (0, 1, 2):
        for sub, ext in (("depth", "npz"), ("points", "ply"), ("mesh", "ply"), ("coverage", "png"), ("frames", "json")):
            assert (out / sub / f"{f:06d}.{ext}").is_file()
    assert (out / "coverage.png").is_file() and (out / "recon_metrics.json").is_file()
    assert summary["reconstructed"] == [0, 1]
    assert list(summary["skipped"]) == ["2"] and "cam03" in summary["skipped"]["2"] and "all black" in summary["skipped"]["2"]
    assert any("WARNING" in m and "frame 2 skipped" in m for m in logs)
    from rigbuild.io.depth import read_depth

    d2 = read_depth(out / "depth" / "000002.npz")
    assert d2["skipped"] and "all black" in d2["reason"] and not np.any(d2["depth"])
    m = json.loads(metrics.read_text())["reconstruction"]
    assert m["skipped_frames"] == 1 and m["sequences"]["seq"]["frames"] == 3
    assert 0.5 < m["mean_coverage"] <= 1.0


def test_accuracy_against_analytic_sphere(stage_run):
    from rigbuild.io.ply import read_ply

    out = stage_run[0]
    for f in (0, 1):
        pts = read_ply(out / "points" / f"{f:06d}.ply")
        err = np.abs(np.linalg.norm(pts["vertices"] - CENTERS[f], axis=1) - RADIUS)
        assert len(err) > 30000
        assert np.median(err) < 0.12 and np.percentile(err, 90) < 0.45
        # normals point outwards (away from the centre)
        radial = (pts["vertices"] - CENTERS[f]) / RADIUS
        assert np.median(np.sum(pts["normals"] * radial, axis=1)) > 0.95
        mesh = read_ply(out / "mesh" / f"{f:06d}.ply")
        em = np.abs(np.linalg.norm(mesh["vertices"] - CENTERS[f], axis=1) - RADIUS)
        assert len(mesh["faces"]) > 10000 and np.median(em) < 0.12 and np.percentile(em, 90) < 0.45


def test_depth_at_through_written_depth_file(stage_run, sphere_session):
    from rigbuild.io.depth import read_depth
    from rigbuild.reconstruct.lift import depth_at

    out = stage_run[0]
    _, cams = sphere_session
    d = read_depth(out / "depth" / "000000.npz")
    k = d["camera_ids"].index("cam02")
    cam = cams[2]
    # pixels on the sphere's image (distorted image coordinates)
    ang = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    pts3 = np.stack([30 * np.cos(ang), 30 * np.sin(ang), np.zeros_like(ang)], 1)
    pts3[:, 2] = np.sqrt(RADIUS ** 2 - 30 ** 2)  # the cap facing camera 2 (at +z, looking along -z)
    uv = cam.project(pts3)
    X = depth_at(d["depth"][k], cam, uv)
    ok = np.all(np.isfinite(X), axis=1)
    assert ok.mean() > 0.9
    err = np.abs(np.linalg.norm(X[ok], axis=1) - RADIUS)
    assert np.median(err) < 0.15
    assert np.allclose(cam.project(X[ok]), uv[ok], atol=1e-3)


def test_fail_mode_and_camera_mismatch(sphere_session, tmp_path):
    from rigbuild.camera import Camera
    from rigbuild.io.cameras import write_cameras
    from rigbuild.reconstruct.sequence import run_frame_job

    root, cams = sphere_session
    with pytest.raises(InputError, match="frame 2.*all black"):
        run_frame_job(root, "seq", [2], root / "cameras.json", {"on_bad_frame": "fail"}, tmp_path / "a")
    write_cameras(tmp_path / "few.json", cams[:4])
    with pytest.raises(InputError, match="cam04"):
        run_frame_job(root, "seq", [0], tmp_path / "few.json", {}, tmp_path / "b")
    small = [Camera(c.id, 320, 240, c.K, c.dist, c.R, c.t) for c in cams]
    write_cameras(tmp_path / "small.json", small)
    with pytest.raises(InputError, match="image size"):
        run_frame_job(root, "seq", [0], tmp_path / "small.json", {}, tmp_path / "c")
    with pytest.raises(InputError, match="not in sequence"):
        run_frame_job(root, "seq", [7], root / "cameras.json", {}, tmp_path / "d")
