"""Deformation gradients, the gradient operator G and deformation transfer on analytic meshes."""

from __future__ import annotations

import numpy as np
import pytest

from rigbuild.errors import InputError
from rigbuild.geometry.deformation_transfer import (
    deformation_gradients,
    deformation_transfer,
    face_components,
    gradient_operator,
    triangle_frames,
)


def grid_mesh(n: int = 9, size: float = 40.0):
    """A curved n x n grid (mm) with triangles; returns vertices (n*n, 3), faces."""
    u = np.linspace(-size / 2, size / 2, n)
    X, Y = np.meshgrid(u, u, indexing="ij")
    Z = 0.01 * (X**2 + 0.5 * Y**2) + 0.1 * X
    verts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return verts, faces


def local_deltas(verts: np.ndarray) -> np.ndarray:
    """Two shapes with compact support: a bump and a sideways shear patch (exact zeros outside)."""
    r = np.linalg.norm(verts[:, :2] - np.array([5.0, 0.0]), axis=1)
    bump = np.clip(1 - (r / 12.0) ** 2, 0, None) ** 2
    d0 = np.zeros_like(verts)
    d0[:, 2] = 3.0 * bump
    d0[:, 0] = 0.5 * bump
    r2 = np.linalg.norm(verts[:, :2] - np.array([-8.0, 6.0]), axis=1)
    w = np.clip(1 - (r2 / 10.0) ** 2, 0, None) ** 2
    d1 = np.stack([1.5 * w, -1.0 * w, 0.4 * w * verts[:, 0] / 20], 1)
    return np.stack([d0, d1])


def test_frames_and_gradients_of_a_known_linear_map():
    verts, faces = grid_mesh(5)
    A = np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.2], [0.05, 0.0, 1.1]])
    T = deformation_gradients(verts, verts @ A.T + np.array([3.0, -2.0, 1.0]), faces)
    # a linear map's gradient in the frame is A on the edges; the 4th column differs (normal
    # scaled by sqrt(area) does not follow A), but A is recovered on the triangle plane
    V = triangle_frames(verts, faces)
    np.testing.assert_allclose(T @ V[..., :2], (A @ V[..., :2]), atol=1e-12)
    # rigid motion -> T is the rotation exactly (4th vertex frame is rotation covariant)
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    T = deformation_gradients(verts, verts @ R.T + 5.0, faces)
    np.testing.assert_allclose(T, np.broadcast_to(R, T.shape), atol=1e-12)


def test_gradient_operator_matches_in_plane_deformation_gradients():
    verts, faces = grid_mesh(7)
    G = gradient_operator(verts, faces)
    assert G.shape == (3 * len(faces), len(verts))
    np.testing.assert_allclose(G @ np.ones(len(verts)), 0.0, atol=1e-12)
    V = triangle_frames(verts, faces)
    n = V[..., 2] / np.linalg.norm(V[..., 2], axis=-1, keepdims=True)
    P = np.eye(3) - n[:, :, None] * n[:, None, :]
    np.testing.assert_allclose((G @ verts).reshape(-1, 3, 3).transpose(0, 2, 1), P, atol=1e-12)
    deformed = verts + local_deltas(verts)[0]
    T = deformation_gradients(verts, deformed, faces)
    GX = (G @ deformed).reshape(-1, 3, 3).transpose(0, 2, 1)
    np.testing.assert_allclose(GX, T @ P, atol=1e-12)


def test_identity_transfer_returns_source_deltas_exactly():
    verts, faces = grid_mesh(11)
    deltas = local_deltas(verts)
    out = deformation_transfer(verts, deltas, faces, verts)
    np.testing.assert_allclose(out, deltas, atol=1e-9)
    # local support is kept exactly
    assert np.all(out[np.linalg.norm(deltas, axis=2) == 0] == 0)


def test_scaled_and_translated_target_gives_scaled_deltas():
    verts, faces = grid_mesh(11)
    deltas = local_deltas(verts)
    out = deformation_transfer(verts, deltas, faces, 1.7 * verts + np.array([10.0, -4.0, 2.0]))
    np.testing.assert_allclose(out, 1.7 * deltas, atol=1e-9)


def test_planar_linear_deformation_transfers_exactly_onto_a_stretched_target():
    verts, faces = grid_mesh(9)
    verts[:, 2] = 0.0  # planar: the target's edges stay in the source's plane
    x0 = verts[40]
    A = np.array([[0.2, 0.1, 0.0], [-0.05, 0.3, 0.0], [0.0, 0.0, 0.0]])
    deltas = (verts - x0) @ A.T  # zero only at vertex 40 (the Dirichlet anchor)
    S = np.diag([1.5, 0.8, 1.0])
    out = deformation_transfer(verts, deltas, faces, verts @ S.T)
    np.testing.assert_allclose(out, (verts - x0) @ S.T @ A.T, atol=1e-9)


