"""Per-frame retargeting (Ribera et al. 2017, sec. 5, eq. 16): ``E_Fit + mu E_Prior + lambda E_Sparse``
with optional weight bounds, a joint residual rigid fit, and the plausibility options
(:mod:`.plausible`)."""

from __future__ import annotations

import numpy as np

from rigbuild.errors import InputError
from rigbuild.retarget.common import visible_mask
from rigbuild.retarget.params import RetargetParams
from rigbuild.retarget.ribera.bounded import _masked_system, _solve_free

def rigid_jacobian(reference: np.ndarray) -> np.ndarray:
    """(M, 3, 6) derivative of the marker positions under a small rigid motion of ``reference`` (M, 3).

    ``x_m(omega, t) ~ x_m + omega x (x_m - c) + t`` with c the centroid: columns 0-2 rotation (rad),
    3-5 translation (mm).
    """
    p = np.asarray(reference, float) - np.asarray(reference, float).mean(0)
    J = np.zeros(p.shape[:1] + (3, 6))
    # omega x p = -[p]_x omega
    J[:, 0, 1], J[:, 0, 2] = p[:, 2], -p[:, 1]
    J[:, 1, 0], J[:, 1, 2] = -p[:, 2], p[:, 0]
    J[:, 2, 0], J[:, 2, 1] = p[:, 1], -p[:, 0]
    J[:, :, 3:] = np.eye(3)
    return J


