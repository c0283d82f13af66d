"""The geometric prior of the retargeting (Ribera et al. 2017, sec. 5, eq. 14-15) and the head scale that
brings the character to the actor's size."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

def mesh_cotangent_laplacian(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """(N, N) cotangent Laplacian of a triangle mesh (libigl ``cotmatrix``; non-finite entries zeroed)."""
    import igl

    L = igl.cotmatrix(np.asarray(vertices, np.float64), np.asarray(faces, np.int64))
    L = sp.csr_matrix(L)
    bad = ~np.isfinite(L.data)
    if bad.any():
        L.data[bad] = 0.0
    return L


def prior_matrix(neutral: np.ndarray, deltas: np.ndarray, faces: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Eq. 15 as a (K, K) quadratic form: ``E_Prior(w) = w^T Q w = (1/N) |L dV w|^2``.

    neutral (N, 3), deltas (K, N, 3) of the character (mm), faces (F, 3). ``L dV`` is precomputed once
    (cotangent Laplacian applied per coordinate); ``scale`` is the uniform scale that brings the rig to the
    actor's head size (the Laplacian's cotangent weights are scale invariant, the deltas scale).
    """
    L = mesh_cotangent_laplacian(neutral, faces)
    K, N, _ = deltas.shape
    Q = np.zeros((K, K))
    for c in range(3):
        LD = L @ deltas[:, :, c].T  # (N, K)
        Q += LD.T @ LD
    return Q * (scale**2) / N


def head_scale(a0: np.ndarray, s0: np.ndarray) -> float:
    """Uniform scale that makes the character's marker set ``s0`` as large as the actor's ``a0`` (RMS radius)."""
    ra = np.sqrt(((a0 - a0.mean(0)) ** 2).sum(1).mean())
    rs = np.sqrt(((s0 - s0.mean(0)) ** 2).sum(1).mean())
    return float(ra / rs) if rs > 0 else 1.0
