"""Scale-proportion matching (rigbuild.retarget.proportion): exact answers on affine and identity maps,
analytic Jacobians, and the inversion of a deformation-transferred (stylized) character."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rigbuild.errors import InputError
from rigbuild.retarget.proportion import (
    KERNELS,
    MARKER_MODES,
    fit_proportion_map,
    local_affine_linear_parts,
    polar_rotation,
    proportion_match,
    transfer_displacements,
    transfer_displacements_mesh,
)


def _markers(M=30, seed=0):
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(M, 3)) * np.array([60.0, 80.0, 40.0])
    d = rng.normal(size=(5, M, 3)) * 3.0
    return n, d


@pytest.fixture(scope="module")
def head():
    from rigbuild.assets.head import procedural_head_rig

    return procedural_head_rig()


@pytest.mark.parametrize("kernel", KERNELS)
def test_rbf_interpolates_centres_and_reproduces_affine_maps(kernel):
    n, _ = _markers()
    rng = np.random.default_rng(1)
    y = n + rng.normal(size=n.shape) * 5.0
    pmap = fit_proportion_map(n, y, kernel)
    np.testing.assert_allclose(pmap(n), y, atol=1e-8)
    A = np.array([[1.2, 0.1, -0.05], [0.02, 0.9, 0.2], [0.0, -0.1, 1.1]])
    b = np.array([3.0, -2.0, 7.0])
    aff = fit_proportion_map(n, n @ A.T + b, kernel)
    np.testing.assert_allclose(aff.weights, 0.0, atol=1e-10)
    x = rng.normal(size=(20, 3)) * 50
    np.testing.assert_allclose(aff(x), x @ A.T + b, atol=1e-8)


@pytest.mark.parametrize("mode", MARKER_MODES[:-1])  # every mode but "none" (which ignores the map)
def test_every_mode_reproduces_an_affine_map_exactly(mode):
    n, d = _markers()
    A = np.array([[1.3, 0.2, 0.0], [-0.1, 0.85, 0.15], [0.05, 0.0, 1.1]])
    y = n @ A.T + np.array([1.0, 2.0, 3.0])
    _, out, _ = proportion_match(n, d, y, mode, k_neighbors=8)
    np.testing.assert_allclose(out, d @ A.T, atol=1e-8)


@pytest.mark.parametrize("mode", MARKER_MODES)
def test_identity_map_leaves_displacements_unchanged(mode):
    n, d = _markers()
    _, out, _ = proportion_match(n, d, n, mode)
    np.testing.assert_allclose(out, d, atol=1e-9)


@pytest.mark.parametrize("kernel", ("r3", "tps"))
def test_jacobian_matches_finite_differences_for_c1_kernels(kernel):
    n, _ = _markers()
    rng = np.random.default_rng(2)
    pmap = fit_proportion_map(n, n + rng.normal(size=n.shape) * 4.0, kernel)
    # at the centres (C^1 kernels have a derivative there) and at points between them
    x = np.vstack([n[:5], rng.normal(size=(5, 3)) * 40])
    J = pmap.jacobian(x)
    h = 1e-4
    fd = np.stack([(pmap(x + h * e) - pmap(x - h * e)) / (2 * h) for e in np.eye(3)], axis=2)
    np.testing.assert_allclose(J, fd, rtol=1e-5, atol=1e-6)


def test_jacobian_of_phi_r_at_centres_is_the_central_difference_limit():
    """phi(r) = r: the centre's own term is left out, which is the symmetric limit
    (f(c + e d) - f(c - e d)) / 2e; the one-sided limit adds w_i |d| (the "rbf" mode's cusp)."""
    n, _ = _markers()
    rng = np.random.default_rng(3)
    pmap = fit_proportion_map(n, n + rng.normal(size=n.shape) * 4.0, "r")
    J = pmap.jacobian(n)
    dirs = rng.normal(size=n.shape)
    e = 1e-6
    central = (pmap(n + e * dirs) - pmap(n - e * dirs)) / (2 * e)
    np.testing.assert_allclose(np.einsum("mij,mj->mi", J, dirs), central, rtol=1e-5, atol=1e-6)
    one_sided = (pmap(n + e * dirs) - pmap(n)) / e
    cusp = pmap.weights * np.linalg.norm(dirs, axis=1, keepdims=True)
    np.testing.assert_allclose(one_sided, central + cusp, rtol=1e-4, atol=1e-5)
    assert np.abs(cusp).max() > 1e-3  # the cusp term is really there


def test_local_affine_parts_are_exact_for_affine_maps_and_local_otherwise():
    n, _ = _markers(M=40)
    A = np.diag([1.5, 0.7, 1.0])
    np.testing.assert_allclose(local_affine_linear_parts(n, n @ A.T, k=6), np.broadcast_to(A, (40, 3, 3)), atol=1e-9)
    # a map that is x 2 for x > 0 and x 1 for x < 0 (far apart halves): markers deep in each half see
    # their own half's scale
    n2 = np.vstack([n[:20] + [300, 0, 0], n[20:] - [300, 0, 0]])
    y2 = np.vstack([2 * n2[:20], n2[20:]])
    parts = local_affine_linear_parts(n2, y2, k=6)
    np.testing.assert_allclose(parts[:20], np.broadcast_to(2 * np.eye(3), (20, 3, 3)), atol=1e-9)
    np.testing.assert_allclose(parts[20:], np.broadcast_to(np.eye(3), (20, 3, 3)), atol=1e-9)


def test_polar_rotation():
    R = Rotation.from_rotvec([0.2, -0.4, 0.1]).as_matrix()
    np.testing.assert_allclose(polar_rotation(2.5 * R), R, atol=1e-12)
    np.testing.assert_allclose(polar_rotation(np.diag([1.3, 0.8, 1.1])), np.eye(3), atol=1e-12)
    S = np.array([[1.2, 0.3, 0.0], [0.3, 0.9, 0.1], [0.0, 0.1, 1.0]])  # symmetric positive definite
    np.testing.assert_allclose(polar_rotation(R @ S), R, atol=1e-12)


def test_deformation_mode_identity_and_similarity_maps_are_exact(head):
    mv = head.marker_vertices
    n, d = head.neutral[mv], head.deltas[:, mv]
    # deformation transfer itself treats displacements below 1e-6 of the bounding box as static, so
    # "exact" here is to 1e-5 of the largest displacement
    tol = 1e-5 * np.abs(d).max()
    ident = fit_proportion_map(n, n)
    np.testing.assert_allclose(transfer_displacements_mesh(ident, head.neutral, head.deltas, head.faces, mv), d,
                               atol=tol)
    R = Rotation.from_rotvec([0.1, 0.3, -0.2]).as_matrix()
    s = 1.15
    sim = fit_proportion_map(n, s * n @ R.T + np.array([5.0, -3.0, 10.0]))
    out = transfer_displacements_mesh(sim, head.neutral, head.deltas, head.faces, mv)
    np.testing.assert_allclose(out, s * d @ R.T, atol=s * tol)


def test_deformation_mode_undoes_a_stylized_character(head):
    """A stylized character's expressions are deformation transfers of the template's; carried back into
    the template's proportions they match the template's marker deltas far better than the paper's RBF
    evaluation (which maps each displacement pointwise)."""
    from rigbuild.synth.characters import make_character

    mv = head.marker_vertices
    char = make_character(head, "stylized")
    truth = head.deltas[:, mv]
    big = np.linalg.norm(truth.reshape(head.n_shapes, -1), axis=1) > 1.0
    err = {}
    for mode in ("rbf", "deformation", "none"):
        _, d, _ = proportion_match(char.neutral[mv], char.deltas[:, mv], head.neutral[mv], mode, mesh=char,
                                   marker_vertices=mv)
        rel = np.linalg.norm((d - truth).reshape(head.n_shapes, -1), axis=1) / np.maximum(
            np.linalg.norm(truth.reshape(head.n_shapes, -1), axis=1), 1e-12)
        err[mode] = float(np.median(rel[big]))
    assert err["deformation"] < 0.1
    assert err["deformation"] < 0.4 * err["rbf"]


def test_stage_stylized_character_correlation(head):
    """Spacetime retargeting (recommended prior setting) onto the stylized procedural character:
    scale_match="deformation" reaches >= 0.9 mean correlation and beats the paper's RBF evaluation."""
    from rigbuild.eval.seol import evaluated_shapes, seol_metrics
    from rigbuild.synth.retarget_scenes import synthetic_performance
    from rigbuild.retarget.seol import retarget_seol, sparse_combination_weights
    from rigbuild.synth.characters import make_character

    case = synthetic_performance(head, n_frames=360, fps=60, seed=3, noise_mm=0.05, gap_fraction=0.01)
    shapes = evaluated_shapes(case["actor"], case["weights"])
    char = make_character(head, "stylized")
    K, M = head.n_shapes, len(head.marker_names)
    kw = dict(prior_corner_hz=0.03, fps=60.0, prior_training=sparse_combination_weights(K, 2000, 0.15, seed=0),
              beta=np.full(M, (2 * np.pi / 60.0) ** 2))
    m = {sm: seol_metrics(retarget_seol(case["markers"], char, scale_match=sm, **kw), case["weights"], shapes)
         for sm in ("rbf", "deformation")}
    assert m["deformation"]["spacetime"]["mean_correlation"] >= 0.9
    assert m["deformation"]["spacetime"]["mean_correlation"] > m["rbf"]["spacetime"]["mean_correlation"] + 0.02
    for sm in m:
        assert m[sm]["spacetime"]["velocity_error"] < m[sm]["perframe_prior"]["velocity_error"]


def test_bad_input_messages(head):
    n, d = _markers()
    with pytest.raises(InputError, match="kernel 'gauss' unknown"):
        fit_proportion_map(n, n, "gauss")
    pmap = fit_proportion_map(n, n)
    with pytest.raises(InputError, match="scale_match 'warp' unknown"):
        transfer_displacements(pmap, n, d, "warp")
    with pytest.raises(InputError, match="needs the target's mesh"):
        transfer_displacements(pmap, n, d, "deformation")
    with pytest.raises(InputError, match="needs the target's mesh"):
        proportion_match(n, d, n, "deformation")
    with pytest.raises(InputError, match="do not match"):
        transfer_displacements(pmap, n, d[:, :5], "rbf")
    with pytest.raises(InputError, match="non-coplanar"):
        fit_proportion_map(n * [1, 1, 0], n)
    with pytest.raises(InputError, match="marker vertices"):
        transfer_displacements_mesh(pmap, head.neutral, head.deltas, head.faces, head.marker_vertices[:5])


def test_coplanar_markers_allowed_on_request():
    """Markers on a plane: the affine part's out-of-plane column is undetermined; allow_coplanar takes the
    minimum-norm solution, which still interpolates the markers exactly."""
    rng = np.random.default_rng(4)
    c = np.c_[rng.normal(size=(10, 2)) * 20, np.zeros(10)]
    y = c + rng.normal(size=(10, 3))
    f = fit_proportion_map(c, y, "r", allow_coplanar=True)
    np.testing.assert_allclose(f(c), y, atol=1e-8)
