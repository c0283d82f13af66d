"""Automatic blendshape transfer (Ribera et al. 2017, sec. 4): personalized sparse actor shapes ``dp``.

- :func:`transfer_blendshapes`: eq. 4 as written (``match: faithful``) and the options beside it
  (``activation``: :func:`key_activations`; ``fit``: :func:`fit_match_transfer`);
- :func:`training_displacements`: the training sequence's stabilized displacements ``da_f = a_f - a0``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from rigbuild.errors import InputError
from rigbuild.geometry.rigid import fit_similarity
from rigbuild.retarget.common import stabilize, visible_mask
from rigbuild.retarget.params import RetargetParams, TransferParams
from rigbuild.retarget.ribera.align_terms import (align_system, align_terms, cross_expression_laplacian,
                                                  soft_masks)
from rigbuild.retarget.ribera.guesses import rbf_transfer
from rigbuild.retarget.ribera.marker_mesh import MarkerTriangulation, marker_laplacian, marker_triangulation
from rigbuild.retarget.ribera.retargeter import RiberaRetargeter
from rigbuild.retarget.ribera.similarity import (correlations, enhance_similarity, key_expressions,
                                                 shape_correlation_matrix, trust_values)
from rigbuild.retarget.ribera.solvers import _cholmod_solve, kron_sum_solve

@dataclass
class TransferResult:
    """Output of :func:`transfer_blendshapes`. Shapes: K shapes, M markers, F training frames."""

    dp: np.ndarray  # (K, M, 3) personalized sparse actor blendshapes
    dg: np.ndarray  # (K, M, 3) RBF initial guesses
    keys: np.ndarray  # (F',) key frame indices into the training sequence
    similarity: np.ndarray  # (K, F) enhanced similarity c~
    trust: np.ndarray  # (K,)
    masks: np.ndarray  # (K, M)
    triangulation: MarkerTriangulation
    info: dict = field(default_factory=dict)


def training_displacements(
    training: np.ndarray, a0: np.ndarray, rigidity: np.ndarray | None = None, stabilize_frames: bool = True
) -> np.ndarray:
    """Actor displacements ``da_f = a_f - a0`` (F, M, 3) of a training sequence with head motion removed."""
    if stabilize_frames:
        training, _, _ = stabilize(training, a0, rigidity)
    return training - a0[None]


def transfer_blendshapes(
    s0: np.ndarray,
    ds: np.ndarray,
    a0: np.ndarray,
    da: np.ndarray,
    params: TransferParams | None = None,
    uv: np.ndarray | None = None,
    contact_pairs: np.ndarray | None = None,
    segment_starts: np.ndarray | None = None,
    dg: np.ndarray | None = None,
    prior: np.ndarray | None = None,
) -> TransferResult:
    """Automatic blendshape transfer (section 4): personalized sparse actor blendshapes.

    Parameters
    ----------
    s0 : (M, 3) character neutral markers; ds : (K, M, 3) character sparse blendshapes (character units).
    a0 : (M, 3) actor neutral markers (mm); da : (F, M, 3) stabilized training displacements (mm, NaN gaps).
    params : :class:`TransferParams`. uv, contact_pairs : see :func:`marker_triangulation`.
    segment_starts : first frame of each concatenated training sequence (for the key-frame filter).

    ``params.match = "faithful"`` minimizes eq. 4 exactly as written. Its weak spot (the paper's sec. 6.3
    notes it): eq. 10's minimizer is a similarity-weighted *mean* of masked key expressions; every key with a
    positive similarity (partial activations, mixtures, near-neutral frames) pulls ``dp_k`` toward a smaller
    shape, and ``diag(u_k)`` damps the actor's data where the character's shape falls off, so the shapes
    shrink. ``match = "activation"`` is one offered option: the
    activation of every shape in every key is solved jointly with the shapes (alternating, starting from the
    RBF guesses; :func:`key_activations`) and the match term becomes
    ``(1/F) sum_f sum_k c~_kf |diag(u_k) (h_kf dp_k - r_kf)|^2`` - the key expression minus what the other
    shapes explain, compared at the shape's activation, with the soft mask as a residual weight. The
    correlations, trust, contrast enhancement, key extraction, E_Mesh and E_CEG are unchanged.
    ``match = "fit"`` (:func:`fit_match_transfer`) matches all training frames with the whole blendshape model
    at sparse activations solved with the section-5 energy.
    ``prior`` (K, K): the E_Prior form for those activations (default none); ``dg``: initial guesses g_k
    (default :func:`rbf_transfer`).

    Returns
    -------
    :class:`TransferResult` with ``dp`` (K, M, 3) in mm.
    """
    params = params or TransferParams()
    if params.match not in ("faithful", "activation", "fit"):
        raise InputError(f"unknown match '{params.match}'", fix="use faithful, activation or fit")
    s0 = np.asarray(s0, float)
    ds = np.asarray(ds, float)
    a0 = np.asarray(a0, float)
    K, M, _ = ds.shape
    if a0.shape != (M, 3) or da.ndim != 3 or da.shape[1:] != (M, 3):
        raise InputError(f"marker count mismatch: character {M}, actor neutral {a0.shape}, training {da.shape}")
    dg = rbf_transfer(s0, ds, a0) if dg is None else np.asarray(dg, float)
    # correlations in the actor's frame: rotate the character's displacements by the s0 -> a0 rotation
    _, Rsa, _ = fit_similarity(s0, a0)
    ds_rot = ds @ Rsa.T
    c = correlations(da, ds_rot)
    t = trust_values(ds)
    sim = enhance_similarity(c, t, params.r)
    keys = key_expressions(sim, segment_starts)
    masks = soft_masks(ds)
    tri = marker_triangulation(s0, ds, uv=uv, contact_pairs=contact_pairs)
    lap = marker_laplacian(a0, tri)

    def solve(h=None, r=None) -> np.ndarray:
        if params.solver == "cholmod":
            A, B = align_system(s0, ds_rot, dg, da[keys], sim[:, keys], masks, lap, params, h, r)
            return _cholmod_solve(A, B).reshape(K, M, 3)
        d, C, Bk, R = align_terms(ds_rot, dg, da[keys], sim[:, keys], masks, lap, params, h, r)
        return kron_sum_solve(d, C, Bk, R)

    info = {"n_keys": int(keys.size), "match": params.match}
    if params.match == "activation":
        dp = dg.copy()
        for _ in range(params.match_iterations):
            h, r = key_activations(dp, da[keys])
            dp = solve(h, r)
    elif params.match == "fit":
        frames = keys if params.fit_frames == "keys" else np.arange(da.shape[0])
        Q = np.zeros((K, K)) if prior is None else np.asarray(prior, float)
        dp, h = fit_match_transfer(ds_rot, dg, a0, da[frames], lap, Q, params)
        info["fit_frames"] = int(frames.size)
        info["activations"] = h
    else:
        dp = solve()
    return TransferResult(dp, dg, keys, sim, t, masks, tri, info=info)


def fit_match_transfer(ds: np.ndarray, dg: np.ndarray, a0: np.ndarray, da: np.ndarray, lap: sp.spmatrix,
                       Q: np.ndarray, params: TransferParams) -> tuple[np.ndarray, np.ndarray]:
    """The ``"fit"`` option of E_Align: match the training frames with the blendshape model itself.

    ``E_Match' = (1/F) sum_f |da_f - J xi_f - sum_k h_kf dp_k|^2`` (visible markers; gaps imputed with the
    model's prediction), ``+ fit_alpha E_Mesh + beta E_CEG`` (eq. 11 and 12-13 unchanged, E_Mesh around the
    guesses g_k). The activations h (F, K) of the training frames and their residual rigid motion xi_f are
    the section-5 retargeting solution (E_Fit + fit_mu E_Prior + fit_lambda E_Sparse, joint rigid fit,
    bounds [0, 1]) with the current dp; dp and h alternate ``match_iterations`` times, starting from g_k.
    As for the faithful term, the minimizer over dp is three (MK x MK) systems, here the Kronecker sum
    ``(H^T H / F + beta/M G^T G) (x) I_M + I_K (x) fit_alpha/M L^T L`` (exact eigen-solve).

    Why: eq. 10 compares each shape with whole key expressions (its minimizer is a similarity-weighted mean of
    masked keys, which shrinks shapes whenever keys mix shapes or are partial); here every frame is explained
    by all shapes at once at their solved activations, and the sparse activations (lambda_cm 0.2) keep shapes
    from trading motion (with a box-only activation fit the shapes drift and the transfer ends below g_k).

    ds (K, M, 3) character shapes (actor orientation), dg (K, M, 3) guesses, a0 (M, 3), da (F, M, 3)
    stabilized training displacements (NaN gaps), lap (M, M) marker Laplacian, Q (K, K) prior (actor scale).
    Returns dp (K, M, 3) mm and h (F, K).
    """
    K, M, _ = dg.shape
    F = max(da.shape[0], 1)
    L = lap.toarray() if sp.issparse(lap) else np.asarray(lap)
    C = (params.fit_alpha / M) * (L.T @ L)
    G = cross_expression_laplacian(shape_correlation_matrix(ds))
    Bc = (params.beta / M) * (G.T @ G)
    ref = ds if params.ceg_reference == "character" else dg
    R0 = np.einsum("kmc,mn->knc", dg, C) + np.einsum("kl,lmc->kmc", Bc, ref) + params.epsilon * dg
    d = np.full((K, M), params.epsilon)
    vis = visible_mask(da)
    hp = RetargetParams(mu=params.fit_mu, lambda_cm=params.fit_lambda_cm, bounds=(0.0, 1.0), rigid="joint")
    dp = np.array(dg, dtype=np.float64, copy=True)
    h = np.zeros((da.shape[0], K))
    for it in range(params.match_iterations):
        rt = RiberaRetargeter(dp, Q, hp, reference=a0)
        h = rt.solve(da, start=h if it else None)  # warm start from the last activations (same minimizer)
        x = da - rt.rigid_motion(da, h)
        for _ in range(2):  # gaps: impute with the current model (EM for the least-squares match)
            x = np.where(vis[..., None], x, np.einsum("fk,kmc->fmc", h, dp))
            dp = kron_sum_solve(d, C, Bc + h.T @ h / F, R0 + np.einsum("fk,fmc->kmc", h, x) / F)
    return dp, h


def key_activations(dp: np.ndarray, da_keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Activations of every shape in every key expression and each shape's share of the key expression.

    dp (K, M, 3) current actor blendshapes; da_keys (F', M, 3) key displacements (NaN gaps). The weights
    ``h`` (K, F') in [0, 1] fit all shapes jointly to each key (least squares, bounds [0, 1]); the target of
    shape k in key f is the key minus what the other shapes explain, ``r_kf = da_f - sum_{l != k} h_lf dp_l``
    (K, F', M, 3).
    """
    K = dp.shape[0]
    rt = RiberaRetargeter(dp, np.zeros((K, K)), RetargetParams(mu=0.0, lambda_cm=0.0, bounds=(0.0, 1.0)))
    h = rt.solve(da_keys).T  # (K, F')
    full = np.einsum("kf,kmc->fmc", h, dp)  # (F', M, 3)
    r = da_keys[None] - full[None] + h[:, :, None, None] * dp[:, None]
    return h, r
