"""Mesh quantities shared by the stages."""

from __future__ import annotations

import numpy as np


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3) of a triangle mesh (vertices (V, 3), faces (F, 3)).

    Isolated vertices (and vertices whose face normals cancel) get the zero vector.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # length = 2 * area
    idx = f.reshape(-1)
    n = np.stack([np.bincount(idx, np.repeat(fn[:, d], 3), minlength=v.shape[0]) for d in range(3)], 1)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def point_cloud_normals(points: np.ndarray, orient: np.ndarray, k: int = 40) -> np.ndarray:
    """Unit normals (N, 3) of a point cloud ``points`` (N, 3) by principal component analysis of each point's
    ``k`` nearest neighbours (the direction of least spread), signed to agree with ``orient`` (N, 3) (e.g. a
    rough normal that faces the camera).

    Normals from neighbouring pixels of a depth map carry the depth noise at a one-pixel baseline (ICT tier:
    7 degrees from the PCA normal at the median); the neighbourhood fit averages it over ~1 mm of surface.
    """
    from scipy.spatial import cKDTree

    P = np.asarray(points, dtype=np.float64)
    if P.shape[0] == 0:
        return np.zeros((0, 3))
    k = int(min(max(k, 3), P.shape[0]))
    _, j = cKDTree(P).query(P, k=k, workers=-1)
    Q = P[j] - P[j].mean(1, keepdims=True)
    C = np.einsum("nki,nkj->nij", Q, Q)
    _, vec = np.linalg.eigh(C)
    n = vec[:, :, 0]
    sign = np.sign(np.einsum("nd,nd->n", n, np.asarray(orient, dtype=np.float64)))
    return n * np.where(sign == 0, 1.0, sign)[:, None]


def points_on_surface(vertices: np.ndarray, faces: np.ndarray, face_ids: np.ndarray, barycentric: np.ndarray,
                      normal_offset: np.ndarray | None = None) -> np.ndarray:
    """Points (..., N, 3) given by triangle ``face_ids`` (N,) and ``barycentric`` (N, 3) on a mesh whose
    ``vertices`` are (..., V, 3) (one mesh or a batch of poses of one topology), moved ``normal_offset`` (N,)
    mm along each triangle's unit normal (the normal of that pose)."""
    v = np.asarray(vertices, dtype=np.float64)
    tri = np.asarray(faces, dtype=np.int64)[np.asarray(face_ids, dtype=np.int64)]  # (N, 3)
    corners = v[..., tri, :]  # (..., N, 3, 3)
    p = np.einsum("...nkc,nk->...nc", corners, np.asarray(barycentric, dtype=np.float64))
    if normal_offset is not None:
        n = np.cross(corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :])
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
        p = p + np.asarray(normal_offset, dtype=np.float64)[:, None] * n
    return p


def closest_surface_points(vertices: np.ndarray, faces: np.ndarray,
                           points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The closest point on a triangle mesh to each of ``points`` (N, 3): (face ids (N,), barycentric (N, 3),
    signed distance (N,) along the triangle's normal, mm; positive on the side the normal points to)."""
    import igl

    V = np.ascontiguousarray(vertices, dtype=np.float64)
    F = np.ascontiguousarray(faces, dtype=np.int64)
    P = np.ascontiguousarray(points, dtype=np.float64)
    _, tri, closest = igl.point_mesh_squared_distance(P, V, F)
    tri = np.asarray(tri, dtype=np.int64).reshape(-1)
    closest = np.ascontiguousarray(closest, dtype=np.float64).reshape(-1, 3)
    f = F[tri]
    bary = np.asarray(igl.barycentric_coordinates(closest, np.ascontiguousarray(V[f[:, 0]]),
                                                  np.ascontiguousarray(V[f[:, 1]]),
                                                  np.ascontiguousarray(V[f[:, 2]]))).reshape(-1, 3)
    n = np.cross(V[f[:, 1]] - V[f[:, 0]], V[f[:, 2]] - V[f[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return tri, bary, np.einsum("nc,nc->n", P - closest, n)
