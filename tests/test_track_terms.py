"""Unit tests with exact answers for the registration's point-to-plane solve, the visibility test of the
closest-point term, and the render-free source surface lookup (depth map + closest point on the mesh)."""

from __future__ import annotations

import numpy as np
from grid_mesh import grid_mesh

from rigbuild.camera import Camera, look_at
from rigbuild.track.laplacian import LaplacianSolver
from rigbuild.track.matches import Source, ViewFrame, closest_surface_points, lift_matches
from rigbuild.track.register import observed_views, solve_point_to_plane


def _grid(n=7, size=12.0):
    return grid_mesh(n, size)


def _front_camera(W=160, H=120, f=200.0, z=100.0, centre=(6.0, 6.0, 0.0)):
    c = np.asarray(centre)
    R, t = look_at(c + [0, 0, z], c, (0, 1, 0))
    return Camera("c", W, H, [[f, 0, W / 2 - 0.5], [0, f, H / 2 - 0.5], [0, 0, 1]], [0, 0, 0, 0, 0], R, t)


def test_point_to_plane_moves_normally_and_slides_tangentially():
    V, F = _grid()
    solver = LaplacianSolver(V, F, eps=1e-9)
    allv = np.arange(V.shape[0])
    nz = np.tile([0.0, 0.0, 1.0], (allv.size, 1))
    # every vertex on the plane z = 1.5: exact answer = the rest mesh lifted by 1.5 (Laplacian unchanged)
    q = V + [0.0, 0.0, 1.5]
    p = solve_point_to_plane(solver, solver.delta_rest, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)),
                             np.zeros(0), allv, q, nz, np.ones(allv.size), 10.0, prior=V)
    np.testing.assert_allclose(p, q, atol=1e-5)  # x, y held only by the 1e-9 Tikhonov term
    # planes z = 0 plus one point constraint dragging a vertex by 0.5 mm in x: the planes do not resist the
    # tangential motion, so the whole sheet translates (exact answer), unlike point-to-point targets
    tri, bary = np.array([0]), np.array([[1.0, 0.0, 0.0]])
    tgt = V[F[0, 0]][None] + [0.5, 0.0, 0.0]
    p = solve_point_to_plane(solver, solver.delta_rest, tri, bary, tgt, np.ones(1), allv, V, nz,
                             np.ones(allv.size), 10.0, prior=V)
    np.testing.assert_allclose(p, V + [0.5, 0.0, 0.0], atol=1e-5)


def test_observed_views_depth_and_facing():
    cam = _front_camera()
    depth = np.full((cam.height, cam.width), 100.0, np.float32)  # the plane z = 0 at 100 mm
    pts = np.array([[6.0, 6.0, 0.0], [6.0, 6.0, -5.0], [6.0, 6.0, 0.0], [6.0, 6.0, 1.0]])
    nrm = np.array([[0, 0, 1.0], [0, 0, 1.0], [0, 0, -1.0], [0, 0, 1.0]])
    n = observed_views(pts, nrm, [(cam, depth), (cam, depth)], tolerance_mm=2.0)
    np.testing.assert_array_equal(n, [2, 0, 0, 2])
    np.testing.assert_array_equal(observed_views(pts, nrm, [(cam, depth)], tolerance_mm=0.5), [1, 0, 0, 0])


def test_closest_surface_points_exact():
    V = np.array([[0, 0, 0.0], [4, 0, 0], [0, 4, 0]])
    F = np.array([[0, 1, 2]])
    tri, bary, d = closest_surface_points(np.array([[1.0, 1.0, 2.0], [1.0, 2.0, -0.5]]), V, F)
    np.testing.assert_array_equal(tri, [0, 0])
    np.testing.assert_allclose(bary, [[0.5, 0.25, 0.25], [0.25, 0.25, 0.5]], atol=1e-12)
    np.testing.assert_allclose(d, [2.0, 0.5], atol=1e-12)


def test_source_surface_points_and_motion_field_from_depth():
    V, F = _grid(n=13, size=24.0)
    cam = _front_camera(centre=(12.0, 12.0, 0.0))
    depth = np.full((cam.height, cam.width), 100.0, np.float32)
    uvs = cam.project(V)
    inside = (uvs[:, 0] > 0) & (uvs[:, 1] > 0) & (uvs[:, 0] < cam.width - 1) & (uvs[:, 1] < cam.height - 1)
    img = np.zeros((cam.height, cam.width, 3), np.uint8)
    src = Source.build(V, F, [ViewFrame(cam, img, depth)], "previous")
    tri, bary, ok = src.views[0].surface_points(uvs[inside])
    assert ok.all()
    np.testing.assert_allclose(np.einsum("nk,nkd->nd", bary, V[F[tri]]), V[inside], atol=1e-6)
    # a pure in-plane translation of the estimate by 1.2 mm in x moves every pixel by f * 1.2 / 100 px
    est = V + [1.2, 0.0, 0.0]
    u0, v0 = np.round(uvs[inside].min(0)).astype(int) + 2
    u1, v1 = np.round(uvs[inside].max(0)).astype(int) - 2
    m = src.motion_field(0, est, step=4, box=(v0, v1, u0, u1))
    assert m.shape == (v1 - v0, u1 - u0, 2)
    np.testing.assert_allclose(m[..., 0], 200.0 * 1.2 / 100.0, atol=1e-3)
    np.testing.assert_allclose(m[..., 1], 0.0, atol=1e-3)


