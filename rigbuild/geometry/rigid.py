"""Rigid and similarity alignment of corresponding point sets (weighted Kabsch / Umeyama)."""

from __future__ import annotations

import numpy as np


def fit_similarity(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None, scale: bool = True
) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares ``dst ~ s R src + t`` (Umeyama 1991), optionally weighted.

    Parameters
    ----------
    src, dst : (N, 3) corresponding points.
    weights : (N,) non-negative weights, or None for uniform.
    scale : if False, ``s`` is fixed to 1 (weighted Kabsch).

    Returns
    -------
    s : float scale; R : (3, 3) rotation (det +1); t : (3,) translation.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    w = np.ones(src.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    wsum = w.sum()
    if wsum <= 0:
        raise ValueError("fit_similarity: weights sum to zero")
    mu_s = (w[:, None] * src).sum(0) / wsum
    mu_d = (w[:, None] * dst).sum(0) / wsum
    a = src - mu_s
    b = dst - mu_d
    cov = (w[:, None] * b).T @ a / wsum
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    if scale:
        var_s = (w * (a * a).sum(1)).sum() / wsum
        s = float(np.trace(np.diag(S) @ D) / var_s) if var_s > 0 else 1.0
    else:
        s = 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def fit_rigid_motion(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted Kabsch: ``(R, t)`` minimizing ``sum_i w_i ||R src_i + t - dst_i||^2``."""
    _, R, t = fit_similarity(src, dst, weights, scale=False)
    return R, t


def apply_rigid(points: np.ndarray, R: np.ndarray, t: np.ndarray, s: float = 1.0) -> np.ndarray:
    """``s R p + t`` for points (..., 3)."""
    return s * np.asarray(points) @ np.asarray(R).T + np.asarray(t)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of rotation matrix ``R`` in degrees (robust near 0 and 180)."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    s = np.linalg.norm(np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])) / 2.0
    return float(np.degrees(np.arctan2(s, c)))


def fit_rigid_motion_batched(src: np.ndarray, dst: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted Kabsch for a batch: ``(R_b, t_b)`` minimizing ``sum_i w_bi ||R_b src_bi + t_b - dst_bi||^2``.

    src, dst : (B, N, 3); weights : (B, N) >= 0 (0 for a missing point; NaN in ``dst`` where ``w = 0`` is
    ignored). Returns R (B, 3, 3) (det +1), t (B, 3). A batch item with weights summing to 0 gets the identity.
    """
    src = np.asarray(src, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    dst = np.where(w[..., None] > 0, np.asarray(dst, dtype=np.float64), 0.0)
    wsum = w.sum(1)
    ok = wsum > 0
    ws = np.where(ok, wsum, 1.0)[:, None]
    mu_s = np.einsum("bn,bnc->bc", w, src) / ws
    mu_d = np.einsum("bn,bnc->bc", w, dst) / ws
    cov = np.einsum("bn,bni,bnj->bij", w, dst - mu_d[:, None], src - mu_s[:, None]) / ws[:, :, None]
    U, _, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    d = np.where(d == 0, 1.0, d)
    U[:, :, 2] *= d[:, None]
    R = U @ Vt
    R[~ok] = np.eye(3)
    t = mu_d - np.einsum("bij,bj->bi", R, mu_s)
    t[~ok] = 0.0
    return R, t
