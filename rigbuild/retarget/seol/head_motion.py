"""Head motion of the source performance (Seol et al. 2012, sec. 3.1): Procrustes removal against the
source neutral, its Gauss-Newton refinement with the expression (an option), re-application to the target,
and the occlusion bridging (frames with too few markers: head motion and markers interpolated in time)."""

from __future__ import annotations

import logging
import os

import numpy as np

from rigbuild.errors import InputError
from rigbuild.retarget.common import bridge_rigid_motion

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
        if gappy.size:
            sol[gappy] = _seen_least_squares(Jw, res[gappy], vis3[gappy])
        Rd = Rotation.from_rotvec(sol[:, :3]).as_matrix()
        t = t + np.einsum("fij,fj->fi", R, sol[:, 3:6])
        R = R @ Rd
    stab = np.einsum("fji,fmj->fmi", R, X - t[:, None, :])
    return stab, R, t


def _seen_least_squares(J: np.ndarray, res: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """Per frame ``argmin ||J_seen x - res_seen||`` over the rows ``seen`` (G, R) of J (R, P); res (G, R) is 0
    where not seen. Normal equations for every frame at once (``J^T J`` less the unseen rows' part);
    a frame whose seen rows leave an unknown (nearly) unobserved gets the minimum-norm least squares
    (``lstsq``) instead. Returns (G, P)."""
    G, P = res.shape[0], J.shape[1]
    unseen = ~seen
    n_unseen = unseen.sum(1)
    order = np.argsort(seen, axis=1, kind="stable")[:, :int(n_unseen.max(initial=0))]  # unseen rows first
    Ju = J[order] * (np.arange(order.shape[1])[None, :] < n_unseen[:, None])[..., None]  # (G, u, P), zero padded
    N = J.T @ J - np.swapaxes(Ju, 1, 2) @ Ju
    rhs = res @ J
    d = np.diagonal(N, axis1=1, axis2=2)
    ok = (d > 1e-9 * d.max(axis=1, keepdims=True)).all(axis=1) & (seen.sum(1) >= P)
    out = np.empty((G, P))
    if ok.any():
        try:
            c = np.linalg.cholesky(N[ok])
            y = np.linalg.solve(c, rhs[ok][..., None])
            out[ok] = np.linalg.solve(np.swapaxes(c, 1, 2), y)[..., 0]
        except np.linalg.LinAlgError:  # not positive definite to working precision: every frame by lstsq
            ok[:] = False
    for f in np.flatnonzero(~ok):
        out[f] = np.linalg.lstsq(J[seen[f]], res[f, seen[f]], rcond=None)[0]
    return out


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