def test_closest_surface_points_with_a_prebuilt_tree_is_the_same_query():
    import igl

    V, F = _grid(n=9, size=16.0)
    rng = np.random.default_rng(3)
    P = rng.uniform([-2, -2, -1], [18, 18, 1], (200, 3))
    tree = igl.AABB()
    tree.init(V, F.astype(np.int64))
    a, b = closest_surface_points(P, V, F), closest_surface_points(P, V, F, tree=tree)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_grid_surface_points_subset_of_a_cached_grid_equals_the_direct_query():
    V, F = _grid(n=13, size=24.0)
    cam = _front_camera(centre=(12.0, 12.0, 0.0))
    depth = np.full((cam.height, cam.width), 100.0, np.float32)
    src = Source.build(V, F, [ViewFrame(cam, np.zeros((cam.height, cam.width, 3), np.uint8), depth)], "previous")
    box = (30, 90, 40, 120)
    sv = src.views[0]
    sv.grid_surface_points(box, 4)  # the motion field's grid, cached
    grid, tri, bary, ok = sv.grid_surface_points(box, 8, offset=4)  # read from it
    assert grid.shape == (len(range(34, 90, 8)), len(range(44, 120, 8)), 2)
    np.testing.assert_array_equal(grid[0, 0], [44, 34])
    t2, b2, ok2 = sv.surface_points(grid.reshape(-1, 2))
    np.testing.assert_array_equal(tri, t2)
    np.testing.assert_array_equal(bary, b2)
    np.testing.assert_array_equal(ok, ok2)
    assert ok.sum() > 0.5 * ok.size


def test_lift_matches_puts_the_source_normal_offset_on_the_target():
    """Plane mesh z = 0, normals (0, 0, 1). A source pixel lifted 0.5 mm above the plane (depth 99.5) anchors
    at the point below it with h = 0.5; matched to the same pixel of a target with depth 99 (the point u'),
    the constraint is c = u' - h n, at the source's base point."""
    from rigbuild.track.features import lift

    V, F = _grid(n=13, size=24.0)
    cam = _front_camera(centre=(12.0, 12.0, 0.0))
    img = np.zeros((cam.height, cam.width, 3), np.uint8)
    d_src = np.full((cam.height, cam.width), 99.5, np.float32)
    d_tgt = np.full((cam.height, cam.width), 99.0, np.float32)
    src = Source.build(V, F, [ViewFrame(cam, img, d_src)], "previous")
    tgt = ViewFrame(cam, img, d_tgt)
    uv = np.array([[80.0, 60.0], [70.0, 50.0], [75.5, 55.25]])
    anchored = src.views[0].anchored(uv)
    assert anchored.ok.all()
    u_src, u_tgt = lift(cam, d_src, uv), lift(cam, d_tgt, uv)
    np.testing.assert_allclose(anchored.h, u_src[:, 2], atol=1e-9)
    np.testing.assert_allclose(anchored.normal, np.tile([0.0, 0.0, 1.0], (3, 1)), atol=1e-12)
    base = np.einsum("nk,nkd->nd", anchored.bary, V[F[anchored.tri]])
    np.testing.assert_allclose(base, u_src * [1, 1, 0], atol=1e-9)
    m = lift_matches(src, 0, anchored, uv, tgt, np.array([1.0, 0.5, 0.25]), "flow")
    assert m.n == 3
    np.testing.assert_allclose(m.targets, u_tgt - u_src * [0, 0, 1], atol=1e-9)
    np.testing.assert_array_equal(m.weights, [1.0, 0.5, 0.25])
    # a prediction check against an estimate 2 mm off rejects at 1 mm, keeps at 3 mm
    est = V + [0.0, 0.0, 2.0]
    assert lift_matches(src, 0, anchored, uv, tgt, np.ones(3), "flow", estimate=est, max_prediction_error_mm=1.0).n == 0
    assert lift_matches(src, 0, anchored, uv, tgt, np.ones(3), "flow", estimate=est, max_prediction_error_mm=3.0).n == 3
