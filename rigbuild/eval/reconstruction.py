"""Ground-truth evaluation of per-frame reconstructions (synthetic sessions).

Accuracy is the distance from ground-truth surface samples (the face-region vertices that at least
``min_cameras`` cameras see) to the reconstructed surface; completeness is the fraction of those
vertices with a reconstructed point within ``completeness_mm``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from rigbuild.camera import Camera
from rigbuild.geometry.mesh import vertex_normals  # noqa: F401 (re-exported)


def _raycasting_scene(vertices: np.ndarray, faces: np.ndarray):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)))
    return scene


def visible_counts(vertices: np.ndarray, faces: np.ndarray, cameras: Sequence[Camera], query: np.ndarray,
                   tol_mm: float = 0.5, min_cos: float = 0.1, border_px: float = 8.0) -> np.ndarray:
    """Number of cameras that see each vertex ``query`` (Q,) of the mesh.

    Seen: projects inside the image (``border_px`` margin), faces the camera (cosine between its normal
    and the direction to the camera > ``min_cos``) and the first ray hit from the camera centre is within
    ``tol_mm`` of the vertex (not occluded).
    """
    import open3d as o3d

    scene = _raycasting_scene(vertices, faces)
    X = vertices[query]
    N = vertex_normals(vertices, faces)[query]
    count = np.zeros(len(query), np.int64)
    for cam in cameras:
        uv = cam.project(X)
        inside = np.all(np.isfinite(uv), axis=1)
        inside &= (uv[:, 0] >= border_px) & (uv[:, 0] <= cam.width - 1 - border_px)
        inside &= (uv[:, 1] >= border_px) & (uv[:, 1] <= cam.height - 1 - border_px)
        to_cam = cam.center - X
        dist = np.linalg.norm(to_cam, axis=1)
        d = to_cam / dist[:, None]
        facing = np.sum(N * d, axis=1) > min_cos
        rays = np.hstack([np.broadcast_to(cam.center, X.shape), -d]).astype(np.float32)
        t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        unoccluded = t_hit >= dist - tol_mm
        count += inside & facing & unoccluded
    return count


def surface_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(P,) unsigned distance of ``points`` to the triangle mesh, mm (inf for an empty mesh)."""
    if len(faces) == 0:
        return np.full(len(points), np.inf)
    scene = _raycasting_scene(vertices, faces)
    import open3d as o3d

    return scene.compute_distance(o3d.core.Tensor(np.ascontiguousarray(points, np.float32))).numpy().astype(np.float64)


def evaluate_frame(gt_vertices: np.ndarray, gt_faces: np.ndarray, face_vertices: np.ndarray,
                   cameras: Sequence[Camera], mesh_vertices: np.ndarray, mesh_faces: np.ndarray,
                   points: np.ndarray, min_cameras: int = 2, completeness_mm: float = 1.0) -> dict:
    """Accuracy and completeness of one reconstructed frame against its ground-truth mesh.

    Parameters
    ----------
    gt_vertices (V, 3), gt_faces (F, 3) : ground-truth mesh, mm (all of it, for occlusion).
    face_vertices (R,) : indices of the face-region vertices evaluated.
    cameras : the capture cameras (with distortion).
    mesh_vertices, mesh_faces : reconstructed surface; points (P, 3) : fused point cloud.

    Returns
    -------
    dict with ``median_error_mm``, ``p90_error_mm``, ``mean_error_mm`` (GT face vertex seen by
    ``min_cameras`` -> reconstructed surface), ``point_median_error_mm``, ``point_p90_error_mm`` (fused
    points within 5 mm of the GT face -> GT surface: accuracy of the cloud itself), ``completeness``
    (fraction of those GT vertices with a fused point within ``completeness_mm``), ``n_evaluated``,
    and ``distances`` (the per-vertex distances, for pooling over frames).
    """
    from scipy.spatial import cKDTree

    face_vertices = np.asarray(face_vertices, np.int64)
    seen = visible_counts(gt_vertices, gt_faces, cameras, face_vertices) >= min_cameras
    q = gt_vertices[face_vertices[seen]]
    d_surf = surface_distance(q, mesh_vertices, mesh_faces)
    if len(points):
        d_pts, _ = cKDTree(points).query(q, k=1)
        # cloud accuracy over the face: points near the GT face region
        d_back, _ = cKDTree(gt_vertices[face_vertices]).query(points, k=1, distance_upper_bound=5.0)
        near = np.isfinite(d_back)
        d_cloud = surface_distance(points[near], gt_vertices, gt_faces)
    else:
        d_pts = np.full(len(q), np.inf)
        d_cloud = np.zeros(0)
    return {
        "median_error_mm": float(np.median(d_surf)) if len(q) else float("nan"),
        "p90_error_mm": float(np.percentile(d_surf, 90)) if len(q) else float("nan"),
        "mean_error_mm": float(np.mean(np.minimum(d_surf, 1e3))) if len(q) else float("nan"),
        "point_median_error_mm": float(np.median(d_cloud)) if len(d_cloud) else float("nan"),
        "point_p90_error_mm": float(np.percentile(d_cloud, 90)) if len(d_cloud) else float("nan"),
        "completeness": float(np.mean(d_pts <= completeness_mm)) if len(q) else float("nan"),
        "n_evaluated": int(len(q)),
        "distances": d_surf,
    }


