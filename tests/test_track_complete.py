"""The whole mesh from a tracked face (rigbuild.track.complete): tiny analytic cases with exact answers."""

from __future__ import annotations

import numpy as np

from rigbuild.geometry.rigid import apply_rigid


def _rotation(axis, deg):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()


def test_bounded_weights_clamp_to_the_box():
    """An orthonormal basis: the unconstrained weights are D^T y; the box clamps each one."""
    from rigbuild.track.complete import bounded_weights

    D = np.eye(4)[:, :3]
    y = np.array([0.4, -0.3, 1.7, 5.0])
    L = np.linalg.cholesky(D.T @ D)
    np.testing.assert_allclose(bounded_weights(L, D.T @ y), [0.4, 0.0, 1.0], atol=1e-12)


def test_untracked_vertices_take_the_fitted_pose_exactly():
    """Frames made as R (b + D w) + t with weights inside [0, 1]: the fit recovers w, R, t and poses the
    untracked vertices (a jaw part moved only by shape 0, an eyeball moved by none) exactly."""
    from rigbuild.track.complete import complete_untracked, fit_expression_and_head

    rng = np.random.default_rng(3)
    N, U, K = 40, 6, 3
    b = rng.normal(0, 30, (N + U, 3))
    D = rng.normal(0, 3, (K, N + U, 3))
    D[1:, N:N + 3] = 0.0  # the jaw part follows shape 0 only
    D[:, N + 3:] = 0.0  # the eyeball follows no shape: the head's motion alone
    W = np.array([[0.0, 0.0, 0.0], [0.7, 0.2, 0.0], [1.0, 0.5, 0.9]])
    Rs = np.stack([_rotation([0, 1, 0], 0), _rotation([1, 2, 0], 5), _rotation([0, 1, 3], -8)])
    ts = np.array([[0, 0, 0], [3.0, -2, 1], [-5, 4, 10]])
    truth = np.stack([apply_rigid(b + np.einsum("k,kvc->vc", W[i], D), Rs[i], ts[i]) for i in range(3)])
    fit = np.arange(N)
    w, R, t = fit_expression_and_head(b[fit], D[:, fit], truth[:, fit], iterations=8)
    np.testing.assert_allclose(w, W, atol=1e-6)
    np.testing.assert_allclose(R, Rs, atol=1e-8)
    tracked = truth.copy()
    tracked[:, N:] = 99.0  # whatever the attachment left there
    out = complete_untracked(tracked, b, D, fit, np.arange(N, N + U), iterations=8)
    np.testing.assert_allclose(out, truth, atol=1e-5)
    np.testing.assert_allclose(out[:, N + 3:], np.stack([apply_rigid(b[N + 3:], Rs[i], ts[i]) for i in range(3)]),
                               atol=1e-5)


def test_shapes_in_world_turn_and_scale_the_deltas():
    from rigbuild.track.complete import shapes_in_world

    R = _rotation([0, 0, 1], 90)
    d = np.array([[[1.0, 0.0, 0.0]]])
    np.testing.assert_allclose(shapes_in_world(d, (2.0, R, np.array([5.0, 5, 5]))), [[[0.0, 2.0, 0.0]]], atol=1e-12)


def test_params_untracked_is_checked():
    import pytest

    from rigbuild.errors import InputError
    from rigbuild.track.params import from_config

    assert from_config({}).untracked == "shapes"
    with pytest.raises(InputError, match="untracked"):
        from_config({"untracked": "glue"})
