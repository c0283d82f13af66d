"""Unit tests of the Laplacian tracking solver on tiny meshes with exact answers."""

from __future__ import annotations

import numpy as np
from grid_mesh import grid_mesh
import pytest
import scipy.sparse as sp

from rigbuild.track.laplacian import (
    LaplacianSolver,
    barycentric_matrix,
    displaced_targets,
    fit_vertex_rotations,
    interpolate,
    interpolated_normals,
    normal_displacement,
    vertex_normals,
)


def _rot(axis, deg):
    import cv2

    return cv2.Rodrigues(np.asarray(axis, float) / np.linalg.norm(axis) * np.radians(deg))[0]


def test_barycentric_matrix_and_interpolation_exact():
    V = np.array([[0, 0, 0], [2, 0, 0], [0, 4, 0], [2, 4, 1]], float)
    F = np.array([[0, 1, 2], [1, 3, 2]])
    B = barycentric_matrix(F, [0, 1], [[0.2, 0.3, 0.5], [1, 0, 0]], 4)
    assert B.shape == (2, 4)
    np.testing.assert_allclose(B.toarray(), [[0.2, 0.3, 0.5, 0], [0, 1, 0, 0]])
    np.testing.assert_allclose(B @ V, [[0.6, 2.0, 0.0], [2, 0, 0]])
    np.testing.assert_allclose(interpolate(V, F, [0, 1], [[0.2, 0.3, 0.5], [0, 0.5, 0.5]]), [[0.6, 2.0, 0.0], [1, 4, 0.5]])


def test_normal_displacement_flat_triangle_exact():
    V = np.array([[0, 0, 0], [3, 0, 0], [0, 3, 0]], float)
    F = np.array([[0, 1, 2]])
    N = vertex_normals(V, F)
    np.testing.assert_allclose(N, [[0, 0, 1]] * 3)
    u = np.array([[1.0, 1.0, 2.5], [0.5, 2.0, -1.25]])
    bary, h, ok = normal_displacement(V, F, N, u, [0, 0])
    assert ok.all()
    np.testing.assert_allclose(h, [2.5, -1.25], atol=1e-12)
    np.testing.assert_allclose(bary, [[1 / 3, 1 / 3, 1 / 3], [1 / 6, 1 / 6, 2 / 3]], atol=1e-12)
    # c = u' - h n: a target displaced by (1, 0, 0) keeps the same normal offset
    c = displaced_targets(u + [1, 0, 0], h, interpolated_normals(N, F, [0, 0], bary))
    np.testing.assert_allclose(c, interpolate(V, F, [0, 0], bary) + [1, 0, 0], atol=1e-12)
    # outside the triangle -> invalid
    _, _, ok2 = normal_displacement(V, F, N, np.array([[5.0, 5.0, 1.0]]), [0])
    assert not ok2[0]


def test_normal_displacement_curved_normals_root():
    """With interpolated (non-constant) normals the returned base point solves (u - b) x n(b) = 0."""
    V, F = grid_mesh(5, 8.0, bump=3.0)
    N = vertex_normals(V, F)
    rng = np.random.default_rng(0)
    tri = rng.integers(0, len(F), 50)
    b0 = rng.dirichlet([4, 4, 4], 50)
    n0 = interpolated_normals(N, F, tri, b0)
    u = interpolate(V, F, tri, b0) + rng.uniform(-0.5, 0.5, (50, 1)) * n0
    bary, h, ok = normal_displacement(V, F, N, u, tri, iterations=20)
    base = interpolate(V, F, tri, bary)
    n = interpolated_normals(N, F, tri, bary)
    assert ok.all()
    np.testing.assert_allclose(np.cross(u - base, n), 0, atol=1e-9)
    np.testing.assert_allclose(bary, b0, atol=1e-8)


def test_fit_vertex_rotations_recovers_rigid_rotation():
    V, F = grid_mesh(5, 8.0, bump=2.0)
    solver = LaplacianSolver(V, F)
    R = _rot([1, 2, 3], 25)
    Rv = fit_vertex_rotations(V, V @ R.T + 5.0, solver.edges, solver.edge_weights)
    np.testing.assert_allclose(Rv, np.broadcast_to(R, Rv.shape), atol=1e-10)


