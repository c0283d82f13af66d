"""Stage-level orchestration of tracking (pure functions over loaded data; I/O lives in scripts/track.py).

- :func:`track_neutral_frame`: painted dots + depth maps of the global neutral frame -> registered neutral.
- :func:`track_rom_sequence`: a ROM sequence's views -> tracked vertices in full template topology,
  confidences, marker trajectories and per-frame statistics.
"""

from __future__ import annotations

from dataclasses import asdict

import numpy as np

from rigbuild.errors import InputError
from rigbuild.rig import Rig
from rigbuild.track.matches import ViewFrame
from rigbuild.track.mesh import TrackingMesh, build_tracking_mesh
from rigbuild.track.register import NeutralRegistration, register_neutral, require_markers
from rigbuild.track.sequence import FrameStats, SequenceTracker, TrackParams, neutral_dots, scan_from_depth


def track_neutral_frame(template: Rig, frames: list[ViewFrame], params: TrackParams | None = None,
                        registration: dict | None = None, dot_vertices: np.ndarray | None = None
                        ) -> tuple[NeutralRegistration, TrackingMesh]:
    """Register the template neutral to the neutral frame's reconstruction (depth maps) and painted dots.

    registration : extra keyword arguments of :func:`register_neutral` (iterations, lam_schedule, ...);
    dot_vertices : (D,) template vertices of the painted dots (:func:`rigbuild.dots.painted_dot_vertices`),
    default the markers.
    """
    require_markers(template)
    p = params or TrackParams()
    dots, rays = neutral_dots(frames, p.dots)
    pts, nrm = scan_from_depth(frames)
    mesh = build_tracking_mesh(template.neutral, template.faces, template.face_region)
    kw = {"depth_views": [(f.camera, f.depth) for f in frames], "dot_vertices": dot_vertices}
    kw.update(registration or {})
    reg = register_neutral(template, pts, nrm, dots, rays, mesh=mesh, **kw)
    return reg, mesh


def track_rom_sequence(template: Rig, neutral_vertices: np.ndarray, anchor_frames: list[ViewFrame],
                       frames: list[list[ViewFrame]], frame_ids: list[int], sequence: str,
                       params: TrackParams | None = None, progress=None, dot_vertices: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[FrameStats]]:
    """Track one ROM sequence from its neutral frame.

    template : the template rig (topology, face region, markers); neutral_vertices (V, 3) mm: the registered
    actor neutral; anchor_frames : the views of the global neutral frame; frames : per frame, its views;
    frame_ids : frame numbers; dot_vertices : (D,) template vertices of the painted dots (default the markers).
    Returns vertices (F, V, 3) float32 mm (full topology), confidence (F, V)
    float32, markers (F, M, 3) mm (lost frames are flagged in stats, not NaN here; scripts/track.py writes them as gaps),
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
    tracker = SequenceTracker(mesh.local(neutral_vertices), mesh.faces, mk_local, anchor_frames, params,
                              mesh.vertex_tri, mesh.vertex_corner)
    V, C, stats = tracker.track(frames, frame_ids, sequence, progress=progress)
    full = np.stack([mesh.to_full(v, neutral_vertices) for v in V]).astype(np.float32)
    conf = np.zeros((V.shape[0], template.n_vertices), np.float32)
    conf[:, mesh.vertex_ids] = C
    markers = full[:, template.marker_vertices].astype(np.float64)
    return full, conf, markers, stats


def stats_rows(stats: list[FrameStats]) -> list[dict]:
    """Per-frame statistics as dict rows (for residuals.csv)."""
    return [asdict(s) for s in stats]
