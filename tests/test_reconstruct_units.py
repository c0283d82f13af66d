"""Unit tests of rigbuild.reconstruct on tiny analytic cases with exact answers."""

from __future__ import annotations

import numpy as np
import pytest

from rigbuild.camera import Camera, look_at
from rigbuild.errors import InputError


def _cam(cid="c0", center=(0.0, 0.0, -500.0), target=(0.0, 0.0, 0.0), W=160, H=120, f=200.0, dist=None):
    R, t = look_at(np.asarray(center, float), np.asarray(target, float), up=(0.0, 1.0, 0.0))
    K = np.array([[f, 0, (W - 1) / 2 + 1.5], [0, f * 1.01, (H - 1) / 2 - 0.5], [0, 0, 1]])
    return Camera(cid, W, H, K, np.zeros(5) if dist is None else dist, R, t)


def _plane_depth(cam: Camera, z_world: float) -> np.ndarray:
    """Exact camera-z depth map of the world plane z = z_world seen by a pinhole camera."""
    H, W = cam.height, cam.width
    v, u = np.mgrid[0:H, 0:W].astype(float)
    d = np.stack([(u - cam.K[0, 2]) / cam.K[0, 0], (v - cam.K[1, 2]) / cam.K[1, 1], np.ones_like(u)], -1)
    dw = d @ cam.R  # world direction for camera z = 1
    s = (z_world - cam.center[2]) / dw[..., 2]
    return s.astype(np.float32)


def test_pair_geometry_matches_camera_projection():
    from rigbuild.reconstruct.stereo import _PairGeometry

    a, b = _cam("a"), _cam("b", center=(150.0, 30.0, -480.0))
    us, vs = np.arange(0, 160, 7), np.arange(0, 120, 5)
    g = _PairGeometry(a, b, 1.0, us, vs)
    U, V = np.meshgrid(us.astype(float), vs.astype(float))
    z = 430.0 + 40 * np.sin(U / 30.0)
    X = np.stack([(U - a.K[0, 2]) / a.K[0, 0] * z, (V - a.K[1, 2]) / a.K[1, 1] * z, z], -1)
    Xw = (X - a.t) @ a.R
    expect = b.project(Xw.reshape(-1, 3), distort=False).reshape(U.shape + (2,))
    mx, my, front = g.project((1.0 / z).astype(np.float32))
    assert front.all()
    assert np.abs(mx - expect[..., 0]).max() < 2e-3
    assert np.abs(my - expect[..., 1]).max() < 2e-3
    # half-resolution level: pixel i <-> 2i
    g2 = _PairGeometry(a, b, 0.5, us / 2.0, vs / 2.0)
    mx2, my2, _ = g2.project((1.0 / z).astype(np.float32))
    assert np.abs(2 * mx2 - expect[..., 0]).max() < 2e-3


def test_ncc_exact_values():
    from rigbuild.reconstruct.stereo import _RefStats, ncc

    rng = np.random.default_rng(0)
    ref = rng.random((40, 50)).astype(np.float32)
    st = _RefStats(ref, 7)
    assert np.allclose(ncc(st, ref.copy())[5:-5, 5:-5], 1.0, atol=1e-3)
    assert np.allclose(ncc(st, (2.5 * ref + 0.3).astype(np.float32))[5:-5, 5:-5], 1.0, atol=1e-3)
    assert np.allclose(ncc(st, (1 - ref).astype(np.float32))[5:-5, 5:-5], -1.0, atol=1e-3)
    valid = np.ones(ref.shape, bool)
    valid[10, 10] = False
    assert ncc(st, ref.copy(), valid)[10, 10] == -1.0


def test_parabola_offset_exact():
    from rigbuild.reconstruct.stereo import _parabola_offset

    x0 = np.array([0.3, -0.2, 0.0, 0.45])
    f = lambda x: 1.0 - 0.7 * (x - x0) ** 2  # noqa: E731
    off = _parabola_offset(f(-1.0), f(0.0), f(1.0))
    assert np.allclose(off, x0, atol=1e-12)