def test_rotations_from_covariances_threaded_blocks_equal_single_and_fix_reflections():
    from rigbuild.track.laplacian import rotations_from_covariances

    rng = np.random.default_rng(4)
    S = rng.normal(size=(5000, 3, 3))
    R1 = rotations_from_covariances(S, workers=1)
    np.testing.assert_array_equal(rotations_from_covariances(S, workers=2), R1)
    np.testing.assert_allclose(np.linalg.det(R1), 1.0, atol=1e-12)
    np.testing.assert_allclose(R1 @ R1.transpose(0, 2, 1), np.broadcast_to(np.eye(3), S.shape), atol=1e-12)
    # a reflection (det -1) is turned into the closest proper rotation: diag(1, 1, -1) -> identity
    np.testing.assert_allclose(rotations_from_covariances(np.diag([3.0, 2.0, -1.0])[None]), np.eye(3)[None], atol=1e-12)


def test_solve_translation_exact_with_all_vertices_constrained():
    V, F = grid_mesh(5, 8.0, bump=2.0)
    solver = LaplacianSolver(V, F)
    t = np.array([1.5, -2.0, 0.25])
    # constrain 3 points only: translation keeps delta, so the solution is exactly rest + t
    tri = np.array([0, 7, 20])
    bary = np.array([[1, 0, 0], [0.2, 0.3, 0.5], [0, 0, 1.0]])
    c = interpolate(V, F, tri, bary) + t
    p, rep = solver.solve(tri, bary, c, np.ones(3), lam=1.0, prior=V + t)
    np.testing.assert_allclose(p, V + t, atol=1e-9)
    assert rep.residual_mm.max() < 1e-9


def test_solve_matches_dense_reference_and_refactor_reuses_symbolic():
    V, F = grid_mesh(6, 10.0, bump=2.0)
    solver = LaplacianSolver(V, F, eps=1e-3)
    rng = np.random.default_rng(1)
    for n_matches in (4, 30):  # different constraint sets, same symbolic factorization
        tri = rng.integers(0, len(F), n_matches)
        bary = rng.dirichlet([1, 1, 1], n_matches)
        c = interpolate(V, F, tri, bary) + rng.normal(0, 0.5, (n_matches, 3))
        w = rng.uniform(0.5, 2.0, n_matches)
        lam = 3.0
        delta = solver.delta_rest + rng.normal(0, 0.1, V.shape)
        p, rep = solver.solve(tri, bary, c, w, lam, delta=delta)
        L = solver.L.toarray()
        B = barycentric_matrix(F, tri, bary, len(V)).toarray()
        M2 = np.diag(w**2)
        A = L.T @ L + lam * B.T @ M2 @ B + 1e-3 * np.eye(len(V))
        ref = np.linalg.solve(A, L.T @ delta + lam * B.T @ M2 @ c + 1e-3 * V)
        np.testing.assert_allclose(p, ref, atol=1e-8)
        # energy reported equals the energy of the solution
        assert rep.laplacian_energy == pytest.approx(np.sum((L @ p - delta) ** 2), rel=1e-9)


def test_rotated_delta_recovers_rigid_rotation_from_sparse_constraints():
    """A rotated copy constrained at a few points: iterating rotated Laplacian coordinates converges to it,
    while fixed rest coordinates cannot reproduce the rotation."""
    V, F = grid_mesh(7, 12.0, bump=3.0)
    solver = LaplacianSolver(V, F)
    R = _rot([0, 1, 0.3], 30)
    target = (V - V.mean(0)) @ R.T + V.mean(0) + [2, 0, 1]
    tri = np.array([0, 11, 35, 50, 71, 60])
    bary = np.full((6, 3), 1 / 3)
    c = interpolate(target, F, tri, bary)
    p, _ = solver.solve(tri, bary, c, np.ones(6), lam=10.0)
    err_fixed = np.abs(p - target).max()
    for _ in range(30):
        p, _ = solver.solve(tri, bary, c, np.ones(6), lam=10.0, delta=solver.rotated_delta(p), prior=p)
    err_rot = np.abs(p - target).max()
    assert err_rot < 0.02 * err_fixed
    assert err_rot < 0.01


def test_solve_rejects_empty_constraints():
    V, F = grid_mesh(4)
    solver = LaplacianSolver(V, F)
    with pytest.raises(ValueError):
        solver.solve(np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), 1.0)
