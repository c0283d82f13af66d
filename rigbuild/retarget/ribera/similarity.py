"""Similarity of actor expressions and character shapes (Ribera et al. 2017, sec. 4.1-4.2).

- eq. 5 correlations ``c_kf`` (:func:`correlations`) and between shapes (:func:`shape_correlation_matrix`);
- eq. 6 trust values ``t_k`` (:func:`trust_values`);
- eq. 7-8 contrast enhancement (:func:`contrast`, :func:`enhance_similarity`);
- sec. 4.2 key expressions (:func:`key_expressions`).
"""

from __future__ import annotations

import numpy as np

from rigbuild.retarget.common import visible_mask
from rigbuild.retarget.params import PAPER_R

def _unit_rows(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(x, axis=1)
    return x / np.maximum(n, 1e-12)[:, None], n


def correlations(da: np.ndarray, ds: np.ndarray) -> np.ndarray:
    """Eq. 5: ``c_kf = da_f . ds_k / (|da_f| |ds_k|)`` (K, F), over the markers visible in frame f.

    da : (F, M, 3) actor marker displacements from the neutral (NaN gaps); ds : (K, M, 3).
    """
    vis = visible_mask(da).astype(np.float64)  # (F, M)
    a = np.nan_to_num(da).reshape(da.shape[0], -1)
    s = ds.reshape(ds.shape[0], -1)
    num = s @ a.T  # (K, F)
    a_norm = np.sqrt((a * a).sum(1))  # (F,)
    s_norm = np.sqrt(np.einsum("kmc,kmc->km", ds, ds) @ vis.T)  # (K, F) over visible markers
    den = s_norm * a_norm[None]
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.where(den > 1e-12, num / np.where(den > 1e-12, den, 1.0), 0.0)
    return c


def shape_correlation_matrix(ds: np.ndarray) -> np.ndarray:
    """(K, K) signed Pearson correlations (eq. 5 form) between sparse blendshapes ds (K, M, 3)."""
    u, n = _unit_rows(ds.reshape(ds.shape[0], -1))
    C = u @ u.T
    C[n < 1e-12] = 0.0
    C[:, n < 1e-12] = 0.0
    return C


def trust_values(ds: np.ndarray) -> np.ndarray:
    """Eq. 6 trust values t_k (K,) in [0, 1].

    Shapes are sorted by total displacement ``d_k = |ds_k|`` (largest first); ``t_k = 1 - r_k / max r``
    with ``r_k`` the sum of positive correlations with the shapes of larger displacement.
    """
    d = np.linalg.norm(ds.reshape(ds.shape[0], -1), axis=1)
    order = np.argsort(-d, kind="stable")
    Cs = np.maximum(shape_correlation_matrix(ds)[np.ix_(order, order)], 0.0)
    r_sorted = np.tril(Cs, -1).sum(1)
    rmax = r_sorted.max()
    t_sorted = 1.0 - r_sorted / rmax if rmax > 0 else np.ones_like(r_sorted)
    t = np.empty_like(t_sorted)
    t[order] = t_sorted
    return t


def contrast(c: np.ndarray, r: float = PAPER_R) -> np.ndarray:
    """Eq. 7: ``b(c) = e^{rc} / (e^{r/2} + e^{rc})`` (a sigmoid centred at 0.5), computed stably."""
    return 0.5 * (1.0 + np.tanh(0.5 * r * (np.asarray(c, float) - 0.5)))


def enhance_similarity(c: np.ndarray, t: np.ndarray, r: float = PAPER_R) -> np.ndarray:
    """Eq. 8: ``c~_kf = (1 - t_k) c+_kf + t_k b(c+_kf)`` for c (K, F), t (K,)."""
    cp = np.maximum(c, 0.0)
    return (1.0 - t)[:, None] * cp + t[:, None] * contrast(cp, r)


def key_expressions(similarity: np.ndarray, segment_starts: np.ndarray | None = None) -> np.ndarray:
    """Section 4.2: key frames of the training sequence (sorted frame indices).

    Each row of ``similarity`` (K, F) is low-pass filtered with a 3-frame Gaussian kernel (1, 2, 1) / 4,
    the rows are summed, and the local peaks (strictly above the previous frame, not below the next) of
    the cumulative curve (with positive similarity) are returned. ``segment_starts``: first frame of each concatenated sequence (the
    filter does not cross sequence boundaries; default: one sequence).
    """
    K, F = similarity.shape
    starts = np.array([0] if segment_starts is None else segment_starts, dtype=np.int64)
    bounds = list(starts) + [F]
    keys = []
    for s, e in zip(bounds[:-1], bounds[1:]):
        x = similarity[:, s:e]
        if x.shape[1] == 0:
            continue
        pad = np.pad(x, ((0, 0), (1, 1)), mode="edge")
        filt = 0.25 * pad[:, :-2] + 0.5 * pad[:, 1:-1] + 0.25 * pad[:, 2:]
        cum = filt.sum(0)
        n = cum.size
        if n == 1:
            keys.append(np.array([s]))
            continue
        prev = np.r_[-np.inf, cum[:-1]]
        nxt = np.r_[cum[1:], -np.inf]
        peaks = np.flatnonzero((cum > prev) & (cum >= nxt) & (cum > 0))
        keys.append(peaks + s)
    return np.concatenate(keys) if keys else np.zeros(0, dtype=np.int64)