class RiberaRetargeter:
    """Per-frame weights minimizing eq. 16: ``(1/M)|da - P w|^2 + mu w^T Q w + (lambda/K) |w|_1``.

    dp : (K, M, 3) personalized sparse actor blendshapes (mm); Q : (K, K) prior form from
    :func:`prior_matrix` (already scaled to the actor's head); params : :class:`RetargetParams`.
    Frames with gaps use their visible markers (E_Fit over the visible ones, normalized by their count).

    reference : (M, 3) the actor's neutral markers; with ``params.rigid == "joint"`` E_Fit becomes
    ``min_xi (1/M)|da - P w - J xi|^2`` with J = :func:`rigid_jacobian` (reference) and xi (6,) a residual
    small rigid motion of the stabilized frame. xi is unbounded and unpenalized, so it is eliminated exactly:
    the normal matrix becomes the Schur complement ``P^T P - P^T J (J^T J)^-1 J^T P`` and the right-hand
    side ``P^T da - P^T J (J^T J)^-1 J^T da`` (per visibility pattern); the K x K bounded solve is unchanged.

    Speed (whole sequences and single frames give the same weights): the normal matrix of each visibility
    pattern is built once and cached (:meth:`_pattern_systems`); all frames are solved together, each
    active-set pass only over the free (off-bound) weights (:func:`_solve_free`); ``solve(..., start=w)``
    seeds the active set from a nearby solution (the rigid re-fit in :meth:`RiberaModel.retarget`).
    """

    def __init__(self, dp: np.ndarray, Q: np.ndarray, params: RetargetParams | None = None,
                 reference: np.ndarray | None = None):
        self.params = params or RetargetParams()
        if self.params.rigid not in ("joint", "fixed"):
            raise InputError(f"unknown rigid mode '{self.params.rigid}'", fix="use joint or fixed")
        self.dp = np.asarray(dp, float)
        K, M, _ = self.dp.shape
        self.K, self.M = K, M
        self.P = self.dp.transpose(1, 2, 0).reshape(M * 3, K)  # rows (m, c)
        self.Q = np.asarray(Q, float)
        Pm = self.dp.transpose(1, 2, 0)  # (M, 3, K)
        self.PtP_m = np.einsum("mck,mcl->mkl", Pm, Pm)  # (M,K,K)
        self._PtP = self.PtP_m.sum(0)
        self.joint = reference is not None and self.params.rigid == "joint"
        if self.joint:
            self.J = rigid_jacobian(reference)  # (M, 3, 6)
            self.PtJ_m = np.einsum("mck,mcj->mkj", Pm, self.J)  # (M, K, 6)
            self.JtJ_m = np.einsum("mci,mcj->mij", self.J, self.J)  # (M, 6, 6)
        self._full, self._full_G = self._system(np.ones(M, bool))
        self._cache: dict[bytes, tuple[np.ndarray, np.ndarray | None]] = {}
        lo, hi = (None, None) if self.params.bounds is None else self.params.bounds
        self.lo = -np.inf if lo is None else float(lo)
        self.hi = np.inf if hi is None else float(hi)

    def _system(self, vis: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Normal matrix (K, K) for visible markers ``vis`` (M,) and, for the joint rigid fit, the (K, 6)
        coupling ``G = P^T J (J^T J)^-1`` that the right-hand side needs."""
        n = max(int(vis.sum()), 1)
        hidden = ~vis
        use_hidden = hidden.sum() < vis.sum()

        def vsum(per_marker: np.ndarray) -> np.ndarray:
            return per_marker.sum(0) - per_marker[hidden].sum(0) if use_hidden else per_marker[vis].sum(0)

        PtP = self._PtP - self.PtP_m[hidden].sum(0) if use_hidden else self.PtP_m[vis].sum(0)
        G = None
        if self.joint:
            PtJ, JtJ = vsum(self.PtJ_m), vsum(self.JtJ_m)
            G = np.linalg.solve(JtJ + 1e-12 * np.trace(JtJ) * np.eye(6), PtJ.T).T  # (K, 6)
            PtP = PtP - G @ PtJ.T
            PtP = 0.5 * (PtP + PtP.T)
        return 2.0 * PtP / n + 2.0 * self.params.mu * self.Q, G

    def _rhs(self, da: np.ndarray, vis: np.ndarray, G: np.ndarray | None = None) -> np.ndarray:
        """(F, K) ``(2/M_f) P^T da_f`` over visible markers (minus ``G_f J^T da_f`` for the joint rigid fit;
        G (F, K, 6) or (K, 6))."""
        a3 = np.where(vis[..., None], np.nan_to_num(da), 0.0)
        a = a3.reshape(da.shape[0], -1)
        n = np.maximum(vis.sum(1), 1)
        b = a @ self.P
        if self.joint and G is not None:
            Jta = np.einsum("fmc,mcj->fj", a3, self.J)  # (F, 6)
            b = b - (np.einsum("fkj,fj->fk", G, Jta) if G.ndim == 3 else Jta @ G.T)
        return 2.0 * b / n[:, None]

    def rigid_motion(self, da: np.ndarray, w: np.ndarray) -> np.ndarray:
        """(F, M, 3) the residual rigid motion ``J xi_f`` that the joint fit attributes to each frame of da
        (F, M, 3) (NaN gaps) with weights w (F, K): ``xi_f = (J^T J)^-1 J^T (da_f - P w_f)`` over the visible
        markers (zeros for ``rigid="fixed"``)."""
        if not self.joint:
            return np.zeros(da.shape)
        vis = visible_mask(da)
        res = np.where(vis[..., None], np.nan_to_num(da) - np.einsum("fk,kmc->fmc", w, self.dp), 0.0)
        JtJ = np.einsum("fm,mij->fij", vis.astype(float), self.JtJ_m)
        Jtr = np.einsum("fmc,mcj->fj", res, self.J)
        xi = np.linalg.solve(JtJ + 1e-12 * np.eye(6), Jtr[..., None])[..., 0]
        return np.einsum("mcj,fj->fmc", self.J, xi)

    def _bounded_solve(self, A: np.ndarray, b: np.ndarray, shared: bool = False,
                       start: np.ndarray | None = None) -> np.ndarray:
        """Batched ``min 1/2 w^T A_f w - b_f^T w`` s.t. lo <= w <= hi by a primal active-set method.

        A (F, K, K) SPD, b (F, K); ``shared``: every A_f is the complete-visibility system (one inverse serves
        the unconstrained start). ``start`` (F, K): a previous solution whose active set (variables at a bound) is the first guess instead of
        the unconstrained solution's violations (a warm start; the minimizer is unique, so only the number
        of passes changes). Exact: KKT signs are checked each pass; frames where the fast primal-dual
        passes do not settle finish with :meth:`_primal_active_set`. Each pass solves only the free
        variables (:func:`_solve_free`).
        """
        F, K = b.shape
        if not (np.isfinite(self.lo) or np.isfinite(self.hi)):
            return np.linalg.solve(A, b[..., None])[..., 0]
        self.last_passes = 0
        self.unconverged = 0
        if start is not None:
            at_lo = start <= self.lo
            at_hi = start >= self.hi
            w = np.clip(start, self.lo, self.hi)
            todo = np.arange(F)
        else:
            # start from the unconstrained solution's violations (one shared inverse when every frame is complete)
            if shared and A.shape[0] > 1:
                if not hasattr(self, "_full_inv"):
                    self._full_inv = np.linalg.inv(self._full)
                w = b @ self._full_inv.T
            else:
                w = np.linalg.solve(A, b[..., None])[..., 0]
            at_lo = w < self.lo
            at_hi = w > self.hi
            todo = np.flatnonzero(at_lo.any(1) | at_hi.any(1))
        for _ in range(self.params.active_set_passes):
            if todo.size == 0:
                break
            self.last_passes += 1
            Ab, bb, lo_b, hi_b = A[todo], b[todo], at_lo[todo], at_hi[todo]
            free = ~(lo_b | hi_b)
            wb = _solve_free(Ab, bb, free, np.where(lo_b, self.lo, self.hi))
            grad = (Ab @ wb[..., None])[..., 0] - bb
            release = (lo_b & (grad < -1e-12)) | (hi_b & (grad > 1e-12))
            new_lo = free & (wb < self.lo - 1e-12)
            new_hi = free & (wb > self.hi + 1e-12)
            w[todo] = wb
            at_lo[todo] = (lo_b & ~release) | new_lo
            at_hi[todo] = (hi_b & ~release) | new_hi
            todo = todo[release.any(1) | new_lo.any(1) | new_hi.any(1)]
        if todo.size:
            w[todo] = self._primal_active_set(A[todo], b[todo], np.clip(w[todo], self.lo, self.hi))
        return np.clip(w, self.lo, self.hi)

    def _primal_active_set(self, A: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Batched primal active-set method from a feasible start (cannot cycle; for the few frames where
        the fast primal-dual active set above did not settle). One constraint changes per step."""
        F, K = b.shape
        lo, hi = self.lo, self.hi
        at_lo = w <= lo
        at_hi = w >= hi
        todo = np.arange(F)
        rows = np.arange(F)
        for _ in range(6 * K + 10):
            if todo.size == 0:
                break
            Ab, bb, lo_b, hi_b, wt = A[todo], b[todo], at_lo[todo], at_hi[todo], w[todo]
            free = ~(lo_b | hi_b)
            wb = _solve_free(Ab, bb, free, np.where(lo_b, lo, hi))
            d = wb - wt
            below = free & (wb < lo - 1e-12)
            above = free & (wb > hi + 1e-12)
            infeasible = below.any(1) | above.any(1)
            with np.errstate(divide="ignore", invalid="ignore"):
                alpha = np.where(below, (lo - wt) / d, np.inf)
                alpha = np.minimum(alpha, np.where(above, (hi - wt) / d, np.inf))
            r = rows[: todo.size]
            blk = np.argmin(alpha, axis=1)
            step = np.clip(alpha[r, blk], 0.0, 1.0)
            w_new = np.where(infeasible[:, None], wt + step[:, None] * d, wb)
            lo_new, hi_new = lo_b.copy(), hi_b.copy()
            inf_r = r[infeasible]
            lo_new[inf_r, blk[infeasible]] |= below[inf_r, blk[infeasible]]
            hi_new[inf_r, blk[infeasible]] |= above[inf_r, blk[infeasible]]
            # feasible frames: check multipliers, release the worst
            grad = (Ab @ w_new[..., None])[..., 0] - bb
            viol = np.where(lo_b, -grad, 0.0) + np.where(hi_b, grad, 0.0)  # > 0: wrong sign
            worst = np.argmax(viol, axis=1)
            release = ~infeasible & (viol[r, worst] > 1e-10)
            rel_r = r[release]
            lo_new[rel_r, worst[release]] = False
            hi_new[rel_r, worst[release]] = False
            w[todo] = np.clip(w_new, lo, hi)
            at_lo[todo] = lo_new
            at_hi[todo] = hi_new
            todo = todo[infeasible | release]
        self.unconverged = int(todo.size)
        return w

    def _pattern_systems(self, vis: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Normal matrices (F, K, K) and joint-rigid couplings (F, K, 6) (or None) for the visibility rows
        vis (F, M): one :meth:`_system` per distinct pattern, kept in a cache across calls (a take's gap
        patterns recur; one frame at a time then costs no re-assembly)."""
        packed = np.packbits(vis, axis=1)
        keys = [r.tobytes() for r in packed]
        cache = self._cache
        for key, row in zip(keys, vis):
            if key not in cache:
                if len(cache) >= self.CACHE_PATTERNS:
                    cache.clear()
                cache[key] = self._system(row)
        A = np.stack([cache[k][0] for k in keys])
        G = np.stack([cache[k][1] for k in keys]) if self.joint else None
        return A, G

    CACHE_PATTERNS = 1024  # (K, K) + (K, 6) floats each: about 25 MB at K = 53

    def solve(self, da: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
        """Weights (F, K) for stabilized actor displacements da (F, M, 3) (NaN gaps).

        ``start`` (F, K): weights of a nearby problem (e.g. the same frames before a rigid re-fit) whose
        active set seeds the bounded solve (with ``bounds`` and lo >= 0); the result is the same minimizer.
        """
        da = np.asarray(da, float)
        if da.ndim == 2:
            return self.solve(da[None], None if start is None else np.asarray(start)[None])[0]
        F = da.shape[0]
        vis = visible_mask(da)
        partial = ~vis.all(1)
        A = np.broadcast_to(self._full, (F, self.K, self.K))
        G = self._full_G
        if partial.any():
            A = A.copy()
            Ap, Gp = self._pattern_systems(vis[partial])
            A[partial] = Ap
            if self.joint:
                G = np.broadcast_to(self._full_G, (F, self.K, 6)).copy()
                G[partial] = Gp
        b = self._rhs(da, vis, G)
        lam = self.params.lambda_mm / self.K
        shared = not partial.any()
        if self.lo >= 0:
            # with w >= 0 the L1 term is linear, (lambda/K) sum_k w_k: exact, no reweighting needed
            return self._bounded_solve(A, b - lam, shared, start=start)
        w = self._bounded_solve(A, b, shared)
        if lam > 0:
            diag_idx = np.arange(self.K)
            for _ in range(self.params.irls_iterations):
                Ai = A.copy()
                Ai[:, diag_idx, diag_idx] += lam / (np.abs(w) + self.params.irls_eps)
                w = self._bounded_solve(Ai, b)
        return w

    def solve_frame(self, da: np.ndarray) -> np.ndarray:
        """Weights (K,) for one stabilized frame da (M, 3)."""
        return self.solve(np.asarray(da, float)[None])[0]
