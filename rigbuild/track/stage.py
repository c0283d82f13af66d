"""The tracking stage: its Snakemake runners and the orchestration over loaded data.

Runners (called by scripts/track.py with paths and the raw ``config["params"]["track"]`` block):

- :func:`run_track_neutral` (rule track_neutral): the global neutral frame -> ``neutral.npz`` and the
  ``tracking`` fragment ``neutral_metrics.json``.
- :func:`run_track_sequence` (rule track_sequence): one ROM sequence -> vertices, markers (npz, c3d),
  residuals (csv, png), overlays and the fragment ``track_metrics.json`` (``tracking.sequences.<seq>``).
- :func:`run_track_summary` (rule track_summary): the sequences' fragments -> ``track_summary.json`` and the
  session fragment ``summary_metrics.json`` (``tracking.lost_frames``, ``tracking.sequence_count``).

Pure functions: :func:`track_neutral_frame` (painted dots + depth maps of the global neutral frame ->
registered neutral) and :func:`track_rom_sequence` (a ROM sequence's views -> tracked vertices in full
template topology, confidences, marker trajectories and per-frame statistics).
The stage never reads the session's ground truth (rules/eval_track.smk evaluates against it).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.rig import Rig
from rigbuild.track.matches import ViewFrame
from rigbuild.track.mesh import TrackingMesh, build_tracking_mesh
from rigbuild.track.params import TrackParams, from_config, unpainted
from rigbuild.track.register import NeutralRegistration, register_neutral, require_markers
from rigbuild.track.sequence import FrameStats, SequenceTracker, neutral_dots, scan_from_depth

log = logging.getLogger("track")


# --------------------------------------------------------------------------------------------- inputs
def read_image_rgb(path: str | os.PathLike) -> np.ndarray:
    """An image file as (H, W, 3) uint8 RGB."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError("image missing or unreadable", path=path, fix="re-run the capture / synth stage")
    return np.ascontiguousarray(img[..., ::-1])


def read_depth_maps(path: str | os.PathLike, cameras, cells: dict | None = None) -> list[np.ndarray]:
    """Depth maps of one frame (one per camera, in camera order) resampled to the distorted image grids.

    path : the reconstruct stage's depth file (:mod:`rigbuild.io.depth`: camera z in mm on undistorted
    pinhole grids, 0 = none); cameras : the calibrated cameras. Returns (H, W) camera z mm per camera (NaN =
    none). ``cells``: a dict the caller keeps for a sequence; each camera's resampling cells
    (:func:`rigbuild.track.features.image_to_pinhole_cells`) are computed once into it."""
    from rigbuild.io.depth import camera_depth_maps
    from rigbuild.track.features import depth_to_image_grid, image_to_pinhole_cells

    path = Path(path)
    if not path.exists():
        raise InputError("depth map missing", path=path,
                         fix="run the reconstruct stage for this sequence (rule reconstruct) before tracking")
    out = []
    for cam, (d, K) in zip(cameras, camera_depth_maps(path, [cam.id for cam in cameras])):
        if d.shape != (cam.height, cam.width):
            raise InputError(f"depth map of camera {cam.id} is {d.shape}, images are {(cam.height, cam.width)}",
                             path=path, fix="re-run reconstruct at the session's image size")
        c = None
        if cells is not None and np.any(cam.dist):
            key = (cam.id, cam.K.tobytes(), np.asarray(cam.dist).tobytes(), np.asarray(K).tobytes(), d.shape)
            c = cells.get(key)
            if c is None:
                c = cells[key] = image_to_pinhole_cells(cam, K, d.shape)
        out.append(depth_to_image_grid(d, cam, K, cells=c))
    return out


def load_views(spec, cameras, sequence: str, frame: int, depth_dir: str | os.PathLike,
               cells: dict | None = None) -> list[ViewFrame]:
    """The views (image + depth map per camera) of one frame of a ROM sequence (``cells``: see
    :func:`read_depth_maps`)."""
    depths = read_depth_maps(Path(depth_dir) / f"{frame:06d}.npz", cameras, cells)
    return [ViewFrame(cam, read_image_rgb(spec.rom_image(sequence, cam.id, frame)), d)
            for cam, d in zip(cameras, depths)]


