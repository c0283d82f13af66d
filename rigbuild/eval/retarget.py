"""Ground-truth evaluation of retargeted weight curves (synthetic sessions; characters share the actor's
ARKit shape names, so the actor's ground-truth weights apply).

Metrics per (method, character): ``weight_mae`` over the shapes the markers can observe (a shape that
moves no marker by 1 mm at weight 1 is reported separately in ``unobservable_mae``), ``mean_correlation``:
mean per-shape Pearson correlation over active observable shapes (ground truth varies by >= 0.05).
The weight-curve metric functions (MAE, per-shape correlation, observable and active shapes) are shared with
:mod:`rigbuild.eval.seol`. :func:`run_eval_retarget` is rule ``eval_retarget``'s runner.
"""

from __future__ import annotations

import os
from typing import Any, Mapping, Sequence

import numpy as np

from rigbuild.errors import InputError

#: A shape is "observable" by a marker set when some marker moves at least this much (mm) at weight 1.
OBSERVABLE_MM = 1.0
#: the ground-truth metrics written to the ``retarget`` fragment (``retarget.<prefix>.<character>.<key>``)
FRAGMENT_KEYS = ("weight_mae", "mean_correlation", "unobservable_mae")


def observable_shapes(sparse_deltas: np.ndarray, threshold_mm: float = OBSERVABLE_MM) -> np.ndarray:
    """(K,) bool: shape k moves some marker by at least ``threshold_mm`` at weight 1.

    sparse_deltas : (K, M, 3) in mm (e.g. the actor's ground-truth ``rig.deltas[:, marker_vertices]``).
    """
    return np.linalg.norm(sparse_deltas, axis=2).max(1) >= threshold_mm


def active_shapes(weights_true: np.ndarray, min_range: float = 0.05) -> np.ndarray:
    """(K,) bool: ground-truth curve k varies (max - min over frames >= ``min_range``)."""
    w = np.asarray(weights_true, dtype=np.float64)
    return (w.max(0) - w.min(0)) >= min_range


def weight_mae(weights: np.ndarray, weights_true: np.ndarray, shapes: np.ndarray | None = None) -> float:
    """Mean absolute error over frames and the selected shapes ((K,) bool or indices; default all)."""
    e = np.abs(np.asarray(weights, float) - np.asarray(weights_true, float))
    if shapes is not None:
        e = e[:, shapes]
    return float(e.mean()) if e.size else float("nan")


def per_shape_correlation(weights: np.ndarray, weights_true: np.ndarray) -> np.ndarray:
    """(K,) Pearson correlation over frames between estimated and true curves (NaN for a constant curve)."""
    a = np.asarray(weights, float)
    b = np.asarray(weights_true, float)
    a = a - a.mean(0)
    b = b - b.mean(0)
    den = np.sqrt((a * a).sum(0) * (b * b).sum(0))
    with np.errstate(invalid="ignore", divide="ignore"):
        r = (a * b).sum(0) / den
    r[den <= 1e-12] = np.nan
    return r


def mean_correlation(weights: np.ndarray, weights_true: np.ndarray, shapes: np.ndarray | None = None) -> float:
    """Mean per-shape Pearson correlation over the selected shapes (a constant estimate counts as 0)."""
    r = per_shape_correlation(weights, weights_true)
    if shapes is not None:
        r = r[shapes]
    r = np.where(np.isnan(r), 0.0, r)
    return float(r.mean()) if r.size else float("nan")


