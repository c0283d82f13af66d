"""Unit tests with exact answers for the registration's point-to-plane solve, the visibility test of the
closest-point term, and the render-free source surface lookup (depth map + closest point on the mesh)."""

from __future__ import annotations

import numpy as np
from grid_mesh import grid_mesh

from rigbuild.camera import Camera, look_at
from rigbuild.track.laplacian import LaplacianSolver
from rigbuild.track.matches import Source, ViewFrame, closest_surface_points
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
