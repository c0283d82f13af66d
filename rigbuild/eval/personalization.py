"""Ground-truth evaluation of the blendshape personalization (synthetic sessions only).

Rule ``eval_personalize`` (:func:`run_eval_personalize`) reads the personalize stage's ``fit.npz`` and
``weights.npz``, the calibrated cameras and the session's ``ground_truth/`` (``cameras.json``,
``actor_rig.npz``, ``rom/<seq>.npz``) and writes the fragment ``results/<session>/eval/personalization_metrics.json``.

Metrics (``personalization.<key>`` in metrics.json; the residuals come from the stage itself). Blendshape
weights and shape amplitudes share a per-shape scale that no fitting data determines (``(a D_k, w_k / a)``
fit identically), so the headline shape and weight numbers are gauge-invariant and the raw forms sit beside
them as ``*_raw``:

- ``expression_error_reduction`` / ``heldout_expression_error_reduction`` (the headline): each rig posed by its
  own fit, ``R_i (b_0 + D w_i) + t_i``, against the ground-truth mesh of the frame: ``1 - e / e*`` of the
  mean vertex distance (mm, unweighted, over the fitted region: the template's face mask with the default
  ``fit_region: face``, every vertex with ``all``) of the personalized
  rig (e) and the D* rig (e*), on the fitting frames and on the held-out frames (the same weight solve with each
  rig); ``*_initial_mm`` / ``*_final_mm`` beside them;
- ``residual_reduction``: ``1 - rms_personalized / rms_initial`` of the fit residual on the fitting
  frames (weights and rigid motion fitted to each rig; the plain RMS of the per-vertex distances over the
  confident vertices, mm); the stage reports beside it ``residual_reduction_weighted``, the distances
  weighted by the tracking confidence M as in the data term of eq. 3, ``sqrt(sum M^2 d^2 / sum M^2)``
  (the two agree on ground-truth meshes, whose confidence is 1);
- ``heldout_residual_reduction`` (and ``*_weighted``): the same on held-out frames not used for the shape
  update;
- ``shape_error_reduction``: ``1 - rms(a D - D_gt) / rms(a* D* - D_gt)`` over the face region (mm), each
  shape of each rig first scaled by its least-squares factor onto the ground truth (``a``: the spread of the
  personalized rig's factors is ``shape_scale_p10`` / ``_median`` / ``_p90``); ``shape_error_reduction_raw``
  without the factors;
- ``weight_mae``: mean |w / a - w_gt| over all fitting frames and shapes (the weights in the gauge of the
  scaled shapes; a shape whose factor is not positive is left out); ``weight_mae_raw``: mean |w - w_gt|;
- ``min_shape_cosine``: min over shapes of the cosine between the personalized and the ground-truth
  displacement field on the face region (scale-free).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

#: the fragment's top-level key in metrics.json
METRICS_KEY = "personalization"


def rms_shape_error(deltas: np.ndarray, gt_deltas: np.ndarray, vertices: np.ndarray | None = None) -> float:
    """RMS per-vertex distance (mm) between (K, V, 3) delta sets over ``vertices`` (default all)."""
    d = deltas if vertices is None else deltas[:, vertices]
    g = gt_deltas if vertices is None else gt_deltas[:, vertices]
    return float(np.sqrt(((d - g) ** 2).sum(-1).mean()))


def shape_cosines(deltas: np.ndarray, gt_deltas: np.ndarray, vertices: np.ndarray | None = None) -> np.ndarray:
    """(K,) cosine similarity of each shape's displacement field with the ground truth's."""
    d = (deltas if vertices is None else deltas[:, vertices]).reshape(deltas.shape[0], -1)
    g = (gt_deltas if vertices is None else gt_deltas[:, vertices]).reshape(gt_deltas.shape[0], -1)
    den = np.linalg.norm(d, axis=1) * np.linalg.norm(g, axis=1)
    return np.where(den > 0, (d * g).sum(1) / np.where(den > 0, den, 1.0), 0.0)


def gauge_scales(deltas: np.ndarray, gt_deltas: np.ndarray, vertices: np.ndarray | None = None) -> np.ndarray:
    """(K,) least-squares factors ``a_k = argmin ||a D_k - D_gt,k||`` over ``vertices``."""
    d = (deltas if vertices is None else deltas[:, vertices]).reshape(deltas.shape[0], -1)
    g = (gt_deltas if vertices is None else gt_deltas[:, vertices]).reshape(gt_deltas.shape[0], -1)
    dd = (d * d).sum(1)
    return np.where(dd > 0, (d * g).sum(1) / np.where(dd > 0, dd, 1.0), 1.0)


def weight_mae(weights: np.ndarray, gt_weights: np.ndarray) -> float:
    """Mean absolute weight error over finite entries of (F, K) arrays."""
    e = np.abs(np.asarray(weights) - np.asarray(gt_weights))
    return float(np.nanmean(e))


def personalization_metrics(
    initial_deltas: np.ndarray,
    deltas: np.ndarray,
    gt_deltas: np.ndarray,
    weights: np.ndarray,
    gt_weights: np.ndarray,
    residual_initial_mm: float,
    residual_final_mm: float,
    face_vertices: np.ndarray | None = None,
    heldout_residual_initial_mm: float | None = None,
    heldout_residual_final_mm: float | None = None,
    heldout_weights: np.ndarray | None = None,
    heldout_gt_weights: np.ndarray | None = None,
) -> dict:
    """All personalization metrics but the expression errors as a flat dict (keys without the
    ``personalization.`` prefix).

    initial_deltas (D*), deltas (personalized), gt_deltas: (K, V, 3) mm; weights / gt_weights (F, K)
    on the fitting frames; residuals in mm (RMS); face_vertices (R,) for the shape metrics.
    """
    e0 = rms_shape_error(initial_deltas, gt_deltas, face_vertices)
    e1 = rms_shape_error(deltas, gt_deltas, face_vertices)
    a0 = gauge_scales(initial_deltas, gt_deltas, face_vertices)
    a1 = gauge_scales(deltas, gt_deltas, face_vertices)
    e0g = rms_shape_error(a0[:, None, None] * initial_deltas, gt_deltas, face_vertices)
    e1g = rms_shape_error(a1[:, None, None] * deltas, gt_deltas, face_vertices)
    cos = shape_cosines(deltas, gt_deltas, face_vertices)
    cos0 = shape_cosines(initial_deltas, gt_deltas, face_vertices)
    a_w = np.where(a1 > 1e-9, a1, np.nan)  # a shape pointing away from its truth has no weight gauge: left out
    out = {
        "residual_initial_mm": residual_initial_mm,
        "residual_final_mm": residual_final_mm,
        "residual_reduction": 1.0 - residual_final_mm / residual_initial_mm if residual_initial_mm > 0 else 0.0,
        "shape_error_initial_mm": e0g,
        "shape_error_final_mm": e1g,
        "shape_error_reduction": 1.0 - e1g / e0g if e0g > 0 else 0.0,
        "shape_error_initial_raw_mm": e0,
        "shape_error_final_raw_mm": e1,
        "shape_error_reduction_raw": 1.0 - e1 / e0 if e0 > 0 else 0.0,
        "shape_scale_p10": float(np.percentile(a1, 10)),
        "shape_scale_median": float(np.median(a1)),
        "shape_scale_p90": float(np.percentile(a1, 90)),
        "weight_mae": weight_mae(np.asarray(weights) / a_w[None, :], gt_weights),
        "weight_mae_raw": weight_mae(weights, gt_weights),
        "min_shape_cosine": float(cos.min()),
        "min_shape_cosine_initial": float(cos0.min()),
        "mean_shape_cosine": float(cos.mean()),
    }
    if heldout_residual_initial_mm is not None and heldout_residual_final_mm is not None:
        out["heldout_residual_initial_mm"] = heldout_residual_initial_mm
        out["heldout_residual_final_mm"] = heldout_residual_final_mm
        out["heldout_residual_reduction"] = (1.0 - heldout_residual_final_mm / heldout_residual_initial_mm
                                             if heldout_residual_initial_mm > 0 else 0.0)
    if heldout_weights is not None and heldout_gt_weights is not None:
        out["heldout_weight_mae"] = weight_mae(np.asarray(heldout_weights) / a_w[None, :], heldout_gt_weights)
        out["heldout_weight_mae_raw"] = weight_mae(heldout_weights, heldout_gt_weights)
    return out


def mean_expression_error(posed: np.ndarray, truth: np.ndarray) -> float:
    """Mean vertex distance (mm) between posed rig meshes and ground-truth meshes, both (F, R, 3) in one world,
    over the frames whose pose is finite (NaN rows: frames the fit skipped)."""
    from rigbuild.eval.tracking import vertex_errors

    ok = np.isfinite(posed).all(axis=(1, 2))
    return float(vertex_errors(posed[ok], truth[ok]).mean()) if ok.any() else float("nan")


def expression_error_metrics(initial_rig: tuple, rig: tuple, initial_fit: tuple, fit: tuple, truth: np.ndarray,
                             vertices: np.ndarray | None = None, similarity=None, prefix: str = "") -> dict:
    """``{prefix}expression_error_{initial,final}_mm`` and ``{prefix}expression_error_reduction``.

    initial_rig, rig : (neutral (V, 3), deltas (K, V, 3)) mm of the D* and the personalized rig; initial_fit,
    fit : (weights (F, K), rotations (F, 3, 3), translations (F, 3) mm), each rig's fit of the same F frames;
    truth (F, R, 3) mm: the ground-truth meshes of those frames on ``vertices`` (R,) (default all), in the
    ground-truth world; similarity : the calibrated-to-ground-truth similarity
    (:func:`rigbuild.eval.frames.calibrated_to_ground_truth`) when the rigs are in the calibrated world.
    """
    from rigbuild.eval.frames import points_to_ground_truth
    from rigbuild.personalize.rigid import pose_rig

    errs = []
    for (b, D), (W, R, t) in ((initial_rig, initial_fit), (rig, fit)):
        posed = pose_rig(b, D, np.nan_to_num(W), R, t, vertices)
        posed[~np.isfinite(np.asarray(W)).all(1)] = np.nan
        if similarity is not None:
            posed = points_to_ground_truth(posed, similarity)
        errs.append(mean_expression_error(posed, truth))
    e0, e1 = errs
    return {f"{prefix}expression_error_initial_mm": e0, f"{prefix}expression_error_final_mm": e1,
            f"{prefix}expression_error_reduction": 1.0 - e1 / e0 if e0 > 0 else 0.0}


def _gt_weights(gt_dir, shape_names: list[str], seqs: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Ground-truth weights (F, K) for the frames (sequence name, session frame number) from
    ``ground_truth/rom/<seq>.npz`` (columns reordered to ``shape_names``)."""
    from pathlib import Path

    out = np.full((len(seqs), len(shape_names)), np.nan)
    cache: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for i, (s, f) in enumerate(zip(seqs, frames)):
        s = str(s)
        if s not in cache:
            with np.load(Path(gt_dir) / "rom" / f"{s}.npz", allow_pickle=False) as z:
                names = [str(n) for n in z["shape_names"]]
                W = z["weights"].astype(np.float64)
                fr = z["frames"].astype(np.int64) if "frames" in z else np.arange(W.shape[0])
            cols = [names.index(n) for n in shape_names]
            cache[s] = (W[:, cols], fr)
        W, fr = cache[s]
        hit = np.flatnonzero(fr == int(f))
        if hit.size:
            out[i] = W[hit[0]]
    return out