def load_template(spec, params: TrackParams) -> Rig:
    """The template rig tracked with (``params.template_rig``, default the session's)."""
    from rigbuild.io.rigs import load_rig

    return load_rig(params.template_for(spec))


def _session(session_dir: str | os.PathLike, cameras_path: str | os.PathLike, params: Mapping | None):
    from rigbuild.dots import painted_dot_vertices
    from rigbuild.io.cameras import read_cameras
    from rigbuild.session import read_session

    tp = from_config(params)
    spec = read_session(Path(session_dir))
    if not spec.painted_dots:
        tp = unpainted(tp)
        log.info("unpainted face (session dots: none): levels %s, neutral registered from landmarks", tp.levels)
    template = load_template(spec, tp)
    return tp, spec, read_cameras(cameras_path), template, painted_dot_vertices(template, spec.dot_stencil_mm)


# --------------------------------------------------------------------------------------------- runners
def run_track_neutral(session_dir: str | os.PathLike, cameras_path: str | os.PathLike,
                      depth_dir: str | os.PathLike, params: Mapping[str, Any] | None,
                      neutral_path: str | os.PathLike, metrics_path: str | os.PathLike) -> dict:
    """Rule track_neutral: register the template to the first ROM sequence's neutral frame.

    depth_dir : that sequence's depth folder; params : ``config["params"]["track"]``. Writes ``neutral.npz``
    (vertices, markers (mm), marker ids/names, similarity, dot labels, sequence, frame; with the ``landmarks``
    coarse level or ``registration.dot_surface_points`` each dot's surface point ``dot_surface_vertices`` /
    ``dot_surface_bary``) and the fragment
    ``{"tracking": {neutral_scan_rms_mm, neutral_dot_rms_mm, neutral_dots_matched, neutral_seconds}}``."""
    from rigbuild.io.atomic import save_npz
    from rigbuild.io.metrics import write_metrics_fragment

    tp, spec, cameras, template, dot_vertices = _session(session_dir, cameras_path, params)
    seq = spec.rom[0]
    frames = load_views(spec, cameras, seq.name, seq.neutral_frame, depth_dir)
    t0 = time.perf_counter()
    reg, _ = track_neutral_frame(template, frames, tp, dot_vertices=dot_vertices,
                                 where=f"sequence '{seq.name}' frame {seq.neutral_frame}")
    extra = {} if reg.dot_surface is None else {"dot_surface_vertices": reg.dot_surface[0],
                                                "dot_surface_bary": reg.dot_surface[1],
                                                "dot_surface_dots": reg.dot_surface[2]}
    save_npz(neutral_path, vertices=reg.vertices.astype(np.float32), markers=reg.markers.astype(np.float32),
             marker_vertices=template.marker_vertices, marker_names=np.asarray(template.marker_names),
             scale=np.float64(reg.similarity[0]), rotation=reg.similarity[1], translation=reg.similarity[2],
             dot_labels=reg.dot_labels, sequence=np.asarray(seq.name), frame=np.int64(seq.neutral_frame), **extra)
    values = {"neutral_scan_rms_mm": reg.scan_rms_mm, "neutral_dot_rms_mm": reg.dot_rms_mm,
              "neutral_dots_matched": int((reg.dot_labels >= 0).sum()), "neutral_seconds": time.perf_counter() - t0}
    return write_metrics_fragment(metrics_path, "tracking", values)


def _write_csv(path: str | os.PathLike, rows: list[dict]) -> None:
    from rigbuild.io.atomic import write_text

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0].keys()))
    w.writeheader()
    w.writerows(rows)
    write_text(path, buf.getvalue())


