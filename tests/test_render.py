"""Tests of the CPU renderer (rigbuild.render) and the synthetic camera rig (rigbuild.synth.rig_layout).

Small images (320x240 .. 640x480) of meshes built here; the GL rasterizer is checked against the embree
ray caster and against the Camera model itself (projection of known surface points, dots, board corners).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from rigbuild.camera import Camera, look_at
from rigbuild.render import TexturedMesh, checker_texture, render_board, render_mesh, speckle_texture
from rigbuild.render.common import intersect_rays_triangles, pixel_rays, undistort_normalized
from rigbuild.render.gl import egl_available, gl_projection
from rigbuild.session import BoardSpec
from rigbuild.synth.rig_layout import (
    board_visibility,
    make_board_poses,
    make_camera_rig,
    view_graph_components,
)

needs_gl = pytest.mark.skipif(not egl_available(), reason="no EGL context on this machine")
DIST = [0.09, -0.03, 1.2e-3, -0.8e-3, 0.0]


# ------------------------------------------------------------------ scene helpers
def uv_sphere(radius=50.0, center=(0.0, 0.0, 0.0), nu=48, nv=24):
    """A UV sphere with welded vertices (one per pole, shared seam) and a separate UV grid."""
    th = np.linspace(0, np.pi, nv + 1)
    ph = np.linspace(0, 2 * np.pi, nu + 1)
    T, P = np.meshgrid(th, ph, indexing="ij")
    uv = np.stack([P / (2 * np.pi), 1 - T / np.pi], -1).reshape(-1, 2)
    grid = np.arange((nv + 1) * (nu + 1)).reshape(nv + 1, nu + 1)
    a, b, c, d = grid[:-1, :-1], grid[:-1, 1:], grid[1:, :-1], grid[1:, 1:]
    Fuv = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    # welded positions: north pole, rings 1..nv-1 (nu each), south pole
    i, j = np.divmod(np.arange((nv + 1) * (nu + 1)), nu + 1)
    pos_of = np.where(i == 0, 0, np.where(i == nv, 1 + (nv - 1) * nu, 1 + (i - 1) * nu + j % nu))
    V = np.zeros((2 + (nv - 1) * nu, 3))
    Tf, Pf = T.reshape(-1), P.reshape(-1)
    V[pos_of] = np.stack([np.sin(Tf) * np.cos(Pf), np.cos(Tf), np.sin(Tf) * np.sin(Pf)], -1) * radius
    return V + np.asarray(center), pos_of[Fuv], uv, Fuv


def box(size=(60.0, 40.0, 30.0), center=(0.0, 0.0, 0.0)):
    s = np.asarray(size) / 2
    V = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float) * s + center
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float)
    fuv = np.tile([[0, 1, 2], [0, 2, 3]], (6, 1))
    return V, F, uv, fuv


def scene_mesh(texture=None):
    """A sphere partly occluding a box behind it (two objects, an occlusion boundary, distortion)."""
    Vs, Fs, uvs, fuvs = uv_sphere(40.0, (10.0, 5.0, 20.0))
    Vb, Fb, uvb, fuvb = box((220.0, 160.0, 20.0), (0.0, 0.0, -40.0))
    V = np.vstack([Vs, Vb])
    F = np.vstack([Fs, Fb + len(Vs)])
    uv = np.vstack([uvs, uvb])
    fuv = np.vstack([fuvs, fuvb + len(uvs)])
    tex = checker_texture(256, 16) if texture is None else texture
    return TexturedMesh(V, F, uv, fuv, tex)


def camera(width=320, height=240, f=300.0, dist=DIST, center=(70.0, 50.0, 300.0), target=(0.0, 0.0, 0.0), cid="c0"):
    R, t = look_at(center, target)
    K = np.array([[f, 0.0, (width - 1) / 2 + 3.2], [0.0, f * 1.001, (height - 1) / 2 - 2.1], [0.0, 0.0, 1.0]])
    return Camera(cid, width, height, K, dist, R, t)


def psnr(a, b):
    mse = np.mean((a.astype(float) - b.astype(float)) ** 2)
    return 10 * np.log10(255.0 ** 2 / mse)


@pytest.fixture(scope="module")
def scene():
    return scene_mesh()


# ------------------------------------------------------------------ unit tests
def test_gl_projection_maps_pixel_centres_to_gl_centres():
    K = np.array([[500.0, 0.7, 150.3], [0.0, 480.0, 110.8], [0.0, 0.0, 1.0]])
    W, H = 320, 240
    P = gl_projection(K, W, H, 10.0, 1000.0)
    for u, v, z in [(0, 0, 50.0), (319, 239, 900.0), (150.3, 110.8, 10.0), (17.25, 200.5, 333.0)]:
        y = (v - K[1, 2]) / K[1, 1]
        x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
        clip = P @ np.array([x * z, y * z, z, 1.0])
        ndc = clip[:3] / clip[3]
        win = (ndc[:2] + 1) / 2 * np.array([W, H])
        np.testing.assert_allclose(win, [u + 0.5, v + 0.5], atol=1e-9)
    ndc_near = (P @ [0, 0, 10.0, 1])[2] / 10.0
    ndc_far = (P @ [0, 0, 1000.0, 1])[2] / 1000.0
    assert ndc_near == pytest.approx(-1.0) and ndc_far == pytest.approx(1.0)


def test_undistort_normalized_inverts_camera_projection():
    cam = camera()
    rng = np.random.default_rng(3)
    uv = rng.uniform([0, 0], [319, 239], (500, 2))
    xy = undistort_normalized(uv, cam.K, cam.dist)
    X = np.hstack([xy * 250.0, np.full((500, 1), 250.0)])
    back = cam.project((X - cam.t) @ cam.R)  # camera frame -> world -> pixels
    assert np.abs(back - uv).max() < 1e-8
    rays = pixel_rays(cam)
    assert rays.shape == (240, 320, 2)
    np.testing.assert_allclose(rays[7, 11], undistort_normalized(np.array([[11.0, 7.0]]), cam.K, cam.dist)[0], atol=1e-12)


def test_intersect_rays_triangles_exact():
    tri = np.array([[[-10.0, -10.0, 100.0], [10.0, -10.0, 100.0], [-10.0, 10.0, 200.0]]])
    xy = np.array([[0.0, 0.0], [0.5, 0.0]])
    z, b = intersect_rays_triangles(xy, tri, np.array([0, 0]))
    # plane: z = 150 + 5 y ; ray (0, 0, 1) hits at z = 150
    assert z[0] == pytest.approx(150.0, abs=1e-12)
    np.testing.assert_allclose(b[0], [0.0, 0.5, 0.5], atol=1e-12)
    P = z[1] * np.array([0.5, 0.0, 1.0])
    np.testing.assert_allclose(b[1] @ tri[0], P, atol=1e-9)
    assert b[1].min() < 0  # the ray at x = 0.5 z misses the triangle


def test_speckle_texture_deterministic_tileable_and_high_frequency():
    a = speckle_texture(256, seed=1)
    assert a.shape == (256, 256, 3) and a.dtype == np.uint8
    assert np.array_equal(a, speckle_texture(256, seed=1))
    assert not np.array_equal(a, speckle_texture(256, seed=2))
    g = a.astype(float).mean(2)
    # skin tone: red > green > blue on average
    m = a.reshape(-1, 3).mean(0)
    assert m[0] > m[1] > m[2]
    # strong fine-scale texture: neighbouring texels differ by several grey levels on average
    inner = np.abs(np.diff(g, axis=1)).mean()
    assert inner > 8.0
    # seamless: the wrap-around step is like any interior step
    wrap = np.abs(g[:, 0] - g[:, -1]).mean()
    assert wrap < 1.5 * inner


def test_numpy_resolve_from_exact_pinhole_ids_matches_ray_casting(scene):
    """The distortion resolve algorithm alone: ids at pinhole pixel centres (by ray casting) -> exact
    depth/id/bary at the distorted pixel centres, compared with casting those rays directly."""
    from rigbuild.render.common import resolve_from_id_buffer
    from rigbuild.render.embree import cast_rays
    from rigbuild.render.gl import pinhole_cover

    cam = camera()
    Kp, (Wp, Hp), mx, my, xy = pinhole_cover(cam)
    V = cam.world_to_camera(scene.vertices)
    u, v = np.meshgrid(np.arange(Wp, dtype=float), np.arange(Hp, dtype=float))
    pin_xy = np.stack([(u - Kp[0, 2]) / Kp[0, 0], (v - Kp[1, 2]) / Kp[1, 1]], -1).reshape(-1, 2)
    _, pin_tri, _ = cast_rays(V, scene.faces, pin_xy)
    pin_ids = (pin_tri + 1).reshape(Hp, Wp).astype(np.int32)
    depth, tri, bary = resolve_from_id_buffer(pin_ids, mx, my, xy, V[scene.faces], scene.faces)
    z, t, b = cast_rays(V, scene.faces, xy.reshape(-1, 2))
    t = t.reshape(tri.shape)
    assert (tri == t).mean() > 0.999
    both = (tri >= 0) & (t >= 0)
    dz = np.abs(depth[both] - z.reshape(tri.shape)[both])
    assert np.mean(dz < 1e-3) > 0.999 and np.median(dz) < 1e-4  # misses: sub-pixel slivers at silhouettes
    same = both & (tri == t)
    assert np.abs(bary[same] - b.reshape(bary.shape)[same]).max() < 1e-4


def test_empty_mesh_renders_background():
    cam = camera(64, 48, f=60.0)
    empty = TexturedMesh(np.zeros((0, 3)), np.zeros((0, 3), int), np.zeros((0, 2)), np.zeros((0, 3), int),
                         checker_texture(8, 2))
    for backend in (["gl"] if egl_available() else []) + ["embree"]:
        r = render_mesh(cam, empty, background=(10, 20, 30), backend=backend)
        assert np.all(r.color == [10, 20, 30]) and np.all(r.tri_id == -1) and np.all(np.isnan(r.depth))


# ------------------------------------------------------------------ renderer vs oracle
@needs_gl
def test_gl_matches_embree_oracle(scene):
    cam = camera()
    g = render_mesh(cam, scene, backend="gl")
    e = render_mesh(cam, scene, backend="embree")
    assert g.color.shape == (240, 320, 3) and g.color.dtype == np.uint8
    assert g.depth.dtype == np.float32 and g.tri_id.dtype == np.int32 and g.bary.dtype == np.float32
    assert e.mask.mean() > 0.3 and np.any(~e.mask)  # both objects and background in view
    both = g.mask & e.mask
    assert np.median(np.abs(g.depth - e.depth)[both]) < 1e-3
    assert (g.tri_id == e.tri_id).mean() > 0.995
    assert np.all(np.isnan(g.depth[~g.mask])) and np.all(g.tri_id[~g.mask] == -1)
    assert psnr(g.color, e.color) > 25.0
    # the occlusion boundary is there: sphere and box triangles both visible
    n_sphere = 2 * 48 * 24
    assert np.any((g.tri_id >= 0) & (g.tri_id < n_sphere)) and np.any(g.tri_id >= n_sphere)


@pytest.mark.parametrize("backend", [pytest.param("gl", marks=needs_gl), "embree"])
def test_tri_id_and_bary_reconstruct_the_ray_hit(scene, backend):
    cam = camera()
    r = render_mesh(cam, scene, backend=backend)
    P = r.points(scene.vertices, scene.faces)
    m = r.mask
    v, u = np.nonzero(m)
    # independent ray: OpenCV's undistortPoints through the Camera, scaled to the rendered depth
    rays = cam.rays(np.stack([u, v], 1).astype(float))  # unit world directions
    d_cam = rays @ cam.R.T
    hit = cam.center + rays * (r.depth[m].astype(float) / d_cam[:, 2])[:, None]
    err = np.linalg.norm(P[m] - hit, axis=1)
    assert np.percentile(err, 99) < 1e-3 and err.max() < 5e-3
    assert np.all(r.bary[m] >= -1e-5) and np.allclose(r.bary[m].sum(1), 1.0, atol=1e-5)
    # the reconstructed surface point projects back onto its pixel centre
    uv = cam.project(P[m])
    assert np.abs(uv - np.stack([u, v], 1)).max() < 1e-3


@pytest.mark.parametrize("backend", [pytest.param("gl", marks=needs_gl), "embree"])
def test_projected_surface_points_land_on_depth_buffer(backend):
    """camera.project(X) of visible surface points -> the depth there equals X's camera z to within the
    depth change of 0.5 px (reprojection error < 0.5 px), with distortion."""
    Vs, Fs, uvs, fuvs = uv_sphere(60.0, (0.0, 0.0, 0.0), 64, 32)
    mesh = TexturedMesh(Vs, Fs, uvs, fuvs, checker_texture(64, 8))
    cam = camera(dist=[-0.1, 0.02, 1e-3, 1e-3, 0.0], f=380.0)
    r = render_mesh(cam, mesh, backend=backend)
    rng = np.random.default_rng(0)
    f = rng.integers(0, len(Fs), 4000)
    b = rng.dirichlet([1, 1, 1], 4000)
    X = np.einsum("nk,nkd->nd", b, Vs[Fs[f]])
    # visible: on the camera-facing side of the (convex) sphere, not grazing
    nrm = X / np.linalg.norm(X, axis=1, keepdims=True)
    view = X - cam.center
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    X = X[(nrm * view).sum(1) < -0.3]
    z = cam.world_to_camera(X)[:, 2]
    uv = cam.project(X)
    p = np.rint(uv).astype(int)
    ok = (p[:, 0] > 1) & (p[:, 0] < 318) & (p[:, 1] > 1) & (p[:, 1] < 238)
    p, z, uv = p[ok], z[ok], uv[ok]
    assert len(z) > 500
    D = r.depth.astype(float)
    dzdu = (D[p[:, 1], p[:, 0] + 1] - D[p[:, 1], p[:, 0] - 1]) / 2
    dzdv = (D[p[:, 1] + 1, p[:, 0]] - D[p[:, 1] - 1, p[:, 0]]) / 2
    assert np.all(np.isfinite(D[p[:, 1], p[:, 0]]))
    # depth at the pixel centre predicted from the point's own depth and the local gradient
    pred = z + dzdu * (p[:, 0] - uv[:, 0]) + dzdv * (p[:, 1] - uv[:, 1])
    resid = np.abs(D[p[:, 1], p[:, 0]] - pred)
    grad = np.hypot(dzdu, dzdv)
    assert np.all(resid <= 0.5 * grad + 1e-3)
    assert np.median(resid) < 0.05 * np.median(grad) + 1e-3  # far better than 0.5 px: exact to a few 1e-2 px


@pytest.mark.parametrize("backend", [pytest.param("gl", marks=needs_gl), "embree"])
def test_painted_dots_are_drawn_where_the_camera_projects_them(backend):
    """Dark dots on a white plane: their image centroids equal camera.project of their centres."""
    quad = np.array([[-80.0, -60.0, 0.0], [80.0, -60.0, 0.0], [80.0, 60.0, 0.0], [-80.0, 60.0, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float)
    gx, gy = np.meshgrid(np.linspace(-60, 60, 5), np.linspace(-40, 40, 4))
    centers = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    mesh = TexturedMesh(quad, faces, uvs, faces, np.full((8, 8, 3), 255, np.uint8),
                        dot_centers=centers, dot_radius_mm=2.5, dot_albedo=(0, 0, 0))
    cam = camera(f=400.0, center=(40.0, 30.0, 320.0))
    r = render_mesh(cam, mesh, backend=backend, ambient=1.0)
    darkness = 255.0 - r.color.astype(float).mean(2)
    darkness[darkness < 3] = 0.0
    truth = cam.project(centers)
    errs = []
    for uv in truth:
        u0, v0 = np.rint(uv).astype(int)
        win = darkness[v0 - 7: v0 + 8, u0 - 7: u0 + 8]
        vv, uu = np.mgrid[v0 - 7: v0 + 8, u0 - 7: u0 + 8]
        c = np.array([(win * uu).sum(), (win * vv).sum()]) / win.sum()
        errs.append(np.linalg.norm(c - uv))
        assert win.sum() > 255 * 10  # a dot of several pixels is there
    tol = 0.1 if backend == "gl" else 0.2  # 1 sample per pixel on the embree path
    assert max(errs) < tol


@needs_gl
def test_same_seed_gives_identical_images(scene):
    cam = camera()
    a = render_mesh(cam, scene, noise_sigma=2.0, seed=5, backend="gl")
    b = render_mesh(cam, scene, noise_sigma=2.0, seed=5, backend="gl")
    c = render_mesh(cam, scene, noise_sigma=2.0, seed=6, backend="gl")
    assert a.color.tobytes() == b.color.tobytes()
    assert np.array_equal(a.depth, b.depth, equal_nan=True) and np.array_equal(a.tri_id, b.tri_id)
    assert a.color.tobytes() != c.color.tobytes()
    noise = a.color.astype(float) - render_mesh(cam, scene, backend="gl").color
    assert 1.5 < noise.std() < 2.5
    geo = render_mesh(cam, scene, backend="gl", with_color=False)
    assert np.array_equal(geo.tri_id, a.tri_id) and np.all(geo.color == 128)
    col = render_mesh(cam, scene, noise_sigma=2.0, seed=5, backend="gl", with_geometry=False)
    assert col.color.tobytes() == a.color.tobytes()  # colour-only renders are the same pixels
    assert np.all(col.tri_id == -1) and np.all(np.isnan(col.depth))
    e1 = render_mesh(cam, scene, noise_sigma=2.0, seed=5, backend="embree")
    e2 = render_mesh(cam, scene, noise_sigma=2.0, seed=5, backend="embree")
    assert e1.color.tobytes() == e2.color.tobytes()


def test_auto_backend_falls_back_to_embree_with_a_warning(scene, monkeypatch):
    import rigbuild.render as render
    import rigbuild.render.gl as gl

    monkeypatch.setattr(gl, "egl_available", lambda: False)
    monkeypatch.setattr(render, "_WARNED", [])
    cam = camera(160, 120, f=150.0)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        r = render_mesh(cam, scene)
    assert any("embree" in str(x.message) for x in w)
    e = render_mesh(cam, scene, backend="embree")
    assert r.color.tobytes() == e.color.tobytes()
    with pytest.raises(ValueError):
        render_mesh(cam, scene, backend="vulkan")


# ------------------------------------------------------------------ rig layout and boards
def test_make_camera_rig_frames_the_face():
    cams = make_camera_rig(8, seed=1)
    assert [c.id for c in cams] == [f"cam{i:02d}" for i in range(8)]
    target = np.array([0.0, 5.0, 40.0])
    az = []
    for c in cams:
        assert (c.width, c.height) == (1280, 960)
        assert np.linalg.norm(c.center - target) == pytest.approx(450.0, rel=0.03)
        uv = c.project(target[None])[0]
        assert np.abs(uv - [639.5, 479.5]).max() < 60  # aimed at the face
        assert abs(c.K[0, 2] - 639.5) < 15 and abs(c.K[1, 2] - 479.5) < 15
        assert -0.1 <= c.dist[0] <= 0.1 and np.all(np.abs(c.dist[1:4]) <= 2e-3)
        # a 230 mm face fills most of the image height: 0.6..1.0 of it
        assert 0.6 < 230.0 * c.K[1, 1] / 450.0 / 960 < 1.0
        az.append(np.degrees(np.arctan2(c.center[0] - target[0], c.center[2] - target[2])))
    assert np.all(np.diff(az) > 10) and az[0] == pytest.approx(-60, abs=3) and az[-1] == pytest.approx(60, abs=3)
    cams16 = make_camera_rig(16, seed=1)
    heights = np.array([c.center[1] for c in cams16])
    assert len(cams16) == 16 and (heights > 40).sum() == 8 and (heights < -30).sum() == 8
    assert np.array_equal(make_camera_rig(8, seed=1)[3].K, cams[3].K)


def test_make_board_poses_connected_and_seen_by_two():
    cams = make_camera_rig(8, width=640, height=480, seed=2)
    spec = BoardSpec(squares_x=7, squares_y=5, square_size_mm=24.0, marker_size_mm=18.0)
    poses, seen = make_board_poses(cams, spec, n_poses=10, seed=3)
    assert len(poses) == len(seen) == 10
    ids = [c.id for c in cams]
    idx = [[ids.index(s) for s in ss] for ss in seen]
    assert all(len(s) >= 2 for s in idx)
    assert len(set(view_graph_components(len(cams), idx))) == 1
    assert set(i for s in idx for i in s) == set(range(len(cams)))
    corners, _ = spec.corner_points()
    for (R, t), s in zip(poses, idx):
        assert np.allclose(R.T @ R, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
        for i in s:  # every corner in the frame of every camera said to see it
            uv = cams[i].project(corners @ R.T + t)
            assert np.all((uv > 0) & (uv < [cams[i].width - 1, cams[i].height - 1]))
        tilt = np.degrees(np.arccos(abs(R[2, 2])))
        assert tilt < 90
    # the visibility test itself: a board turned away is seen by nobody
    R, t = poses[0]
    flip = np.diag([1.0, -1.0, -1.0])
    assert board_visibility(cams, spec, R @ flip, t) == []


@needs_gl
def test_charuco_corners_detected_with_subpixel_accuracy():
    import cv2

    cams = make_camera_rig(3, width=640, height=480, arc_deg=(-40, 40), seed=4)
    spec = BoardSpec(squares_x=7, squares_y=5, square_size_mm=24.0, marker_size_mm=18.0)
    poses, seen = make_board_poses(cams, spec, n_poses=3, seed=5)
    detector = cv2.aruco.CharucoDetector(spec.opencv_board())
    corners, _ = spec.corner_points()
    byid = {c.id: c for c in cams}
    n_images, errors = 0, []
    for k, ((R, t), s) in enumerate(zip(poses, seen)):
        for cid in s:
            cam = byid[cid]
            img = render_board(cam, spec, R, t, noise_sigma=1.0, seed=k, backend="gl")
            cc, ci, _, _ = detector.detectBoard(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
            assert ci is not None and len(ci) == len(corners), f"pose {k} {cid}: corners missing"
            truth = cam.project(corners @ R.T + t)[ci.ravel()]
            errors.append(cc.reshape(-1, 2) - truth)
            n_images += 1
    e = np.concatenate(errors)
    assert n_images >= 6
    assert np.sqrt((e ** 2).sum(1).mean()) < 0.3
    assert np.abs(e.mean(0)).max() < 0.05  # no half-pixel bias


def test_chessboard_board_renders_with_embree():
    import cv2

    spec = BoardSpec(type="chessboard", squares_x=8, squares_y=6, square_size_mm=20.0)
    cam = camera(640, 480, f=600.0, dist=[0.05, 0.0, 0.0, 0.0, 0.0], center=(0.0, 0.0, 400.0))
    # board facing the camera: board z points away from it (world -z), board y down (world -y)
    R = np.diag([1.0, -1.0, -1.0])
    t = np.array([-60.0, 40.0, 0.0])
    img = render_board(cam, spec, R, t, backend="embree")
    gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    ok, pts = cv2.findChessboardCorners(gray, (7, 5))
    assert ok
    pts = cv2.cornerSubPix(gray, pts, (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4))
    corners, _ = spec.corner_points()
    truth = cam.project(corners @ R.T + t)
    # OpenCV may order the grid from either end; compare as point sets
    d = np.linalg.norm(pts.reshape(-1, 1, 2) - truth[None], axis=2).min(1)
    assert np.sqrt((d ** 2).mean()) < 0.3
    back = render_board(cam, spec, R @ np.diag([1.0, -1.0, -1.0]), t, backend="embree")
    seen = back.astype(int).sum(2) != 3 * 128
    assert seen.sum() > 20000 and back[seen].std() < 1.0  # the blank back side: uniform


# ------------------------------------------------------------------ realistic scale (ICT head, 1280x960)
@pytest.mark.slow
@pytest.mark.data
@needs_gl
def test_ict_head_gl_matches_embree_at_full_resolution(ict_rig):
    rig = ict_rig
    marker_ids = rig.landmarks[rig.landmarks >= 0]
    mesh = TexturedMesh(rig.neutral, rig.faces, rig.uvs, rig.face_uvs, speckle_texture(2048),
                        dot_centers=rig.neutral[marker_ids], dot_radius_mm=1.5)
    cams = make_camera_rig(8, seed=0)
    for cam in (cams[0], cams[3]):
        g = render_mesh(cam, mesh, backend="gl")
        e = render_mesh(cam, mesh, backend="embree")
        both = g.mask & e.mask
        assert both.mean() > 0.3
        assert np.median(np.abs(g.depth - e.depth)[both]) < 1e-3
        assert (g.tri_id == e.tri_id).mean() > 0.995
        assert psnr(g.color, e.color) > 28.0
        # every face vertex in view projects onto the rendered head
        uv = cam.project(rig.neutral[:6706])
        assert np.all((uv >= 0) & (uv <= [cam.width - 1, cam.height - 1]))


def test_make_camera_rig_k3_range_leaves_the_rest_of_the_layout():
    plain = make_camera_rig(8, seed=4)
    with_k3 = make_camera_rig(8, seed=4, k3_range=(-0.05, 0.05))
    k3 = np.array([c.dist[4] for c in with_k3])
    assert np.all(np.abs(k3) <= 0.05) and np.ptp(k3) > 0.02 and all(c.dist[4] == 0 for c in plain)
    for a, b in zip(plain, with_k3):
        assert np.array_equal(a.K, b.K) and np.array_equal(a.R, b.R) and np.array_equal(a.dist[:4], b.dist[:4])
        assert np.abs(a.dist[2:4]).max() > 0  # tangential terms are drawn on every lens


def _point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    """Brute force: the nearest of a dense barycentric grid over the triangle (accurate to ~1e-3 of its size)."""
    s = np.linspace(0.0, 1.0, 201)
    u, v = np.meshgrid(s, s)
    keep = u + v <= 1.0
    u, v = u[keep], v[keep]
    pts = a + u[:, None] * (b - a) + v[:, None] * (c - a)
    return float(np.linalg.norm(pts - p, axis=1).min())


def test_dot_candidates_keep_dots_in_reach_in_ascending_order():
    from rigbuild.render.common import dot_candidates

    tri = np.array([[[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]]])
    centres = np.array([[100.0, 100.0, 0.0],   # far
                        [3.0, 3.0, 0.0],       # inside
                        [12.5, 0.0, 0.0],      # 2.5 mm beyond a corner: within r 1 + margin 2
                        [20.0, 0.0, 0.0]])     # 10 mm away
    cand = dot_candidates(tri, centres, np.ones(4), margin_mm=2.0)
    assert cand.shape == (1, 4) and cand.dtype == np.int32
    assert 1 in cand[0] and 2 in cand[0] and 0 not in cand[0]
    kept = cand[0][cand[0] >= 0]
    assert np.all(np.diff(kept) > 0)
    assert np.all(cand[0][len(kept):] == -1)
    # more candidates than slots: the triangle is marked for every dot
    many = dot_candidates(tri, np.tile([[2.0, 2.0, 0.0]], (5, 1)), np.ones(5), margin_mm=2.0, k=4)
    assert many.tolist() == [[-2, -1, -1, -1]]
    assert dot_candidates(tri, np.zeros((0, 3)), np.ones(0), 2.0).tolist() == [[-1, -1, -1, -1]]


def test_dot_candidates_never_miss_a_dot_within_reach():
    from rigbuild.render.common import dot_candidates

    rng = np.random.default_rng(3)
    tri = rng.uniform(-20, 20, (40, 1, 3)) + rng.normal(0, 4, (40, 3, 3))
    centres = rng.uniform(-25, 25, (60, 3))
    radii = rng.uniform(1.0, 2.0, 60)
    cand = dot_candidates(tri, centres, radii, margin_mm=2.0, k=60)
    for f in range(tri.shape[0]):
        for i in range(centres.shape[0]):
            if _point_triangle_distance(centres[i], *tri[f]) < radii[i] + 2.0 - 1e-2:
                assert i in cand[f], (f, i)