def test_select_neighbours_and_convergence():
    from rigbuild.reconstruct.stereo import convergence_point, select_neighbours

    cams = []
    for k, yaw in enumerate(np.deg2rad([-40, -20, 0, 20, 40])):
        c = 450 * np.array([np.sin(yaw), 0.0, np.cos(yaw)]) + np.array([1.0, 2.0, 3.0])
        cams.append(_cam(f"c{k}", center=c, target=(1.0, 2.0, 3.0)))
    assert np.allclose(convergence_point(cams), [1.0, 2.0, 3.0], atol=1e-9)
    nb = select_neighbours(cams, 2, min_angle_deg=5, max_angle_deg=30)
    assert sorted(nb[2]) == [1, 3]
    assert nb[0] == [1]  # 40 deg to camera 2 exceeds max_angle_deg


def test_masks_and_bad_images():
    from rigbuild.reconstruct.masks import foreground_mask, image_problem

    H, W = 120, 160
    v, u = np.mgrid[0:H, 0:W]
    disk = (u - 80) ** 2 + (v - 60) ** 2 < 30 ** 2
    rng = np.random.default_rng(1)
    img = np.full((H, W), 0.5, np.float32) + rng.normal(0, 0.004, (H, W)).astype(np.float32)
    img[disk] = 0.5 + 0.25 * (rng.random(disk.sum()) - 0.5)  # textured subject, same mean as the backdrop
    m = foreground_mask(img, dilate_px=2, erode_px=2)
    assert (m & disk).sum() / disk.sum() > 0.98
    assert (m & ~disk).sum() / disk.sum() < 0.25
    assert foreground_mask(img, threshold=0).all()
    assert image_problem(np.zeros((H, W), np.float32)) == "all black"
    assert image_problem(np.ones((H, W), np.float32)) == "saturated"
    assert image_problem(img) is None


def test_depth_at_plane_with_distortion():
    from rigbuild.reconstruct.lift import depth_at

    cam = _cam(dist=np.array([-0.1, 0.02, 0.001, -0.001, 0.0]))
    from rigbuild.reconstruct.stereo import pinhole

    depth = _plane_depth(pinhole(cam), 40.0)
    uv = np.array([[10.3, 20.7], [80.0, 60.0], [150.2, 100.9]])
    X = depth_at(depth, cam, uv)
    assert np.allclose(X[:, 2], 40.0, atol=1e-3)
    assert np.allclose(cam.project(X), uv, atol=1e-3)
    # hole -> NaN
    depth[55:65, 75:85] = 0
    assert np.isnan(depth_at(depth, cam, np.array([[80.0, 60.0]]))).all()


def test_consistency_filter_keeps_surface_and_drops_outlier():
    from rigbuild.reconstruct.filter import consistency_filter

    a, b = _cam("a"), _cam("b", center=(120.0, 0.0, -485.0))
    da, db = _plane_depth(a, 0.0), _plane_depth(b, 0.0)
    da[60, 80] += 25.0  # an outlier
    res = consistency_filter([da, db], [a, b], [[1], [0]], abs_tol_mm=0.5, rel_tol=0.0, min_views=2)
    assert res.depth[0][60, 80] == 0
    kept = res.depth[0] > 0
    assert kept.sum() > 0.4 * kept.size
    assert np.abs(res.points[0][:, 2]).max() < 1e-2  # fused points lie on the plane z = 0
    assert set(np.unique(res.n_views[0][kept])) == {2}


def test_voxel_average_and_normals():
    from rigbuild.reconstruct.filter import point_map
    from rigbuild.reconstruct.fuse import pixel_normals, voxel_average

    P = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.2, 0.1, 0.1]])
    A = np.array([[1.0], [3.0], [5.0]])
    Q, B = voxel_average(P, 1.0, A)
    order = np.argsort(Q[:, 0])
    assert np.allclose(Q[order], [[0.2, 0.2, 0.2], [1.2, 0.1, 0.1]])
    assert np.allclose(B[order, 0], [2.0, 5.0])
    cam = _cam()
    pm = point_map(_plane_depth(cam, 0.0), cam)
    n = pixel_normals(pm, cam, np.array([60, 30]), np.array([80, 100]))
    assert np.allclose(n, [[0, 0, -1], [0, 0, -1]], atol=1e-5)  # facing the camera at z = -500


