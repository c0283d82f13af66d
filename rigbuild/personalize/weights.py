"""Per-frame blendshape weights (Ma et al. 2016, eq. 3-4) as a box-constrained QP.

For one frame with rigid motion removed the energy is

    ||M (D w - r)||^2 + lambda_s (1^T w)^2 + lambda_t sum_{n in neighbours} ||w - w_n||^2,   0 <= w <= 1

(``D`` (3V, K) the pose offsets, ``r`` (3V,) the rigidly aligned frame minus the neutral, ``M`` the
per-vertex confidence, ``(1^T w)^2`` the squared-L1 sparsity which equals ``||w||_1^2`` because
``w >= 0``, and ``neighbours`` the previous and next frame of a contiguous sequence). It is the QP
``min 1/2 w^T H w + f^T w`` with

    H = D^T M^2 D + lambda_s 1 1^T + lambda_t n I,   f = -(D^T M^2 r + lambda_t sum_n w_n).

Two exact solvers: :func:`solve_box_qp_active_set` (numpy primal active set, default) and
:func:`solve_box_qp_cvxopt` (cvxopt ``coneqp`` with tight tolerances; the defaults are only about
3e-3 accurate, see /work/shared/notes/stack.md).
"""

from __future__ import annotations

import numpy as np


def weight_qp(gram: np.ndarray, dtr: np.ndarray, lambda_s: float, lambda_t: float,
              neighbours: list[np.ndarray] | tuple = ()) -> tuple[np.ndarray, np.ndarray]:
    """Hessian and linear term of the per-frame weight QP.

    gram : (K, K) ``D^T M^2 D`` (mm^2); dtr : (K,) ``D^T M^2 r`` (mm^2);
    neighbours : weight vectors (K,) of the adjacent frames of a contiguous sequence.
    Returns H (K, K), f (K,) for ``min 1/2 w^T H w + f^T w`` (the energy is ``w^T H w + 2 f^T w + c``).
    """
    K = gram.shape[0]
    H = gram + lambda_s * np.ones((K, K))
    f = -np.asarray(dtr, dtype=np.float64).copy()
    if len(neighbours):
        H = H + lambda_t * len(neighbours) * np.eye(K)
        for wn in neighbours:
            f -= lambda_t * wn
    return H, f


def solve_box_qp_active_set(H: np.ndarray, f: np.ndarray, lo: float = 0.0, hi: float = 1.0,
                            x0: np.ndarray | None = None, max_iter: int = 500) -> np.ndarray:
    """Exact ``argmin 1/2 x^T H x + f^T x`` subject to ``lo <= x <= hi`` (H SPD), primal active set.

    Starts from ``x0`` clipped to the box (warm start: the previous solution; without ``x0``, block
    principal pivoting (:func:`solve_box_qp_pivoting`) usually finishes the job), solves the
    equality-constrained problem on the free variables, steps to the first blocking bound, and frees
    the bound variable with the most negative multiplier until the KKT conditions hold (to 1e-12
    relative). H (K, K), f (K,) -> x (K,).
    """
    K = f.shape[0]
    if x0 is None:  # cold start: block principal pivoting from the unconstrained minimum, usually exact
        try:
            x0, done = solve_box_qp_pivoting(H, f, lo, hi)
            if done:
                return x0
        except np.linalg.LinAlgError:
            x0 = np.zeros(K)
    x = np.clip(np.asarray(x0, dtype=np.float64), lo, hi)
    at_lo = x <= lo
    at_hi = x >= hi
    scale = max(1.0, float(np.abs(np.diag(H)).max()), float(np.abs(f).max()))
    tol = 1e-12 * scale
    for _ in range(max_iter):
        free = ~(at_lo | at_hi)
        g = H @ x + f
        if free.any():
            Hf = H[np.ix_(free, free)]
            step = np.zeros(K)
            step[free] = -np.linalg.solve(Hf, g[free])
        else:
            step = np.zeros(K)
        if np.abs(step).max() > 1e-15 * max(1.0, np.abs(x).max()):
            # ratio test against the bounds of the free variables
            alpha = 1.0
            block = -1
            with np.errstate(divide="ignore", invalid="ignore"):
                up = np.where(free & (step > 0), (hi - x) / step, np.inf)
                dn = np.where(free & (step < 0), (lo - x) / step, np.inf)
            a_up, a_dn = up.min(), dn.min()
            if a_up < alpha or a_dn < alpha:
                if a_up <= a_dn:
                    alpha, block, to_hi = a_up, int(np.argmin(up)), True
                else:
                    alpha, block, to_hi = a_dn, int(np.argmin(dn)), False
            x = x + max(alpha, 0.0) * step
            if block >= 0:
                if to_hi:
                    x[block] = hi
                    at_hi[block] = True
                else:
                    x[block] = lo
                    at_lo[block] = True
                continue
            g = H @ x + f
        # multipliers: at lower bound need g >= 0, at upper bound need g <= 0
        viol = np.where(at_lo, -g, 0.0) + np.where(at_hi, g, 0.0)
        j = int(np.argmax(viol))
        if viol[j] <= tol:
            return x
        at_lo[j] = False
        at_hi[j] = False
    return x


