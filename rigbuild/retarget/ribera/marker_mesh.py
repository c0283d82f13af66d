"""E_Mesh's marker mesh (Ribera et al. 2017, sec. 4.4, eq. 11): a triangulation of the markers in a 2D
parameterization with eyelid / lip contact edges, and its cotangent Laplacian."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import Delaunay, cKDTree

@dataclass
class MarkerTriangulation:
    """Triangulation of the M markers: triangles (T, 3), contact edges (C, 2), uv (M, 2)."""

    triangles: np.ndarray
    contact_edges: np.ndarray
    uv: np.ndarray

    @property
    def edges(self) -> np.ndarray:
        """(E, 2) unique sorted edges of the triangles plus the contact edges."""
        t = self.triangles
        e = np.vstack([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]], self.contact_edges.reshape(-1, 2)])
        return np.unique(np.sort(e, axis=1), axis=0)


def planar_parameterization(points: np.ndarray) -> np.ndarray:
    """(M, 2) 2D parameterization of face markers (M, 3): projection on their two principal axes.

    A face marker set is a shallow cap; its two largest principal directions are the face's width and
    height. Used when the character has no UV layout for the markers.
    """
    p = np.asarray(points, float)
    c = p - p.mean(0)
    _, _, Vt = np.linalg.svd(c, full_matrices=False)
    return c @ Vt[:2].T


def _triangle_min_angle(uv: np.ndarray, tris: np.ndarray) -> np.ndarray:
    a, b, c = uv[tris[:, 0]], uv[tris[:, 1]], uv[tris[:, 2]]

    def ang(p, q, r):
        u, v = q - p, r - p
        cos = (u * v).sum(1) / np.maximum(np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1), 1e-300)
        return np.degrees(np.arccos(np.clip(cos, -1, 1)))

    return np.minimum(np.minimum(ang(a, b, c), ang(b, c, a)), ang(c, a, b))


def marker_triangulation(
    s0: np.ndarray,
    ds: np.ndarray,
    uv: np.ndarray | None = None,
    contact_pairs: np.ndarray | None = None,
    min_boundary_angle_deg: float = 12.0,
    contact_ratio: float = 0.5,
    contact_neighbours: int = 6,
) -> MarkerTriangulation:
    """Triangulate the markers in a 2D parameterization and add eyelid / lip contact edges.

    Parameters
    ----------
    s0 : (M, 3) neutral marker positions (character); ds : (K, M, 3) sparse blendshapes.
    uv : (M, 2) parameterization (default :func:`planar_parameterization` of ``s0``).
    contact_pairs : (C, 2) marker index pairs to connect (upper/lower eyelid, upper/lower lip). Default:
        detected - pairs among each marker's ``contact_neighbours`` nearest neighbours whose distance changes
        by more than ``contact_ratio`` (relative) in some blendshape (lids closing, lips parting).
    min_boundary_angle_deg : boundary slivers of the Delaunay triangulation below this angle are peeled off.
    """
    s0 = np.asarray(s0, float)
    M = s0.shape[0]
    uv = planar_parameterization(s0) if uv is None else np.asarray(uv, float)
    tris = Delaunay(uv).simplices.astype(np.int64)
    # peel thin boundary triangles (convex-hull slivers) repeatedly
    for _ in range(M):
        e = np.sort(np.vstack([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
        _, inv, cnt = np.unique(e, axis=0, return_inverse=True, return_counts=True)
        boundary_edge = (cnt[inv.reshape(-1)] == 1).reshape(3, -1).T
        on_boundary = boundary_edge.any(1)
        thin = on_boundary & (_triangle_min_angle(uv, tris) < min_boundary_angle_deg)
        if not thin.any() or thin.sum() == tris.shape[0]:
            break
        tris = tris[~thin]
    if contact_pairs is None:
        tree = cKDTree(s0)
        kk = min(contact_neighbours + 1, M)
        _, nn = tree.query(s0, k=kk)
        pairs = np.unique(np.sort(np.column_stack([np.repeat(np.arange(M), kk - 1), nn[:, 1:].ravel()]), axis=1), axis=0)
        rest = np.linalg.norm(s0[pairs[:, 0]] - s0[pairs[:, 1]], axis=1)
        moved = s0[None] + ds
        d = np.linalg.norm(moved[:, pairs[:, 0]] - moved[:, pairs[:, 1]], axis=2)  # (K, P)
        change = np.abs(d - rest[None]).max(0) / np.maximum(rest, 1e-9)
        contact = pairs[change > contact_ratio]
    else:
        contact = np.asarray(contact_pairs, dtype=np.int64).reshape(-1, 2)
    tri_edges = np.unique(np.sort(np.vstack([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1), axis=0)
    if contact.size:
        known = {tuple(e) for e in tri_edges.tolist()}
        contact = np.array([e for e in np.sort(contact, axis=1).tolist() if tuple(e) not in known], dtype=np.int64)
    return MarkerTriangulation(tris, contact.reshape(-1, 2), uv)


def marker_laplacian(points: np.ndarray, tri: MarkerTriangulation) -> sp.csr_matrix:
    """(M, M) cotangent Laplacian of the marker triangulation at ``points`` (M, 3), plus contact edges.

    ``(L x)_i = sum_j w_ij (x_j - x_i)`` with cotangent weights ``w_ij = (cot a_ij + cot b_ij) / 2``
    (Pinkall and Polthier 1993). Contact edges, which belong to no triangle, get the mean absolute
    cotangent weight of the triangulation.
    """
    p = np.asarray(points, float)
    M = p.shape[0]
    t = tri.triangles
    rows, cols, vals = [], [], []
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        # angle at k opposite edge (i, j)
        u = p[t[:, i]] - p[t[:, k]]
        v = p[t[:, j]] - p[t[:, k]]
        cot = (u * v).sum(1) / np.maximum(np.linalg.norm(np.cross(u, v), axis=1), 1e-12)
        rows += [t[:, i], t[:, j]]
        cols += [t[:, j], t[:, i]]
        vals += [0.5 * cot, 0.5 * cot]
    W = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(M, M)).tocsr()
    if tri.contact_edges.size:
        wc = float(np.abs(W.data).mean()) if W.nnz else 1.0
        c = tri.contact_edges
        W = W + sp.coo_matrix((np.full(2 * len(c), wc), (np.r_[c[:, 0], c[:, 1]], np.r_[c[:, 1], c[:, 0]])), shape=(M, M)).tocsr()
    return (W - sp.diags(np.asarray(W.sum(1)).ravel())).tocsr()
