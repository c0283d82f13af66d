"""The per-frame baselines of Seol et al. 2012, sec. 7 / fig. 11 (no constraint, weights in a range, the PCA
prior) and the velocity error that compares them with the spacetime solution."""

from __future__ import annotations

import numpy as np
import scipy.linalg
from scipy.optimize import lsq_linear

from rigbuild.errors import InputError
from rigbuild.geometry.box_qp import solve_box_qp_batched
from rigbuild.retarget.params import DEFAULT_ALPHA_PERFRAME, DEFAULT_WEIGHT_RANGE

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
    the two differ only by the movement matching; solved exactly per frame as a box QP on ``G_t + alpha P``
    (:func:`_bounded_perframe`)."""
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
    """``min_w w^T G_t w - 2 rhs_t^T w`` subject to ``lo <= w <= hi`` for every frame t, exactly: every frame at
    once by block principal pivoting (:func:`rigbuild.geometry.box_qp.solve_box_qp_batched`); a frame it leaves
    unconverged is solved by bounded-variable least squares ``||C^T w - C^-1 rhs_t||`` with ``G_t = C C^T`` (the
    same minimizer). G (K, K) shared or Gt (F, K, K) per frame; rhs (F, K) -> (F, K). A ridge of 1e-12 of the mean
    diagonal keeps frames whose seen markers leave a shape unobserved positive definite."""
    lo, hi = float(bounds[0]), float(bounds[1])
    F, K = rhs.shape
    eps = 1e-12 * max(np.trace(G) / K, 1e-12) * np.eye(K)
    H = np.broadcast_to(G + eps, (F, K, K)) if Gt is None else Gt + eps
    out, converged = solve_box_qp_batched(H, -np.asarray(rhs, dtype=np.float64), lo, hi)
    for f in np.flatnonzero(~converged):
        C = np.linalg.cholesky(H[f])
        r = scipy.linalg.solve_triangular(C, rhs[f], lower=True)
        out[f] = lsq_linear(C.T, r, bounds=(lo, hi), method="bvls", tol=tol).x
    return out


def solve_perframe_range(B: np.ndarray, S: np.ndarray, bounds: tuple[float, float] = DEFAULT_WEIGHT_RANGE,
                         tol: float = 1e-12, visibility: np.ndarray | None = None) -> np.ndarray:
    """"Range PF": ``min ||B w_t - s_t||^2`` subject to ``lo <= w <= hi`` per frame (Bregler et al. 2002).

    Exact per frame: the box QP on the K x K normal equations ``B^T B`` (with ``visibility`` the per-frame
    ``B_vis^T B_vis``), every frame at once (:func:`_bounded_perframe`). B (3M, K), S (F, 3M) -> (F, K).
    """
    Gt, rhs_all = _perframe_normal(B, S, visibility)
    return _bounded_perframe(B.T @ B, Gt, rhs_all, bounds, tol)


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
