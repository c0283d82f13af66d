"""Solvers of the spacetime normal equations (block tridiagonal in time, K x K blocks): the Kronecker-sum
eigen-solve (whole-frame pins, constant beta), block Thomas, and block Thomas over the free variables of a
bounded solve."""

from __future__ import annotations

import numpy as np
import scipy.linalg
from scipy.linalg import lapack

def solve_block_tridiagonal(diag: np.ndarray, upper: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve a symmetric positive definite block tridiagonal system by block Thomas (block LDL^T).

    diag : (n, K, K) diagonal blocks ``A_t``; upper : (n-1, K, K) blocks ``A_{t,t+1}`` (the lower
    ones are their transposes); rhs : (n, K) or (n, K, c). Returns x with rhs's shape. O(n K^3).
    """
    n = diag.shape[0]
    vec = rhs.ndim == 2
    r = rhs[..., None] if vec else rhs
    K, c = r.shape[1], r.shape[2]
    Z = np.empty((max(n - 1, 0), K, K))
    g = np.empty((n, K, c))
    Dt = diag[0]
    yt = r[0]
    for t in range(n):
        if t > 0:
            O = upper[t - 1]
            Dt = diag[t] - O.T @ Z[t - 1]
            yt = r[t] - O.T @ g[t - 1]
        if t < n - 1:
            sol = np.linalg.solve(Dt, np.concatenate([upper[t], yt], axis=1))
            Z[t] = sol[:, :K]
            g[t] = sol[:, K:]
        else:
            g[t] = np.linalg.solve(Dt, yt)
    x = np.empty_like(g)
    x[n - 1] = g[n - 1]
    for t in range(n - 2, -1, -1):
        x[t] = g[t] - Z[t] @ x[t + 1]
    return x[..., 0] if vec else x


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


def solve_block_tridiagonal_free(diag: np.ndarray, upper: np.ndarray, rhs: np.ndarray,
                                 free: np.ndarray) -> np.ndarray:
    """:func:`solve_block_tridiagonal` over the ``free`` (n, K) variables only (the others 0; their known
    values already moved to ``rhs``): block Thomas (block Cholesky, LAPACK ``posv`` per frame) with per-frame
    blocks of the free variables' size, so a bounded solve whose weights sit mostly at a bound pays for the
    free ones only. Returns (n, K)."""
    n, K = rhs.shape
    idx = [np.flatnonzero(free[t]) for t in range(n)]
    Z: list[np.ndarray] = [np.zeros((0, 0))] * n
    g: list[np.ndarray] = [np.zeros(0)] * n
    posv = lapack.dposv
    for t in range(n):
        i = idx[t]
        m = i.size
        if m == 0:
            continue
        D = diag[t][i[:, None], i]
        nxt = idx[t + 1] if t < n - 1 else i[:0]
        rhs_t = np.empty((m, nxt.size + 1))
        rhs_t[:, :-1] = upper[t][i[:, None], nxt] if nxt.size else 0.0
        rhs_t[:, -1] = rhs[t, i]
        prev = idx[t - 1] if t > 0 else i[:0]
        if prev.size:
            O = upper[t - 1][prev[:, None], i]
            D = D - O.T @ Z[t - 1]
            rhs_t[:, -1] -= O.T @ g[t - 1]
        _, sol, info = posv(D, rhs_t, lower=1)
        if info != 0:
            sol = np.linalg.solve(D, rhs_t)  # not positive definite to working precision: LU
        Z[t], g[t] = sol[:, :-1], sol[:, -1]
    x = np.zeros((n, K))
    x[n - 1, idx[n - 1]] = g[n - 1]
    for t in range(n - 2, -1, -1):
        if idx[t].size:
            x[t, idx[t]] = g[t] - (Z[t] @ x[t + 1, idx[t + 1]] if idx[t + 1].size else 0.0)
    return x


#: below this fraction of free variables the pinned solve eliminates the pinned ones (else identity rows)
REDUCED_FREE_FRACTION = 0.8


def _solve_pinned_block_tridiagonal(A: np.ndarray, U: np.ndarray, rhs: np.ndarray, mask: np.ndarray,
                                    vals: np.ndarray) -> np.ndarray:
    """Solve the block tridiagonal system (diag ``A`` (n, K, K), upper ``U`` (n-1, K, K), ``rhs``
    (n, K)) with the variables where ``mask`` (n, K) is True fixed to ``vals``: their known values move
    to the right-hand side; the free variables are solved by :func:`solve_block_tridiagonal_free` when
    they are few, else the fixed rows become identity rows of the full solve. Returns (n, K)."""
    n = A.shape[0]
    r = rhs - np.einsum("tkl,tl->tk", A, vals)
    if n > 1:
        r[:-1] -= np.einsum("tkl,tl->tk", U, vals[1:])
        r[1:] -= np.einsum("tlk,tl->tk", U, vals[:-1])
    if (~mask).mean() < REDUCED_FREE_FRACTION:
        return np.where(mask, vals, solve_block_tridiagonal_free(A, U, r, ~mask))
    keep = 1.0 - mask.astype(np.float64)
    A = A * keep[:, :, None] * keep[:, None, :]
    ti, ki = np.nonzero(mask)
    A[ti, ki, ki] = 1.0
    if n > 1:
        U = U * keep[:-1, :, None] * keep[1:, None, :]
    r = np.where(mask, vals, r)
    return solve_block_tridiagonal(A, U, r)


#: a primal-dual pass that changes the active set in fewer than this fraction of the frames is followed by
#: local passes over those frames and ``LOCAL_PASS_HALO`` frames around them (then a global pass checks)
LOCAL_PASS_FRACTION = 0.1


LOCAL_PASS_HALO = 10


def _dilate_frames(frames: np.ndarray, halo: int) -> np.ndarray:
    """(n,) bool: ``frames`` (n,) bool grown by ``halo`` frames on each side."""
    c = np.convolve(frames.astype(np.int64), np.ones(2 * halo + 1, dtype=np.int64))  # length n + 2 halo
    return c[halo:halo + frames.size] > 0
