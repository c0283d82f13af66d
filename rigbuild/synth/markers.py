"""Performance markers as an optical mocap system records them: hand-placed on the skin, noisy, with gaps.

The markers are painted dots (:func:`rigbuild.synth.dots.place_painted_dots` from the rig's marker vertices,
the same hand-placement offsets as the registration dots), so they sit off the template's vertices and move
with the skin. A marker is reconstructed in a frame only when at least ``min_cameras`` cameras see it
(:func:`marker_visibility`): it projects inside the image, its surface faces the camera, and the ray from the
camera centre reaches it before any other part of the mesh (an embree ray cast, ``embreex``, against the
deformed, head-moved mesh of that frame; the ICT's eye render helpers and eyelash strips do not occlude:
:func:`occluding_faces`). Elsewhere the sample is a gap (NaN).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from rigbuild.synth.dots import PaintedDots, dot_centres


#: ICT topology: vertices from here on are render helpers (lacrimal fluid, eye blend and occlusion meshes,
#: eyelash strips; ICT-FaceKit README geometry table), not surfaces that hide a marker from a camera.
ICT_N_VERTICES = 26719
ICT_FIRST_HELPER_VERTEX = 24591


def occluding_faces(rig) -> np.ndarray:
    """(F_o,) triangle ids that can hide a marker: for an ICT-topology rig (26,719 vertices) the triangles of
    the skin, mouth and eye sockets, gums, tongue, teeth and eyeballs (every vertex < 24,591); otherwise all."""
    faces = np.asarray(rig.faces)
    if rig.n_vertices == ICT_N_VERTICES:
        return np.flatnonzero((faces < ICT_FIRST_HELPER_VERTEX).all(1))
    return np.arange(faces.shape[0])


def outward_sign(vertices: np.ndarray, faces: np.ndarray) -> float:
    """+1 if the triangles' ``(b - a) x (c - a)`` normals point away from the mesh centroid on the whole
    (area-weighted), else -1. vertices (V, 3), faces (F, 3)."""
    v = np.asarray(vertices, dtype=np.float64)
    n = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    c = v[faces].mean(1) - v.mean(0)
    return 1.0 if float(np.einsum("fi,fi->", n, c)) >= 0 else -1.0


def _ray_first_hit(vertices: np.ndarray, faces: np.ndarray, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance (N,) along unit rays to the first triangle hit (inf on a miss), embree in float32."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(vertices, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.int32))
    res = scene.run(np.ascontiguousarray(origins, dtype=np.float32), np.ascontiguousarray(dirs, dtype=np.float32),
                    output=1)
    hit = (np.asarray(res["geomID"]) >= 0) & (np.asarray(res["primID"]) >= 0)
    return np.where(hit, np.asarray(res["tfar"], dtype=np.float64), np.inf)


def marker_visibility(vertices: np.ndarray, faces: np.ndarray, placement: PaintedDots, cameras: Sequence,
                      occlusion_tol_mm: float = 0.5, sign: float = 1.0,
                      occluders: np.ndarray | None = None) -> np.ndarray:
    """Which cameras see each marker on one posed mesh: (C, M) bool.

    vertices (V, 3) world mm of the frame; faces (F, 3); placement: the M markers; cameras:
    :class:`~rigbuild.camera.Camera` list. Seen = projects inside the image (distortion included, pixel
    centres in [-0.5, size - 0.5]), in front of the camera, faces it (``sign * n . (c - x) > 0`` with ``n``
    the normal of the marker's triangle), and the first surface the camera ray meets lies within
    ``occlusion_tol_mm`` of the marker's distance (rays cast against ``faces[occluders]``; None: all faces).
    """
    V = np.asarray(vertices, dtype=np.float64)
    X = dot_centres(placement, V)
    tv = placement.triangle_vertices
    n = sign * np.cross(V[tv[:, 1]] - V[tv[:, 0]], V[tv[:, 2]] - V[tv[:, 0]])
    out = np.zeros((len(cameras), X.shape[0]), dtype=bool)
    if X.shape[0] == 0:
        return out
    origins, dirs, dist, cand = [], [], [], []
    for c, cam in enumerate(cameras):
        uv = cam.project(X)
        inside = np.isfinite(uv).all(1) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= cam.width - 0.5) \
            & (uv[:, 1] >= -0.5) & (uv[:, 1] <= cam.height - 0.5)
        to_cam = cam.center[None] - X
        facing = np.einsum("mi,mi->m", n, to_cam) > 0
        ok = np.flatnonzero(inside & facing)
        if ok.size:
            r = X[ok] - cam.center[None]
            d = np.linalg.norm(r, axis=1)
            origins.append(np.repeat(cam.center[None], ok.size, 0))
            dirs.append(r / d[:, None])
            dist.append(d)
            cand.append(np.stack([np.full(ok.size, c), ok], 1))
    if not cand:
        return out
    occ = faces if occluders is None else np.asarray(faces)[occluders]
    t_hit = _ray_first_hit(V, occ, np.concatenate(origins), np.concatenate(dirs))
    cm = np.concatenate(cand)
    seen = t_hit >= np.concatenate(dist) - occlusion_tol_mm
    out[cm[seen, 0], cm[seen, 1]] = True
    return out


def performance_markers(
    actor,
    weights: np.ndarray,
    R: np.ndarray | None,
    t: np.ndarray | None,
    placement: PaintedDots,
    cameras: Sequence | None,
    noise_mm: float = 0.3,
    seed: int = 0,
    min_cameras: int = 2,
    occlusion_tol_mm: float = 0.5,
    return_seen: bool = False,
    normal_sign: float | None = None,
    occluders: np.ndarray | None = None,
):
    """Recorded marker trajectories (F, M, 3) mm with NaN gaps where fewer than ``min_cameras`` cameras see
    a marker.

    Parameters
    ----------
    actor : the actor :class:`~rigbuild.rig.Rig`; weights (F, K) its expression weights per frame.
    R (F, 3, 3), t (F, 3) mm : rigid head motion ``x' = R x + t`` applied after the expression (None: none).
    placement : the markers on the actor's skin (:func:`rigbuild.synth.dots.place_painted_dots` from
        ``actor.marker_vertices`` with ``missing_fraction=0``, so marker j is site j).
    cameras : the capture cameras (:func:`marker_visibility`); None: no occlusion gaps.
    noise_mm : standard deviation (mm) of isotropic Gaussian noise on each axis of each sample.
    seed : noise seed.
    min_cameras : a marker is reconstructed in a frame when at least this many cameras see it.
    occlusion_tol_mm : see :func:`marker_visibility`.
    return_seen : also return the (F, M) int count of cameras seeing each marker.
    normal_sign : +1 / -1: the sign making ``(b - a) x (c - a)`` point out of the skin; None: from
        :func:`outward_sign` of the actor's neutral (right for a closed or head-like mesh).
    occluders : triangle ids that can hide a marker (None: :func:`occluding_faces` of the actor, which leaves
        out the ICT's eye render helpers).

    Returns markers (F, M, 3) (and seen (F, M) when ``return_seen``).
    """
    W = np.asarray(weights, dtype=np.float64)
    F = W.shape[0]
    faces = actor.faces
    sign = outward_sign(actor.neutral, faces) if normal_sign is None else float(normal_sign)
    flat = actor.deltas.reshape(actor.n_shapes, -1)
    M = len(placement)
    occ = occluding_faces(actor) if occluders is None else np.asarray(occluders)
    clean = np.empty((F, M, 3))
    seen = np.zeros((F, M), dtype=np.int64)
    for f in range(F):
        V = actor.neutral + (W[f] @ flat).reshape(-1, 3)
        if R is not None:
            V = V @ np.asarray(R[f]).T + (0 if t is None else np.asarray(t[f]))
        clean[f] = dot_centres(placement, V)
        if cameras is not None:
            seen[f] = marker_visibility(V, faces, placement, cameras, occlusion_tol_mm, sign, occ).sum(0)
    rng = np.random.default_rng(seed)
    out = clean + rng.normal(scale=noise_mm, size=clean.shape) if noise_mm > 0 else clean.copy()
    if cameras is not None:
        out[seen < min_cameras] = np.nan
    return (out, seen) if return_seen else out
