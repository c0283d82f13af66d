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