def test_depth_file_roundtrip(tmp_path):
    from rigbuild.io.depth import read_depth, read_depth_frame, write_depth

    cams = [_cam("a"), _cam("b", center=(100.0, 0, -480.0))]
    rng = np.random.default_rng(0)
    depth = (420 + 100 * rng.random((2, 120, 160))).astype(np.float32)
    depth[0, :10] = 0
    conf = rng.random((2, 120, 160)).astype(np.float32)
    write_depth(tmp_path / "f.npz", cams, depth, conf, frame=7)
    d = read_depth(tmp_path / "f.npz")
    assert d["camera_ids"] == ["a", "b"] and d["frame"] == 7 and not d["skipped"]
    assert np.abs(d["depth"] - depth).max() <= 0.0026
    assert (d["depth"][0, :10] == 0).all()
    assert np.abs(d["confidence"][depth > 0] - conf[depth > 0]).max() <= 0.5 / 255 + 1e-6
    fr = read_depth_frame(tmp_path / "f.npz")
    assert np.allclose(fr.cameras[1].center, cams[1].center)
    write_depth(tmp_path / "s.npz", cams, np.zeros_like(depth), conf, skipped=True, reason="view b missing")
    s = read_depth(tmp_path / "s.npz")
    assert s["skipped"] and s["reason"] == "view b missing" and (s["depth"] == 0).all()
    with pytest.raises(InputError):
        read_depth(tmp_path / "absent.npz")


def test_ply_roundtrip(tmp_path):
    from rigbuild.io.ply import read_ply, write_ply

    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) * 12.5
    F = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    N = np.eye(3)[[0, 1, 2, 0]]
    C = np.array([[0.0, 0.5, 1.0]] * 4)
    write_ply(tmp_path / "m.ply", V, faces=F, normals=N, colors=C)
    m = read_ply(tmp_path / "m.ply")
    assert np.array_equal(m["faces"], F) and np.allclose(m["vertices"], V) and np.allclose(m["normals"], N)
    assert m["colors"].tolist()[0] == [0, 128, 255]
    import open3d as o3d

    o = o3d.io.read_triangle_mesh(str(tmp_path / "m.ply"))  # readable by other tools
    assert len(o.triangles) == 4


def test_closed_surface_checks():
    from rigbuild.reconstruct.fuse import boundary_edge_count, keep_components

    tet = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    assert boundary_edge_count(tet) == (0, 0)
    assert boundary_edge_count(tet[:3]) == (3, 0)
    V = np.vstack([np.eye(3), [[0, 0, 0]], np.eye(3) + 5, [[5, 5, 5]]])
    F = np.vstack([tet, tet[:2] + 4])
    V2, F2 = keep_components(V, F, largest_only=True)
    assert len(V2) == 4 and len(F2) == 4


def test_params_validation():
    from rigbuild.reconstruct.params import ReconstructParams

    p = ReconstructParams.from_dict({"window": 9, "min_views": 3, "on_bad_frame": "fail"})
    assert p.stereo.window == 9 and p.min_views == 3 and p.on_bad_frame == "fail"
    for bad in ({"windw": 7}, {"window": 8}, {"on_bad_frame": "ignore"}, {"depth_range_mm": [500, 400]}):
        with pytest.raises(InputError):
            ReconstructParams.from_dict(bad)


def test_bad_views_are_reported():
    from rigbuild.reconstruct.frame import ReconstructParams, check_views, reconstruct_frame

    cams = [_cam("a"), _cam("b", center=(100.0, 0, -480.0)), _cam("c", center=(-100.0, 0, -480.0))]
    rng = np.random.default_rng(0)
    ok = (rng.random((120, 160)) * 255).astype(np.uint8)
    probs = check_views([ok, None, np.zeros((120, 160), np.uint8)], cams)
    assert len(probs) == 2 and "missing" in probs[0] and "all black" in probs[1]
    probs = check_views([ok, np.full((120, 160), 255, np.uint8), ok[:100]], cams)
    assert "saturated" in probs[0] and "160x100" in probs[1]
    with pytest.raises(InputError, match="view b: missing"):
        reconstruct_frame([ok, None, ok], cams, ReconstructParams())