def test_component_moving_as_a_whole_keeps_its_scaled_mean_motion():
    verts, faces = grid_mesh(5)
    other = verts + np.array([100.0, 0.0, 0.0])
    all_v = np.concatenate([verts, other])
    all_f = np.concatenate([faces, faces + len(verts)])
    assert face_components(len(all_v), all_f).max() == 1
    d = np.zeros_like(all_v)
    d[len(verts):] = np.array([0.0, 2.0, -1.0])  # second component translates rigidly
    c = all_v[len(verts):].mean(0)
    tgt = all_v.copy()
    tgt[len(verts):] = c + 2.0 * (all_v[len(verts):] - c)  # that component is twice as big
    out = deformation_transfer(all_v, d, all_f, tgt)
    np.testing.assert_allclose(out[len(verts):], np.broadcast_to([0.0, 4.0, -2.0], (len(verts), 3)), atol=1e-9)
    np.testing.assert_array_equal(out[: len(verts)], 0.0)


def test_anchor_vertices_stay_static():
    verts, faces = grid_mesh(11)
    deltas = local_deltas(verts)
    peak = int(np.argmax(deltas[0, :, 2]))
    out = deformation_transfer(verts, deltas, faces, verts, anchor=np.array([peak]))
    np.testing.assert_array_equal(out[:, peak], 0.0)
    assert np.abs(out[0] - deltas[0]).max() > 0.1  # pinning the peak changes the solution


def test_topology_mismatch_is_a_clear_error():
    verts, faces = grid_mesh(5)
    with pytest.raises(InputError, match="same topology"):
        deformation_transfer(verts, local_deltas(verts), faces, verts[:-1])


def test_ict_identity_transfer(ict_rig):
    sub = ict_rig.subset(["jawOpen", "eyeBlink_L"])
    out = deformation_transfer(sub.neutral, sub.deltas, sub.faces, sub.neutral)
    # ICT OBJs carry rounding noise below the support tolerance (5e-4 mm); everything else is exact
    assert np.abs(out - sub.deltas).max() < 1e-3


def test_two_worker_processes_give_the_same_transfer():
    verts, faces = grid_mesh(11)
    deltas = np.concatenate([local_deltas(verts), 0.5 * local_deltas(verts)[::-1]])
    target = verts * np.array([1.2, 0.9, 1.1]) + 0.02 * verts[:, [1, 2, 0]] ** 2 / 10
    serial = deformation_transfer(verts, deltas, faces, target)
    np.testing.assert_array_equal(deformation_transfer(verts, deltas, faces, target, workers=2), serial)
    sample = np.array([3, 40, 60, 77, 100])
    sampled = deformation_transfer(verts, deltas, faces, target, sample_vertices=sample, workers=2)
    np.testing.assert_allclose(sampled, serial[:, sample], atol=1e-12)


def test_aligned_transfer_onto_a_rotated_target_rotates_the_shapes():
    """A target that is the source turned 150 degrees, scaled 1.2 and moved (a tracked neutral in the cameras'
    world): the aligned transfer returns the source shapes turned and scaled with it, exactly; the plain
    transfer moves the target along the source's axes instead (cosine with the right answer well below 1)."""
    import cv2

    from rigbuild.geometry.deformation_transfer import deformation_transfer_aligned

    V, F = grid_mesh()
    D = local_deltas(V)
    R = cv2.Rodrigues(np.array([0.2, 1.0, 0.3]) / np.linalg.norm([0.2, 1.0, 0.3]) * np.radians(150))[0]
    target = 1.2 * V @ R.T + [10.0, -4.0, 300.0]
    expected = 1.2 * D @ R.T
    got = deformation_transfer_aligned(V, D, F, target)
    np.testing.assert_allclose(got, expected, atol=1e-6)
    plain = deformation_transfer(V, D, F, target)
    cos = np.sum(plain * expected) / (np.linalg.norm(plain) * np.linalg.norm(expected))
    assert cos < 0.9
    # an already aligned target: the same as the plain transfer
    np.testing.assert_allclose(deformation_transfer_aligned(V, D, F, V + [1.0, 2.0, 3.0]),
                               deformation_transfer(V, D, F, V + [1.0, 2.0, 3.0]), atol=1e-9)
