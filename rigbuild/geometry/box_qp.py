"""Many small box-constrained QPs at once: ``argmin 1/2 x^T H_b x + f_b^T x`` s.t. ``lo <= x <= hi`` per item.

Block principal pivoting (Judice and Pires 1994) run on the whole batch: every item guesses which variables
sit at which bound, the free ones are solved exactly by one batched linear solve per round, and each item swaps
every variable that violates primal feasibility or the sign of its multiplier (with the single-swap backup rule
when the count of violations stops falling). Items drop out of the batch as they converge. The per-frame solver
of the personalization (:func:`rigbuild.personalize.weights.solve_box_qp_pivoting`) is the same method one
item at a time; this one is for thousands of frames (marker-space weight solves).
"""

from __future__ import annotations

import numpy as np


def solve_free_subsystems(H: np.ndarray, rhs: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(B, K): ``x[free] = H[free, free]^-1 rhs[free]`` per item, 0 elsewhere; H (B, K, K), rhs (B, K), free (B, K)
    bool. The free variables of each item are gathered into the leading rows of a (B, n, n) system (n: the most
    free variables of any item, identity padding), so a batch of sparse solutions costs n^3, not K^3, per item."""
    B, K = rhs.shape
    nf = free.sum(1)
    n = int(nf.max(initial=0))
    out = np.zeros((B, K))
    if n == 0:
        return out
    order = np.argsort(~free, axis=1, kind="stable")[:, :n]  # free indices first, in index order
    valid = np.arange(n)[None, :] < nf[:, None]
    b_idx = np.arange(B)[:, None]
    A = H[b_idx[:, :, None], order[:, :, None], order[:, None, :]]
    both = valid[:, :, None] & valid[:, None, :]
    A = np.where(both, A, 0.0) + (~valid)[:, :, None] * np.eye(n)
    r = np.where(valid, rhs[b_idx, order], 0.0)
    x = np.linalg.solve(A, r[..., None])[..., 0]
    rows, cols = np.nonzero(valid)
    out[rows, order[rows, cols]] = x[rows, cols]
    return out


def solve_box_qp_batched(H: np.ndarray, f: np.ndarray, lo: float = 0.0, hi: float = 1.0,
                         x0: np.ndarray | None = None, max_rounds: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """Exact box QPs for a batch.

    H : (B, K, K) symmetric positive definite; f : (B, K); lo < hi scalars; x0 : (B, K) a guess whose
    bound pattern starts the pivoting (default: the unconstrained minimum). Returns x (B, K) in the box and
    converged (B,) bool (the KKT conditions hold to 1e-12 relative; items that did not converge within
    ``max_rounds`` hold their last iterate, clipped).
    """
    H = np.asarray(H, dtype=np.float64)
    f = np.asarray(f, dtype=np.float64)
    B, K = f.shape
    x = np.zeros((B, K))
    converged = np.zeros(B, dtype=bool)
    if B == 0:
        return x, converged
    guess = np.linalg.solve(H, -f[..., None])[..., 0] if x0 is None else np.asarray(x0, dtype=np.float64)
    at_lo = guess <= lo
    at_hi = (guess >= hi) & ~at_lo
    scale = np.maximum(1.0, np.maximum(np.abs(np.diagonal(H, axis1=1, axis2=2)).max(1), np.abs(f).max(1)))
    tol = 1e-12 * scale
    best = np.full(B, K + 1)
    backup_left = np.full(B, 3)
    todo = np.arange(B)
    for _ in range(max_rounds):
        if todo.size == 0:
            break
        Hs, fs = H[todo], f[todo]
        free = ~(at_lo[todo] | at_hi[todo])
        xfix = np.where(at_hi[todo], hi, lo).astype(np.float64)
        xfix[free] = 0.0
        rhs = -(fs + np.einsum("bkl,bl->bk", Hs, xfix))
        xs = xfix + solve_free_subsystems(Hs, rhs, free)
        g = np.einsum("bkl,bl->bk", Hs, xs) + fs
        t = tol[todo][:, None]
        bad_lo = free & (xs < lo - 1e-12)
        bad_hi = free & (xs > hi + 1e-12)
        bad_mlo = at_lo[todo] & (g < -t)
        bad_mhi = at_hi[todo] & (g > t)
        bad = bad_lo | bad_hi | bad_mlo | bad_mhi
        n_bad = bad.sum(1)
        done = n_bad == 0
        x[todo] = np.clip(xs, lo, hi)
        converged[todo[done]] = True
        # swap rule per item: all violators while their count falls (or a few more times), else the last one
        improve = n_bad < best[todo]
        use_all = improve | (backup_left[todo] > 0)
        backup_left[todo] = np.where(improve, 3, np.where(use_all, backup_left[todo] - 1, backup_left[todo]))
        best[todo] = np.minimum(best[todo], n_bad)
        last = np.zeros_like(bad)
        rows = np.flatnonzero(~use_all & ~done)
        if rows.size:
            last[rows, K - 1 - np.argmax(bad[rows][:, ::-1], axis=1)] = True
        swap = np.where(use_all[:, None], bad, last)
        lo_t, hi_t = at_lo[todo], at_hi[todo]
        at_lo[todo] = np.where(swap & bad_lo, True, np.where(swap & (bad_mlo | bad_hi), False, lo_t))
        at_hi[todo] = np.where(swap & bad_hi, True, np.where(swap & (bad_mhi | bad_lo), False, hi_t))
        todo = todo[~done]
    return x, converged