def _write_sequence_outputs(outputs: Mapping[str, str], template: Rig, fps: float, frame_ids: list[int],
                            V: np.ndarray, C: np.ndarray, markers: np.ndarray, stats: list[FrameStats],
                            frames: list[list[ViewFrame]], title: str) -> None:
    """vertices.npz, markers.npz/.c3d, residuals.csv/.png and the overlays of a tracked sequence.

    V (F, V, 3) float32 mm, C (F, V) confidences, markers (F, M, 3) mm (lost frames already NaN)."""
    from rigbuild.io.atomic import save_npz
    from rigbuild.io.markers import write_markers_c3d
    from rigbuild.track.plots import draw_overlay, residual_plot

    lost = np.asarray([s.lost for s in stats], dtype=bool)
    save_npz(outputs["vertices"], vertices=V, confidence=C, frames=np.asarray(frame_ids), lost=lost)
    save_npz(outputs["markers"], markers=markers.astype(np.float32), marker_names=np.asarray(template.marker_names),
             fps=np.float64(fps), frames=np.asarray(frame_ids))
    write_markers_c3d(outputs["c3d"], markers, template.marker_names, fps)
    rows = stats_rows(stats)
    _write_csv(outputs["residuals_csv"], rows)
    residual_plot(outputs["residuals_png"], rows, title)
    ov = Path(outputs["overlay"])
    ov.mkdir(parents=True, exist_ok=True)
    peak = int(np.argmax([np.abs(V[i] - V[0]).max() for i in range(len(V))]))
    for i in sorted({0, peak, len(V) - 1}):
        draw_overlay(ov / f"{frame_ids[i]:06d}.jpg", frames[i], V[i], markers[i], template.face_vertices)


def run_track_sequence(session: str, session_dir: str | os.PathLike, cameras_path: str | os.PathLike,
                       neutral_path: str | os.PathLike, sequence: str, depth_dir: str | os.PathLike,
                       anchor_depth_dir: str | os.PathLike, params: Mapping[str, Any] | None, threads: int,
                       outputs: Mapping[str, str]) -> dict:
    """Rule track_sequence: track one ROM sequence from its neutral frame.

    session : the session's name (plot titles); depth_dir, anchor_depth_dir : depth folders of the sequence
    and of the first ROM sequence (its neutral frame is the anchor); params : ``config["params"]["track"]``;
    threads : the rule's threads (``workers``); outputs : paths by name (vertices, markers, c3d,
    residuals_csv, residuals_png, overlay, metrics). The fragment is
    ``{"tracking": {"sequences": {<seq>: {frames, lost_frames, seconds_per_frame, median_residual_mm, lost}}}}``.
    """
    from rigbuild.io.metrics import write_metrics_fragment

    tp, spec, cameras, template, dot_vertices = _session(session_dir, cameras_path, params)
    seq = next((s for s in spec.rom if s.name == sequence), None)
    if seq is None:
        raise InputError(f"no ROM sequence '{sequence}'", path=Path(session_dir) / "session.yaml")
    tp.workers = max(int(threads), 1)
    with np.load(neutral_path) as z:
        neutral = z["vertices"].astype(np.float64)
        dot_surface = (z["dot_surface_vertices"], z["dot_surface_bary"]) if "dot_surface_vertices" in z else None
    anchor_seq = spec.rom[0]
    cells: dict = {}  # each camera's depth resampling, computed once for the sequence
    anchor = load_views(spec, cameras, anchor_seq.name, anchor_seq.neutral_frame, anchor_depth_dir, cells)
    frame_ids = [f for f in seq.frames if f >= seq.neutral_frame]
    frames = [load_views(spec, cameras, seq.name, f, depth_dir, cells) for f in frame_ids]
    t0 = time.perf_counter()
    V, C, markers, stats = track_rom_sequence(template, neutral, anchor, frames, frame_ids, seq.name, tp,
                                              progress=lambda s: log.info("frame %d: %s", s.frame, s),
                                              dot_vertices=dot_vertices, dot_surface=dot_surface)
    seconds = time.perf_counter() - t0
    lost = np.asarray([s.lost for s in stats], dtype=bool)
    if lost.any():  # lost frames reach the retargeting stages as marker gaps, not as wrong positions
        markers = markers.copy()
        markers[lost] = np.nan
        log.warning("%s: %d lost frame(s) %s written as marker gaps (NaN)", seq.name, int(lost.sum()),
                    [s.frame for s in stats if s.lost])
    _write_sequence_outputs(outputs, template, spec.fps, frame_ids, V, C, markers, stats, frames,
                            f"{session} / {seq.name}")
    seq_metrics = {"frames": len(frame_ids), "lost_frames": int(sum(s.lost for s in stats)),
                   "seconds_per_frame": seconds / max(len(frame_ids), 1),
                   "median_residual_mm": float(np.nanmedian([s.residual_median_mm for s in stats]))}
    return write_metrics_fragment(outputs["metrics"], "tracking", {"sequences": {seq.name: seq_metrics}})


