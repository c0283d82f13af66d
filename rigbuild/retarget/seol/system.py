"""The spacetime system (Seol et al. 2012, sec. 4-5, eq. 4 ``E = E_match + alpha E_prior``, sec. 7.1's
Sobolev term, gaps and the bounded / sparse options): :class:`SeolSystem`, its exact solve over all frames and
its bounded solve."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
import scipy.linalg

from rigbuild.errors import InputError
from rigbuild.geometry.block_tridiagonal import (block_tridiagonal_gradient, solve_box_qp_block_tridiagonal,
                                                 solve_pinned_block_tridiagonal)
from rigbuild.retarget.params import DEFAULT_ALPHA
from rigbuild.retarget.seol.checks import _frame_indices, shape_index, weight_interval
from rigbuild.retarget.seol.solvers import _path_laplacian_free, _solve_kronecker

#: most active-set passes of the bounded spacetime solve in :func:`retarget_seol`
BOUNDED_MAX_PASSES = 200


@dataclass
class SeolSystem:
    """Everything the spacetime solve and later edits need (save it next to the weight curves).

    B : (3M, K) target marker blendshapes after scale-proportion matching, mm.
    S : (F, 3M) source marker displacements from the source neutral, head motion removed, mm.
    prior_P, prior_p : the prior as ``w^T P w - 2 p^T w`` (:meth:`PcaPrior.quadratic`).
    alpha : prior weight (sec. 5; the paper's 0.01).
    beta : None, (M,) per-marker Sobolev weight (sec. 7.1), or (F, M) per frame and marker.
    ridge : relative Tikhonov weight on velocities (``+ ridge * tr(G)/K * ||w_t - w_{t-1}||^2``) so
        that shapes the markers do not see stay determined; 1e-6 leaves the solution unchanged in
        practice.
    shape_names : K names; marker_names : M names.
    visibility : None (every marker seen in every frame) or (F, M) bool, False where a marker is a
        gap. Gaps are left out of the energy instead of being invented: a velocity term of marker m
        between frames t-1 and t counts only when m is seen in both, a Sobolev term only when m is
        seen at t (entries of ``S`` at gaps are ignored and may be NaN). The system then has
        time-varying blocks ``G_t = B_vis(t)^T B_vis(t)`` (still block tridiagonal, O(frames)).
    bounds : None (the paper: unconstrained) or (lo, hi), the weight range the solution is kept in
        (:meth:`solve_bounded`); edits of a bounded solution stay in it.
    sparsity : lambda >= 0 of an L1 term ``lambda sum_t ||w_t||_1`` added to eq. (4) (mm^2 per unit
        weight; not in the paper, Ribera et al. 2017's E_Sparse). On weights >= 0 it is the linear term
        ``lambda 1^T w``, so it needs ``bounds`` with a non-negative low end.
    """

    B: np.ndarray
    S: np.ndarray
    prior_P: np.ndarray
    prior_p: np.ndarray
    alpha: float = DEFAULT_ALPHA
    beta: np.ndarray | None = None
    ridge: float = 1e-6
    shape_names: list[str] = field(default_factory=list)
    marker_names: list[str] = field(default_factory=list)
    visibility: np.ndarray | None = None
    bounds: tuple[float, float] | None = None
    sparsity: float = 0.0

    def __post_init__(self) -> None:
        self.B = np.asarray(self.B, dtype=np.float64)
        if self.bounds is not None:
            self.bounds = weight_interval(self.bounds)
        self.sparsity = float(self.sparsity)
        if not (np.isfinite(self.sparsity) and self.sparsity >= 0):
            raise InputError(f"sparsity must be a finite number >= 0, got {self.sparsity}", path="config")
        if self.sparsity > 0 and (self.bounds is None or self.bounds[0] < 0):
            raise InputError("the sparsity (L1) term needs weights bounded below by 0", path="config",
                             fix="set weight_bounds: [0, 1] with sparsity, or sparsity: 0")
        self.S = np.asarray(self.S, dtype=np.float64)
        if self.B.ndim != 2 or self.S.ndim != 2 or self.S.shape[1] != self.B.shape[0]:
            raise InputError(f"SeolSystem: B {self.B.shape} and S {self.S.shape} do not match (need (3M,K), (F,3M))")
        if self.visibility is not None:
            vis = np.asarray(self.visibility, dtype=bool)
            if vis.shape != (self.S.shape[0], self.B.shape[0] // 3):
                raise InputError(f"SeolSystem: visibility must be ({self.S.shape[0]}, {self.B.shape[0] // 3}), "
                                 f"got {vis.shape}")
            vis3 = np.repeat(vis, 3, axis=1)
            if not np.all(np.isfinite(self.S[vis3])):
                raise InputError("SeolSystem: the source displacements contain NaN at visible markers")
            self.S = np.where(vis3, self.S, 0.0)
            self.visibility = None if vis.all() else vis
        if not np.all(np.isfinite(self.S)):
            raise InputError("SeolSystem: the source displacements contain NaN (fill the marker gaps first, "
                             "or pass visibility)")
        if self.beta is not None:
            self.beta = np.asarray(self.beta, dtype=np.float64)
            M = self.B.shape[0] // 3
            if self.beta.shape not in ((M,), (self.n_frames, M)):
                raise InputError(f"Sobolev beta must be ({M},) or ({self.n_frames}, {M}), got {self.beta.shape}")
            if np.any(self.beta < 0):
                raise InputError("Sobolev beta must be non-negative")
        self._G = self.B.T @ self.B
        scale = max(np.trace(self._G) / max(self.n_shapes, 1), 1e-12)
        self._G_reg = self._G + self.ridge * scale * np.eye(self.n_shapes)
        self._pos_eps = 1e-10 * scale
        self._SB = self.S @ self.B  # (F, K): B^T s_t for every frame
        self._eig: tuple[np.ndarray, np.ndarray] | None = None  # (mu, U) of the constant-in-time case

    @property
    def n_frames(self) -> int:
        return int(self.S.shape[0])

    @property
    def n_shapes(self) -> int:
        return int(self.B.shape[1])

    # -------------------------------------------------------------- pieces of the energy
    def _beta3(self, frames: np.ndarray) -> np.ndarray | None:
        """(n, 3M) per-coordinate Sobolev weights for ``frames`` or None."""
        if self.beta is None:
            return None
        b = self.beta if self.beta.ndim == 2 else np.broadcast_to(self.beta, (self.n_frames, self.beta.size))
        return np.repeat(b[frames], 3, axis=1)

    def _position_terms(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        """Per-frame positional matrix (alpha P + Q_t + eps I) and rhs (alpha p + B^T beta_t s_t).

        Returns Pc (K, K) if constant in time (flag True) else (n, K, K), and rhs (n, K).
        """
        K = self.n_shapes
        base = self.alpha * self.prior_P + self._pos_eps * np.eye(K)
        rhs = np.broadcast_to(self.alpha * self.prior_p, (frames.size, K)).copy()
        b3 = self._beta3(frames)
        if b3 is None:
            return base, rhs, True
        if self.visibility is not None:
            b3 = b3 * np.repeat(self.visibility[frames], 3, axis=1)
            rhs += (b3 * self.S[frames]) @ self.B
            Q = np.einsum("ik,ti,il->tkl", self.B, b3, self.B, optimize=True)
            return base[None] + Q, rhs, False
        rhs += (b3 * self.S[frames]) @ self.B
        if self.beta.ndim == 1:
            return base + self.B.T @ (b3[0][:, None] * self.B), rhs, True
        Q = np.einsum("ik,ti,il->tkl", self.B, b3, self.B, optimize=True)
        return base[None] + Q, rhs, False

    def solve(self, pin_mask: np.ndarray, pin_values: np.ndarray, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Minimize ``E = E_match + alpha E_prior (+ Sobolev)`` over frames ``start..stop-1``.

        pin_mask : (n, K) bool, True where a weight is known (boundary condition); pin_values :
        (n, K) the known values (ignored elsewhere); n = stop - start. Velocity terms only couple
        frames inside the window (editing, sec. 6, solves only the range). Returns W (n, K).
        """
        stop = self.n_frames if stop is None else stop
        n = stop - start
        K = self.n_shapes
        mask = np.asarray(pin_mask, dtype=bool)
        vals = np.where(mask, np.asarray(pin_values, dtype=np.float64), 0.0)
        if mask.shape != (n, K) or vals.shape != (n, K):
            raise InputError(f"pins must be ({n}, {K}), got {mask.shape}")
        frames = np.arange(start, stop)
        G = self._G_reg
        Pc, rpos, constant = self._position_terms(frames)
        if self.visibility is not None:
            return solve_pinned_block_tridiagonal(*self._quadratic(start, stop), mask, vals)
        # movement rhs: (L SB)_t = B^T (v_t - v_{t+1}) with v_t = s_t - s_{t-1} inside the window
        SB = self._SB[start:stop]
        rv = np.zeros((n, K))
        if n > 1:
            dSB = np.diff(SB, axis=0)  # B^T v_t for t = 1..n-1
            rv[1:] += dSB
            rv[:-1] -= dSB
        rhs = rv + rpos - 0.5 * self.sparsity  # (the L1 term on weights >= 0 is linear)
        full = mask.all(axis=1)
        none = ~mask.any(axis=1)
        W = vals.copy()
        if constant and np.all(full | none):
            free = np.flatnonzero(none)
            if free.size == 0:
                return W
            # move pinned neighbours to the right-hand side: off-diagonal blocks are -G
            pinned_rows = np.flatnonzero(full)
            r = rhs.copy()
            if pinned_rows.size:
                GW = vals @ G  # row t: (G w_t)^T (G symmetric)
                for off in (-1, 1):
                    nb = pinned_rows + off
                    ok = (nb >= 0) & (nb < n)
                    r[nb[ok]] += GW[pinned_rows[ok]]
            Ld, Lo = _path_laplacian_free(n, free)
            if self._eig is None:  # Pc is the same for every window: decompose once
                self._eig = scipy.linalg.eigh(Pc, G)
            W[free] = _solve_kronecker(Ld, Lo, G, Pc, r[free], self._eig)
            return W
        # general path: block tridiagonal with pinned variables eliminated (identity rows)
        return solve_pinned_block_tridiagonal(*self._quadratic(start, stop), mask, vals)

    def _quadratic(self, start: int = 0, stop: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Eq. (4) over frames ``start..stop-1`` as ``E = 1/2 w^T H w - r^T w + const`` (half of eq. (4), with
        the sparsity term's ``lambda / 2`` in r): H block tridiagonal with
        diagonal blocks A (n, K, K) and upper blocks U (n-1, K, K) (``H[t, t+1] = U[t]``), r (n, K)."""
        stop = self.n_frames if stop is None else stop
        n, K = stop - start, self.n_shapes
        frames = np.arange(start, stop)
        Pc, rpos, constant = self._position_terms(frames)
        rv = np.zeros((n, K))
        if self.visibility is not None:
            Gp, dSB = self._pair_terms(frames)
            A = (Pc if not constant else np.broadcast_to(Pc, (n, K, K))).copy()
            if n > 1:
                rv[1:] += dSB
                rv[:-1] -= dSB
                A[1:] += Gp
                A[:-1] += Gp
            return A, -Gp, rv + rpos - 0.5 * self.sparsity
        # movement rhs: (L SB)_t = B^T (v_t - v_{t+1}) with v_t = s_t - s_{t-1} inside the window
        if n > 1:
            dSB = np.diff(self._SB[start:stop], axis=0)
            rv[1:] += dSB
            rv[:-1] -= dSB
        G = self._G_reg
        deg = np.full(n, 2.0)
        deg[0] -= 1.0
        deg[-1] -= 1.0
        A = deg[:, None, None] * G[None] + (Pc[None] if constant else Pc)
        return A, np.broadcast_to(-G, (max(n - 1, 0), K, K)).copy(), rv + rpos - 0.5 * self.sparsity

    def gradient(self, W: np.ndarray, start: int = 0, stop: int | None = None,
                 quadratic: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """(n, K) gradient of eq. (4)'s energy over frames ``start..stop-1`` at W (n, K): ``H w - r``
        (:meth:`_quadratic`; pass its result as ``quadratic`` to reuse it)."""
        A, U, r = self._quadratic(start, stop) if quadratic is None else quadratic
        return block_tridiagonal_gradient(A, U, r, W)

    def _pair_terms(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Velocity blocks with gaps: for consecutive frames (t-1, t) of ``frames``,
        ``G_t = B^T diag(seen at t-1 and t) B + ridge`` (n-1, K, K) and ``B^T diag(...) (s_t - s_{t-1})``
        (n-1, K). Only pairs with a gap pay for their own block (``G`` minus the missing rows)."""
        vis = self.visibility[frames]
        pair = vis[1:] & vis[:-1]  # (n-1, M)
        n1 = pair.shape[0]
        K = self.n_shapes
        Gp = np.broadcast_to(self._G_reg, (n1, K, K)).copy()
        B3 = self.B.reshape(-1, 3, K)
        for t in np.flatnonzero(~pair.all(axis=1)):
            Bm = B3[~pair[t]].reshape(-1, K)
            Gp[t] -= Bm.T @ Bm
        p3 = np.repeat(pair, 3, axis=1)
        dS = np.where(p3, np.diff(self.S[frames], axis=0), 0.0)
        return Gp, dS @ self.B

    # ------------------------------------------------------------------------- pins helpers
    def pins_for(self, boundary_frames: Sequence[int] = (0, -1),
                 pins: Mapping[int, Mapping[str, float] | np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Pin mask / values (F, K): every weight 0 (neutral) at ``boundary_frames`` (default the
        first and last frame), plus user pins ``{frame: {shape: value}}`` or ``{frame: (K,) array}``."""
        F, K = self.n_frames, self.n_shapes
        mask = np.zeros((F, K), bool)
        vals = np.zeros((F, K))
        mask[_frame_indices(boundary_frames, F, "boundary frames")] = True
        for frame, v in (pins or {}).items():
            f = int(_frame_indices([frame], F, "pinned frame")[0])
            if isinstance(v, Mapping):
                for name, value in v.items():
                    k = shape_index(self.shape_names, name)
                    mask[f, k] = True
                    vals[f, k] = float(value)
            else:
                arr = np.asarray(v, dtype=np.float64).reshape(-1)
                if arr.size != K:
                    raise InputError(f"pinned frame {f}: {arr.size} weights for {K} shapes")
                mask[f] = True
                vals[f] = arr
        return mask, vals

    def solve_bounded(self, pin_mask: np.ndarray, pin_values: np.ndarray, bounds: tuple[float, float] | None = None,
                      max_iterations: int = 50, tolerance: float = 1e-9, start: int = 0,
                      stop: int | None = None, linear: np.ndarray | None = None) -> tuple[np.ndarray, int]:
        """:meth:`solve` with every free weight kept in ``bounds`` = (lo, hi) (not in the paper): the exact
        spacetime minimizer under the bounds by a primal-dual active set
        (:func:`rigbuild.geometry.block_tridiagonal.solve_box_qp_block_tridiagonal`), so the movement matching is
        re-solved around a bound instead of being cut off as a clamp would. ``bounds`` defaults to the system's;
        ``start``/``stop`` as in :meth:`solve`; ``linear`` (n, K): an extra linear term ``sum linear_tk w_tk`` of
        eq. (4) (the reweighted sparsity option of :func:`~rigbuild.retarget.seol.retarget.retarget_seol`).
        Returns (W (n, K) within bounds, passes).
        """
        bounds = self.bounds if bounds is None else bounds
        if bounds is None:
            raise InputError("solve_bounded needs bounds (the system has none)", fix="pass bounds=(lo, hi)")
        lo, hi = weight_interval(bounds)
        # the energy does not change between passes, only the pins: assemble it once (half of a pass's time)
        quad = self._quadratic(start, stop)
        if linear is not None:  # (the quadratic is half of eq. (4))
            quad = (quad[0], quad[1], quad[2] - 0.5 * np.asarray(linear, dtype=np.float64))
        user = np.array(pin_mask, dtype=bool, copy=True)
        if user.shape != quad[2].shape or np.shape(pin_values) != quad[2].shape:
            raise InputError(f"pins must be {quad[2].shape}, got {user.shape}")
        vals = np.where(user, np.asarray(pin_values, dtype=np.float64), 0.0)
        return solve_box_qp_block_tridiagonal(*quad, lo, hi, user, vals, max_iterations, tolerance)

    def solve_spacetime(self, boundary_frames: Sequence[int] = (0, -1),
                        pins: Mapping[int, Mapping[str, float] | np.ndarray] | None = None) -> np.ndarray:
        """The paper's retargeting: eq. (4) over all frames with boundary frames and pins. (F, K)."""
        mask, vals = self.pins_for(boundary_frames, pins)
        return self.solve(mask, vals)

    # -------------------------------------------------------------------------- save / load
    def save(self, path: str | os.PathLike) -> None:
        """Write the system to an npz (atomically) for later spacetime edits."""
        from rigbuild.io.atomic import save_npz

        save_npz(path, B=self.B, S=self.S, prior_P=self.prior_P, prior_p=self.prior_p,
                 alpha=np.float64(self.alpha), ridge=np.float64(self.ridge),
                 beta=np.zeros(0) if self.beta is None else self.beta,
                 shape_names=np.asarray(self.shape_names, dtype=str),
                 marker_names=np.asarray(self.marker_names, dtype=str),
                 visibility=np.zeros((0, 0), bool) if self.visibility is None else self.visibility,
                 bounds=np.zeros(0) if self.bounds is None else np.asarray(self.bounds, dtype=np.float64),
                 sparsity=np.float64(self.sparsity))

    @classmethod
    def load(cls, path: str | os.PathLike) -> "SeolSystem":
        try:
            z = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read the spacetime system: {exc}", path=path,
                             fix="pass the system.npz written by the retarget_seol stage") from None
        need = {"B", "S", "prior_P", "prior_p", "alpha", "shape_names"}
        if not need <= set(z.files):
            raise InputError(f"not a spacetime system file (missing {sorted(need - set(z.files))})", path=path)
        beta = z["beta"] if "beta" in z.files and z["beta"].size else None
        return cls(B=z["B"], S=z["S"], prior_P=z["prior_P"], prior_p=z["prior_p"], alpha=float(z["alpha"]),
                   beta=beta, ridge=float(z["ridge"]) if "ridge" in z.files else 1e-6,
                   shape_names=[str(s) for s in z["shape_names"]],
                   marker_names=[str(s) for s in z["marker_names"]] if "marker_names" in z.files else [],
                   visibility=z["visibility"] if "visibility" in z.files and z["visibility"].size else None,
                   bounds=tuple(z["bounds"]) if "bounds" in z.files and z["bounds"].size else None,
                   sparsity=float(z["sparsity"]) if "sparsity" in z.files else 0.0)