def ground_truth_metrics(gt_dir, shape_names: list[str], initial_deltas: np.ndarray, deltas: np.ndarray,
                         face_vertices: np.ndarray | None, weights: np.ndarray, seqs: np.ndarray, frames: np.ndarray,
                         heldout_weights: np.ndarray | None = None, heldout_seqs: np.ndarray | None = None,
                         heldout_frames: np.ndarray | None = None) -> dict:
    """GT metrics of a session (``ground_truth/actor_rig.npz`` and ``rom/<seq>.npz``): shape error
    reduction, cosines and weight MAE as in :func:`personalization_metrics` (residuals are not GT
    metrics and are left to the caller)."""
    from rigbuild.io.rigs import read_rig_npz

    actor = read_rig_npz(Path(gt_dir) / "actor_rig.npz").subset(shape_names)
    gw = _gt_weights(gt_dir, shape_names, seqs, frames)
    hgw = (_gt_weights(gt_dir, shape_names, heldout_seqs, heldout_frames) if heldout_weights is not None else None)
    m = personalization_metrics(initial_deltas, deltas, actor.deltas, weights, gw, 1.0, 1.0, face_vertices,
                                heldout_weights=heldout_weights, heldout_gt_weights=hgw)
    for k in ("residual_initial_mm", "residual_final_mm", "residual_reduction"):
        m.pop(k)
    return m


