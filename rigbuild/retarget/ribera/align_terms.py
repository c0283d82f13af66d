"""The E_Align energy of the blendshape transfer (Ribera et al. 2017, eq. 4 = E_Match + alpha E_Mesh +
beta E_CEG) as normal equations.

- eq. 10 soft masks ``u_k`` (:func:`soft_masks`) and E_Match (:func:`match_terms`);
- eq. 11 E_Mesh (``alpha/M L^T L`` around the guesses g_k, L from :mod:`.marker_mesh`);
- eq. 12-13 E_CEG: the signed cross-expression graph Laplacian (:func:`cross_expression_laplacian`);
- the whole system in Kronecker form (:func:`align_terms`, solved by :func:`.solvers.kron_sum_solve`) or
  assembled sparse (:func:`align_system`, solved by CHOLMOD).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from rigbuild.retarget.common import visible_mask
from rigbuild.retarget.params import TransferParams
from rigbuild.retarget.ribera.similarity import shape_correlation_matrix

def soft_masks(ds: np.ndarray) -> np.ndarray:
    """Eq. 10 soft masks u_k (K, M): ``|ds_k^m| / max_m |ds_k^m|`` (0 for a shape that moves no marker)."""
    n = np.linalg.norm(ds, axis=2)
    mx = n.max(1, keepdims=True)
    return np.where(mx > 1e-12, n / np.maximum(mx, 1e-12), 0.0)


def cross_expression_laplacian(C: np.ndarray) -> np.ndarray:
    """Eq. 12 signed graph Laplacian G (K, K) of the cross-expression graph with edge weights C (K, K).

    ``(G x)_k = (1 / sum_{l != k} |c_kl|) sum_{l != k} c_kl (x_l - x_k)``.
    """
    W = np.array(C, dtype=np.float64)
    np.fill_diagonal(W, 0.0)
    n = np.abs(W).sum(1)
    Wn = np.where(n[:, None] > 1e-12, W / np.maximum(n, 1e-12)[:, None], 0.0)
    return Wn - np.diag(Wn.sum(1))


def match_terms(da_keys: np.ndarray, sim_keys: np.ndarray, masks: np.ndarray,
                activations: np.ndarray | None = None, targets: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """E_Match's normal-equation pieces: the diagonal d (K, M) and right-hand side b (K, M, 3).

    Faithful (eq. 10): ``(1/F) sum_f sum_k c~_kf |dp_k - diag(u_k) da_f|^2`` over visible markers.
    With ``activations`` h (K, F') and ``targets`` r (K, F', M, 3): the activation-aware option
    ``(1/F) sum c~_kf |diag(u_k) (h_kf dp_k - r_kf)|^2`` (the mask as a residual weight).
    """
    Fk = max(da_keys.shape[0], 1)
    vis = visible_mask(da_keys).astype(np.float64)  # (F', M)
    if activations is None:
        d_match = (sim_keys @ vis) / Fk
        b_match = np.einsum("kf,km,fmc->kmc", sim_keys, masks, np.nan_to_num(da_keys)) / Fk
    else:
        h = activations
        u2 = masks * masks
        d_match = ((sim_keys * h * h) @ vis) * u2 / Fk
        b_match = np.einsum("kf,km,kfmc->kmc", sim_keys * h, u2, np.nan_to_num(targets) * vis[None, :, :, None]) / Fk
    return d_match, b_match


def align_terms(
    ds: np.ndarray,
    dg: np.ndarray,
    da_keys: np.ndarray,
    sim_keys: np.ndarray,
    masks: np.ndarray,
    lap: sp.spmatrix,
    params: TransferParams,
    activations: np.ndarray | None = None,
    targets: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The E_Align normal equations in Kronecker form: d (K, M), C (M, M), Bk (K, K), R (K, M, 3).

    ``A = diag(d) + I_K (x) C + Bk (x) I_M`` (one matrix for x, y and z); see :func:`align_system` for the
    terms. :func:`kron_sum_solve` solves it.
    """
    K, M, _ = ds.shape
    d_match, b_match = match_terms(da_keys, sim_keys, masks, activations, targets)
    L = lap.toarray() if sp.issparse(lap) else np.asarray(lap)
    C = (params.alpha / M) * (L.T @ L)
    G = cross_expression_laplacian(shape_correlation_matrix(ds))
    Bk = (params.beta / M) * (G.T @ G)
    ref = ds if params.ceg_reference == "character" else dg
    R = (b_match + params.epsilon * dg + np.einsum("kmc,mn->knc", dg, C) + np.einsum("kl,lmc->kmc", Bk, ref))
    return d_match + params.epsilon, C, Bk, R


def align_system(
    s0: np.ndarray,
    ds: np.ndarray,
    dg: np.ndarray,
    da_keys: np.ndarray,
    sim_keys: np.ndarray,
    masks: np.ndarray,
    lap: sp.spmatrix,
    params: TransferParams,
    activations: np.ndarray | None = None,
    targets: np.ndarray | None = None,
) -> tuple[sp.csr_matrix, np.ndarray]:
    """Normal equations of E_Align (eq. 4) = E_Match + alpha E_Mesh + beta E_CEG (+ epsilon |dp - dg|^2),
    assembled sparse from :func:`align_terms` (``A = diag(d) + I_K (x) C + Bk (x) I_M``, ``B = R``).

    Unknown ordering ``index = k * M + m``; the same (MK x MK) matrix serves x, y and z. da_keys (F', M, 3)
    (NaN gaps), sim_keys (K, F'), masks (K, M), lap (M, M). Returns A (MK, MK) and B (MK, 3).

    With ``activations`` h (K, F') and ``targets`` r (K, F', M, 3) the match term becomes the activation-aware
    ``(1/F) sum c~_kf |h_kf dp_k - diag(u_k) r_kf|^2`` (see :func:`transfer_blendshapes`, ``match``).
    """
    d, C, Bk, R = align_terms(ds, dg, da_keys, sim_keys, masks, lap, params, activations, targets)
    K, M = d.shape
    A = (sp.diags(d.ravel()) + sp.kron(sp.identity(K, format="csr"), sp.csr_matrix(C), format="csr")
         + sp.kron(sp.csr_matrix(Bk), sp.identity(M, format="csr"), format="csr"))
    return A.tocsr(), R.reshape(K * M, 3)
