"""Symmetric positive definite block tridiagonal systems (one K x K block per frame, coupled to the next frame)
and box-constrained quadratic programs over them: the energy ``E(W) = 1/2 w^T H w - r^T w`` of weights W (n, K)
with H block tridiagonal (diagonal blocks A (n, K, K), upper blocks U (n-1, K, K), ``H[t, t+1] = U[t]``).

Spacetime weight solves have this form: Seol et al.'s eq. (4) (:class:`rigbuild.retarget.seol.SeolSystem`) and the
actor-rig solve's temporal term (:func:`rigbuild.retarget.actor_rig.solve_actor_weights`).
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
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


def solve_pinned_block_tridiagonal(A: np.ndarray, U: np.ndarray, rhs: np.ndarray, mask: np.ndarray,
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


def dilate_frames(frames: np.ndarray, halo: int) -> np.ndarray:
    """(n,) bool: ``frames`` (n,) bool grown by ``halo`` frames on each side."""
    c = np.convolve(frames.astype(np.int64), np.ones(2 * halo + 1, dtype=np.int64))  # length n + 2 halo
    return c[halo:halo + frames.size] > 0


def block_tridiagonal_gradient(A: np.ndarray, U: np.ndarray, r: np.ndarray, W: np.ndarray) -> np.ndarray:
    """(n, K) gradient ``H w - r`` of ``1/2 w^T H w - r^T w`` at W (n, K); H given by A (n, K, K), U (n-1, K, K)."""
    W = np.asarray(W, dtype=np.float64)
    g = np.einsum("tij,tj->ti", A, W) - r
    if W.shape[0] > 1:
        g[:-1] += np.einsum("tij,tj->ti", U, W[1:])
        g[1:] += np.einsum("tji,tj->ti", U, W[:-1])
    return g


def block_tridiagonal_matrix(A: np.ndarray, U: np.ndarray) -> sparse.csc_matrix:
    """(n K, n K) sparse H of diagonal blocks A (n, K, K) and upper blocks U (n-1, K, K) (``H[t+1, t] = U[t]^T``)."""
    n, K = A.shape[:2]
    t, i, j = np.meshgrid(np.arange(n), np.arange(K), np.arange(K), indexing="ij")
    rows, cols, data = [(t * K + i).ravel()], [(t * K + j).ravel()], [A.ravel()]
    if n > 1:
        tu, iu, ju = t[:-1], i[:-1], j[:-1]
        rows += [(tu * K + iu).ravel(), ((tu + 1) * K + ju).ravel()]
        cols += [((tu + 1) * K + ju).ravel(), (tu * K + iu).ravel()]
        data += [U.ravel(), U.ravel()]
    return sparse.csc_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(n * K,) * 2)


def solve_box_qp_interior(A: np.ndarray, U: np.ndarray, r: np.ndarray, lo: float, hi: float, pin_mask: np.ndarray,
                          pin_values: np.ndarray) -> np.ndarray:
    """The box QP of :func:`solve_box_qp_block_tridiagonal` by an interior-point method (cvxopt ``solvers.qp`` on the
    sparse H of the free weights, tolerances 1e-10): polynomial, so it cannot cycle, but its weights only approach
    the bounds. A (n, K, K), U (n-1, K, K), r (n, K), pin_mask / pin_values (n, K). Returns W (n, K) in the box."""
    import cvxopt
    import cvxopt.solvers

    H = block_tridiagonal_matrix(A, U)
    pin = pin_mask.reshape(-1)
    free = np.flatnonzero(~pin)
    W = np.where(pin_mask, pin_values, 0.0).reshape(-1)
    if free.size == 0:
        return W.reshape(r.shape)
    Hf = H[free]
    q = Hf[:, np.flatnonzero(pin)] @ W[pin] - r.reshape(-1)[free]

    def spmatrix(M: sparse.spmatrix) -> cvxopt.spmatrix:
        M = M.tocoo()
        return cvxopt.spmatrix(M.data.tolist(), M.row.tolist(), M.col.tolist(), size=M.shape)

    m = free.size
    G = sparse.vstack([sparse.eye(m), -sparse.eye(m)])
    h = np.concatenate([np.full(m, hi), np.full(m, -lo)])
    opts = {"show_progress": False, "abstol": 1e-10, "reltol": 1e-10, "feastol": 1e-10, "maxiters": 200}
    sol = cvxopt.solvers.qp(spmatrix(Hf[:, free]), cvxopt.matrix(q), spmatrix(G), cvxopt.matrix(h), options=opts)
    W[free] = np.clip(np.array(sol["x"]).reshape(-1), lo, hi)
    return W.reshape(r.shape)


#: after this many passes without a KKT point (or half of ``max_iterations`` if fewer) the passes restart from the
#: interior point's sets; the bounded Seol solves that settle by themselves take 7 to 21 passes
INTERIOR_AFTER_PASSES = 40

#: a weight of the interior-point solution within this fraction of the box's width of a bound starts at that bound
INTERIOR_BOUND_FRACTION = 1e-6


def solve_box_qp_block_tridiagonal(A: np.ndarray, U: np.ndarray, r: np.ndarray, lo: float, hi: float,
                                   pin_mask: np.ndarray | None = None, pin_values: np.ndarray | None = None,
                                   max_iterations: int = 50, tolerance: float = 1e-9,
                                   x0: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """``argmin 1/2 w^T H w - r^T w`` s.t. ``lo <= w <= hi`` for the free weights, the ``pin_mask`` (n, K) ones held
    at ``pin_values`` (n, K); H block tridiagonal (A (n, K, K), U (n-1, K, K)), r (n, K).

    Primal-dual active set (Hintermueller, Ito and Kunisch 2002): from the unconstrained minimizer's violations
    (or ``x0``'s bound pattern), each pass solves with the bound pins, keeps the pins whose Lagrange multiplier
    (the energy's gradient) has the right sign and pins every free weight outside the bounds; it stops when a
    global pass no longer changes the sets (a KKT point). A pass that changes the sets in few frames is followed
    by local passes over those frames (:data:`LOCAL_PASS_FRACTION`, :data:`LOCAL_PASS_HALO`; the other frames
    keep their weights) until they settle, then a global pass checks. On an ill-conditioned H the passes can
    cycle: when a global pass repeats a set, or after :data:`INTERIOR_AFTER_PASSES` passes, an interior-point solve
    (:func:`solve_box_qp_interior`, which cannot cycle) gives new sets (its weights within
    :data:`INTERIOR_BOUND_FRACTION` of a bound) and the passes restart from them, which in practice reach the exact
    KKT point in a few passes. Each pass solves only the free weights (:func:`solve_block_tridiagonal_free`).
    Returns (W (n, K) within the bounds, passes); passes is ``max_iterations + 1`` when no exact KKT point was
    reached and W is the interior-point solution (or, had the interior point not run, the last pass clipped).
    """
    A, U, r = np.asarray(A, dtype=np.float64), np.asarray(U, dtype=np.float64), np.asarray(r, dtype=np.float64)
    user = np.zeros(r.shape, dtype=bool) if pin_mask is None else np.asarray(pin_mask, dtype=bool)
    vals = np.where(user, np.asarray(pin_values if pin_values is not None else 0.0, dtype=np.float64), 0.0)
    if x0 is None:
        W = solve_pinned_block_tridiagonal(A, U, r, user, vals)  # the unconstrained minimizer: first guess
        at_lo = ~user & (W < lo)
        at_hi = ~user & (W > hi)
    else:  # a guess's bound pattern starts the passes
        W = np.where(user, vals, np.clip(np.asarray(x0, dtype=np.float64), lo, hi))
        at_lo = ~user & (W <= lo)
        at_hi = ~user & (W >= hi) & ~at_lo
    seen: set[bytes] = set()
    seen_local: set[bytes] = set()
    interior = None  # the interior-point weights, once computed
    window = None  # frames of a local pass (None: a global pass)
    for it in range(1, max_iterations + 1):
        if interior is None and it > min(max_iterations // 2, INTERIOR_AFTER_PASSES):
            interior, at_lo, at_hi = _interior_sets(A, U, r, lo, hi, user, vals)
            W, window, seen = interior, None, set()
        fixed = user | at_lo | at_hi
        v = np.where(at_lo, lo, np.where(at_hi, hi, vals))
        if window is None:
            W_new = solve_pinned_block_tridiagonal(A, U, r, fixed, v)
        else:  # local pass: the frames outside the window keep their weights
            out = np.broadcast_to(~window[:, None], fixed.shape)
            W_new = solve_pinned_block_tridiagonal(A, U, r, fixed | out, np.where(out, W, v))
        g = block_tridiagonal_gradient(A, U, r, W_new)
        scale = tolerance * max(1.0, float(np.abs(g).max()))
        free = ~fixed
        below, above = free & (W_new < lo - tolerance), free & (W_new > hi + tolerance)
        # keep a bound whose multiplier has the right sign, add every violator
        new_lo = ~user & ((at_lo & (g >= -scale)) | below)
        new_hi = ~user & ((at_hi & (g <= scale)) | above)
        if window is not None:
            new_lo = np.where(window[:, None], new_lo, at_lo)
            new_hi = np.where(window[:, None], new_hi, at_hi)
        changed = ((new_lo != at_lo) | (new_hi != at_hi)).any(1)
        W = W_new
        if not changed.any():
            if window is None:
                return W, it  # a global pass with no change: a KKT point
            window = None  # the local passes settled: verify with a global pass
            continue
        key = np.packbits(np.concatenate([new_lo, new_hi], axis=1)).tobytes()
        if window is None:
            if key in seen:  # the passes cycle: restart from the interior point's sets (once)
                if interior is not None:
                    break
                interior, at_lo, at_hi = _interior_sets(A, U, r, lo, hi, user, vals)
                W, seen = interior, set()
                continue
            seen.add(key)
            seen_local = set()
        elif key in seen_local:  # the local passes cycle: back to global passes
            window = None
            at_lo, at_hi = new_lo, new_hi
            continue
        seen_local.add(key)
        # few frames changed: the next passes re-solve only around them
        window = dilate_frames(changed, LOCAL_PASS_HALO) if changed.mean() < LOCAL_PASS_FRACTION else None
        at_lo, at_hi = new_lo, new_hi
    return (np.clip(W, lo, hi) if interior is None else interior), max_iterations + 1


def _interior_sets(A: np.ndarray, U: np.ndarray, r: np.ndarray, lo: float, hi: float, user: np.ndarray,
                   vals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The interior-point weights (n, K) and the lower / upper bound sets (n, K) bool they suggest."""
    W = solve_box_qp_interior(A, U, r, lo, hi, user, vals)
    near = INTERIOR_BOUND_FRACTION * (hi - lo)
    at_lo = ~user & (W <= lo + near)
    return W, at_lo, ~user & ~at_lo & (W >= hi - near)
