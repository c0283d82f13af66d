"""Per-frame rigid head motion for the personalization (Ma et al. 2016, eq. 2-3).

The model pose of frame ``i`` is ``x_i = R_i (b_0 + D w_i) + t_i``; with the weights fixed the energy
``sum_v m_v^2 ||R_i y_v + t_i - p_v||^2`` (``y`` = the posed rig, ``m`` the per-vertex confidence of
the tracked frame) is minimized in closed form by weighted Kabsch (SVD) with weights ``m^2``.
"""

from __future__ import annotations

import numpy as np

from rigbuild.geometry.rigid import fit_rigid_motion


def fit_frame_rigid(model: np.ndarray, frame: np.ndarray, confidence: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` minimizing ``sum_v c_v^2 ||R model_v + t - frame_v||^2``.

    model, frame : (N, 3) mm (rig frame and world); confidence : (N,) in [0, 1].
    Returns R (3, 3), t (3,) mm.
    """
    return fit_rigid_motion(model, frame, np.asarray(confidence, dtype=np.float64) ** 2)


def to_rig_frame(frame: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``R^T (p - t)``: a world-space frame (..., 3) brought back into the rig's coordinate frame."""
    return (np.asarray(frame) - t) @ R


def pose_rig(neutral: np.ndarray, deltas: np.ndarray, weights: np.ndarray, rotations: np.ndarray,
             translations: np.ndarray, vertices: np.ndarray | None = None) -> np.ndarray:
    """The model poses ``x_i = R_i (b_0 + D w_i) + t_i`` (F, R, 3) mm of a fit.

    neutral (V, 3) mm, deltas (K, V, 3) mm, weights (F, K), rotations (F, 3, 3), translations (F, 3) mm;
    vertices (R,): evaluate only these (default all). NaN rows (skipped frames) give NaN poses.
    """
    b = np.asarray(neutral, np.float64)
    D = np.asarray(deltas, np.float64)
    if vertices is not None:
        b, D = b[vertices], D[:, vertices]
    rig = b[None] + np.einsum("fk,kvc->fvc", np.asarray(weights, np.float64), D, optimize=True)
    return np.einsum("fij,fvj->fvi", np.asarray(rotations, np.float64), rig, optimize=True) \
        + np.asarray(translations, np.float64)[:, None, :]