def run_track_summary(sequence_metrics: Sequence[str | os.PathLike], summary_path: str | os.PathLike,
                      metrics_path: str | os.PathLike) -> dict:
    """Rule track_summary: the sequences' fragments -> ``track_summary.json`` (``{"tracking": {lost_frames,
    sequences (count)}, "sequences": {<seq>: per-sequence values}}``) and the session fragment
    ``{"tracking": {"lost_frames": total, "sequence_count": n}}``."""
    from rigbuild.io.atomic import write_json
    from rigbuild.io.metrics import write_metrics_fragment

    per: dict[str, dict] = {}
    for p in sequence_metrics:
        per.update(json.loads(Path(p).read_text())["tracking"]["sequences"])
    lost = int(sum(int(d.get("lost_frames", 0)) for d in per.values()))
    write_json(summary_path, {"tracking": {"lost_frames": lost, "sequences": len(per)}, "sequences": per})
    return write_metrics_fragment(metrics_path, "tracking", {"lost_frames": lost, "sequence_count": len(per)})


# --------------------------------------------------------------------------------------------- tracking
def track_neutral_frame(template: Rig, frames: list[ViewFrame], params: TrackParams | None = None,
                        dot_vertices: np.ndarray | None = None, where: str = "the neutral frame"
                        ) -> tuple[NeutralRegistration, TrackingMesh]:
    """Register the template neutral to the neutral frame's reconstruction (depth maps) and painted dots.

    params : :class:`TrackParams` (its ``dots`` detect the dots, none are used without the ``features`` level;
    its ``registration`` drives :func:`register_neutral`; ``registration.coarse: landmarks`` also finds and
    triangulates the face landmarks, :func:`rigbuild.track.landmarks3d.neutral_landmarks`); dot_vertices : (D,) template vertices of the painted
    dots (:func:`rigbuild.dots.painted_dot_vertices`), default the markers; where : the frame, for errors
    ("sequence 'rom01' frame 0").
    """
    require_markers(template)
    p = params or TrackParams()
    landmarks = None
    if p.registration.coarse == "landmarks":
        from rigbuild.track.landmarks3d import neutral_landmarks

        landmarks = neutral_landmarks(template, [f.camera for f in frames], [f.image for f in frames], where)
    if "features" in p.levels:
        dots, rays = neutral_dots(frames, p.dots)
    elif p.registration.coarse == "dots":
        raise InputError(f"{where}: without the painted-dot level (levels {list(p.levels)}) the neutral cannot be "
                         "registered from dots", path="config params.track.registration.coarse",
                         fix="use coarse: landmarks, or add 'features' to params.track.levels")
    else:  # an unpainted face: landmarks, closest points and the depth maps alone
        dots, rays = np.zeros((0, 3)), None
    pts, nrm = scan_from_depth(frames)
    mesh = build_tracking_mesh(template.neutral, template.faces, template.face_region)
    reg = register_neutral(template, pts, nrm, dots, rays, p.registration, mesh=mesh,
                           depth_views=[(f.camera, f.depth) for f in frames], dot_vertices=dot_vertices,
                           landmarks=landmarks)
    return reg, mesh


