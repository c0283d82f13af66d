"""Unit tests of the stage's no-ground-truth pieces: the cross-view stereo consistency on analytic planes and
the report pictures' helpers (reference camera, scaled camera, displacement, picture layout)."""

from __future__ import annotations

import numpy as np
import pytest

from rigbuild.camera import Camera, look_at
from rigbuild.reconstruct.consistency import depth_differences, stereo_consistency, view_points

W, H, F = 160, 120, 200.0


def _cam(name: str, center) -> Camera:
    """A pinhole camera at ``center`` looking along +z (R = I)."""
    K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])
    return Camera(name, W, H, K, np.zeros(5), np.eye(3), -np.asarray(center, float))


def test_plane_with_known_offset_gives_exactly_the_offset():
    """Two parallel cameras 40 mm apart see the plane z = 500: camera b's depth is 0.7 mm too far. Every
    compared pixel, both directions, disagrees by exactly 0.7 mm."""
    a, b = _cam("a", (0, 0, 0)), _cam("b", (40, 0, 0))
    da = np.full((H, W), 500.0, np.float32)
    db = np.full((H, W), 500.7, np.float32)
    d = depth_differences(view_points(da, a, None), db, b)
    assert np.allclose(d, 0.7, atol=2e-5)
    # disparity 40 * 200 / 500 = 16 px: the columns of a that land inside b (bilinear needs u < W - 1)
    assert abs(len(d) - (W - 16) * (H - 1)) <= H
    out = stereo_consistency([da, db], [a, b], [[1], [0]], max_pixels=None)
    assert out["median_mm"] == pytest.approx(0.7, abs=2e-5) and out["p90_mm"] == pytest.approx(0.7, abs=2e-5)
    assert out["n_pixels"] > 2 * (W - 17) * (H - 1) - 2 * H
    # sampling fewer pixels changes the count, not the answer
    sub = stereo_consistency([da, db], [a, b], [[1], [0]], max_pixels=2000)
    assert sub["median_mm"] == pytest.approx(0.7, abs=2e-5) and 1500 < sub["n_pixels"] < 2 * 2000