def truth_meshes(gt_dir, seqs: np.ndarray, frames: np.ndarray, vertices: np.ndarray | None) -> np.ndarray:
    """Ground-truth meshes (F, R, 3) mm of the frames (sequence name, session frame number) on ``vertices``."""
    from rigbuild.eval.tracking import truth_frames

    seqs, frames = np.asarray(seqs).astype(str), np.asarray(frames)
    out = None
    for s in dict.fromkeys(seqs):
        rows = np.flatnonzero(seqs == s)
        V = truth_frames(gt_dir, s, frames[rows])
        V = V if vertices is None else V[:, vertices]
        if out is None:
            out = np.empty((seqs.size, *V.shape[1:]))
        out[rows] = V
    return out


#: fit.npz arrays the expression errors need (written by the personalize stage)
FIT_POSE_KEYS = ("initial_neutral", "neutral", "initial_weights", "initial_rotations", "initial_translations",
                 "rotations", "translations")


def evaluate_personalization(gt_dir: str | os.PathLike, weights_npz: str | os.PathLike, fit_npz: str | os.PathLike,
                             cameras_json: str | os.PathLike | None = None) -> dict:
    """Ground-truth metrics of a personalize job's outputs (``results/<session>/personalize/weights.npz`` and
    ``fit.npz``): :func:`ground_truth_metrics` and :func:`expression_error_metrics` on the fitting and the
    held-out frames. With ``cameras_json`` (the calibrated cameras) the rigs are first mapped from the
    calibrated world into the ground-truth world (similarity on the camera centres)."""
    from rigbuild.errors import InputError

    with np.load(weights_npz, allow_pickle=False) as z:
        shape_names = [str(n) for n in z["shape_names"]]
        seqs, frames = z["sequence"], z["frame"]
        heldout_seqs = z["heldout_sequence"] if "heldout_sequence" in z else None
        heldout_frames = z["heldout_frame"] if "heldout_frame" in z else None
    with np.load(fit_npz, allow_pickle=False) as z:
        missing = [k for k in FIT_POSE_KEYS if k not in z]
        if missing:
            raise InputError(f"fit.npz lacks {', '.join(missing)} (written by an older rigbuild)", path=fit_npz,
                             fix="rerun the personalize rule: snakemake --forcerun personalize")
        fit = {k: z[k] for k in z.files}
    region = fit.get("fit_vertices")
    sim = None
    D0, D1 = fit["initial_deltas"], fit["deltas"]
    if cameras_json is not None:
        from rigbuild.eval.frames import calibrated_to_ground_truth, vectors_to_ground_truth

        sim = calibrated_to_ground_truth(gt_dir, cameras_json)
        D0, D1 = vectors_to_ground_truth(D0, sim), vectors_to_ground_truth(D1, sim)
    held = "heldout_weights" in fit and heldout_seqs is not None
    m = ground_truth_metrics(gt_dir, shape_names, D0, D1, region, fit["weights"], seqs, frames,
                             fit["heldout_weights"] if held else None, heldout_seqs, heldout_frames)
    rigs = ((fit["initial_neutral"], fit["initial_deltas"]), (fit["neutral"], fit["deltas"]))
    frame_sets = [("", seqs, frames)] + ([("heldout_", heldout_seqs, heldout_frames)] if held else [])
    for prefix, s, f in frame_sets:
        fits = [tuple(fit[f"{prefix}{which}{k}"] for k in ("weights", "rotations", "translations"))
                for which in ("initial_", "")]
        m.update(expression_error_metrics(*rigs, *fits, truth_meshes(gt_dir, s, f, region), region, sim, prefix))
    return m


def run_eval_personalize(gt_dir: str | os.PathLike, weights_npz: str | os.PathLike, fit_npz: str | os.PathLike,
                         cameras_json: str | os.PathLike | None, metrics_path: str | os.PathLike) -> dict:
    """Rule ``eval_personalize``: :func:`evaluate_personalization` written as the fragment
    ``{"personalization": {...}}`` at ``metrics_path``; returns the metrics."""
    from rigbuild.io.metrics import write_metrics_fragment

    metrics = evaluate_personalization(Path(gt_dir), weights_npz, fit_npz, cameras_json)
    write_metrics_fragment(metrics_path, METRICS_KEY, metrics)
    return metrics
