"""Stage test: a textured sphere session on disk (ray-cast ground truth) through the reconstruct stage.

Checks the outputs (depth/points/mesh/coverage per frame, recon_summary.json, renders, the metrics fragments),
the stereo consistency gate, accuracy against the analytic sphere, depth_at through the written depth file,
bad-input handling (skip / fail / cameras that do not match the session), and that the ground-truth keys come
from the eval rules, not the stage.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from recon_scene import camera_arc, render, sphere_scene, uv_sphere
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
    # ground truth as rigbuild.synth.session lays it out (for the eval rules only)
    v, f, _ = uv_sphere(RADIUS)
    f = f[:, ::-1]  # outward normals (visibility faces the cameras)
    gt = root / "ground_truth"
    (gt / "rom").mkdir(parents=True)
    np.savez(gt / "rom" / "seq.npz", vertices=np.stack([v + CENTERS[k] for k in (0, 1, 2)]), frames=np.arange(3))
    np.savez(gt / "actor_rig.npz", neutral=v, deltas=np.zeros((0,) + v.shape), shape_names=np.zeros(0, str), faces=f)
    write_cameras(gt / "cameras.json", cams)
    return root, cams


@pytest.fixture(scope="module")
def stage_run(sphere_session, tmp_path_factory):
    """The stage's three rules on the session: reconstruct_frame (x3), reconstruct_summary, reconstruct_pool."""
    from rigbuild.io.metrics import gather_metrics
    from rigbuild.reconstruct.stage import run_reconstruct_frame, run_reconstruct_pool, run_reconstruct_summary

    root, cams = sphere_session
    out = tmp_path_factory.mktemp("results") / "seq"
    logs = []
    records = run_reconstruct_frame(root, "seq", [0, 1, 2], root / "cameras.json", {"on_bad_frame": "skip"}, out,
                                    log=logs.append)
    summary = run_reconstruct_summary(root, "seq", [out / "frames" / f"{f:06d}.json" for f in (0, 1, 2)], out,
                                      out / "sequence_metrics.json")
    run_reconstruct_pool([out / "sequence_metrics.json"], out.parent / "reconstruction_metrics.json")
    metrics = gather_metrics([out / "sequence_metrics.json", out.parent / "reconstruction_metrics.json"])
    return out, metrics, records, summary, logs


def test_outputs_exist_and_bad_frame_is_reported(stage_run):
    out, metrics, records, summary, logs = stage_run
    for f in (0, 1, 2):
        for sub, ext in (("depth", "npz"), ("points", "ply"), ("mesh", "ply"), ("coverage", "png"), ("frames", "json"),
                         ("geometry", "npz")):
            assert (out / sub / f"{f:06d}.{ext}").is_file()
    assert (out / "coverage.png").is_file() and (out / "recon_summary.json").is_file()
    assert summary["reconstructed"] == [0, 1]
    assert list(summary["skipped"]) == ["2"] and "cam03" in summary["skipped"]["2"] and "all black" in summary["skipped"]["2"]
    assert any("WARNING" in m and "frame 2 skipped" in m for m in logs)
    from rigbuild.io.depth import read_depth

    d2 = read_depth(out / "depth" / "000002.npz")
    assert d2["skipped"] and "all black" in d2["reason"] and not np.any(d2["depth"])
    m = metrics["reconstruction"]
    assert m["skipped_frames"] == 1 and m["sequences"]["seq"]["frames"] == 3
    assert 0.5 < m["mean_coverage"] <= 1.0


def test_stereo_consistency_is_the_stages_gate(stage_run):
    """Per frame, per sequence (median of the frames) and pooled (the worst sequence); on the sphere (sensor
    noise 1/255, depth error ~0.1 mm) the views' depths agree to a few tenths of a millimetre."""
    out, metrics, records, summary, logs = stage_run
    per_frame = [r["stereo_consistency_mm"] for r in records if not r["skipped"]]
    assert len(per_frame) == 2 and all(0.0 < c < 0.4 for c in per_frame)
    assert sum("stereo consistency" in m for m in logs) == 2  # each frame's progress line
    assert summary["stereo_consistency_mm"] == pytest.approx(np.median(per_frame))
    m = metrics["reconstruction"]
    assert m["sequences"]["seq"]["stereo_consistency_mm"] == pytest.approx(summary["stereo_consistency_mm"])
    assert m["stereo_consistency_mm"] == pytest.approx(summary["stereo_consistency_mm"])