def test_tilted_plane_agrees_across_views_and_holes_are_not_compared():
    """A tilted plane seen by a camera and a converging one: true depths agree to float precision; pixels
    without depth in either view are left out, and no overlap gives NaN."""
    n = np.array([0.3, -0.2, -1.0])
    n /= np.linalg.norm(n)
    c = n @ np.array([0.0, 0.0, 480.0])  # plane n.X = c through (0, 0, 480)
    cams = [_cam("a", (0, 0, 0))]
    R, t = look_at(np.array([120.0, 10.0, 20.0]), np.array([0.0, 0.0, 480.0]))
    cams.append(Camera("b", W, H, cams[0].K, np.zeros(5), R, t))
    depths = []
    for cam in cams:
        v, u = np.mgrid[0:H, 0:W].astype(float)
        ray_c = np.stack([(u - cam.K[0, 2]) / F, (v - cam.K[1, 2]) / F, np.ones_like(u)], -1)
        ray_w = ray_c @ cam.R  # world direction of each pixel's ray (z component 1 in the camera)
        depths.append((c - n @ cam.center) / (ray_w @ n))  # camera z of the plane along each ray
    depths = [d.astype(np.float32) for d in depths]
    exact = stereo_consistency(depths, cams, [[1], [0]], max_pixels=None)
    assert exact["n_pixels"] > 5000 and exact["median_mm"] < 1e-3
    holed = [d.copy() for d in depths]
    holed[1][:, : W // 2] = 0
    holed[1][holed[1] > 0] += 0.25
    got = stereo_consistency(holed, cams, [[1], [0]], max_pixels=None)
    assert 0 < got["n_pixels"] < exact["n_pixels"] and got["median_mm"] == pytest.approx(0.25, abs=2e-3)
    none = stereo_consistency([depths[0], np.zeros_like(depths[1])], cams, [[1], [0]])
    assert np.isnan(none["median_mm"]) and none["n_pixels"] == 0


def test_reference_view_and_scaled_camera():
    from rigbuild.reconstruct.renders import reference_view, scaled_pinhole

    cams = []
    for k, x in enumerate((-300.0, -120.0, 40.0, 200.0, 300.0)):
        R, t = look_at(np.array([x, 0.0, 450.0]), np.zeros(3))
        cams.append(Camera(f"c{k}", W, H, _cam("x", (0, 0, 0)).K, np.zeros(5), R, t))
    assert reference_view(cams) == 2
    small = scaled_pinhole(cams[1], W // 2)
    assert (small.width, small.height) == (W // 2, H // 2)
    X = np.array([[10.0, -5.0, 3.0], [-20.0, 8.0, -4.0]])
    # same view: a point's pixel scales about the pixel corner (OpenCV centres: (u + 0.5) * s - 0.5)
    assert np.allclose(small.project(X), (cams[1].project(X) + 0.5) * 0.5 - 0.5, atol=1e-9)


def test_mean_displacement_and_picture_layout():
    from rigbuild.reconstruct.renders import frame_picture, mean_displacement

    rng = np.random.default_rng(0)
    P = rng.uniform(-50, 50, (3000, 3)) * np.array([1, 1, 0])  # points on the plane z = 0
    assert mean_displacement(P, P + np.array([0, 0, 2.0])) == pytest.approx(2.0)
    assert np.isnan(mean_displacement(P, np.zeros((0, 3))))
    cam = _cam("a", (0, 0, -400))
    depth = np.zeros((H, W), np.float32)
    depth[30:90, 40:120] = np.linspace(395, 405, 80)[None, :]
    V = np.array([[-60, -40, 0], [60, -40, 0], [60, 40, 0], [-60, 40, 0]], float)
    Fc = np.array([[0, 2, 1], [0, 3, 2]])
    img = frame_picture(depth, V, Fc, cam, "t", width=80)
    assert img.shape == (60, 160, 3) and img.dtype == np.uint8
    assert np.ptp(img[25, 30:50], axis=0).max() > 0  # the depth ramp is colour-mapped
    assert img[30, 120].mean() > img[2, 82].mean() + 30  # the lit quad over the background


def test_write_renders_picks_the_neutral_and_the_farthest_frame(tmp_path):
    """Four frames of a plane patch 400 mm in front of three cameras; frame 1 is the session's neutral, frame 3
    moved 6 mm towards the cameras (2 moved 2 mm), frame 0 is not among the reconstructed frames passed."""
    from rigbuild.io.depth import write_depth
    from rigbuild.io.ply import write_ply
    from rigbuild.reconstruct.renders import write_renders

    cams = []
    for k, x in enumerate((-150.0, 10.0, 150.0)):
        R, t = look_at(np.array([x, 0.0, -400.0]), np.zeros(3))
        cams.append(Camera(f"c{k}", W, H, _cam("x", (0, 0, 0)).K, np.zeros(5), R, t))
    g = np.linspace(-40, 40, 21)
    X, Y = np.meshgrid(g, g)
    idx = np.arange(21 * 21).reshape(21, 21)
    faces = np.concatenate([np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:]], -1).reshape(-1, 3),
                            np.stack([idx[:-1, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 3)])
    for f, dz in ((0, 0.0), (1, 0.0), (2, -2.0), (3, -6.0)):
        V = np.stack([X.ravel(), Y.ravel(), np.full(X.size, dz)], 1)
        write_ply(tmp_path / "mesh" / f"{f:06d}.ply", V, faces=faces)
        depth = np.zeros((3, H, W), np.float32)
        depth[:, 20:100, 30:130] = 400.0 + dz
        write_depth(tmp_path / "depth" / f"{f:06d}.npz", cams, depth, (depth > 0).astype(np.float32), frame=f)
    info = write_renders(tmp_path, [1, 2, 3], neutral_frame=1, name="rom00", width=120)
    assert (info["neutral"], info["peak"], info["reference_camera"]) == (1, 3, "c1")
    assert info["displacement_mm"]["3"] == pytest.approx(6.0, abs=1e-4)
    assert info["displacement_mm"]["2"] == pytest.approx(2.0, abs=1e-4)
    assert sorted(p.name for p in (tmp_path / "renders").iterdir()) == ["000001.png", "000003.png"]
    # a skipped neutral frame: the first reconstructed frame stands in; nothing reconstructed: an empty folder
    assert write_renders(tmp_path, [2, 3], neutral_frame=1)["neutral"] == 2
    empty = tmp_path / "empty"
    assert write_renders(empty, [], neutral_frame=0)["peak"] is None and not any((empty / "renders").iterdir())