def align_to_ground_truth(estimated: Sequence[Camera], truth: Sequence[Camera]) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity ``x_gt = s R x_est + t`` from the calibrated world to the ground-truth world, fitted
    (Umeyama) on the camera centres matched by id. Identity if fewer than 3 cameras match."""
    from rigbuild.geometry.rigid import fit_similarity

    gt = {c.id: c for c in truth}
    pairs = [(c.center, gt[c.id].center) for c in estimated if c.id in gt]
    if len(pairs) < 3:
        return 1.0, np.eye(3), np.zeros(3)
    src, dst = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
    s, R, t = fit_similarity(src, dst)
    return float(s), R, t


class SequenceEvaluator:
    """Evaluates each reconstructed frame of one ROM sequence of a synthetic session.

    rom_npz : ``ground_truth/rom/<sequence>.npz`` (vertices per frame, ``frames``); actor_rig_npz :
    ``ground_truth/actor_rig.npz`` (faces, face region); truth_cameras_json : ``ground_truth/cameras.json``;
    cameras : the calibrated cameras (session order). Reconstructions (in the calibrated world) are mapped
    to the ground-truth world by :func:`align_to_ground_truth` before measuring.
    """

    def __init__(self, rom_npz, actor_rig_npz, truth_cameras_json, cameras: Sequence[Camera], min_cameras: int = 2,
                 completeness_mm: float = 1.0):
        from rigbuild.io.cameras import read_cameras
        from rigbuild.io.rigs import read_rig_npz

        with np.load(rom_npz, allow_pickle=False) as z:
            self.vertices = z["vertices"].astype(np.float64)
            self.frames = [int(f) for f in z["frames"]] if "frames" in z.files else list(range(len(self.vertices)))
        rig = read_rig_npz(actor_rig_npz)
        self.faces = rig.faces
        self.face_vertices = rig.face_vertices
        self.gt_cameras = read_cameras(truth_cameras_json)
        self.s, self.R, self.t = align_to_ground_truth(cameras, self.gt_cameras)
        self.min_cameras = min_cameras
        self.completeness_mm = completeness_mm
        self.per_frame: dict[int, dict] = {}
        self._dist: list[np.ndarray] = []
        self._complete: list[float] = []
        self._n: list[int] = []

    def to_ground_truth(self, X: np.ndarray) -> np.ndarray:
        return self.s * np.asarray(X, float) @ self.R.T + self.t

    def __call__(self, frame: int, rec) -> dict:
        """Evaluate the reconstruction of ``frame``: anything with ``mesh_vertices`` (V, 3), ``mesh_faces``
        (F, 3) and ``points`` (P, 3) in the calibrated world, mm (a ``FrameReconstruction``, or the frame's
        ``geometry/<frame>.npz``)."""
        i = self.frames.index(int(frame))
        r = evaluate_frame(self.vertices[i], self.faces, self.face_vertices, self.gt_cameras,
                           self.to_ground_truth(rec.mesh_vertices), rec.mesh_faces, self.to_ground_truth(rec.points),
                           self.min_cameras, self.completeness_mm)
        d = r.pop("distances")
        self._dist.append(d)
        self._complete.append(r["completeness"])
        self._n.append(r["n_evaluated"])
        self.per_frame[int(frame)] = r
        return r

    def summary(self) -> dict:
        """Pooled over frames: ``median_error_mm``, ``p90_error_mm``, ``completeness`` (vertex-weighted),
        plus the worst frame's values (``worst_frame_*``) and ``frames_evaluated``."""
        if not self._dist:
            return {"frames_evaluated": 0}
        d = np.concatenate(self._dist)
        pf = list(self.per_frame.values())
        return {
            "median_error_mm": float(np.median(d)),
            "p90_error_mm": float(np.percentile(d, 90)),
            "completeness": float(np.average(self._complete, weights=self._n)),
            "point_median_error_mm": float(np.nanmedian([p["point_median_error_mm"] for p in pf])),
            "worst_frame_median_error_mm": float(max(p["median_error_mm"] for p in pf)),
            "worst_frame_p90_error_mm": float(max(p["p90_error_mm"] for p in pf)),
            "worst_frame_completeness": float(min(p["completeness"] for p in pf)),
            "frames_evaluated": len(pf),
            "alignment_scale": self.s,
        }


