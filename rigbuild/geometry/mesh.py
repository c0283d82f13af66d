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