def test_visibility_counts_occlusion():
    from rigbuild.eval.reconstruction import surface_distance, visible_counts

    # two parallel squares (z = 0 in front, z = 50 behind), cameras at z = -500 looking at +z
    sq = np.array([[-100.0, -100, 0], [100, -100, 0], [100, 100, 0], [-100, 100, 0]])
    V = np.vstack([sq, sq + [0, 0, 50]])
    F = np.array([[0, 2, 1], [0, 3, 2], [4, 6, 5], [4, 7, 6]])  # normals towards -z
    cams = [_cam("a", W=400, H=400), _cam("b", center=(60.0, 0.0, -500.0), W=400, H=400)]
    cnt = visible_counts(V, F, cams, np.arange(8), border_px=0)
    assert cnt[:4].tolist() == [2, 2, 2, 2] and cnt[4:].tolist() == [0, 0, 0, 0]
    d = surface_distance(np.array([[0.0, 0.0, 3.0], [0.0, 0.0, -2.0]]), sq, F[:2])
    assert np.allclose(d, [3.0, 2.0], atol=1e-4)


def test_coverage_tiles_draw_the_depth_grid_image():
    """The coverage montage shows each view's undistorted image (the grid its depth map is on), grey at 0.6,
    depth pixels + 90 green, foreground without depth + 110 red."""
    from rigbuild.reconstruct.frame import FrameReconstruction
    from rigbuild.reconstruct.sequence import coverage_tiles
    from rigbuild.reconstruct.stereo import pinhole

    cam = pinhole(_cam(dist=np.array([-0.1, 0.02, 0.0, 0.0, 0.0])))
    H, W = cam.height, cam.width
    und = np.zeros((H, W, 3), np.uint8)
    und[:, : W // 2] = 200
    depth = np.zeros((1, H, W), np.float32)
    depth[0, 60:90] = 400.0
    mask = np.zeros((1, H, W), bool)
    mask[0, 90:] = True
    empty = np.zeros((0, 3))
    rec = FrameReconstruction([cam], depth, depth * 0, depth.astype(np.uint8), mask, empty, empty, empty, empty,
                              np.zeros((0, 3), np.int64), {"coverage": {cam.id: 0.5}}, [und])
    t = coverage_tiles(rec, tile_width=W).astype(int)
    assert t.shape == (H, W, 3)
    assert (t[40:60, : W // 2] == 120).all() and (t[40:60, W // 2:] == 0).all()
    assert (t[60:90, : W // 2] == (120, 210, 120)).all() and (t[60:90, W // 2:] == (0, 90, 0)).all()
    assert (t[90:, : W // 2] == (120, 120, 230)).all() and (t[90:, W // 2:] == (0, 0, 110)).all()


def test_mask_of_a_distorted_view_ignores_the_undistortion_fill():
    """A bright disk on a uniform grey backdrop seen through pincushion distortion: undistorting fills the corners
    with black, which as the backdrop level would make the whole captured field foreground; the mask is found on the
    captured image and resampled, so it is the disk (and the fill is background)."""
    import cv2

    from rigbuild.reconstruct.masks import foreground_mask, pinhole_foreground_mask
    from rigbuild.reconstruct.stereo import to_gray_float, undistort_view

    cam = _cam(W=320, H=240, f=220.0, dist=np.array([0.3, 0.05, 0.0, 0.0, 0.0]))
    img = np.full((240, 320), 110, np.uint8)
    cv2.circle(img, (160, 120), 50, 230, -1)
    und, _ = undistort_view(img, cam)
    assert (und == 0).mean() > 0.02  # the fill is there
    old = foreground_mask(to_gray_float(und), dilate_px=0, erode_px=0)  # on the undistorted image: the backdrop too
    assert old[und > 0].mean() > 0.95
    m = pinhole_foreground_mask(img, cam, dilate_px=0, erode_px=0)
    disk = undistort_view((img > 170).astype(np.uint8), cam)[0]
    near = cv2.dilate(disk, np.ones((11, 11), np.uint8)) > 0  # the blur and the texture window widen the edge
    assert m[disk > 0].all() and not m[~near].any()