def test_renders_at_neutral_and_peak_frame(stage_run):
    """renders/<frame>.png for the neutral frame (0) and the peak (1: the sphere moved 2.7 mm; 2 is skipped),
    seen by the most frontal camera of the arc: a depth panel and a shaded mesh panel, 480 px each."""
    out, _, _, summary, _ = stage_run
    r = summary["renders"]
    assert (r["neutral"], r["peak"], r["reference_camera"]) == (0, 1, "cam02")
    assert sorted(p.name for p in (out / "renders").iterdir()) == ["000000.png", "000001.png"]
    assert 1.0 < r["displacement_mm"]["1"] < 3.0
    img = cv2.imread(str(out / "renders" / "000001.png"))
    assert img.shape == (360, 960, 3)
    depth_panel, mesh_panel = img[30:330, :480].astype(int), img[30:330, 480:].astype(int)
    # the sphere fills the middle of both panels: coloured depth (not grey) and lit grey surface
    mid = (slice(120, 180), slice(210, 270))
    assert np.ptp(depth_panel[mid], axis=-1).mean() > 40
    assert mesh_panel[mid].mean() > 80 and np.ptp(mesh_panel[mid], axis=-1).max() < 5
    assert mesh_panel[:20, :20].mean() < 40  # background


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


def test_ground_truth_keys_come_from_the_eval_rules(stage_run, sphere_session, tmp_path):
    """The stage's records and fragments hold no errors; eval_reconstruction_sequence / eval_reconstruction
    (rules/eval_reconstruct.smk) add them, and the gathered keys are the session's reconstruction.* keys."""
    from rigbuild.eval.reconstruction import run_eval_reconstruction_pool, run_eval_reconstruction_sequence
    from rigbuild.io.metrics import flatten_metrics, gather_metrics

    out, metrics, records, summary, _ = stage_run
    root, _ = sphere_session
    stage_keys = set(flatten_metrics(metrics))
    assert stage_keys == {"reconstruction.skipped_frames", "reconstruction.mean_coverage",
                          "reconstruction.stereo_consistency_mm"} | {
        f"reconstruction.sequences.seq.{k}" for k in ("mean_coverage", "stereo_consistency_mm", "seconds_per_frame",
                                                      "frames", "skipped_frames")}
    assert not any("ground_truth" in r for r in records) and "ground_truth" not in summary
    gt = root / "ground_truth"
    frames = [f"{f:06d}" for f in (0, 1, 2)]
    errors = run_eval_reconstruction_sequence(
        root / "session.yaml", "seq", root / "cameras.json", [out / "frames" / f"{f}.json" for f in frames],
        [out / "geometry" / f"{f}.npz" for f in frames], gt / "rom" / "seq.npz", gt / "actor_rig.npz",
        gt / "cameras.json", tmp_path / "seq_metrics.json", tmp_path / "frames.json")
    assert errors["frames_evaluated"] == 2  # frame 2 was skipped
    assert errors["median_error_mm"] < 0.2 and errors["completeness"] > 0.5  # plumbing, not accuracy
    detail = json.loads((tmp_path / "frames.json").read_text())
    assert sorted(detail["per_frame"]) == ["0", "1"]
    assert errors["median_error_mm"] == max(e["median_error_mm"] for e in detail["per_frame"].values())
    pooled = run_eval_reconstruction_pool([tmp_path / "seq_metrics.json"], tmp_path / "reconstruction_metrics.json")
    assert pooled == {k: errors[k] for k in ("median_error_mm", "p90_error_mm", "completeness")}
    flat = flatten_metrics(gather_metrics([out / "sequence_metrics.json", out.parent / "reconstruction_metrics.json",
                                           tmp_path / "seq_metrics.json", tmp_path / "reconstruction_metrics.json"]))
    assert set(flat) - stage_keys == {"reconstruction.median_error_mm", "reconstruction.p90_error_mm",
                                      "reconstruction.completeness"} | {
        f"reconstruction.sequences.seq.{k}" for k in (
            "median_error_mm", "p90_error_mm", "completeness", "mean_median_error_mm", "mean_p90_error_mm",
            "mean_completeness", "point_median_error_mm", "frames_evaluated")}


def test_unknown_reconstruct_key_fails_with_did_you_mean(sphere_session, tmp_path):
    from rigbuild.reconstruct.params import from_config
    from rigbuild.reconstruct.stage import run_reconstruct_frame

    with pytest.raises(InputError, match=r"unknown key 'params.reconstruct.poisson_dept' \(did you mean 'poisson_depth'\?\)"):
        from_config({"poisson_dept": 9})
    with pytest.raises(InputError, match="did you mean 'min_ncc'"):  # a StereoParams field, given flat
        from_config({"min_nc": 0.4})
    assert from_config({"min_ncc": 0.4, "min_views": 3}).stereo.min_ncc == 0.4
    root, _ = sphere_session
    with pytest.raises(InputError, match="did you mean 'on_bad_frame'"):
        run_reconstruct_frame(root, "seq", [0], root / "cameras.json", {"on_bad_fram": "skip"}, tmp_path / "x")
    assert not (tmp_path / "x").exists()


def test_fail_mode_and_camera_mismatch(sphere_session, tmp_path):
    from rigbuild.camera import Camera
    from rigbuild.io.cameras import write_cameras
    from rigbuild.reconstruct.stage import run_reconstruct_frame as run_frame_job

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