def track_rom_sequence(template: Rig, neutral_vertices: np.ndarray, anchor_frames: list[ViewFrame],
                       frames: list[list[ViewFrame]], frame_ids: list[int], sequence: str,
                       params: TrackParams | None = None, progress=None, dot_vertices: np.ndarray | None = None,
                       dot_surface: tuple[np.ndarray, np.ndarray] | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[FrameStats]]:
    """Track one ROM sequence from its neutral frame.

    template : the template rig (topology, face region, markers); neutral_vertices (V, 3) mm: the registered
    actor neutral; anchor_frames : the views of the global neutral frame; frames : per frame, its views;
    frame_ids : frame numbers; dot_vertices : (D,) template vertices of the painted dots (default the markers);
    dot_surface : (vertex ids (D', 3), bary (D', 3)) each detected dot's own surface point on the registered
    neutral (``neutral.npz``'s ``dot_surface_*``: the ``landmarks`` coarse level, or ``dot_surface_points``): the
    dots are tracked from there instead of from ``dot_vertices``.
    Returns vertices (F, V, 3) float32 mm (full topology), confidence (F, V)
    float32, markers (F, M, 3) mm (lost frames are flagged in stats, not NaN here; :func:`run_track_sequence`
    writes them as gaps),
    stats per frame.
    """
    require_markers(template)
    if len(frames) == 0:
        raise InputError(f"sequence '{sequence}' has no frames", path="session.yaml", fix="check rom frames")
    mesh = build_tracking_mesh(template.neutral, template.faces, template.face_region)
    dot_vertices = template.marker_vertices if dot_vertices is None else np.asarray(dot_vertices, np.int64)
    mk_local = mesh.full_to_local[dot_vertices]
    if np.any(mk_local < 0):
        raise InputError("some painted dot (marker or stencil) vertices are not on the tracked face mesh",
                         fix="markers and stencil dots must lie on the connected skin surface of the template")
    points = None if dot_surface is None else local_surface_points(mesh, *dot_surface)
    tracker = SequenceTracker(mesh.local(neutral_vertices), mesh.faces, mk_local, anchor_frames, params,
                              mesh.vertex_tri, mesh.vertex_corner, dot_points=points)
    V, C, stats = tracker.track(frames, frame_ids, sequence, progress=progress)
    full = np.stack([mesh.to_full(v, neutral_vertices) for v in V])
    if (params or TrackParams()).untracked == "shapes" and mesh.untracked.size and template.n_shapes:
        full = pose_untracked(template, mesh, neutral_vertices, full)
    full = full.astype(np.float32)
    conf = np.zeros((V.shape[0], template.n_vertices), np.float32)
    conf[:, mesh.vertex_ids] = C
    markers = full[:, template.marker_vertices].astype(np.float64)
    return full, conf, markers, stats


def pose_untracked(template: Rig, mesh: TrackingMesh, neutral_vertices: np.ndarray, full: np.ndarray) -> np.ndarray:
    """Tracked full meshes (F, V, 3) mm with the vertices outside the tracking mesh posed by the template's shapes
    (:func:`rigbuild.track.complete.complete_untracked`), the shapes carried onto the registered neutral
    ``neutral_vertices`` (V, 3) mm by the similarity of the template's face region onto it."""
    from rigbuild.geometry.rigid import fit_similarity
    from rigbuild.track.complete import complete_untracked, shapes_in_world

    face = template.face_vertices
    sim = fit_similarity(template.neutral[face], np.asarray(neutral_vertices, np.float64)[face])
    return complete_untracked(full, neutral_vertices, shapes_in_world(template.deltas, sim), face, mesh.untracked)


def local_surface_points(mesh: TrackingMesh, vertices: np.ndarray, bary: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Surface points given as full-topology triangle corners (N, 3) and barycentrics (N, 3) -> tracking-mesh
    triangles (N,) and the barycentrics in those triangles' corner order; InputError if a triangle is not tracked."""
    vertices = np.asarray(vertices, np.int64).reshape(-1, 3)
    bary = np.asarray(bary, np.float64).reshape(-1, 3)
    local = mesh.full_to_local[vertices]
    index = {tuple(sorted(f)): i for i, f in enumerate(mesh.faces.tolist())}
    tri = np.array([index.get(tuple(sorted(f)), -1) for f in local.tolist()], np.int64)
    if np.any(tri < 0) or np.any(local < 0):
        raise InputError("a dot's surface point is not on the tracked face mesh",
                         fix="re-run track_neutral with the same template rig")
    out = np.zeros_like(bary)
    for c in range(3):  # reorder each point's barycentrics to its tracking-mesh triangle's corners
        out += np.where(mesh.faces[tri] == local[:, c:c + 1], bary[:, c:c + 1], 0.0)
    return tri, out


def stats_rows(stats: list[FrameStats]) -> list[dict]:
    """Per-frame statistics as dict rows (for residuals.csv)."""
    return [asdict(s) for s in stats]
