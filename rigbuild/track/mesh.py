"""The tracking mesh: the part of the template's topology that the Laplacian solve deforms.

Template heads carry disconnected parts (ICT: eyeballs, teeth, gums, tear ducts) that cameras barely see
and whose Laplacian has a null space. The tracking mesh is the connected component(s) touching the
face region; every other vertex rides along with the displacement of its nearest tracked vertices
(inverse-distance weights fixed in the rest pose), so outputs stay in the full template topology.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from rigbuild.errors import InputError


@dataclass
class TrackingMesh:
    """Sub-mesh of a template used for tracking.

    vertex_ids : (T,) full-mesh ids of the tracked vertices (sorted); faces : (F', 3) triangles in
    tracked-vertex numbering; n_full : V of the full mesh; face_local : (R,) face-region vertices in
    tracked numbering; attach_ids (U, k) tracked-local neighbours and attach_w (U, k) weights for the
    untracked vertices ``untracked`` (U,) full ids; vertex_tri (T,) one triangle containing each tracked
    vertex and vertex_corner (T,) the vertex's corner in it.
    """

    vertex_ids: np.ndarray
    faces: np.ndarray
    n_full: int
    face_local: np.ndarray
    untracked: np.ndarray
    attach_ids: np.ndarray
    attach_w: np.ndarray
    vertex_tri: np.ndarray
    vertex_corner: np.ndarray
    full_to_local: np.ndarray

    @property
    def n(self) -> int:
        return int(self.vertex_ids.size)

    def local(self, full_vertices: np.ndarray) -> np.ndarray:
        """(V, 3) full-topology positions -> (T, 3) tracked positions."""
        return np.asarray(full_vertices)[..., self.vertex_ids, :]

    def to_full(self, tracked: np.ndarray, rest_full: np.ndarray) -> np.ndarray:
        """(T, 3) tracked positions -> (V, 3) full positions; untracked vertices move with the
        inverse-distance-weighted displacement of their nearest tracked vertices relative to ``rest_full``."""
        rest_full = np.asarray(rest_full, dtype=np.float64)
        out = rest_full.copy()
        out[self.vertex_ids] = tracked
        if self.untracked.size:
            disp = tracked - rest_full[self.vertex_ids]
            out[self.untracked] += np.einsum("uk,ukd->ud", self.attach_w, disp[self.attach_ids])
        return out

    def vertex_points(self, local_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Surface-point form (tri (N,), bary (N, 3)) of tracked vertices ``local_ids`` (one-hot barycentrics)."""
        local_ids = np.asarray(local_ids, dtype=np.int64)
        bary = np.zeros((local_ids.size, 3))
        bary[np.arange(local_ids.size), self.vertex_corner[local_ids]] = 1.0
        return self.vertex_tri[local_ids], bary


def build_tracking_mesh(vertices: np.ndarray, faces: np.ndarray, face_region: np.ndarray | None,
                        k_attach: int = 4) -> TrackingMesh:
    """The connected components of ``faces`` that contain a face-region vertex.

    vertices (V, 3) mm rest pose; faces (F, 3); face_region (R,) full ids or None (= all vertices).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    V = vertices.shape[0]
    if faces.size == 0:
        raise InputError("template has no triangles", fix="use a triangle-mesh template rig")
    adj = sp.coo_matrix((np.ones(faces.size), (faces.ravel(), np.roll(faces, 1, axis=1).ravel())), shape=(V, V))
    _, label = connected_components(adj, directed=False)
    region = np.arange(V) if face_region is None else np.asarray(face_region, dtype=np.int64)
    keep_labels = np.unique(label[region])
    used = np.zeros(V, dtype=bool)
    used[np.unique(faces)] = True
    keep = np.isin(label, keep_labels) & used
    ids = np.flatnonzero(keep)
    full_to_local = np.full(V, -1, dtype=np.int64)
    full_to_local[ids] = np.arange(ids.size)
    fmask = keep[faces].all(axis=1)
    sub_faces = full_to_local[faces[fmask]]
    face_local = full_to_local[region]
    face_local = face_local[face_local >= 0]
    untracked = np.flatnonzero(~keep)
    if untracked.size:
        k = min(k_attach, ids.size)
        d, nn = cKDTree(vertices[ids]).query(vertices[untracked], k=k)
        d = d.reshape(untracked.size, k)
        nn = nn.reshape(untracked.size, k)
        w = 1.0 / np.maximum(d, 1e-6)
        w /= w.sum(1, keepdims=True)
    else:
        nn = np.zeros((0, 1), dtype=np.int64)
        w = np.zeros((0, 1))
    vertex_tri = np.full(ids.size, -1, dtype=np.int64)
    vertex_corner = np.zeros(ids.size, dtype=np.int64)
    for c in range(3):
        vertex_tri[sub_faces[:, c]] = np.arange(sub_faces.shape[0])
        vertex_corner[sub_faces[:, c]] = c
    return TrackingMesh(ids, sub_faces, V, face_local, untracked, nn, w, vertex_tri, vertex_corner, full_to_local)
