"""Block tridiagonal systems and box QPs over them (rigbuild/geometry/block_tridiagonal.py): exact answers against
the same problem assembled densely and solved by cvxopt."""

from __future__ import annotations

import numpy as np
import pytest

from rigbuild.geometry.block_tridiagonal import (block_tridiagonal_gradient, block_tridiagonal_matrix,
                                                 solve_box_qp_block_tridiagonal, solve_box_qp_interior,
                                                 solve_pinned_block_tridiagonal)


def _problem(n=14, K=4, seed=0):
    """A random SPD block tridiagonal H (diagonal blocks A, upper blocks U) and r, and H assembled densely."""
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, K + 2, K))
    A = X.transpose(0, 2, 1) @ X + 2.0 * np.eye(K)
    U = 0.4 * rng.normal(size=(n - 1, K, K))
    H = np.zeros((n * K, n * K))
    for t in range(n):
        H[t * K:(t + 1) * K, t * K:(t + 1) * K] = A[t]
    for t in range(n - 1):
        H[t * K:(t + 1) * K, (t + 1) * K:(t + 2) * K] = U[t]
        H[(t + 1) * K:(t + 2) * K, t * K:(t + 1) * K] = U[t].T
    assert np.linalg.eigvalsh(H).min() > 0
    r = 3.0 * rng.normal(size=(n, K))
    return A, U, r, H


def _cvxopt_box_qp(H, r, lo, hi, mask, vals):
    import cvxopt

    n = H.shape[0]
    free = np.flatnonzero(~mask.reshape(-1))
    pin = np.flatnonzero(mask.reshape(-1))
    eye = np.eye(n)
    G = np.vstack([eye[free], -eye[free]])
    h = np.concatenate([np.full(free.size, hi), np.full(free.size, -lo)])
    cvxopt.solvers.options.update({"show_progress": False, "abstol": 1e-12, "reltol": 1e-12, "feastol": 1e-12})
    args = [cvxopt.matrix(H), cvxopt.matrix(-r.reshape(-1)), cvxopt.matrix(G), cvxopt.matrix(h)]
    if pin.size:
        args += [cvxopt.matrix(eye[pin]), cvxopt.matrix(vals.reshape(-1)[pin])]
    return np.array(cvxopt.solvers.qp(*args)["x"]).reshape(mask.shape)


def test_gradient_and_pinned_solve_match_the_dense_system():
    A, U, r, H = _problem()
    W = np.random.default_rng(1).normal(size=r.shape)
    np.testing.assert_allclose(block_tridiagonal_gradient(A, U, r, W).reshape(-1), H @ W.reshape(-1) - r.reshape(-1),
                               atol=1e-10)
    mask = np.zeros(r.shape, bool)
    mask[3, 1] = mask[7] = True
    vals = np.where(mask, 0.25, 0.0)
    x = solve_pinned_block_tridiagonal(A, U, r, mask, vals)
    g = H @ x.reshape(-1) - r.reshape(-1)
    assert np.array_equal(x[mask], vals[mask]) and np.abs(g[~mask.reshape(-1)]).max() < 1e-9


@pytest.mark.parametrize("pinned,start", [(False, "unconstrained"), (True, "unconstrained"), (False, "guess"),
                                          (True, "guess")])
def test_box_qp_is_the_dense_minimizer(pinned, start):
    A, U, r, H = _problem(seed=2)
    mask = np.zeros(r.shape, bool)
    if pinned:
        mask[0] = mask[-1] = True
    vals = np.where(mask, 0.5, 0.0)
    x0 = None if start == "unconstrained" else np.random.default_rng(3).uniform(-0.5, 1.5, size=r.shape)
    W, passes = solve_box_qp_block_tridiagonal(A, U, r, 0.0, 1.0, mask, vals, x0=x0)
    assert passes <= 50 and W.min() >= 0.0 and W.max() <= 1.0
    free = ~mask
    assert np.any(W[free] == 0.0) and np.any(W[free] == 1.0) and np.any((W[free] > 0) & (W[free] < 1))
    np.testing.assert_allclose(W, _cvxopt_box_qp(H, r, 0.0, 1.0, mask, vals), atol=1e-6)


def test_sparse_matrix_is_the_dense_assembly():
    A, U, _, H = _problem(n=5, K=3, seed=4)
    np.testing.assert_array_equal(block_tridiagonal_matrix(A, U).toarray(), H)


def test_interior_point_is_the_dense_minimizer():
    A, U, r, H = _problem(seed=2)
    mask = np.zeros(r.shape, bool)
    mask[0] = True
    vals = np.where(mask, 0.5, 0.0)
    W = solve_box_qp_interior(A, U, r, 0.0, 1.0, mask, vals)
    assert np.array_equal(W[mask], vals[mask]) and W.min() >= 0.0 and W.max() <= 1.0
    np.testing.assert_allclose(W, _cvxopt_box_qp(H, r, 0.0, 1.0, mask, vals), atol=1e-6)


def _ill_conditioned_problem(n=60, K=12, seed=7):
    """Blocks with eigenvalues spread over eight decades, strongly coupled in time, and a right-hand side that
    pushes about a third of the weights against a bound: the kind of H on which the primal-dual passes cycle."""
    rng = np.random.default_rng(seed)
    Q = np.linalg.qr(rng.normal(size=(n, K, K)))[0]
    A = (Q * np.logspace(-4, 4, K)[None, None, :]) @ Q.transpose(0, 2, 1) + 2.0 * np.eye(K)
    U = -np.eye(K)[None].repeat(n - 1, axis=0)  # coupling -I: H >= (min eig A - 2) I = 1e-4 I, still SPD
    r = 30.0 * rng.normal(size=(n, K))
    return A, U, r


def test_box_qp_reaches_the_kkt_point_where_the_primal_dual_passes_cycle():
    """On this H the primal-dual passes alone never settle (without the interior-point restart the solver stopped
    after 200 passes with weights 1.0 off); restarted from the interior point's sets they reach the exact
    minimizer."""
    A, U, r = _ill_conditioned_problem()
    n, K = r.shape
    W, passes = solve_box_qp_block_tridiagonal(A, U, r, 0.0, 1.0, max_iterations=200)
    assert passes <= 200
    ref = _cvxopt_box_qp(block_tridiagonal_matrix(A, U).toarray(), r, 0.0, 1.0, np.zeros((n, K), bool),
                         np.zeros((n, K)))
    np.testing.assert_allclose(W, ref, atol=1e-6)
    g = block_tridiagonal_gradient(A, U, r, W)
    interior = (W > 0) & (W < 1)
    assert np.abs(g[interior]).max() < 1e-6 and g[W == 0].min() > -1e-6 and g[W == 1].max() < 1e-6
