"""Batched box-constrained quadratic programs ``min 1/2 w^T A_f w - b_f^T w, lo <= w <= hi`` (the weight
bounds of the retargeting, eq. 16 with bounds): free-variable solves."""

from __future__ import annotations

import numpy as np

from rigbuild.geometry.box_qp import solve_free_subsystems


def _solve_free(A: np.ndarray, b: np.ndarray, free: np.ndarray, fixed_values: np.ndarray) -> np.ndarray:
    """Batched ``A_f w_f = b_f`` over the free variables with the others held at ``fixed_values``.

    A (F, K, K), b (F, K), free (F, K) bool, fixed_values (F, K) (read where not free). Returns w (F, K):
    the fixed values, and on the free set ``w_S = A_SS^-1 (b_S - A_SN w_N)``
    (:func:`rigbuild.geometry.box_qp.solve_free_subsystems`).
    """
    wf = np.where(free, 0.0, fixed_values)
    if b.shape[0] == 1:  # one frame (retargeting one frame at a time): index the free set directly
        i = np.flatnonzero(free[0])
        if i.size:
            wf[0, i] = np.linalg.solve(A[0][i[:, None], i], b[0, i] - A[0][i] @ wf[0])
        return wf
    return wf + solve_free_subsystems(A, b - (A @ wf[..., None])[..., 0], free)


def box_qp(A: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray, passes: int = 6,
           start: np.ndarray | None = None, w0: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Batched ``min 1/2 w^T A_f w - b_f^T w`` s.t. ``lo_f <= w_f <= hi_f`` by a primal-dual active-set method.

    A (F, K, K) SPD, b (F, K); lo, hi (F, K) bounds (a variable with ``hi <= lo`` is pinned at ``hi``: a
    shape switched off in that frame). ``start`` (F, K): a previous solution whose active set is the first
    guess (a warm start; the minimizer is unique, only the number of passes changes); ``w0`` (F, K): the
    unconstrained solution when the caller has it (else solved here). Exact: KKT signs are checked each pass;
    frames where ``passes`` fast passes do not settle finish with :func:`primal_active_set`. Each pass solves
    only the free variables (:func:`_solve_free`). Returns w (F, K) and ``{"passes", "unconverged"}``.
    """
    F, K = b.shape
    pinned = hi <= lo
    info = {"passes": 0, "unconverged": 0}
    if start is not None:
        at_lo = (start <= lo) & ~pinned
        at_hi = (start >= hi) | pinned
        w = np.clip(start, lo, hi)
        todo = np.arange(F)
    else:
        w = np.linalg.solve(A, b[..., None])[..., 0] if w0 is None else w0
        at_lo = (w < lo) & ~pinned
        at_hi = (w > hi) | pinned
        todo = np.flatnonzero(at_lo.any(1) | at_hi.any(1))
    for _ in range(passes):
        if todo.size == 0:
            break
        info["passes"] += 1
        Ab, bb, lo_b, hi_b, l_b, h_b = A[todo], b[todo], at_lo[todo], at_hi[todo], lo[todo], hi[todo]
        free = ~(lo_b | hi_b)
        wb = _solve_free(Ab, bb, free, np.where(lo_b, l_b, h_b))
        grad = (Ab @ wb[..., None])[..., 0] - bb
        release = ((lo_b & (grad < -1e-12)) | (hi_b & (grad > 1e-12))) & ~pinned[todo]
        new_lo = free & (wb < l_b - 1e-12)
        new_hi = free & (wb > h_b + 1e-12)
        w[todo] = wb
        at_lo[todo] = (lo_b & ~release) | new_lo
        at_hi[todo] = (hi_b & ~release) | new_hi
        todo = todo[release.any(1) | new_lo.any(1) | new_hi.any(1)]
    if todo.size:
        w[todo], info["unconverged"] = primal_active_set(A[todo], b[todo], np.clip(w[todo], lo[todo], hi[todo]),
                                                         lo[todo], hi[todo])
    return np.clip(w, lo, hi), info


def primal_active_set(A: np.ndarray, b: np.ndarray, w: np.ndarray, lo: np.ndarray,
                      hi: np.ndarray) -> tuple[np.ndarray, int]:
    """Batched primal active-set method from a feasible start w (F, K) (cannot cycle; for the few frames where
    the fast primal-dual passes of :func:`box_qp` did not settle). One constraint changes per step. lo, hi
    (F, K) as there. Returns w and the number of frames still unconverged after ``6 K + 10`` steps."""
    F, K = b.shape
    pinned = hi <= lo
    at_lo = (w <= lo) & ~pinned
    at_hi = (w >= hi) | pinned
    todo = np.arange(F)
    rows = np.arange(F)
    for _ in range(6 * K + 10):
        if todo.size == 0:
            break
        Ab, bb, lo_b, hi_b, wt, l_b, h_b = A[todo], b[todo], at_lo[todo], at_hi[todo], w[todo], lo[todo], hi[todo]
        free = ~(lo_b | hi_b)
        wb = _solve_free(Ab, bb, free, np.where(lo_b, l_b, h_b))
        d = wb - wt
        below = free & (wb < l_b - 1e-12)
        above = free & (wb > h_b + 1e-12)
        infeasible = below.any(1) | above.any(1)
        with np.errstate(divide="ignore", invalid="ignore"):
            alpha = np.where(below, (l_b - wt) / d, np.inf)
            alpha = np.minimum(alpha, np.where(above, (h_b - wt) / d, np.inf))
        r = rows[: todo.size]
        blk = np.argmin(alpha, axis=1)
        step = np.clip(alpha[r, blk], 0.0, 1.0)
        w_new = np.where(infeasible[:, None], wt + step[:, None] * d, wb)
        lo_new, hi_new = lo_b.copy(), hi_b.copy()
        inf_r = r[infeasible]
        lo_new[inf_r, blk[infeasible]] |= below[inf_r, blk[infeasible]]
        hi_new[inf_r, blk[infeasible]] |= above[inf_r, blk[infeasible]]
        # feasible frames: check multipliers, release the worst (never a pinned variable)
        grad = (Ab @ w_new[..., None])[..., 0] - bb
        viol = np.where(lo_b, -grad, 0.0) + np.where(hi_b & ~pinned[todo], grad, 0.0)  # > 0: wrong sign
        worst = np.argmax(viol, axis=1)
        release = ~infeasible & (viol[r, worst] > 1e-10)
        rel_r = r[release]
        lo_new[rel_r, worst[release]] = False
        hi_new[rel_r, worst[release]] = False
        w[todo] = np.clip(w_new, l_b, h_b)
        at_lo[todo] = lo_new
        at_hi[todo] = hi_new
        todo = todo[infeasible | release]
    return w, int(todo.size)
