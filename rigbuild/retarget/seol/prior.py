"""The PCA prior of the target's blendshapes (Seol et al. 2012, sec. 5, ``E_prior = v^T Lambda^-1 v``) and
its strength as a corner frequency; the sparse-combination training set (an option)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigbuild.errors import InputError

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
    try:
        _, sv, Vt = np.linalg.svd(Xc, full_matrices=False)
    except np.linalg.LinAlgError:  # LAPACK's divide and conquer (gesdd) does not converge on some matrices
        import scipy.linalg

        _, sv, Vt = scipy.linalg.svd(Xc, full_matrices=False, lapack_driver="gesvd")
    lam = sv**2 / X.shape[0]
    keep = lam > rel_tol * max(lam.max(initial=0.0), 1e-300)
    if not keep.any():
        raise InputError("PCA prior: the training shapes do not move the markers")
    return PcaPrior(eigvecs=Vt[keep].T.copy(), eigvals=lam[keep], mean_delta=mean)


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
