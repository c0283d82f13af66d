"""Spacetime expression cloning for blendshapes (Seol, Lewis, Seo, Choi, Anjyo, Noh 2012).

Every part of the paper, in marker space:

- sec. 3.1 head motion removal by Procrustes against the source neutral, kept for re-synthesis:
  :func:`remove_head_motion`, :func:`head_motion_about_pivot`, :func:`apply_head_motion`;
- sec. 3.2 scale-proportion matching: an RBF warp ``d(x) = sum_i w_i |x - c_i| + q(x)`` (linear
  polynomial ``q``) from the target's neutral markers to the source's, applied to the marker positions
  of every target blendshape: :func:`fit_rbf_warp`, :func:`scale_proportion_match`; options beside it
  (``scale_match`` of :func:`retarget_seol`, :mod:`rigbuild.retarget.proportion`): deformation transfer
  of the target's blendshapes onto the RBF-warped target mesh (``"deformation"``, the inverse of how
  stylized rigs are built), the RBF's Jacobian, per-marker local affine maps, other kernels;
- sec. 4 movement matching ``min_W ||D (B W)^T - D S^T||_F^2`` with boundary frames (pins);
- sec. 5 the PCA prior of the target's blendshapes ``E_prior = v^T Lambda^-1 v``,
  ``v = E^T (B w + n_tgt - t_bar)``: :func:`build_pca_prior`; ``E = E_match + alpha E_prior`` solved as
  one sparse system over all frames: :meth:`SeolSystem.solve`;
- sec. 7 / fig. 11 the per-frame baselines (no constraint, weights in [-0.5, 1.5], PCA prior) and the
  velocity error: :func:`solve_perframe_unconstrained`, :func:`solve_perframe_range`,
  :func:`solve_perframe_prior`, :func:`velocity_error_per_frame`;
- prior strength as a corner frequency (:func:`alpha_from_corner_hz`) and a combination training set
  for the prior (:func:`sparse_combination_weights`); marker gaps left out of the energy
  (``visibility`` of :class:`SeolSystem`, ``gaps="mask"`` of :func:`retarget_seol`);
- sec. 7.1 the Sobolev variant ``+ sum_t (B w_t - s_t)^T diag(beta_t) (B w_t - s_t)``, beta per marker
  (region) and optionally only at chosen frames: ``beta`` of :class:`SeolSystem`, :func:`sobolev_beta`.

Spacetime editing (sec. 6) is in :mod:`rigbuild.retarget.editing` and uses :meth:`SeolSystem.solve`
on a frame window.

The normal equations of ``E`` over frames are block tridiagonal in time (K x K blocks):
``A_t = deg_t G + alpha P + Q_t``, off-diagonal ``-G`` with ``G = B^T B``, ``P = B^T E Lambda^-1 E^T B``,
``Q_t = B^T diag(beta_t) B``. When every pin fixes whole frames and beta does not vary in time the
matrix is the Kronecker sum ``L (x) G + I (x) (alpha P + Q)`` (L the path Laplacian of the free
frames); a generalized eigendecomposition ``U^T G U = I, U^T (alpha P + Q) U = diag(mu)`` decouples it
into K scalar tridiagonal systems ``(L + mu_k I) y_k = ...`` solved with one LAPACK ``gtsv`` call
(:func:`_solve_kronecker`). Otherwise (pins of single shapes, frame-varying beta) a block Thomas
(block LDL^T) recursion is used (:func:`solve_block_tridiagonal`). Both cost O(frames).

Conventions: marker positions in mm; ``S`` is (F, 3M) source displacements from the source neutral
after head motion removal, flattened marker-major (x, y, z per marker); ``B`` is (3M, K), the
columns the target's (deformed) marker blendshape deltas; weights ``W`` are (F, K) (the paper's W^T).
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, field, fields, replace
from typing import Mapping, Sequence

import numpy as np
import scipy.linalg
from scipy.linalg import lapack

from rigbuild.errors import InputError
from rigbuild.retarget.common import bridge_rigid_motion, lowpass_markers
from rigbuild.retarget.params import (  # noqa: F401  (the paper's defaults, re-exported)
    DEFAULT_ALPHA,
    DEFAULT_ALPHA_PERFRAME,
    DEFAULT_WEIGHT_RANGE,
    GAP_MODES,
    RIGID_WEIGHTS,
    SCALE_MATCH_MODES,
    SeolParams,
)
from rigbuild.retarget.proportion import ProportionMap, fit_proportion_map, proportion_match
from rigbuild.rig import Rig


# ----------------------------------------------------------------------------- sec. 3.1 head motion
def remove_head_motion(
    markers: np.ndarray, neutral: np.ndarray, rigid_weights: np.ndarray | None = None,
    path: str | os.PathLike | None = None, min_visible: int = 3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Procrustes head-motion removal (sec. 3.1), with occlusion gaps bridged.

    Parameters
    ----------
    markers : (F, M, 3) mm, world space, NaN where a marker is missing.
    neutral : (M, 3) mm, the source neutral pose ``Y`` (no NaN).
    rigid_weights : (M,) non-negative weight of each marker in the fit (e.g. 1 on forehead / nose
        markers, 0 on the lips), or None for all markers equally (the paper).
    path : the take's file, for messages.
    min_visible : a frame needs this many visible markers (at least 3) for its own fit.

    A frame where fewer than 3 markers of positive weight are visible is fitted on all its visible markers
    (uniform weights); a frame with fewer than ``min_visible`` visible markers gets the head motion bridged
    from the fitted frames around it (:func:`rigbuild.retarget.common.bridge_rigid_motion`; a warning counts
    them). Only a take with no frame of 3 visible markers is an :class:`InputError` (naming ``path``).

    Returns
    -------
    stabilized : (F, M, 3) markers in the neutral's frame, ``R_f^T (x - t_f)`` (NaN kept).
    R : (F, 3, 3), t : (F, 3) head motion, ``markers[f] ~ R[f] @ stabilized[f] + t[f]``.
    """
    X = np.asarray(markers, dtype=np.float64)
    Y = np.asarray(neutral, dtype=np.float64)
    F, M, _ = X.shape
    if Y.shape != (M, 3) or not np.all(np.isfinite(Y)):
        raise InputError(f"source neutral must be a finite ({M}, 3) array, got {Y.shape}", path=path)
    from rigbuild.retarget.common import batched_rigid_fit

    w = np.ones(M) if rigid_weights is None else np.asarray(rigid_weights, dtype=np.float64)
    valid = np.all(np.isfinite(X), axis=2)
    ok = valid & (w > 0)[None]
    wts = np.where(ok, w[None], 0.0)
    fallback = (ok.sum(1) < 3) & (valid.sum(1) >= 3)
    wts[fallback] = valid[fallback]
    fitted = valid.sum(1) >= max(3, int(min_visible))
    if not fitted.any():
        raise InputError(f"no frame of the take has {max(3, int(min_visible))} visible markers for the head-motion "
                         f"fit ({F} frames, "
                         f"at most {int(valid.sum(1).max(initial=0))} visible)", path=path,
                         fix="check the take's marker names against the character's marker map, or fill its gaps")
    # weighted Kabsch per frame (R Y + t ~ X), all frames at once
    R, t = batched_rigid_fit(Y, np.where(wts[..., None] > 0, X, 0.0), wts)
    if not fitted.all():
        logging.getLogger("rigbuild.retarget.seol").warning(
            "%s: %d frame(s) with fewer than %d visible markers: head motion bridged from the frames around them",
            path or "take", int((~fitted).sum()), max(3, int(min_visible)))
        R, t = bridge_rigid_motion(R, t, fitted)
    stabilized = np.einsum("fji,fmj->fmi", R, X - t[:, None, :])
    return stabilized, R, t


