"""Seol's own solver of the spacetime normal equations: the Kronecker-sum eigen-solve (whole-frame pins,
constant beta). The general block tridiagonal solves and the bounded active-set solve are
:mod:`rigbuild.geometry.block_tridiagonal`'s."""

from __future__ import annotations

import numpy as np
import scipy.linalg
from scipy.linalg import lapack

from rigbuild.geometry.block_tridiagonal import (  # noqa: F401  (the package's public names)
    LOCAL_PASS_FRACTION,
    LOCAL_PASS_HALO,
    REDUCED_FREE_FRACTION,
    solve_block_tridiagonal,
    solve_block_tridiagonal_free,
)


def _path_laplacian_free(n: int, free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal (nf,) and super-diagonal (nf-1,) of the path Laplacian over n frames restricted to
    the free frames (indices ``free``, sorted); the super-diagonal is -1 between consecutive free
    frames that are neighbours in time, else 0."""
    deg = np.full(n, 2.0)
    if n >= 1:
        deg[0] -= 1.0
        deg[-1] -= 1.0
    d = deg[free]
    off = np.where(np.diff(free) == 1, -1.0, 0.0)
    return d, off


def _solve_kronecker(Ldiag: np.ndarray, Loff: np.ndarray, G: np.ndarray, Pc: np.ndarray,
                     rhs: np.ndarray, eig: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Solve ``(L (x) G + I (x) Pc) vec(X) = vec(rhs)`` for X (nf, K), L tridiagonal (Ldiag, Loff).

    Generalized eigendecomposition ``U^T G U = I``, ``U^T Pc U = diag(mu)`` (``eig = (mu, U)`` if
    precomputed) turns it into K scalar tridiagonal systems ``(L + mu_k I) y_k = (rhs U)_k``, stacked
    shape-major into one LAPACK ``gtsv`` call.
    """
    nf, K = rhs.shape
    mu, U = scipy.linalg.eigh(Pc, G) if eig is None else eig
    Y = rhs @ U  # (nf, K)
    d = (Ldiag[None, :] + mu[:, None]).reshape(-1)
    off = np.zeros((K, nf))
    off[:, : nf - 1] = Loff[None, :]
    e = off.reshape(-1)[:-1]
    _, _, _, y, info = lapack.dgtsv(e.copy(), d, e.copy(), Y.T.reshape(-1).copy())
    if info != 0:
        raise np.linalg.LinAlgError(f"tridiagonal solve failed (info={info}): the system is singular")
    return y.reshape(K, nf).T @ U.T
