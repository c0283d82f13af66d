"""Per-frame retargeting (Ribera et al. 2017, sec. 5, eq. 16): ``E_Fit + mu E_Prior + lambda E_Sparse``
with optional weight bounds, a joint residual rigid fit, and the plausibility options
(:mod:`.plausible`)."""

from __future__ import annotations

import numpy as np

from rigbuild.errors import InputError
from rigbuild.retarget.common import visible_mask
from rigbuild.retarget.params import RetargetParams
from rigbuild.retarget.ribera.bounded import box_qp
from rigbuild.retarget.ribera.plausible import (ANTAGONIST_ROUNDS, REWEIGHT_PASSES, REWEIGHT_TOLERANCE,
                                              antagonist_pins, antagonist_slopes, reweighted_slopes,
                                              still_upper_bounds, support_masks)


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

    Plausibility options (``params.sparsity``, ``antagonists``, ``still_gate``; :mod:`.plausible`; need
    bounds from 0): antagonist_pairs (P, 2) shape indices that are never on together; marker_ranges (M,)
    each marker's range over the training sequence (mm), the still-region gate's noise scale.
    """

    def __init__(self, dp: np.ndarray, Q: np.ndarray, params: RetargetParams | None = None,
                 reference: np.ndarray | None = None, antagonist_pairs: np.ndarray | None = None,
                 marker_ranges: np.ndarray | None = None):
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
        # plausibility options (:mod:`.plausible`): antagonist index pairs, still-region support and noise
        self.antagonist_pairs = np.zeros((0, 2), np.int64) if antagonist_pairs is None else np.asarray(
            antagonist_pairs, np.int64).reshape(-1, 2)
        self.still_noise = None if marker_ranges is None else np.asarray(marker_ranges, float)
        self.support = support_masks(self.dp)
        if (self.params.sparsity != "l1" or self.params.antagonists or self.params.still_gate) and self.lo < 0:
            raise InputError("the plausibility options (sparsity, antagonists, still_gate) need weight bounds "
                             "from 0", fix="set bounds: [0, 1]")

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
        A = 2.0 * PtP / n + 2.0 * self.params.mu * self.Q
        # a shape that moves none of the visible markers (and no prior) has no curvature: a ridge of 1e-12 of the
        # mean diagonal keeps A positive definite, and the L1 term then holds that shape at its lower bound
        A[np.diag_indices(self.K)] += 1e-12 * max(float(np.trace(A)) / self.K, 1e-300)
        return A, G

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
                       start: np.ndarray | None = None, hi: np.ndarray | None = None) -> np.ndarray:
        """Batched ``min 1/2 w^T A_f w - b_f^T w`` s.t. lo <= w <= hi (:func:`.bounded.box_qp`).

        A (F, K, K) SPD, b (F, K); ``shared``: every A_f is the complete-visibility system (one inverse serves
        the unconstrained start); ``start`` (F, K): a warm start (same minimizer, fewer passes); ``hi``
        (F, K): per-frame upper bounds (default the params' bound; a shape with hi <= lo is held at 0).
        """
        F, K = b.shape
        if not (np.isfinite(self.lo) or np.isfinite(self.hi)) and hi is None:
            return np.linalg.solve(A, b[..., None])[..., 0]
        lo_a = np.full((F, K), self.lo)
        hi_a = np.full((F, K), self.hi) if hi is None else np.minimum(hi, self.hi)
        w0 = None
        if start is None and shared and F > 1:
            if not hasattr(self, "_full_inv"):
                self._full_inv = np.linalg.inv(self._full)
            w0 = b @ self._full_inv.T
        w, info = box_qp(A, b, lo_a, hi_a, self.params.active_set_passes, start=start, w0=w0)
        self.last_passes, self.unconverged = info["passes"], info["unconverged"]
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

    def solve(self, da: np.ndarray, start: np.ndarray | None = None, plain: bool = False) -> np.ndarray:
        """Weights (F, K) for stabilized actor displacements da (F, M, 3) (NaN gaps), frames in time order
        (the plausibility options smooth their decisions over time).

        ``start`` (F, K): weights of a nearby problem (e.g. the same frames before a rigid re-fit) whose
        active set seeds the bounded solve (with ``bounds`` and lo >= 0); the result is the same minimizer.
        ``plain``: eq. 16 only, without the plausibility options (a first pass for the rigid re-fit).
        """
        da = np.asarray(da, float)
        if da.ndim == 2:
            return self.solve(da[None], None if start is None else np.asarray(start)[None], plain)[0]
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
            # eq. 16 with w >= 0: the L1 term is linear, (lambda/K) sum_k w_k: exact, no reweighting needed
            if plain or not self.plausible:
                return self._bounded_solve(A, b - lam, shared, start=start)
            return self._solve_plausible(A, b, da, lam, shared, start)
        w = self._bounded_solve(A, b, shared)
        if lam > 0:
            diag_idx = np.arange(self.K)
            for _ in range(self.params.irls_iterations):
                Ai = A.copy()
                Ai[:, diag_idx, diag_idx] += lam / (np.abs(w) + self.params.irls_eps)
                w = self._bounded_solve(Ai, b)
        return w

    @property
    def plausible(self) -> bool:
        """Whether any plausibility option (:mod:`.plausible`) is on."""
        p = self.params
        return p.sparsity != "l1" or p.antagonists or (p.still_gate and self.still_noise is not None)

    def _solve_plausible(self, A: np.ndarray, b: np.ndarray, da: np.ndarray, lam: float, shared: bool,
                         start: np.ndarray | None) -> np.ndarray:
        """The bounded solve with the options of :mod:`.plausible`: still-region upper bounds, the log
        sparsity penalty's reweighting passes, then antagonist exclusion rounds (each a warm-started exact
        bounded solve)."""
        p = self.params
        hi = None
        if p.still_gate and self.still_noise is not None:
            hi = still_upper_bounds(da, self.support, p.still_ratio * self.still_noise, self.hi,
                                    p.coherence_frames)
        w = self._bounded_solve(A, b - lam, shared, start=start, hi=hi)
        slopes = lam
        push = p.antagonists and self.antagonist_pairs.size and p.antagonist_lambda_cm > 0
        if p.sparsity == "log" or push:
            lam_s = p.sparsity_lambda_mm / self.K
            gamma = p.antagonist_lambda_mm / self.K
            for _ in range(REWEIGHT_PASSES):
                slopes = reweighted_slopes(w, lam_s, p.sparsity_eps, p.coherence_frames) if p.sparsity == "log" \
                    else np.full(w.shape, lam)
                if push:
                    slopes = slopes + antagonist_slopes(w, self.antagonist_pairs, gamma, p.coherence_frames)
                w_prev, w = w, self._bounded_solve(A, b - slopes, start=w, hi=hi)
                if np.abs(w - w_prev).max(initial=0.0) < REWEIGHT_TOLERANCE:
                    break
        if p.antagonists and self.antagonist_pairs.size:
            hi_a = np.full(w.shape, self.hi) if hi is None else hi.copy()
            for _ in range(ANTAGONIST_ROUNDS):
                pin = antagonist_pins(w, self.antagonist_pairs, p.coherence_frames)
                if not pin.any():
                    break
                hi_a[pin] = self.lo
                rows = np.flatnonzero(pin.any(1))
                sl = slopes if np.ndim(slopes) == 0 else slopes[rows]
                w[rows] = self._bounded_solve(A[rows], b[rows] - sl, start=w[rows], hi=hi_a[rows])
        return w

    def solve_frame(self, da: np.ndarray) -> np.ndarray:
        """Weights (K,) for one stabilized frame da (M, 3)."""
        return self.solve(np.asarray(da, float)[None])[0]