def align_to_truth(weights: np.ndarray, names: Sequence[str], true_weights: np.ndarray,
                   true_names: Sequence[str], path: str | os.PathLike | None = None,
                   truth_path: str | os.PathLike | None = None) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Columns of both weight arrays for the shape names they share (estimated order kept). ``path`` (the
    weight curves) and ``truth_path`` (the ground truth / actor's rig) are named in errors."""
    tn = [str(n) for n in true_names]
    shared = [n for n in names if n in tn]
    if not shared:
        raise InputError(
            f"the character's {len(names)} shapes ({', '.join(map(str, list(names)[:4]))}, ...) share no name with "
            f"the actor's rig's {len(tn)} ({', '.join(tn[:4])}, ...){'' if truth_path is None else f' in {truth_path}'}",
            path=path, fix="name the character's blendshapes as the actor's rig does (ARKit names), e.g. rename "
            "them when building the character, so its weights can be compared shape by shape")
    if weights.shape[0] != true_weights.shape[0]:
        raise InputError(f"{weights.shape[0]} retargeted frames vs {true_weights.shape[0]} ground-truth frames"
                         f"{'' if truth_path is None else f' in {truth_path}'}", path=path,
                         fix="evaluate the weight curves of the performance the ground truth belongs to")
    a = weights[:, [list(names).index(n) for n in shared]]
    b = true_weights[:, [tn.index(n) for n in shared]]
    return a, b, shared


def retarget_metrics(weights: np.ndarray, names: Sequence[str], true_weights: np.ndarray,
                     true_names: Sequence[str], actor_sparse_deltas: np.ndarray,
                     path: str | os.PathLike | None = None, truth_path: str | os.PathLike | None = None) -> dict:
    """Metrics of weights (F, K) against ground truth (F, K').

    actor_sparse_deltas : (K', M, 3) mm, the actor's ground-truth shapes at the marker vertices, in
    ``true_names`` order (defines which shapes the markers observe). path, truth_path : named in errors.
    """
    a, b, shared = align_to_truth(np.asarray(weights, float), list(names), np.asarray(true_weights, float), true_names,
                                  path, truth_path)
    tn = [str(n) for n in true_names]
    obs_all = observable_shapes(actor_sparse_deltas)
    obs = np.array([obs_all[tn.index(n)] for n in shared])
    act = active_shapes(b) & obs
    r = per_shape_correlation(a, b)
    return {
        "weight_mae": weight_mae(a, b, obs),
        "mean_correlation": mean_correlation(a, b, act),
        "unobservable_mae": weight_mae(a, b, ~obs) if (~obs).any() else float("nan"),
        "n_observable": int(obs.sum()),
        "n_active": int(act.sum()),
        "unobservable_shapes": [n for n, o in zip(shared, obs) if not o],
        "per_shape_correlation": {n: (None if np.isnan(v) else float(v)) for n, v in zip(shared, r)},
    }


def run_eval_retarget(weights_csv: str | os.PathLike, truth_npz: str | os.PathLike, actor_rig: str | os.PathLike,
                      method: str, character: str, ribera: Mapping[str, Any] | None,
                      metrics_path: str | os.PathLike, details_path: str | os.PathLike) -> dict:
    """Rule ``eval_retarget``: one job's weight curves vs ``ground_truth/performances/<perf>.npz`` (weights,
    shape_names) with the actor's rig (``ground_truth/actor_rig.npz``, its marker map).

    Writes the fragment ``{"retarget": {<prefix>: {<character>: {weight_mae, mean_correlation,
    unobservable_mae}}}}`` at ``metrics_path`` (prefixes: :func:`rigbuild.retarget.methods.metric_prefixes`
    with ``params.retarget.ribera.primary``) and every metric (per-shape correlations, unobservable shapes)
    at ``details_path``; returns the metrics."""
    from rigbuild.io.atomic import write_json
    from rigbuild.io.curves import read_weight_curves_csv
    from rigbuild.io.metrics import write_metrics_fragment
    from rigbuild.io.rigs import read_rig_npz
    from rigbuild.retarget.methods import method_metrics
    from rigbuild.retarget.params import ribera_from_config

    primary = ribera_from_config(ribera).primary
    w, names, _ = read_weight_curves_csv(weights_csv)
    with np.load(truth_npz, allow_pickle=False) as z:
        tw = z["weights"].astype(np.float64)
        tn = [str(s) for s in z["shape_names"]]
    align_to_truth(w, names, tw, tn, weights_csv, truth_npz)  # a clear error before the actor's rig is read
    actor = read_rig_npz(actor_rig).subset(tn)
    m = retarget_metrics(w, names, tw, tn, actor.deltas[:, actor.marker_vertices], weights_csv, truth_npz)
    write_json(details_path, {"method": method, "character": character, **m})
    write_metrics_fragment(metrics_path, "retarget",
                           method_metrics(method, character, {k: m[k] for k in FRAGMENT_KEYS}, primary))
    return m


def true_marker_placement(actor, truth: Mapping[str, np.ndarray], frame: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Where each performance marker truly sits on the actor's skin: (face ids (M,), barycentric (M, 3)) on the
    actor's rig, from one frame of the clean ground-truth markers brought back by the true head motion
    (``q = R^T (x - t)``) onto the actor posed with the true weights (the closest point is the marker's own
    skin point: the generator places markers on the skin). truth: ``ground_truth/performances/<perf>.npz``."""
    from rigbuild.geometry.mesh import closest_surface_points

    names = [str(s) for s in truth["shape_names"]]
    rig = actor.subset(names)
    w = np.asarray(truth["weights"], dtype=np.float64)[frame]
    q = (np.asarray(truth["markers"], dtype=np.float64)[frame] - truth["translation"][frame]) @ truth["rotation"][frame]
    posed = rig.neutral + np.einsum("k,kvc->vc", w, rig.deltas)
    face_ids, bary, _ = closest_surface_points(posed, rig.faces, q)
    return face_ids, bary


def marker_map_errors(marker_map: Mapping[str, Any], actor, truth: Mapping[str, np.ndarray], rig=None,
                      path: str | os.PathLike | None = None) -> tuple[np.ndarray, np.ndarray]:
    """How far each marker of ``marker_map`` (``marker_map.json``'s ``markers``: face, barycentric and normal
    offset on ``rig``, which shares the actor's topology) is from its true skin point
    (:func:`true_marker_placement`), in the ground truth's marker order: (position (M,), skin (M,)) mm.

    position : the marker's point on the rig's neutral, the rig brought onto the actor's neutral by the rigid
        motion that best aligns their face-region vertices (all vertices without a face region), against the
        true point on the actor's neutral: what a marker map gives a solver (the rig's own error included);
    skin : the map's triangle and barycentric coordinates on the actor's neutral against the true ones: where
        on the skin the marker was placed, whatever the rig's shape (None ``rig``: the actor's).
    """
    from rigbuild.geometry.mesh import points_on_surface
    from rigbuild.geometry.rigid import fit_rigid_motion

    names = [str(s) for s in truth["marker_names"]]
    missing = [n for n in names if n not in marker_map]
    if missing:
        raise InputError(f"the marker map lacks the performance's markers {missing[:6]}", path=path)
    rig = actor if rig is None else rig
    if rig.n_vertices != actor.n_vertices or int(max(marker_map[n]["face"] for n in names)) >= actor.faces.shape[0]:
        raise InputError("the marker map's rig is not of the actor's topology", path=path,
                         fix="evaluate a map made on a rig of the actor's topology")
    faces = np.array([int(marker_map[n]["face"]) for n in names])
    bary = np.array([marker_map[n]["barycentric"] for n in names], dtype=np.float64)
    offset = np.array([float(marker_map[n].get("normal_offset_mm", 0.0)) for n in names])
    true_faces, true_bary = true_marker_placement(actor, truth)
    ref = points_on_surface(actor.neutral, actor.faces, true_faces, true_bary)
    skin = np.linalg.norm(points_on_surface(actor.neutral, actor.faces, faces, bary) - ref, axis=1)
    region = actor.face_region if actor.face_region is not None else np.arange(actor.n_vertices)
    R, t = fit_rigid_motion(rig.neutral[region], actor.neutral[region])
    placed = points_on_surface(rig.neutral, rig.faces, faces, bary, offset) @ R.T + t
    return np.linalg.norm(placed - ref, axis=1), skin


def run_eval_actor_rig(weights_csv: str | os.PathLike, marker_map_json: str | os.PathLike,
                       truth_npz: str | os.PathLike, actor_rig: str | os.PathLike, metrics_path: str | os.PathLike,
                       details_path: str | os.PathLike, source: str = "actor_rig",
                       solve_npz: str | os.PathLike | None = None) -> dict:
    """Rule ``eval_actor_rig``: the actor weights solved from a rig (the personalized one, or the template for
    ``source`` ``template_rig``) vs the true performance weights (:func:`retarget_metrics`), and the marker map
    vs the markers' true skin points (:func:`marker_map_errors`; the map's ``rig`` is read from the map).
    Fragment ``retarget.<source>_weights.{weight_mae, mean_correlation, unobservable_mae, marker_map_error_mm,
    marker_map_p95_error_mm, marker_map_skin_error_mm, marker_map_placed_error_mm}`` (the last over the markers
    seen in a placing frame; the headline counts every marker), and, when the job's ``solve_npz`` holds the solve
    from the unrefined rig (``params.retarget.actor_rig.refine_iterations``), ``unrefined_mean_correlation`` and
    ``unrefined_weight_mae`` beside them; every number at ``details_path``."""
    import json

    from rigbuild.io.atomic import write_json
    from rigbuild.io.curves import read_weight_curves_csv
    from rigbuild.io.metrics import write_metrics_fragment
    from rigbuild.io.rigs import read_rig_npz

    w, names, _ = read_weight_curves_csv(weights_csv)
    with np.load(truth_npz, allow_pickle=False) as z:
        truth = {k: z[k] for k in z.files}
    tn = [str(s) for s in truth["shape_names"]]
    actor = read_rig_npz(actor_rig)
    sub = actor.subset(tn)
    m = retarget_metrics(w, names, truth["weights"].astype(np.float64), tn, sub.deltas[:, sub.marker_vertices],
                         weights_csv, truth_npz)
    from rigbuild.io.rigs import load_rig

    doc = json.loads(open(marker_map_json).read())
    rig = load_rig(doc["rig"], units="mm") if "rig" in doc else None
    err, skin = marker_map_errors(doc.get("markers", {}), actor, truth, rig, marker_map_json)
    m["marker_map_error_mm"] = float(err.mean())
    m["marker_map_p95_error_mm"] = float(np.percentile(err, 95))
    m["marker_map_skin_error_mm"] = float(skin.mean())
    markers = doc.get("markers", {})
    placed = np.array([bool(markers[str(n)].get("placed", True)) for n in truth["marker_names"]])
    m["marker_map_placed_error_mm"] = float(err[placed].mean()) if placed.any() else float("nan")
    m["markers_unplaced"] = int((~placed).sum())
    m["marker_map_errors_mm"] = {str(n): float(e) for n, e in zip(truth["marker_names"], err)}
    keys = FRAGMENT_KEYS + ("marker_map_error_mm", "marker_map_p95_error_mm", "marker_map_skin_error_mm",
                            "marker_map_placed_error_mm")
    if solve_npz is not None:
        with np.load(solve_npz, allow_pickle=False) as z:
            unrefined = z["unrefined_weights"].astype(np.float64) if "unrefined_weights" in z.files else None
            solve_names = [str(n) for n in z["shape_names"]] if "shape_names" in z.files else list(names)
        if unrefined is not None:
            u = retarget_metrics(unrefined, solve_names, truth["weights"].astype(np.float64), tn,
                                 sub.deltas[:, sub.marker_vertices], solve_npz, truth_npz)
            m["unrefined_mean_correlation"], m["unrefined_weight_mae"] = u["mean_correlation"], u["weight_mae"]
            keys += ("unrefined_mean_correlation", "unrefined_weight_mae")
    write_json(details_path, {"method": source, **m})
    write_metrics_fragment(metrics_path, "retarget", {f"{source}_weights": {k: m[k] for k in keys}})
    return m


def run_eval_take_markers(marker_map_json: str | os.PathLike, truth_npz: str | os.PathLike,
                          actor_rig: str | os.PathLike, metrics_path: str | os.PathLike) -> dict:
    """Rule ``eval_take_markers``: a take's markers placed on the tracked neutral (rule ``take_markers``) vs their
    true skin points: the map's triangles and barycentric coordinates on the actor's neutral against the true ones
    (:func:`marker_map_errors`' skin error), and the same for the marker set's vertices the map started from (the
    actor rig's ``marker_vertices``: where the methods read the range of motion without the map). Fragment
    ``retarget.take_markers.{marker_map_skin_error_mm, marker_map_skin_p95_error_mm, marker_set_skin_error_mm}``."""
    import json

    from rigbuild.geometry.mesh import points_on_surface
    from rigbuild.io.metrics import write_metrics_fragment
    from rigbuild.io.rigs import read_rig_npz

    with np.load(truth_npz, allow_pickle=False) as z:
        truth = {k: z[k] for k in z.files}
    actor = read_rig_npz(actor_rig)
    try:
        markers = json.loads(open(marker_map_json).read())["markers"]
    except (OSError, ValueError, KeyError) as e:
        raise InputError(f"cannot read the take's marker map ({e})", path=marker_map_json,
                         fix="re-run rule take_markers for this performance") from None
    _, skin = marker_map_errors(markers, actor, truth, None, marker_map_json)
    index = {str(n): i for i, n in enumerate(actor.marker_names)}
    names = [str(n) for n in truth["marker_names"]]
    true_faces, true_bary = true_marker_placement(actor, truth)
    ref = points_on_surface(actor.neutral, actor.faces, true_faces, true_bary)
    start = np.linalg.norm(actor.neutral[actor.marker_vertices[[index[n] for n in names]]] - ref, axis=1)
    values = {"marker_map_skin_error_mm": float(skin.mean()),
              "marker_map_skin_p95_error_mm": float(np.percentile(skin, 95)),
              "marker_set_skin_error_mm": float(start.mean())}
    write_metrics_fragment(metrics_path, "retarget", {"take_markers": values})
    return values
