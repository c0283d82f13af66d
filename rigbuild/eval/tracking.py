"""Tracking accuracy against ground truth (synthetic sessions only; the tracking stage never calls this).

The headline region is the template's **whole face mask** (``face_vertices``: the ICT face region, eye and
mouth linings included): ``tracking.mean_error_mm``, ``p95_error_mm``, ``end_drift_mm``,
``neutral_error_mm`` and their ``corr_*`` forms, per session and per sequence. Parts of the mask (the lip
linings inside the closed mouth, the eyelid linings, the nostrils, under the chin and behind the jaw) are in
no camera's view at the neutral and follow the tracker's Laplacian prior; a user sees them all the same.

The region **as the capture sees it** is reported beside it with the prefix ``visible_``: face-mask vertices
that at least two cameras see on the ground-truth neutral (in the image, facing the camera, not occluded:
:func:`rigbuild.eval.reconstruction.visible_counts`, the same rule the reconstruction metrics use).

Two error kinds over those vertices:

- **vertex error** (the acceptance metric): ``|tracked_v(t) - truth_v(t)|`` with the template's vertex
  correspondence; it includes the neutral registration's tangential error (which vertex of the actor a
  template vertex lands on).
- **correspondence-tracking error**: each tracked vertex's registered neutral position is attached to the
  closest point of the ground-truth neutral surface (triangle + barycentrics); its reference at frame ``t``
  is that surface point on the ground-truth mesh of frame ``t``. This isolates the tracking (frame to frame
  and drift) from the registration.
"""

from __future__ import annotations

import numpy as np


