"""Solvers of the transfer's (MK x MK) E_Align systems (Ribera et al. 2017, sec. 4.6): the exact /
preconditioned Kronecker-sum solve and a sparse Cholesky (CHOLMOD) of the assembled matrix."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

def _cholmod_solve(A: sp.spmatrix, B: np.ndarray) -> np.ndarray:
    """Solve SPD ``A X = B`` (B: (n, r)) with cvxopt's CHOLMOD (one factorization, r right-hand sides)."""
    import cvxopt
    import cvxopt.cholmod

    A = sp.tril(A).tocoo()
    Ac = cvxopt.spmatrix(A.data.tolist(), A.row.tolist(), A.col.tolist(), A.shape)
    X = cvxopt.matrix(np.asfortranarray(B, dtype=np.float64))
    cvxopt.cholmod.options["supernodal"] = 2
    cvxopt.cholmod.linsolve(Ac, X, uplo="L")
    return np.array(X).reshape(B.shape)


def kron_sum_solve(
    d: np.ndarray, C: np.ndarray, Bk: np.ndarray, R: np.ndarray, tol: float = 1e-10, max_iter: int = 200
) -> np.ndarray:
    """Solve ``(diag(d) + I_K (x) C + Bk (x) I_M) x = r`` for every coordinate, exploiting the Kronecker sum.

    This is the E_Align system of :func:`align_system` in the ordering ``index = k * M + m``: d (K, M)
    diagonal (E_Match, epsilon), C (M, M) = ``alpha/M L^T L`` (E_Mesh), Bk (K, K) = ``beta/M G^T G``
    (E_CEG); R (K, M, 3) right-hand sides, one per coordinate. When ``d`` is constant over markers the
    matrix is a Kronecker sum ``B (x) I + I (x) C`` and is solved exactly by diagonalizing B (K x K) and C
    (M x M); otherwise that Kronecker sum (with ``d`` averaged over markers) preconditions conjugate
    gradients. Returns x (K, M, 3).
    """
    K, M = d.shape
    dbar = d.mean(1)
    lam, U = np.linalg.eigh(Bk + np.diag(dbar))
    sig, V = np.linalg.eigh(C)
    denom = lam[:, None] + sig[None, :]

    Ut, Vt = U.T, V.T

    def precond(X: np.ndarray) -> np.ndarray:  # X (3, K, M)
        return U @ ((Ut @ X @ V) / denom) @ Vt

    def matvec(X: np.ndarray) -> np.ndarray:
        return d * X + X @ C + Bk @ X

    R = np.ascontiguousarray(np.moveaxis(R, 2, 0))
    x = precond(R)
    if np.allclose(d, dbar[:, None], rtol=1e-12, atol=0.0):
        return np.moveaxis(x, 0, 2)
    r = R - matvec(x)
    z = precond(r)
    p = z.copy()
    rz = (r * z).sum((1, 2))
    rnorm0 = np.sqrt((R * R).sum((1, 2))) + 1e-300
    for _ in range(max_iter):
        Ap = matvec(p)
        step = rz / np.maximum((p * Ap).sum((1, 2)), 1e-300)
        x += step[:, None, None] * p
        r -= step[:, None, None] * Ap
        if np.all(np.sqrt((r * r).sum((1, 2))) <= tol * rnorm0):
            break
        z = precond(r)
        rz_new = (r * z).sum((1, 2))
        p = z + (rz_new / np.maximum(rz, 1e-300))[:, None, None] * p
        rz = rz_new
    return np.moveaxis(x, 0, 2)