def refine_head_motion(
    markers: np.ndarray, neutral: np.ndarray, B: np.ndarray, R: np.ndarray, t: np.ndarray,
    rigid_weights: np.ndarray | None = None, iterations: int = 3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refine the Procrustes head motion jointly with per-frame expression weights (Gauss-Newton).

    Procrustes against the neutral (sec. 3.1) is biased by the expression itself (a jaw opening
    rotates the fit by several degrees when every marker counts). Each iteration linearizes
    ``x_fm ~ R_f exp([omega_f]) (y_m + B_m w_f + tau_f) + t_f`` in (omega, tau, w) and solves all frames
    with one batched weighted least squares (6 + K unknowns per frame); 2-3 iterations converge.

    markers : (F, M, 3), NaN at gaps (a frame with gaps is solved on its seen markers only);
    neutral : (M, 3); B : (3M, K) marker blendshapes of the (scale-matched) target; R, t : initial
    head motion; rigid_weights : (M,) per-marker weights.
    Returns stabilized (F, M, 3) (NaN kept at gaps), R (F, 3, 3), t (F, 3).
    """
    from scipy.spatial.transform import Rotation

    X = np.asarray(markers, dtype=np.float64)
    Y = np.asarray(neutral, dtype=np.float64)
    F, M, _ = X.shape
    K = B.shape[1]
    w = np.ones(M) if rigid_weights is None else np.asarray(rigid_weights, dtype=np.float64)
    sw = np.sqrt(np.repeat(w, 3))
    J = np.zeros((M, 3, 6 + K))
    # omega x y_m = -[y_m]_x omega
    J[:, 0, 1], J[:, 0, 2] = Y[:, 2], -Y[:, 1]
    J[:, 1, 0], J[:, 1, 2] = -Y[:, 2], Y[:, 0]
    J[:, 2, 0], J[:, 2, 1] = Y[:, 1], -Y[:, 0]
    J[:, :, 3:6] = np.eye(3)
    J[:, :, 6:] = B.reshape(M, 3, K)
    Jw = J.reshape(3 * M, -1) * sw[:, None]
    pinv = np.linalg.pinv(Jw)
    vis = np.all(np.isfinite(X), axis=2)
    gappy = np.flatnonzero(~vis.all(axis=1))
    vis3 = np.repeat(vis, 3, axis=1)
    R = np.array(R, dtype=np.float64, copy=True)
    t = np.array(t, dtype=np.float64, copy=True)
    for _ in range(int(iterations)):
        stab = np.einsum("fji,fmj->fmi", R, X - t[:, None, :])
        res = np.where(vis3, (stab - Y[None]).reshape(F, -1), 0.0) * sw
        sol = res @ pinv.T
        for f in gappy:
            sol[f] = np.linalg.lstsq(Jw[vis3[f]], res[f, vis3[f]], rcond=None)[0]
        Rd = Rotation.from_rotvec(sol[:, :3]).as_matrix()
        t = t + np.einsum("fij,fj->fi", R, sol[:, 3:6])
        R = R @ Rd
    stab = np.einsum("fji,fmj->fmi", R, X - t[:, None, :])
    return stab, R, t


def head_motion_about_pivot(R: np.ndarray, t: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """Translation of ``pivot`` (3,) under the head motion: ``d_f = R_f p + t_f - p`` (F, 3) mm.

    With it the motion reads ``x' = R_f (x - p) + p + d_f``, which can be re-applied to a target
    whose own pivot plays the role of ``p`` (:func:`apply_head_motion`).
    """
    p = np.asarray(pivot, dtype=np.float64)
    return np.einsum("fij,j->fi", R, p) + t - p


def apply_head_motion(points: np.ndarray, R: np.ndarray, pivot_translation: np.ndarray,
                      pivot: np.ndarray) -> np.ndarray:
    """Re-apply a head motion to target geometry (sec. 7, fig. 15).

    points : (F, N, 3) or (N, 3) target positions without head motion; R : (F, 3, 3);
    pivot_translation : (F, 3) from :func:`head_motion_about_pivot`; pivot : (3,) the target's pivot
    (e.g. the centroid of its neutral markers). Returns (F, N, 3) ``R_f (x - pivot) + pivot + d_f``.
    """
    P = np.asarray(points, dtype=np.float64)
    if P.ndim == 2:
        P = np.broadcast_to(P, (R.shape[0],) + P.shape)
    c = np.asarray(pivot, dtype=np.float64)
    return np.einsum("fij,fnj->fni", R, P - c) + c + np.asarray(pivot_translation)[:, None, :]


def fill_marker_gaps(markers: np.ndarray) -> np.ndarray:
    """Fill NaN gaps (F, M, 3) by linear interpolation in time per marker (ends hold the nearest
    sample). A marker missing in every frame is an :class:`InputError`."""
    X = np.array(markers, dtype=np.float64, copy=True)
    F, M, _ = X.shape
    valid = np.all(np.isfinite(X), axis=2)
    frames = np.arange(F)
    for j in np.flatnonzero(~valid.all(axis=0)):
        ok = valid[:, j]
        if not ok.any():
            raise InputError(f"marker {j} has no sample in any frame", fix="drop it from the marker map")
        for c in range(3):
            X[:, j, c] = np.interp(frames, frames[ok], X[ok, j, c])
    return X


# ------------------------------------------------------------------------- sec. 3.2 RBF warp
#: ``d(x) = sum_i w_i |x - c_i| + a_0 + A x`` (sec. 3.2): a :class:`~rigbuild.retarget.proportion.ProportionMap`
#: with ``phi(r) = r`` (centers (n, 3); weights (n, 3); affine (4, 3) rows [1, x, y, z]).
RbfWarp = ProportionMap


def fit_rbf_warp(centers: np.ndarray, targets: np.ndarray) -> RbfWarp:
    """Fit the interpolating RBF with ``phi(r) = r`` plus a linear polynomial: ``d(c_i) = targets_i``.

    centers : (n, 3) target-neutral marker positions; targets : (n, 3) source-neutral positions.
    Solves ``[[Phi, P], [P^T, 0]] [w; a] = [targets; 0]`` (n + 4 unknowns per coordinate); ``d``
    reproduces affine maps exactly. Needs n >= 4 non-coplanar centers.
    (:func:`rigbuild.retarget.proportion.fit_proportion_map` with ``kernel="r"``.)
    """
    return fit_proportion_map(centers, targets, "r")


def scale_proportion_match(
    target_neutral: np.ndarray, target_deltas: np.ndarray, source_neutral: np.ndarray
) -> tuple[np.ndarray, np.ndarray, RbfWarp]:
    """Deform the target's marker blendshapes to the source's scale and proportion (sec. 3.2).

    target_neutral : (M, 3) target neutral markers; target_deltas : (K, M, 3) marker deltas of the
    target's shapes; source_neutral : (M, 3) source neutral markers (all mm).
    Returns ``neutral* = d(n)`` (= source_neutral up to round-off), ``deltas*_k = d(n + b_k) - d(n)``
    (K, M, 3), and the warp ``d``.
    """
    warp = fit_rbf_warp(target_neutral, source_neutral)
    n_star = warp(target_neutral)
    shapes_star = warp(np.asarray(target_neutral)[None] + np.asarray(target_deltas))
    return n_star, shapes_star - n_star[None], warp


# ---------------------------------------------------------------------------- sec. 5 PCA prior
@dataclass
class PcaPrior:
    """PCA of the target's blendshapes taken as frames (sec. 5).

    eigvecs : (3M, h) orthonormal ``E``; eigvals : (h,) ``lambda_k`` (mm^2, non-zero ones only);
    mean_delta : (3M,) ``t_bar - n_tgt`` (mean of the training deltas).
    """

    eigvecs: np.ndarray
    eigvals: np.ndarray
    mean_delta: np.ndarray

    def coefficients(self, deltas: np.ndarray) -> np.ndarray:
        """``v = E^T (B w + n_tgt - t_bar)`` for flattened deltas (..., 3M) -> (..., h)."""
        return (np.asarray(deltas) - self.mean_delta) @ self.eigvecs

    def energy(self, deltas: np.ndarray) -> np.ndarray:
        """``E_prior = v^T Lambda^-1 v`` per row of (..., 3M) deltas."""
        v = self.coefficients(deltas)
        return (v * v / self.eigvals).sum(-1)

    def quadratic(self, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``E_prior(w) = w^T P w - 2 p^T w + const`` for ``B`` (3M, K): returns P (K, K), p (K,)."""
        EB = self.eigvecs.T @ B
        EBs = EB / self.eigvals[:, None]
        P = EB.T @ EBs
        p = EBs.T @ (self.eigvecs.T @ self.mean_delta)
        return 0.5 * (P + P.T), p


def build_pca_prior(training_deltas: np.ndarray, rel_tol: float = 1e-9) -> PcaPrior:
    """PCA prior from training shapes (sec. 5): by default the target's own blendshape deltas, one
    shape per "frame" (more animation frames of the target can be appended).

    training_deltas : (N, 3M) flattened marker deltas (mm). Eigenvalues are those of the sample
    covariance (divided by N); components with ``lambda <= rel_tol * lambda_max`` are dropped (the
    paper keeps the ``h`` eigenvectors with non-zero eigenvalues).
    """
    X = np.asarray(training_deltas, dtype=np.float64)
    mean = X.mean(0)
    Xc = X - mean
    _, sv, Vt = np.linalg.svd(Xc, full_matrices=False)
    lam = sv**2 / X.shape[0]
    keep = lam > rel_tol * max(lam.max(initial=0.0), 1e-300)
    if not keep.any():
        raise InputError("PCA prior: the training shapes do not move the markers")
    return PcaPrior(eigvecs=Vt[keep].T.copy(), eigvals=lam[keep], mean_delta=mean)


# -------------------------------------------------------------------- sec. 7.1 Sobolev weights
def sobolev_beta(marker_names: Sequence[str], region_betas: Mapping[str, float],
                 n_frames: int | None = None, frames: Sequence[int] | None = None) -> np.ndarray:
    """Per-marker Sobolev weights ``beta`` (sec. 7.1) from regions given as name patterns.

    region_betas : ``{regex: beta}`` matched (case-insensitive, ``re.search``) against marker names,
    e.g. ``{"lip|mouth": 1.0, "lid": 0.5}``; a marker takes the largest matching beta, else 0.
    frames : if given (with ``n_frames``), beta applies only at those frames (e.g. where the lips
    must close) and the result is (n_frames, M); otherwise (M,) for every frame.
    """
    beta = np.zeros(len(marker_names))
    for pattern, value in region_betas.items():
        rx = re.compile(pattern, re.IGNORECASE)
        hit = np.array([bool(rx.search(n)) for n in marker_names])
        beta[hit] = np.maximum(beta[hit], float(value))
    if frames is None:
        return beta
    if n_frames is None:
        raise InputError("sobolev_beta: frames given without n_frames")
    out = np.zeros((n_frames, beta.size))
    fr = _frame_indices(frames, n_frames, "Sobolev frames")
    out[fr] = beta
    return out


def sobolev_beta_from_corner_hz(n_markers: int, corner_hz: float, fps: float) -> np.ndarray:
    """(M,) uniform sec. 7.1 Sobolev weights ``beta = (2 pi corner_hz / fps)^2`` for every marker.

    Per temporal frequency ``w`` (radians per frame) the velocity term weighs a residual by
    ``2 - 2 cos w ~ w^2`` and the position term by ``beta``: with this beta, residual motion slower
    than ``corner_hz`` is charged as position error (no drift of the weights over a long take, e.g.
    after a gap or against the prior's pull), faster motion as velocity error (the paper's movement
    matching). Independent of units and marker count; 1 Hz at 60 fps gives 0.011.
    """
    if corner_hz < 0 or fps <= 0:
        raise InputError(f"Sobolev corner {corner_hz} Hz at {fps} fps", fix="use corner_hz >= 0 and fps > 0")
    return np.full(int(n_markers), (2.0 * np.pi * float(corner_hz) / float(fps)) ** 2)


# ---------------------------------------------------------------------- block tridiagonal solvers
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


def _frame_indices(frames: Sequence[int], n_frames: int, what: str) -> np.ndarray:
    out = []
    for f in frames:
        fi = int(f)
        if fi < -n_frames or fi >= n_frames:
            raise InputError(
                f"{what}: frame {fi} is outside the sequence (frames 0..{n_frames - 1})",
                fix=f"use frames between 0 and {n_frames - 1} (negative values count from the end)",
            )
        out.append(fi % n_frames)
    return np.asarray(out, dtype=np.int64)


#: most active-set passes of the bounded spacetime solve in :func:`retarget_seol`
BOUNDED_MAX_PASSES = 200


def weight_interval(bounds: Sequence[float]) -> tuple[float, float]:
    """``(lo, hi)`` as floats; :class:`InputError` unless ``lo < hi``."""
    lo, hi = (float(v) for v in bounds)
    if not lo < hi:
        raise InputError(f"weight bounds {list(bounds)} are not an interval", path="config",
                         fix="give [low, high] with low < high, e.g. [0, 1]")
    return lo, hi


# ------------------------------------------------------------------------------ the system
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
            return _solve_pinned_block_tridiagonal(*self._quadratic(start, stop), mask, vals)
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
        return _solve_pinned_block_tridiagonal(*self._quadratic(start, stop), mask, vals)

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
        W = np.asarray(W, dtype=np.float64)
        g = np.einsum("tij,tj->ti", A, W) - r
        if W.shape[0] > 1:
            g[:-1] += np.einsum("tij,tj->ti", U, W[1:])
            g[1:] += np.einsum("tji,tj->ti", U, W[:-1])
        return g

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
                      stop: int | None = None) -> tuple[np.ndarray, int]:
        """:meth:`solve` with every free weight kept in ``bounds`` = (lo, hi) (not in the paper).

        Primal-dual active set (Hintermueller, Ito and Kunisch 2002): from the unconstrained minimizer's
        violations, each pass solves with the bound pins, keeps the pins whose Lagrange multiplier (the energy's
        gradient, :meth:`gradient`) has the right sign and pins every free weight outside the bounds; it
        stops when a global pass no longer changes the sets (a KKT point). A pass that changes the sets in
        few frames is followed by local passes over those frames (:data:`LOCAL_PASS_FRACTION`; the other
        frames keep their weights) until they settle, then a global pass checks. When a set repeats (the primal-dual passes can
        cycle) the monotone primal method finishes: from a feasible point, step towards each pass's
        solution up to the first bound crossed (pinning it), and at a feasible minimizer release the pins
        whose multiplier has the wrong sign; the energy falls every pass, so it cannot cycle. After
        ``max_iterations`` the weights are clipped. Each pass solves only the free weights
        (:func:`solve_block_tridiagonal_free`). Each pass is the exact spacetime minimizer under its
        pins, so the movement matching is re-solved around the bound instead of being cut off as a clamp
        would. ``bounds`` defaults to the system's; ``start``/``stop`` as in :meth:`solve`.
        Returns (W (n, K) within bounds, passes).
        """
        bounds = self.bounds if bounds is None else bounds
        if bounds is None:
            raise InputError("solve_bounded needs bounds (the system has none)", fix="pass bounds=(lo, hi)")
        lo, hi = weight_interval(bounds)
        # the energy does not change between passes, only the pins: assemble it once (half of a pass's time)
        quad = self._quadratic(start, stop)
        user = np.array(pin_mask, dtype=bool, copy=True)
        if user.shape != quad[2].shape or np.shape(pin_values) != quad[2].shape:
            raise InputError(f"pins must be {quad[2].shape}, got {user.shape}")
        vals = np.where(user, np.asarray(pin_values, dtype=np.float64), 0.0)
        W = _solve_pinned_block_tridiagonal(*quad, user, vals)  # the unconstrained minimizer: first guess
        at_lo = ~user & (W < lo)
        at_hi = ~user & (W > hi)
        seen: set[bytes] = set()
        primal = False
        window = None  # frames of a local pass (None: a global pass)
        for it in range(1, max_iterations + 1):
            fixed = user | at_lo | at_hi
            v = np.where(at_lo, lo, np.where(at_hi, hi, vals))
            if window is None:
                W_new = _solve_pinned_block_tridiagonal(*quad, fixed, v)
            else:  # local pass: the frames outside the window keep their weights
                out = np.broadcast_to(~window[:, None], fixed.shape)
                W_new = _solve_pinned_block_tridiagonal(*quad, fixed | out, np.where(out, W, v))
            g = self.gradient(W_new, start, stop, quad)
            scale = tolerance * max(1.0, float(np.abs(g).max()))
            free = ~fixed
            below, above = free & (W_new < lo - tolerance), free & (W_new > hi + tolerance)
            if not primal:
                # primal-dual pass: keep a bound whose multiplier has the right sign, add every violator
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
                    if key in seen:  # the primal-dual passes cycle: finish with the monotone primal method
                        primal = True
                        W = np.clip(W_new, lo, hi)
                        at_lo, at_hi = ~user & (W <= lo), ~user & (W >= hi)
                        continue
                    seen.add(key)
                    seen_local: set[bytes] = set()
                elif key in seen_local:  # the local passes cycle: back to global passes
                    window = None
                    at_lo, at_hi = new_lo, new_hi
                    continue
                seen_local.add(key)
                # few frames changed: the next passes re-solve only around them
                window = _dilate_frames(changed, LOCAL_PASS_HALO) if changed.mean() < LOCAL_PASS_FRACTION else None
            elif below.any() or above.any():
                # primal pass from the feasible W: step towards W_new up to the first bound it crosses
                d = W_new - W
                with np.errstate(divide="ignore", invalid="ignore"):
                    ratio = np.where(below, (lo - W) / d, np.where(above, (hi - W) / d, np.inf))
                step = float(np.clip(ratio.min(), 0.0, 1.0))
                W = np.clip(W + step * d, lo, hi)
                block = (below | above) & (ratio <= step + 1e-12)
                new_lo, new_hi = at_lo | (block & below), at_hi | (block & above)
            else:
                # feasible minimizer under the pins: release every pin whose multiplier has the wrong sign
                W = W_new
                new_lo = at_lo & ~(g < -scale)
                new_hi = at_hi & ~(g > scale)
            if np.array_equal(new_lo, at_lo) and np.array_equal(new_hi, at_hi) and not (below.any() or above.any()):
                return W, it
            at_lo, at_hi = new_lo, new_hi
        return np.clip(W, lo, hi), max_iterations + 1

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