def sequence_errors(per_frame: Sequence[dict]) -> dict:
    """``reconstruction.sequences.<seq>.*`` from the evaluated frames (frame order): the worst frame's
    ``median_error_mm`` / ``p90_error_mm`` / ``completeness`` (the acceptance is per frame), the means over
    frames (``mean_*``), the worst ``point_median_error_mm`` and ``frames_evaluated``; {} without frames."""
    ev = list(per_frame)
    if not ev:
        return {}
    return {
        "median_error_mm": float(max(e["median_error_mm"] for e in ev)),
        "p90_error_mm": float(max(e["p90_error_mm"] for e in ev)),
        "completeness": float(min(e["completeness"] for e in ev)),
        "mean_median_error_mm": float(np.mean([e["median_error_mm"] for e in ev])),
        "mean_p90_error_mm": float(np.mean([e["p90_error_mm"] for e in ev])),
        "mean_completeness": float(np.mean([e["completeness"] for e in ev])),
        "point_median_error_mm": float(max(e["point_median_error_mm"] for e in ev)),
        "frames_evaluated": len(ev),
    }


def pool_sequence_errors(per_seq: dict) -> dict:
    """Session-level ``reconstruction.*`` acceptance keys: the worst sequence's ``median_error_mm``,
    ``p90_error_mm`` and ``completeness`` over the sequences that have them ({} if none)."""
    ev = [v for v in per_seq.values() if "median_error_mm" in v]
    if not ev:
        return {}
    return {"median_error_mm": float(max(v["median_error_mm"] for v in ev)),
            "p90_error_mm": float(max(v["p90_error_mm"] for v in ev)),
            "completeness": float(min(v["completeness"] for v in ev))}


def run_eval_reconstruction_sequence(session_yaml, sequence: str, cameras_json, record_paths, geometry_paths,
                                     rom_npz, actor_rig_npz, truth_cameras_json, fragment_path, detail_path,
                                     log=print) -> dict:
    """Rule ``eval_reconstruction_sequence``: every reconstructed frame of a sequence vs its ground-truth mesh.

    record_paths, geometry_paths : per frame ``frames/<f>.json`` (skipped frames are not evaluated) and
    ``geometry/<f>.npz`` (same order). Writes the fragment ``{"reconstruction": {"sequences": {<seq>:
    sequence_errors}}}`` at ``fragment_path`` and ``{"per_frame": {<f>: errors}, "ground_truth":
    sequence_errors}`` at ``detail_path``; returns the sequence's errors.
    """
    import json
    from pathlib import Path
    from types import SimpleNamespace

    from rigbuild.io.atomic import write_json
    from rigbuild.io.cameras import read_cameras
    from rigbuild.io.metrics import write_metrics_fragment
    from rigbuild.session import read_session

    spec = read_session(Path(session_yaml).parent)
    by_id = {c.id: c for c in read_cameras(cameras_json)}
    evaluator = SequenceEvaluator(rom_npz, actor_rig_npz, truth_cameras_json, [by_id[c] for c in spec.cameras])
    records = [json.loads(Path(p).read_text()) for p in record_paths]
    per_frame: dict[int, dict] = {}
    for rec, geo in sorted(zip(records, geometry_paths), key=lambda rg: rg[0]["frame"]):
        if rec.get("skipped"):
            continue
        with np.load(geo, allow_pickle=False) as z:
            ev = evaluator(rec["frame"], SimpleNamespace(**{k: z[k] for k in ("points", "mesh_vertices", "mesh_faces")}))
        per_frame[int(rec["frame"])] = ev
        log(f"{sequence} frame {rec['frame']} vs ground truth: median {ev['median_error_mm']:.3f} mm, "
            f"p90 {ev['p90_error_mm']:.3f} mm, completeness {ev['completeness']:.3f}")
    errors = sequence_errors(list(per_frame.values()))
    write_json(detail_path, {"per_frame": {str(f): e for f, e in per_frame.items()}, "ground_truth": errors})
    write_metrics_fragment(fragment_path, "reconstruction", {"sequences": {sequence: errors}} if errors else {})
    return errors


def run_eval_reconstruction_pool(fragment_paths, out_path) -> dict:
    """Rule ``eval_reconstruction``: the sequences' error fragments -> ``{"reconstruction":
    pool_sequence_errors(...)}`` at ``out_path``."""
    from rigbuild.io.metrics import gather_metrics, write_metrics_fragment

    per_seq = gather_metrics(fragment_paths).get("reconstruction", {}).get("sequences", {})
    return write_metrics_fragment(out_path, "reconstruction", pool_sequence_errors(per_seq))["reconstruction"]