def solve_box_qp_pivoting(H: np.ndarray, f: np.ndarray, lo: float = 0.0, hi: float = 1.0,
                          x0: np.ndarray | None = None, max_iter: int = 50) -> tuple[np.ndarray, bool]:
    """Block principal pivoting (Judice and Pires 1994) for the box QP: guess which variables sit at
    which bound, solve the free ones exactly, and swap *every* variable that violates primal
    feasibility or the multiplier signs at once (with the single-swap backup rule when the number of
    violations stops falling). Usually 2-5 linear solves. Returns (x, converged)."""
    K = f.shape[0]
    if x0 is None:
        x0 = np.linalg.solve(H, -f)
    at_lo = x0 <= lo
    at_hi = (x0 >= hi) & ~at_lo
    best, backup_left = K + 1, 3
    tol = 1e-12 * max(1.0, float(np.abs(np.diag(H)).max()), float(np.abs(f).max()))
    for _ in range(max_iter):
        free = ~(at_lo | at_hi)
        x = np.where(at_hi, hi, lo).astype(np.float64)
        if free.any():
            rhs = -(f[free] + H[np.ix_(free, ~free)] @ x[~free])
            x[free] = np.linalg.solve(H[np.ix_(free, free)], rhs)
        g = H @ x + f
        bad_lo = free & (x < lo - 1e-12)
        bad_hi = free & (x > hi + 1e-12)
        bad_mlo = at_lo & (g < -tol)
        bad_mhi = at_hi & (g > tol)
        bad = bad_lo | bad_hi | bad_mlo | bad_mhi
        n_bad = int(bad.sum())
        if n_bad == 0:
            return np.clip(x, lo, hi), True
        if n_bad < best:
            best, backup_left = n_bad, 3
            swap = bad
        elif backup_left > 0:
            backup_left -= 1
            swap = bad
        else:  # backup rule: swap only the largest-index violator
            swap = np.zeros(K, dtype=bool)
            swap[np.flatnonzero(bad)[-1]] = True
        at_lo = np.where(swap & bad_lo, True, np.where(swap & (bad_mlo | bad_hi), False, at_lo))
        at_hi = np.where(swap & bad_hi, True, np.where(swap & (bad_mhi | bad_lo), False, at_hi))
    return np.clip(x, lo, hi), False


def solve_box_qp_cvxopt(H: np.ndarray, f: np.ndarray, lo: float = 0.0, hi: float = 1.0,
                        tol: float = 1e-12) -> np.ndarray:
    """Same QP with cvxopt's interior-point ``solvers.qp`` at tight tolerances. H (K, K), f (K,) -> x (K,)."""
    import cvxopt
    from cvxopt import solvers

    K = f.shape[0]
    Gm = np.vstack([-np.eye(K), np.eye(K)])
    h = np.concatenate([-lo * np.ones(K), hi * np.ones(K)])
    opts = {"show_progress": False, "abstol": tol, "reltol": tol, "feastol": tol, "maxiters": 200}
    sol = solvers.qp(cvxopt.matrix(0.5 * (H + H.T)), cvxopt.matrix(f), cvxopt.matrix(Gm), cvxopt.matrix(h),
                     options=opts)
    return np.clip(np.array(sol["x"]).reshape(-1), lo, hi)


def solve_box_qp(H: np.ndarray, f: np.ndarray, x0: np.ndarray | None = None, method: str = "active_set",
                 hi: float = 1.0) -> np.ndarray:
    """Dispatch: ``method`` ``"active_set"`` (default, exact, warm-started) or ``"cvxopt"``; box ``[0, hi]``."""
    if method == "active_set":
        return solve_box_qp_active_set(H, f, hi=hi, x0=x0)
    if method == "cvxopt":
        return solve_box_qp_cvxopt(H, f, hi=hi)
    raise ValueError(f"unknown QP method '{method}' (use active_set or cvxopt)")


def qp_energy(H: np.ndarray, f: np.ndarray, x: np.ndarray) -> float:
    """``1/2 x^T H x + f^T x``."""
    return float(0.5 * x @ H @ x + f @ x)
