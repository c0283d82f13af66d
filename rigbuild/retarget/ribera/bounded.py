"""Batched box-constrained quadratic programs ``min 1/2 w^T A_f w - b_f^T w, lo <= w <= hi`` (the weight
bounds of the retargeting, eq. 16 with bounds): free-variable solves."""

from __future__ import annotations

import numpy as np

def _masked_system(A: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Rows/columns of fixed variables of A (F, K, K) replaced by the identity (free: (F, K) bool)."""
    f = free.astype(A.dtype)
    out = A * f[:, :, None]
    out *= f[:, None, :]
    k = np.arange(A.shape[1])
    out[:, k, k] += 1.0 - f
    return out


def _solve_free(A: np.ndarray, b: np.ndarray, free: np.ndarray, fixed_values: np.ndarray) -> np.ndarray:
    """Batched ``A_f w_f = b_f`` over the free variables with the others held at ``fixed_values``.

    A (F, K, K), b (F, K), free (F, K) bool, fixed_values (F, K) (read where not free). Returns w (F, K):
    the fixed values, and on the free set ``w_S = A_SS^-1 (b_S - A_SN w_N)``. Solved as (F, m, m) systems
    with m the largest free count (free variables gathered first, the padding an identity block), which
    for sparse weights is a fraction of the (K, K) cost of :func:`_masked_system`.
    """
    F, K = b.shape
    wf = np.where(free, 0.0, fixed_values)
    rhs = b - (A @ wf[..., None])[..., 0]
    n_free = free.sum(1)
    m = int(n_free.max()) if F else 0
    if m == 0:
        return wf
    order = np.argsort(~free, axis=1, kind="stable")[:, :m]  # free variables first
    valid = np.arange(m)[None, :] < n_free[:, None]
    rows = np.arange(F)[:, None]
    Ar = A[rows[:, :, None], order[:, :, None], order[:, None, :]]
    pair = valid[:, :, None] & valid[:, None, :]
    Ar = np.where(pair, Ar, np.eye(m)[None])
    br = np.where(valid, np.take_along_axis(rhs, order, axis=1), 0.0)
    x = np.linalg.solve(Ar, br[..., None])[..., 0]
    w = wf.copy()
    w[np.broadcast_to(rows, order.shape)[valid], order[valid]] = x[valid]
    return w
