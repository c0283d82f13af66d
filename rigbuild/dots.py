"""The painted dot pattern of a capture session: the rig's markers plus a stencil of registration dots.

A studio paints dots on the actor through a stencil cut from the template, so every dot sits at a known
template vertex. The markers (:mod:`rigbuild.assets.markers`) are the named dots the retargeting stages use;
the **stencil** adds unnamed dots between them, about ``spacing_mm`` apart, so that the neutral registration
knows where the template's skin lands on the actor's away from the markers too (the surface alone does not
say where along it a vertex belongs).

The stencil is a pure function of the template and the spacing (the session's ``dot_stencil_mm``), so the
synthetic generator that paints it and the tracker that looks for it agree without storing vertex lists.
"""

from __future__ import annotations

import numpy as np

from rigbuild.errors import InputError
from rigbuild.geometry.mesh import vertex_normals
from rigbuild.rig import Rig

#: Multi-PIE 68 landmark ranges kept free of stencil dots (dots on lips and lids would be painted on the
#: parts that fold and slide; the markers already cover them).
LIP_LANDMARKS = np.arange(48, 68)
EYE_LANDMARKS = np.arange(36, 48)


def stencil_candidates(rig: Rig, reach_mm: float = 80.0, lip_clearance_mm: float = 6.0,
                       eye_clearance_mm: float = 6.0, max_angle_deg: float = 100.0) -> np.ndarray:
    """Face-region vertices (C,) where a stencil dot may be painted.

    Kept: vertices whose normal is within ``max_angle_deg`` of the face's forward direction (the mean normal at
    the markers), within ``reach_mm`` of a marker (the painted area, not ears or neck), and at least
    ``lip_clearance_mm`` / ``eye_clearance_mm`` from the lip and eye landmarks (when the rig defines them).
    """
    mk = rig.marker_vertices
    if mk.size == 0:
        raise InputError(f"rig '{rig.name}' has no markers: the dot stencil is laid out around them",
                         fix="give the template a marker set (rigbuild/assets/marker_sets/<rig>.json)")
    fv = rig.face_vertices
    P = rig.neutral
    n = vertex_normals(P, rig.faces)
    forward = n[mk].mean(0)
    forward /= max(np.linalg.norm(forward), 1e-12)
    keep = n[fv] @ forward >= np.cos(np.radians(max_angle_deg))
    d_marker = np.linalg.norm(P[fv][:, None] - P[mk][None], axis=2).min(1)
    keep &= d_marker <= reach_mm
    if rig.landmarks is not None:
        for ids, clearance in ((LIP_LANDMARKS, lip_clearance_mm), (EYE_LANDMARKS, eye_clearance_mm)):
            lm = rig.landmarks[ids[ids < rig.landmarks.size]]
            lm = lm[lm >= 0]
            if lm.size:
                keep &= np.linalg.norm(P[fv][:, None] - P[lm][None], axis=2).min(1) >= clearance
    return fv[keep]


def dot_stencil(rig: Rig, spacing_mm: float, **candidate_options) -> np.ndarray:
    """Stencil dot vertices (S,) of ``rig``: farthest-point sampling of :func:`stencil_candidates`, seeded with
    the markers, adding the candidate farthest from every dot placed so far while that distance is at least
    ``spacing_mm``. Every candidate ends within ``spacing_mm`` of a dot (markers included) and no two dots are
    closer than ``spacing_mm`` unless both are markers. Deterministic."""
    if not np.isfinite(spacing_mm) or spacing_mm <= 0:
        raise InputError(f"dot stencil spacing must be a positive number of mm, got {spacing_mm}",
                         path="session.yaml", fix="set dot_stencil_mm to e.g. 16, or remove it (markers only)")
    cand = stencil_candidates(rig, **candidate_options)
    P = rig.neutral[cand]
    gap = np.linalg.norm(P[:, None] - rig.neutral[rig.marker_vertices][None], axis=2).min(1)
    chosen = []
    while P.shape[0]:
        i = int(np.argmax(gap))
        if gap[i] < spacing_mm:
            break
        chosen.append(i)
        gap = np.minimum(gap, np.linalg.norm(P - P[i], axis=1))
    return cand[np.asarray(chosen, dtype=np.int64)]


def painted_dot_vertices(rig: Rig, stencil_spacing_mm: float | None = None) -> np.ndarray:
    """Vertices (D,) of every painted dot: the markers (first, in marker order), then the stencil dots when
    ``stencil_spacing_mm`` is given (None: markers only)."""
    if stencil_spacing_mm is None:
        return rig.marker_vertices.copy()
    return np.concatenate([rig.marker_vertices, dot_stencil(rig, float(stencil_spacing_mm))])