def shape_index(shape_names: Sequence[str], name: str) -> int:
    """Index of ``name`` in ``shape_names``; :class:`InputError` listing the known names if absent."""
    try:
        return list(shape_names).index(name)
    except ValueError:
        raise InputError(f"weight name '{name}' is not a shape of the rig",
                         fix=f"use one of: {', '.join(shape_names)}") from None


# -------------------------------------------------------------------- sec. 7 per-frame baselines
def _perframe_normal(B: np.ndarray, S: np.ndarray, visibility: np.ndarray | None):
    """Per-frame normal equations with gaps left out: ``G_t = B_vis^T B_vis`` (F, K, K) or None when
    every marker is seen (then ``G = B^T B`` for all frames), and ``B_vis^T s_t`` (F, K)."""
    S = np.asarray(S, dtype=np.float64)
    if visibility is None or np.all(visibility):
        return None, S @ B
    vis3 = np.repeat(np.asarray(visibility, bool), 3, axis=1)
    rhs = np.where(vis3, S, 0.0) @ B
    K = B.shape[1]
    Gt = np.broadcast_to(B.T @ B, (S.shape[0], K, K)).copy()
    B3 = B.reshape(-1, 3, K)
    vis = np.asarray(visibility, bool)
    for f in np.flatnonzero(~vis.all(axis=1)):
        Bm = B3[~vis[f]].reshape(-1, K)
        Gt[f] -= Bm.T @ Bm
    return Gt, rhs