def vertex_errors(tracked: np.ndarray, truth: np.ndarray, vertices: np.ndarray | None = None) -> np.ndarray:
    """(F, R) per-frame per-vertex distances (mm) between tracked and truth (F, V, 3), on ``vertices`` (R,)."""
    tracked = np.asarray(tracked, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    if tracked.shape != truth.shape:
        raise ValueError(f"tracked {tracked.shape} and truth {truth.shape} differ")
    if vertices is not None:
        tracked = tracked[:, vertices]
        truth = truth[:, vertices]
    return np.linalg.norm(tracked - truth, axis=2)


def landmark_nme(predicted: np.ndarray, truth: np.ndarray, outer_eye=(36, 45)) -> float:
    """Normalized mean error of 2-D landmarks: mean over points of |predicted - truth| (px) divided by the
    truth's outer-eye-corner distance (iBUG 68: points 36 and 45). predicted, truth: (N, 2) px."""
    p, t = np.asarray(predicted, np.float64), np.asarray(truth, np.float64)
    if p.shape != t.shape:
        raise ValueError(f"predicted {p.shape} and truth {t.shape} differ")
    return float(np.linalg.norm(p - t, axis=1).mean() / np.linalg.norm(t[outer_eye[0]] - t[outer_eye[1]]))


#: iBUG 68 loops of the lip contours (outer 48-59, inner 60-67) and the eyelid margins (36-41, 42-47)
LIP_LOOPS = (tuple(range(48, 60)), tuple(range(60, 68)))
EYELID_LOOPS = (tuple(range(36, 42)), tuple(range(42, 48)))


def _polyline_distance(points: np.ndarray, loops: list[np.ndarray]) -> np.ndarray:
    """(N,) distance (mm) of ``points`` (N, 3) to the closed polylines ``loops`` (each (K, 3))."""
    d = np.full(points.shape[0], np.inf)
    for L in loops:
        a, b = L, np.roll(L, -1, axis=0)
        ab = b - a
        t = np.clip(np.einsum("nkd,kd->nk", points[:, None] - a[None], ab) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
        q = a[None] + t[..., None] * ab[None]
        d = np.minimum(d, np.linalg.norm(points[:, None] - q, axis=2).min(1))
    return d


def contour_regions(neutral: np.ndarray, landmarks: np.ndarray | None, face_vertices: np.ndarray,
                    lip_mm: float = 6.0, eyelid_mm: float = 4.0) -> dict[str, np.ndarray]:
    """Vertex sets of the lips and the eyelids on a template: face-mask vertices within ``lip_mm`` of the lip
    contour loops or ``eyelid_mm`` of the eyelid-margin loops of its 68 landmarks (``Rig.landmarks``; mm on the
    template neutral (V, 3)). Empty dict when the template has no 68 landmarks."""
    if landmarks is None or np.asarray(landmarks).size != 68 or np.any(np.asarray(landmarks) < 0):
        return {}
    face_vertices = np.asarray(face_vertices, np.int64)
    L = np.asarray(neutral, np.float64)[np.asarray(landmarks, np.int64)]
    P = np.asarray(neutral, np.float64)[face_vertices]
    out = {}
    for name, loops, r in (("lips", LIP_LOOPS, lip_mm), ("eyelids", EYELID_LOOPS, eyelid_mm)):
        out[name] = face_vertices[_polyline_distance(P, [L[list(lp)] for lp in loops]) <= r]
    return out


def surface_anchors(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points of ``points`` (N, 3) on the mesh (vertices, faces): triangle ids (N,), barycentrics (N, 3)."""
    import igl

    _, tri, closest = igl.point_mesh_squared_distance(np.asarray(points, float), np.asarray(vertices, float),
                                                      np.asarray(faces, np.int64))
    f = np.asarray(faces)[tri]
    V = np.asarray(vertices, float)
    bary = igl.barycentric_coordinates(closest, V[f[:, 0]], V[f[:, 1]], V[f[:, 2]])
    return tri.astype(np.int64), np.asarray(bary, float)


def tracking_summary(tracked: np.ndarray, truth: np.ndarray, faces: np.ndarray, face_vertices: np.ndarray,
                     registered_neutral: np.ndarray | None = None, truth_neutral: np.ndarray | None = None
                     ) -> dict:
    """Error summary of one sequence.

    tracked, truth : (F, V, 3) mm; faces (T, 3); face_vertices (R,). With ``registered_neutral`` (V, 3) and
    ``truth_neutral`` (V, 3) the correspondence-tracking errors are added.
    Returns dict: mean_error_mm, p95_error_mm, end_error_mm (last frame mean), first_error_mm,
    per_frame_mean_mm (F,), and corr_* equivalents.
    """
    e = vertex_errors(tracked, truth, face_vertices)
    out = {
        "mean_error_mm": float(e.mean()),
        "p95_error_mm": float(np.percentile(e, 95)),
        "first_error_mm": float(e[0].mean()),
        "end_error_mm": float(e[-1].mean()),
        "per_frame_mean_mm": e.mean(1).tolist(),
        "errors": e,
    }
    if registered_neutral is not None and truth_neutral is not None:
        tri, bary = surface_anchors(np.asarray(registered_neutral)[face_vertices], truth_neutral, faces)
        f = np.asarray(faces)[tri]
        ref = np.einsum("nk,fnkd->fnd", bary, np.asarray(truth, float)[:, f])
        c = np.linalg.norm(np.asarray(tracked, float)[:, face_vertices] - ref, axis=2)
        out.update({"corr_mean_error_mm": float(c.mean()), "corr_p95_error_mm": float(np.percentile(c, 95)),
                    "corr_end_error_mm": float(c[-1].mean()), "corr_per_frame_mean_mm": c.mean(1).tolist(),
                    "corr_errors": c})
    return out


def session_tracking_metrics(summaries: dict[str, dict]) -> dict:
    """Combine per-sequence summaries into the ``tracking`` metrics: mean_error_mm and p95_error_mm over all
    frames of all sequences, end_drift_mm = mean over sequences of the last-frame mean error, and corr_*."""
    if not summaries:
        return {}
    allv = np.concatenate([s["errors"].ravel() for s in summaries.values()])
    out = {"mean_error_mm": float(allv.mean()), "p95_error_mm": float(np.percentile(allv, 95)),
           "end_drift_mm": float(np.mean([s["end_error_mm"] for s in summaries.values()]))}
    if all("corr_errors" in s for s in summaries.values()):
        c = np.concatenate([s["corr_errors"].ravel() for s in summaries.values()])
        out.update({"corr_mean_error_mm": float(c.mean()), "corr_p95_error_mm": float(np.percentile(c, 95)),
                    "corr_end_drift_mm": float(np.mean([s["corr_end_error_mm"] for s in summaries.values()]))})
    return out


def truth_frames(gt_dir, sequence: str, frame_ids) -> np.ndarray:
    """Ground-truth vertices (F, V, 3) mm of ``frame_ids`` of ``ground_truth/rom/<sequence>.npz``."""
    from pathlib import Path

    with np.load(Path(gt_dir) / "rom" / f"{sequence}.npz") as z:
        fr = [int(f) for f in z["frames"]] if "frames" in z else list(range(z["vertices"].shape[0]))
        missing = [int(f) for f in frame_ids if int(f) not in fr]
        if missing:
            raise ValueError(f"ground truth of {sequence} has no frames {missing}")
        return z["vertices"][[fr.index(int(f)) for f in frame_ids]].astype(np.float64)


def observed_face_vertices(truth_neutral: np.ndarray, faces: np.ndarray, cameras, face_vertices: np.ndarray,
                           min_cameras: int = 2) -> np.ndarray:
    """The face-region vertices (subset of ``face_vertices`` (R,)) that at least ``min_cameras`` of ``cameras``
    see on the ground-truth neutral ``truth_neutral`` (V, 3) mm with triangles ``faces`` (T, 3)."""
    from rigbuild.eval.reconstruction import visible_counts

    face_vertices = np.asarray(face_vertices, np.int64)
    seen = visible_counts(np.asarray(truth_neutral, np.float64), np.asarray(faces, np.int64), cameras,
                          face_vertices) >= min_cameras
    return face_vertices[seen]


def ground_truth_tracking_metrics(gt_dir, cameras, faces: np.ndarray, face_vertices: np.ndarray,
                                  neutral: np.ndarray, neutral_at: tuple[str, int],
                                  sequences: dict[str, tuple[np.ndarray, np.ndarray]],
                                  min_cameras: int = 2, regions: dict[str, np.ndarray] | None = None
                                  ) -> tuple[dict, dict]:
    """Tracking accuracy of a synthetic session against its ``ground_truth/`` folder.

    gt_dir : the session's ground_truth folder (with ``cameras.json``, the true cameras); cameras : the
    calibrated ``cameras.json`` (estimates are mapped into the ground-truth world by the camera-centre
    similarity); faces (T, 3), face_vertices (R,) of the template; neutral (V, 3) mm: the registered neutral,
    taken at ``neutral_at`` = (sequence, frame); sequences : name -> (tracked vertices (F, V, 3) mm, frame ids
    (F,)); min_cameras : a face-region vertex is in the visible region (the ``visible_*`` values) when that many
    true cameras see it on the true neutral (:func:`observed_face_vertices`).
    Returns (session values, per-sequence summaries without the error arrays). Session values over the
    whole face mask ``face_vertices``: ``neutral_error_mm`` + :func:`session_tracking_metrics`; the same over
    the observed region prefixed ``visible_``; ``observed_face_vertices`` / ``observed_face_fraction``.
    Per sequence: :func:`tracking_summary`'s scalars and curves over the whole mask, and
    ``visible_{mean,p95,end}_error_mm`` over the observed region. ``regions`` (name -> vertex ids, e.g.
    :func:`contour_regions`' lips and eyelids) add ``<name>_mean_error_mm`` over all tracked frames (and per
    sequence), and ``neutral_<name>_error_mm`` on the registered neutral; ``all_vertices`` is every vertex of the
    mesh (teeth, tongue, eyes, head included).
    """
    from pathlib import Path

    from rigbuild.eval.frames import calibrated_to_ground_truth, points_to_ground_truth
    from rigbuild.io.cameras import read_cameras

    sim = calibrated_to_ground_truth(gt_dir, cameras)
    neutral_gt = points_to_ground_truth(np.asarray(neutral, np.float64), sim)
    truth_neutral = truth_frames(gt_dir, neutral_at[0], [neutral_at[1]])[0]
    face_vertices = np.asarray(face_vertices, np.int64)
    observed = observed_face_vertices(truth_neutral, faces, read_cameras(Path(gt_dir) / "cameras.json"),
                                      face_vertices, min_cameras)
    values = {"neutral_error_mm": float(vertex_errors(neutral_gt[None], truth_neutral[None],
                                                      face_vertices).mean()),
              "visible_neutral_error_mm": float(vertex_errors(neutral_gt[None], truth_neutral[None],
                                                              observed).mean()),
              "observed_face_vertices": int(observed.size),
              "observed_face_fraction": float(observed.size / max(face_vertices.size, 1))}
    summaries, visible_summaries = {}, {}
    regions = {"all_vertices": np.arange(truth_neutral.shape[0]), **(regions or {})}
    region_errors = {k: [] for k in regions}
    region_means = {}
    for name, (V, frame_ids) in sequences.items():
        tracked = points_to_ground_truth(np.asarray(V, np.float64), sim)
        truth = truth_frames(gt_dir, name, frame_ids)
        summaries[name] = tracking_summary(tracked, truth, faces, face_vertices, neutral_gt, truth_neutral)
        visible_summaries[name] = tracking_summary(tracked, truth, faces, observed, neutral_gt, truth_neutral)
        region_means[name] = {}
        for k, ids in regions.items():
            region_errors[k].append(vertex_errors(tracked, truth, ids).ravel())
            if region_errors[k][-1].size:
                region_means[name][f"{k}_mean_error_mm"] = float(region_errors[k][-1].mean())
    for k, ids in regions.items():  # each region on the registered neutral: what every frame starts from
        if np.asarray(ids).size:
            values[f"neutral_{k}_error_mm"] = float(vertex_errors(neutral_gt[None], truth_neutral[None], ids).mean())
    for k, errs in region_errors.items():
        if errs and np.concatenate(errs).size:
            values[f"{k}_mean_error_mm"] = float(np.concatenate(errs).mean())
    values.update(session_tracking_metrics(summaries))
    values.update({f"visible_{k}": v for k, v in session_tracking_metrics(visible_summaries).items()})
    per = {n: {k: v for k, v in s.items() if not k.endswith("errors")} for n, s in summaries.items()}
    for n, s in visible_summaries.items():
        per[n].update({f"visible_{k}": s[k] for k in ("mean_error_mm", "p95_error_mm", "end_error_mm")})
        per[n].update(region_means[n])
    return values, per


def run_eval_tracking(session_dir, gt_cameras, gt_sequences, cameras, neutral, vertices,
                      track_params=None, metrics_path=None, min_cameras: int = 2, detail_path=None) -> dict:
    """Rule eval_track: a synthetic session's tracking accuracy -> the ``tracking`` fragment.

    session_dir : the session folder (session.yaml: the template rig); gt_cameras : its
    ``ground_truth/cameras.json``; gt_sequences : the ``ground_truth/rom/<seq>.npz`` files (every ROM
    sequence: the evaluation reads them and nothing else of ground_truth/); cameras : the calibrated
    cameras.json; neutral : the tracked ``neutral.npz``; vertices : each sequence's tracked
    ``vertices.npz`` (``track/<seq>/vertices.npz``); track_params : ``config["params"]["track"]`` (its
    ``template_rig``). The fragment holds :func:`ground_truth_tracking_metrics`' session values and, under
    ``sequences.<seq>``, its per-sequence scalars; ``detail_path`` (JSON) gets the per-frame curves over the
    whole mask (``per_frame_mean_mm``, ``corr_per_frame_mean_mm`` per sequence).
    """
    from pathlib import Path

    from rigbuild.io.metrics import write_metrics_fragment
    from rigbuild.io.rigs import load_rig
    from rigbuild.session import read_session
    from rigbuild.track.params import from_config

    gt_dir = Path(gt_cameras).parent
    declared = {Path(p).resolve() for p in gt_sequences}
    spec = read_session(Path(session_dir))
    template = load_rig(from_config(track_params).template_for(spec))
    with np.load(neutral) as z:
        neutral_v = z["vertices"].astype(np.float64)
        neutral_at = (str(z["sequence"]), int(z["frame"]))
    tracked = {}
    for p in vertices:
        with np.load(p) as z:
            tracked[Path(p).parent.name] = (z["vertices"].astype(np.float64), z["frames"].astype(np.int64))
    needed = {(gt_dir / "rom" / f"{name}.npz").resolve() for name in [neutral_at[0], *tracked]}
    if not needed <= declared:
        raise ValueError(f"ground-truth files read but not declared: {sorted(map(str, needed - declared))}")
    regions = contour_regions(template.neutral, template.landmarks, template.face_vertices)
    values, per = ground_truth_tracking_metrics(gt_dir, cameras, template.faces, template.face_vertices,
                                                neutral_v, neutral_at, tracked, min_cameras, regions)
    curves = {name: {k: d.pop(k) for k in list(d) if isinstance(d[k], list)} for name, d in per.items()}
    values["sequences"] = per
    if detail_path is not None:
        from rigbuild.io.atomic import write_json

        write_json(detail_path, {"sequences": curves})
    if metrics_path is not None:
        return write_metrics_fragment(metrics_path, "tracking", values)
    return {"tracking": values}