def solve_perframe_unconstrained(B: np.ndarray, S: np.ndarray, visibility: np.ndarray | None = None) -> np.ndarray:
    """"No Const": ``min ||B w_t - s_t||^2`` per frame (least squares over the markers seen at t when
    ``visibility`` (F, M) is given). B (3M, K), S (F, 3M) -> (F, K). Where the markers seen at t leave shapes
    unobserved (occlusion gaps), the minimum-norm least-squares weights (those shapes at 0)."""
    Gt, rhs = _perframe_normal(B, S, visibility)
    if Gt is None:
        return np.linalg.lstsq(B, np.asarray(S).T, rcond=None)[0].T
    try:
        return np.linalg.solve(Gt, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return (np.linalg.pinv(Gt, hermitian=True) @ rhs[..., None])[..., 0]


def solve_perframe_prior(B: np.ndarray, S: np.ndarray, prior_P: np.ndarray, prior_p: np.ndarray,
                         alpha: float = DEFAULT_ALPHA_PERFRAME, visibility: np.ndarray | None = None,
                         bounds: tuple[float, float] | None = None, sparsity: float = 0.0) -> np.ndarray:
    """"Prior PF": ``min ||B w_t - s_t||^2 + alpha E_prior(w_t)`` per frame (closed form). (F, K).

    ``bounds`` (lo, hi) and ``sparsity`` (``+ sparsity 1^T w_t``, the L1 norm on weights >= 0): the same
    constraints as a bounded spacetime solve (:attr:`SeolSystem.bounds`, :attr:`SeolSystem.sparsity`), so
    the two differ only by the movement matching; solved exactly per frame by bounded-variable least
    squares on the Cholesky factor of ``G_t + alpha P``."""
    Gt, rhs = _perframe_normal(B, S, visibility)
    if bounds is None:
        if sparsity:
            raise InputError("the per-frame sparsity term needs bounds with a non-negative low end")
        if Gt is None:
            A = B.T @ B + alpha * prior_P
            return np.linalg.solve(A, (rhs + alpha * prior_p).T).T
        return np.linalg.solve(Gt + alpha * prior_P, (rhs + alpha * prior_p)[..., None])[..., 0]
    return _bounded_perframe(B.T @ B + alpha * prior_P, None if Gt is None else Gt + alpha * prior_P,
                             rhs + alpha * prior_p - 0.5 * float(sparsity), bounds)


def _bounded_perframe(G: np.ndarray, Gt: np.ndarray | None, rhs: np.ndarray, bounds: tuple[float, float],
                      tol: float = 1e-12) -> np.ndarray:
    """``min_w w^T G_t w - 2 rhs_t^T w`` subject to ``lo <= w <= hi`` for every frame t: bounded-variable
    least squares ``||C^T w - C^-1 rhs_t||`` with ``G_t = C C^T`` (same minimizer). G (K, K) shared or
    Gt (F, K, K) per frame; rhs (F, K) -> (F, K)."""
    from scipy.optimize import lsq_linear

    lo, hi = float(bounds[0]), float(bounds[1])
    K = G.shape[0]
    eps = 1e-12 * max(np.trace(G) / K, 1e-12) * np.eye(K)
    C = np.linalg.cholesky(G + eps)
    out = np.empty((rhs.shape[0], K))
    for f, b in enumerate(rhs):
        Cf = C if Gt is None else np.linalg.cholesky(Gt[f] + eps)
        r = scipy.linalg.solve_triangular(Cf, b, lower=True)
        out[f] = lsq_linear(Cf.T, r, bounds=(lo, hi), method="bvls", tol=tol).x
    return out


def solve_perframe_range(B: np.ndarray, S: np.ndarray, bounds: tuple[float, float] = DEFAULT_WEIGHT_RANGE,
                         tol: float = 1e-12, visibility: np.ndarray | None = None) -> np.ndarray:
    """"Range PF": ``min ||B w_t - s_t||^2`` subject to ``lo <= w <= hi`` per frame (Bregler et al. 2002).

    Exact bounded-variable least squares (scipy ``lsq_linear``, method ``bvls``) per frame on the
    reduced K x K problem ``||C^T w - C^-1 B^T s_t||`` with ``B^T B = C C^T`` (same minimizer; with
    ``visibility`` the per-frame ``B_vis^T B_vis``). B (3M, K), S (F, 3M) -> (F, K).
    """
    Gt, rhs_all = _perframe_normal(B, S, visibility)
    return _bounded_perframe(B.T @ B, Gt, rhs_all, bounds, tol)


# --------------------------------------------------------------------------- fig. 11 error
def velocity_error_per_frame(W: np.ndarray, B: np.ndarray, S: np.ndarray,
                             visibility: np.ndarray | None = None) -> np.ndarray:
    """``||B (w_t - w_{t-1}) - (s_t - s_{t-1})||^2`` per frame (F,) mm^2 (frame 0: 0). Its sum is the
    paper's ``||D (B W)^T - D S^T||_F^2`` (fig. 11 (a)); per-frame curves are fig. 11 (b). With
    ``visibility`` (F, M) only markers seen at both t-1 and t count (gaps have no measured velocity)."""
    S = np.asarray(S, dtype=np.float64)
    R = np.diff(np.asarray(W), axis=0) @ B.T - np.diff(S, axis=0)
    if visibility is not None:
        vis = np.asarray(visibility, bool)
        R = np.where(np.repeat(vis[1:] & vis[:-1], 3, axis=1), R, 0.0)
    out = np.zeros(np.asarray(W).shape[0])
    out[1:] = (R * R).sum(1)
    return out


# ------------------------------------------------------------------- prior strength and training
def alpha_from_corner_hz(corner_hz: float, B: np.ndarray, prior_P: np.ndarray, fps: float) -> float:
    """The prior weight ``alpha`` of eq. (4) for a prior strength given as a corner frequency (Hz).

    In the velocity domain a positional prior acts, per generalized eigendirection ``k`` of
    ``(P, G = B^T B)`` with eigenvalue ``mu_k``, as the temporal high-pass ``L(w) / (L(w) + alpha mu_k)``
    (``L(w) = 2 - 2 cos w``, w in radians per frame): motion slower than ``w_k = sqrt(alpha mu_k)`` is
    pulled to the prior's mean. Taking the mean ratio ``mu = tr(P) / tr(G)`` (per mm^2 of marker
    motion) and ``w = 2 pi corner_hz / fps`` gives ``alpha = (2 pi corner_hz / fps)^2 tr(G) / tr(P)``.
    This alpha does not depend on the unit of length (mm vs cm), the number of markers (``tr G``
    grows with it, ``P`` does not), the number of shapes or training frames, the frame rate, or the
    length of the take. The paper's ``alpha = 0.01`` was for its own units/markers/fps.
    """
    trP = float(np.trace(prior_P))
    if trP <= 0:
        raise InputError("the prior matrix has no positive curvature (empty training set?)")
    return float((2 * np.pi * corner_hz / fps) ** 2 * np.trace(B.T @ B) / trP)


def corner_hz_from_alpha(alpha: float, B: np.ndarray, prior_P: np.ndarray, fps: float) -> float:
    """Inverse of :func:`alpha_from_corner_hz`: the mean corner frequency (Hz) of a raw ``alpha``."""
    return float(fps / (2 * np.pi) * np.sqrt(max(alpha, 0.0) * np.trace(prior_P) / np.trace(B.T @ B)))


def sparse_combination_weights(n_shapes: int, n_frames: int = 2000, density: float = 0.15,
                               seed: int = 0) -> np.ndarray:
    """(n_frames, K) weight vectors of a synthetic "animation of the target" for the PCA prior (sec. 5
    allows any target animation as training data; fig. 13 (d) adds expressive poses): every shape is
    on with probability ``density`` at a weight uniform in [0, 1].

    Why: with the paper's training set (one blendshape per frame, plus the neutral) and a full-rank
    ``B`` the prior is exactly ``E_prior = (K+1) (|w - c|^2 + (1^T (w - c))^2)``, ``c = 1/(K+1)``: it
    does not depend on the shapes at all and charges the *sum* of the weights K+1 times more than any
    single weight (the training poses never combine shapes). Real performances combine many shapes, so
    that prior pushes the cheapest (small, nearly collinear) shapes negative. Adding combinations
    removes the sum penalty.
    """
    rng = np.random.default_rng(seed)
    return (rng.random((n_frames, n_shapes)) < density) * rng.random((n_frames, n_shapes))


# --------------------------------------------------------------------------- the whole method
@dataclass
class SeolResult:
    """weights (F, K) of the spacetime solution; shape_names; head_rotation (F, 3, 3) and
    head_translation (F, 3) = pivot translation of the source head (re-apply with
    :func:`apply_head_motion` about ``target_pivot``); system for edits; baselines {name: (F, K)};
    velocity_error {name: (F,)} per-frame curves (fig. 11) for "spacetime" and every baseline."""

    weights: np.ndarray
    shape_names: list[str]
    head_rotation: np.ndarray
    head_translation: np.ndarray
    source_pivot: np.ndarray
    target_pivot: np.ndarray
    system: SeolSystem
    warp: RbfWarp
    baselines: dict[str, np.ndarray] = field(default_factory=dict)
    velocity_error: dict[str, np.ndarray] = field(default_factory=dict)
    alpha: float = DEFAULT_ALPHA


def target_marker_blendshapes(target: Rig, marker_names: Sequence[str] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The target's neutral markers (M, 3) and marker deltas (K, M, 3), in ``marker_names`` order
    (default: the rig's marker order), mm."""
    rig = target if target.units == "mm" else target.to_units("mm")
    idx = _marker_vertex_ids(rig, marker_names)
    return rig.neutral[idx], rig.deltas[:, idx, :]


def _marker_vertex_ids(rig: Rig, marker_names: Sequence[str] | None) -> np.ndarray:
    """(M,) vertex ids of ``marker_names`` on ``rig`` (default: the rig's marker order)."""
    if rig.marker_vertices.size == 0:
        raise InputError(f"target rig '{rig.name}' has no marker set", fix="attach the marker set (Rig.with_markers)")
    if marker_names is None:
        return np.asarray(rig.marker_vertices)
    pos = {n: i for i, n in enumerate(rig.marker_names)}
    missing = [n for n in marker_names if n not in pos]
    if missing:
        raise InputError(f"markers {missing} are not on target rig '{rig.name}'",
                         fix="use a marker map whose names exist on the target rig")
    return np.asarray(rig.marker_vertices)[[pos[n] for n in marker_names]]


def retarget_seol(
    source_markers: np.ndarray,
    target: Rig,
    marker_names: Sequence[str] | None = None,
    source_neutral: np.ndarray | None = None,
    params: SeolParams | None = None,
    *,
    fps: float | None = None,
    beta: np.ndarray | None = None,
    prior_training: np.ndarray | None = None,
    remove_head: bool = True,
    baselines: bool = True,
    source_path: str | os.PathLike | None = None,
    **options,
) -> SeolResult:
    """Retarget a marker performance onto a blendshape target (Seol et al. 2012, all sections).

    Parameters
    ----------
    source_markers : (F, M, 3) mm, world space (or head-stabilized with ``remove_head=False``), NaN
        for gaps; markers in the order of ``marker_names``.
    target : the target rig with a marker set; markers are picked by ``marker_names`` (default: the
        rig's own marker order, which must then match the source's).
    source_neutral : (M, 3) the actor's neutral markers; default the first frame (the paper's actor
        holds a neutral face at the start). Used for Procrustes (sec. 3.1), the RBF (sec. 3.2) and as
        the origin of the displacements ``S``.
    params : :class:`~rigbuild.retarget.params.SeolParams` (``params.retarget.seol``; default: the paper's
        settings); ``**options`` override single fields (``alpha=1e-4, gaps="interpolate"``). Its fields:

        - ``alpha`` (eq. 4) or ``prior_corner_hz`` (the prior strength as a corner frequency,
          :func:`alpha_from_corner_hz`; independent of units, marker count and frame rate; needs ``fps``);
        - ``boundary_frames``, ``boundary_values`` (``"neutral"``: all weights 0 there, the paper's protocol;
          ``"perframe"``: the Range-PF per-frame solution, for takes that do not start and end on a
          neutral face) and ``pins`` ``{frame: {shape: value}}`` or ``{frame: (K,) weights}``;
        - ``rigid_weights``: ``"rigidity"`` (markers the target's shapes move little count more in
          Procrustes, :func:`rigbuild.retarget.common.rigidity_weights` of the scale-matched shapes) or
          ``"uniform"`` (the paper); ``head_refine_iterations``: Gauss-Newton refinements of the head motion
          jointly with per-frame weights (:func:`refine_head_motion`; 0 = the paper's plain Procrustes);
        - ``sobolev`` / ``sobolev_corner_hz``: the sec. 7.1 term (:func:`sobolev_beta`,
          :func:`sobolev_beta_from_corner_hz`), used when ``beta`` is not given;
        - ``gaps``: ``"mask"`` (marker gaps left out of every energy term, of the head-motion fits and of
          the baselines; :class:`SeolSystem` ``visibility``) or ``"interpolate"`` (filled linearly in time
          first; the paper does not discuss gaps, and interpolation invents motion during a gap);
        - ``prior_combinations``, ``prior_combination_density``: a sparse-combination training set of the
          PCA prior (:func:`sparse_combination_weights`), used when ``prior_training`` is not given;
        - ``scale_match``: how the target's marker blendshapes are carried into the source's proportions
          (:mod:`rigbuild.retarget.proportion`): ``"rbf"`` (sec. 3.2, the paper: ``d(n + b) - d(n)``),
          ``"deformation"`` (the target's blendshapes deformation-transferred onto the RBF-warped target
          mesh), ``"jacobian"``, ``"local_affine"``, ``"affine"`` or ``"none"`` (the target's own marker
          deltas); ``scale_match_kernel``: the RBF's ``phi`` (``"r"`` the paper, ``"r3"``, ``"tps"``);
        - ``marker_lowpass_hz``: zero-phase low-pass of the source markers before anything else
          (:func:`rigbuild.retarget.common.lowpass_markers`; needs ``fps``; not in the paper: its velocity
          matching passes marker noise into the weights wherever the prior is weaker than the data);
        - ``weight_bounds`` (lo, hi): the spacetime solution kept in the rig's weight range
          (:meth:`SeolSystem.solve_bounded`; the paper's is unconstrained); ``sparsity``: an L1 term
          ``sparsity * sum |w|`` (mm^2 per unit weight; Ribera et al. 2017's E_Sparse, not in the paper;
          needs ``weight_bounds`` from 0);
        - ``alpha_perframe``, ``weight_range``: the "Prior PF" and "Range PF" baselines (sec. 7).
    fps : frames per second of the take (for ``prior_corner_hz``, ``sobolev_corner_hz``, the low-pass).
    beta : Sobolev weights (M,) or (F, M) (sec. 7.1), overriding ``sobolev`` / ``sobolev_corner_hz``.
    prior_training : (N, K) extra target weight vectors ("animations of the target") added to the PCA
        training set after the neutral and the one-shape-per-frame set; overrides ``prior_combinations``.
    remove_head : remove the head motion (sec. 3.1); False for head-stabilized markers.
    baselines : also compute the sec. 7 per-frame baselines and all velocity-error curves.
    source_path : the take's file, named in errors and warnings.

    Occlusion gaps: head motion is fitted on each frame's visible markers and bridged over frames with fewer
    than half of them (:func:`min_visible_markers`, :func:`remove_head_motion`); such frames' markers are
    then filled by interpolation in time
    (:func:`bridge_sparse_frames`) so the movement matching stays connected across them; other gaps follow
    ``gaps``.

    With ``weight_bounds`` or ``sparsity`` the spacetime solve is no longer the paper's: the "perframe_prior"
    baseline then gets the same bounds and sparsity (the comparison isolates the movement matching, as in
    fig. 11), and the paper's unconstrained spacetime solution is added as ``baselines["spacetime_paper"]``.

    Returns :class:`SeolResult`.
    """
    p = _with_options(params, options)
    X, Y, n_tgt, d_star, warp = _matched_source_and_target(source_markers, target, marker_names, source_neutral, p,
                                                           fps)
    F, M, _ = X.shape
    K = d_star.shape[0]
    B = d_star.reshape(K, -1).T
    R, t, stab = _stabilized(X, Y, B, d_star, p, remove_head, source_path)
    stab = bridge_sparse_frames(stab, source_path, min_visible_markers(M))
    vis = np.all(np.isfinite(stab), axis=2)
    if vis.all():
        vis = None
    S = (stab - Y[None]).reshape(F, -1)
    src_pivot = Y.mean(0)
    head_d = head_motion_about_pivot(R, t, src_pivot)
    mnames = list(marker_names) if marker_names is not None else list(target.marker_names)
    if prior_training is None and int(p.prior_combinations or 0) > 0:
        prior_training = sparse_combination_weights(K, int(p.prior_combinations), float(p.prior_combination_density))
    P, pp, alpha = _prior(d_star, B, prior_training, p, fps)
    if beta is None:
        beta = _sobolev_from_params(p, mnames, F, fps)
    names = list(target.shape_names)
    system = SeolSystem(B=B, S=S, prior_P=P, prior_p=pp, alpha=alpha, beta=beta, ridge=SPACETIME_RIDGE,
                        shape_names=names, marker_names=mnames, visibility=vis,
                        bounds=None if p.weight_bounds is None else tuple(p.weight_bounds),
                        sparsity=float(p.sparsity or 0.0))
    S = system.S  # gaps zeroed (ignored through visibility)
    mask, vals = _boundary_pins(system, p, B, S, vis, F)
    W = _solve_spacetime(system, mask, vals)
    result = SeolResult(weights=W, shape_names=names, head_rotation=R, head_translation=head_d,
                        source_pivot=src_pivot, target_pivot=n_tgt.mean(0), system=system, warp=warp,
                        alpha=float(alpha))
    result.velocity_error["spacetime"] = velocity_error_per_frame(W, B, S, vis)
    if baselines:
        _add_baselines(result, system, B, S, P, pp, p, mask, vals, vis)
    return result


#: Tikhonov weight of the spacetime system (:class:`SeolSystem` ``ridge``)
SPACETIME_RIDGE = 1e-6
#: neighbourhood size of ``scale_match = "local_affine"``
SCALE_MATCH_NEIGHBORS = 12


def _with_options(params: SeolParams | None, options: Mapping) -> SeolParams:
    """``params`` (default :class:`SeolParams`) with single fields overridden (unknown names fail)."""
    from rigbuild.params import check_keys

    base = params if params is not None else SeolParams()
    check_keys(options, [f.name for f in fields(SeolParams)], "retarget_seol")
    return replace(base, **options) if options else base


def _matched_source_and_target(source_markers, target: Rig, marker_names, source_neutral, p: SeolParams,
                               fps: float | None):
    """Source markers (F, M, 3) (low-passed), the source neutral Y (M, 3), the target's neutral markers and its
    marker blendshapes carried into the source's proportions (sec. 3.2): n_tgt (M, 3), d_star (K, M, 3), warp."""
    X = np.asarray(source_markers, dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != 3:
        raise InputError(f"source markers must be (F, M, 3), got {X.shape}")
    F, M, _ = X.shape
    if F < 2:
        raise InputError(f"the performance has {F} frame(s); spacetime retargeting needs at least 2")
    if p.marker_lowpass_hz is not None:
        X = lowpass_markers(X, fps, float(p.marker_lowpass_hz))
    n_tgt, d_tgt = target_marker_blendshapes(target, marker_names)
    if n_tgt.shape[0] != M:
        raise InputError(f"{M} source markers but {n_tgt.shape[0]} target markers",
                         fix="pass marker_names so both sides use the same markers")
    if source_neutral is None:
        source_neutral = fill_marker_gaps(X)[0] if not np.all(np.isfinite(X[0])) else X[0]
    Y = np.asarray(source_neutral, dtype=np.float64)
    if Y.shape != (M, 3) or not np.all(np.isfinite(Y)):
        raise InputError(f"source neutral must be a finite ({M}, 3) array, got {Y.shape}")
    if p.scale_match not in SCALE_MATCH_MODES:
        raise InputError(f"scale_match '{p.scale_match}' unknown", fix=f"use one of {list(SCALE_MATCH_MODES)}")
    mesh = mvid = None
    if p.scale_match == "deformation":
        mesh = target if target.units == "mm" else target.to_units("mm")
        mvid = _marker_vertex_ids(mesh, marker_names)
    _, d_star, warp = proportion_match(n_tgt, d_tgt, Y, p.scale_match, p.scale_match_kernel, SCALE_MATCH_NEIGHBORS,
                                       mesh=mesh, marker_vertices=mvid)
    if p.gaps not in GAP_MODES:
        raise InputError(f"gaps '{p.gaps}' unknown", fix="use 'mask' or 'interpolate'")
    if p.gaps == "interpolate":
        X = fill_marker_gaps(X)
    return X, Y, n_tgt, d_star, warp


#: a frame with fewer than this fraction of the markers visible is bridged (head motion and markers
#: interpolated in time): a few markers neither fix a head pose nor observe the shapes
MIN_VISIBLE_FRACTION = 0.5


def min_visible_markers(n_markers: int) -> int:
    """Visible markers a frame needs for its own head-motion fit and movement matching:
    ``max(3, ceil(MIN_VISIBLE_FRACTION * M))``."""
    return max(3, int(np.ceil(MIN_VISIBLE_FRACTION * n_markers)))


def bridge_sparse_frames(stab: np.ndarray, path: str | os.PathLike | None = None,
                         min_visible: int = 3) -> np.ndarray:
    """Stabilized markers (F, M, 3) with every frame that has fewer than ``min_visible`` visible markers
    filled by per-marker linear interpolation in time (:func:`fill_marker_gaps` on those frames only; a
    marker never seen stays a gap). A warning counts the frames. Returns a new array (or ``stab`` itself)."""
    vis = np.all(np.isfinite(stab), axis=2)
    sparse = vis.sum(1) < min_visible
    if not sparse.any():
        return stab
    if sparse.all():
        raise InputError(f"no frame of the take has {min_visible} visible markers", path=path,
                         fix="check the take's marker names against the character's marker map, or fill its gaps")
    src = np.where(sparse[:, None, None], np.nan, stab)  # interpolate from the frames with enough markers
    seen = np.all(np.isfinite(src), axis=2).any(0)
    filled = fill_marker_gaps(src[:, seen])
    out = np.array(stab, dtype=np.float64, copy=True)
    sub = out[:, seen]
    sub[sparse] = np.where(np.isfinite(sub[sparse]), sub[sparse], filled[sparse])
    out[:, seen] = sub
    logging.getLogger("rigbuild.retarget.seol").warning(
        "%s: %d frame(s) with fewer than %d visible markers: markers interpolated in time over them",
        path or "take", int(sparse.sum()), min_visible)
    return out


def _stabilized(X: np.ndarray, Y: np.ndarray, B: np.ndarray, d_star: np.ndarray, p: SeolParams,
                remove_head: bool, path: str | os.PathLike | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Head motion (sec. 3.1): R (F, 3, 3), t (F, 3) and the stabilized markers (F, M, 3)."""
    F = X.shape[0]
    if not remove_head:
        return np.broadcast_to(np.eye(3), (F, 3, 3)).copy(), np.zeros((F, 3)), X
    if p.rigid_weights not in RIGID_WEIGHTS:
        raise InputError(f"rigid_weights '{p.rigid_weights}' unknown", fix=f"use one of {list(RIGID_WEIGHTS)}")
    rigid_weights = None
    if p.rigid_weights == "rigidity":
        from rigbuild.retarget.common import rigidity_weights

        rigid_weights = rigidity_weights(d_star)
    need = min_visible_markers(X.shape[1])
    _, R, t = remove_head_motion(X, Y, rigid_weights, path, need)
    if int(p.head_refine_iterations) > 0:
        _, R, t = refine_head_motion(X, Y, B, R, t, rigid_weights, int(p.head_refine_iterations))
        # frames with too few markers keep the bridged head motion (their refinement is underdetermined)
        R, t = bridge_rigid_motion(R, t, np.all(np.isfinite(X), axis=2).sum(1) >= need)
    return R, t, np.einsum("fji,fmj->fmi", R, X - t[:, None, :])


def _prior(d_star: np.ndarray, B: np.ndarray, prior_training: np.ndarray | None, p: SeolParams,
           fps: float | None) -> tuple[np.ndarray, np.ndarray, float]:
    """The sec. 5 PCA prior's quadratic form (P (K, K), p (K,)) and the prior weight alpha.

    The training "animation": the neutral, then one blendshape per frame, then ``prior_training``. Without
    the neutral frame the centred PCA has near-zero eigenvalues along directions where all shapes agree,
    which makes the neutral itself implausible and drives large cancelling weights."""
    K = d_star.shape[0]
    flat = d_star.reshape(K, -1)
    train = np.vstack([np.zeros((1, flat.shape[1])), flat])
    if prior_training is not None:
        pt = np.asarray(prior_training, dtype=np.float64)
        if pt.ndim != 2 or pt.shape[1] != K:
            raise InputError(f"prior training weights must be (N, {K}), got {pt.shape}")
        train = np.vstack([train, pt @ flat])
    P, pp = build_pca_prior(train).quadratic(B)
    alpha = float(p.alpha)
    if p.prior_corner_hz is not None:
        if not fps or fps <= 0:
            raise InputError("prior_corner_hz needs the take's fps", fix="pass fps=<frames per second>")
        alpha = alpha_from_corner_hz(float(p.prior_corner_hz), B, P, float(fps))
    return P, pp, alpha


def _sobolev_from_params(p: SeolParams, marker_names: Sequence[str], n_frames: int,
                         fps: float | None) -> np.ndarray | None:
    """Sec. 7.1 weights from ``sobolev`` (regions, frames) and ``sobolev_corner_hz`` (their maximum), or None."""
    beta = None
    if p.sobolev:
        sob = p.sobolev
        beta = sobolev_beta(marker_names, sob.get("regions", {}), n_frames if sob.get("frames") else None,
                            sob.get("frames"))
    if p.sobolev_corner_hz is not None:
        if not fps:
            raise InputError("sobolev_corner_hz needs the take's fps", fix="pass fps=<frames per second>")
        uniform = sobolev_beta_from_corner_hz(len(marker_names), float(p.sobolev_corner_hz), float(fps))
        beta = uniform if beta is None else np.maximum(beta, uniform)
    return beta


def _boundary_pins(system: SeolSystem, p: SeolParams, B: np.ndarray, S: np.ndarray, vis: np.ndarray | None,
                   n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Pin mask and values (F, K) of the boundary frames and the extra pins."""
    pins = {int(f): v for f, v in (p.pins or {}).items()}
    if p.boundary_values == "neutral":
        return system.pins_for(p.boundary_frames, pins)
    if p.boundary_values == "perframe":
        fr = _frame_indices(p.boundary_frames, n_frames, "boundary frames")
        lim = tuple(p.weight_range) if p.weight_bounds is None else tuple(p.weight_bounds)
        bpins = {int(f): v for f, v in zip(fr, solve_perframe_range(
            B, S[fr], lim, visibility=None if vis is None else vis[fr]))}
        return system.pins_for((), {**bpins, **pins})
    raise InputError(f"boundary_values '{p.boundary_values}' unknown", fix="use 'neutral' or 'perframe'")


def _solve_spacetime(system: SeolSystem, mask: np.ndarray, vals: np.ndarray) -> np.ndarray:
    """The spacetime solution (F, K): unconstrained, or within ``system.bounds`` (active set)."""
    if system.bounds is None:
        return system.solve(mask, vals)
    W, passes = system.solve_bounded(mask, vals, max_iterations=BOUNDED_MAX_PASSES)
    if passes > BOUNDED_MAX_PASSES:
        logging.getLogger("rigbuild.retarget.seol").warning(
            "bounded spacetime solve: no KKT point after %d active-set passes; weights clipped to %s",
            BOUNDED_MAX_PASSES, list(system.bounds))
    return W


def _add_baselines(result: SeolResult, system: SeolSystem, B: np.ndarray, S: np.ndarray, P: np.ndarray, pp: np.ndarray,
                   p: SeolParams, mask: np.ndarray, vals: np.ndarray, vis: np.ndarray | None) -> None:
    """The sec. 7 per-frame baselines (and the paper's unconstrained spacetime solve when the spacetime
    solve is bounded) with their velocity-error curves, added to ``result``."""
    result.baselines["no_constraint"] = solve_perframe_unconstrained(B, S, vis)
    result.baselines["perframe_range"] = solve_perframe_range(B, S, tuple(p.weight_range), visibility=vis)
    result.baselines["perframe_prior"] = solve_perframe_prior(B, S, P, pp, float(p.alpha_perframe),
                                                              visibility=vis, bounds=system.bounds,
                                                              sparsity=system.sparsity)
    if system.bounds is not None:
        paper = replace(system, bounds=None, sparsity=0.0, visibility=vis)
        result.baselines["spacetime_paper"] = paper.solve(mask, vals)
    for name, Wb in result.baselines.items():
        result.velocity_error[name] = velocity_error_per_frame(Wb, B, S, vis)
