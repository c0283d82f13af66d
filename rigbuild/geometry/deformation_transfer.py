"""Deformation gradients and deformation transfer (Sumner and Popovic 2004) for same-topology meshes.

Per triangle ``f`` with corners ``a, b, c`` the *4th-vertex frame* is
``V_f = [b - a, c - a, n_f / sqrt(|n_f|)]`` with ``n_f = (b - a) x (c - a)`` (Sumner and Popovic 2004,
eq. 1-3); the deformation gradient of a deformed copy is ``T_f = V~_f V_f^{-1}`` (3, 3).

The linear *gradient operator* ``G`` (3F, V) maps a per-vertex scalar (one coordinate of a deformed
mesh) to its per-triangle gradient on the reference mesh. Stacking the x, y, z coordinates as three
columns, ``(G X)[3f + j, c] = T_f[c, j]`` restricted to the triangle's plane, i.e. ``G X`` gives
``T_f P_f`` with ``P_f`` the projector onto the reference triangle's plane. This is Sumner and
Popovic's unknown 4th vertex eliminated in closed form (Botsch et al. 2006, "Deformation transfer for
detail-preserving surface editing", show the two are equivalent up to the normal component, which
cannot be matched by any vertex positions): it is linear in the vertices, the same for x, y and z
(so the coordinates are three right-hand sides of one factored system), and it is the operator
``G`` that Ma et al. 2016 (eq. 7) use in the deformation regularization ``E_r``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph

from rigbuild.errors import InputError
from rigbuild.geometry.sparse_cholesky import SparseCholesky


def triangle_frames(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """4th-vertex frames ``[b - a, c - a, n / sqrt(|n|)]`` as columns.

    vertices : (..., V, 3); faces : (F, 3). Returns (..., F, 3, 3) (columns are the frame vectors).
    """
    v = np.asarray(vertices, dtype=np.float64)
    a = v[..., faces[:, 0], :]
    e1 = v[..., faces[:, 1], :] - a
    e2 = v[..., faces[:, 2], :] - a
    n = np.cross(e1, e2)
    nn = np.sqrt(np.linalg.norm(n, axis=-1, keepdims=True))
    e3 = n / np.maximum(nn, 1e-300)
    return np.stack([e1, e2, e3], axis=-1)


def deformation_gradients(reference: np.ndarray, deformed: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per-triangle deformation gradients ``T_f = V~_f V_f^{-1}`` with the 4th-vertex frame.

    reference : (V, 3); deformed : (..., V, 3) same topology; faces : (F, 3).
    Returns (..., F, 3, 3). Raises InputError for degenerate (zero-area) reference triangles.
    """
    Vr = triangle_frames(reference, faces)
    det = np.linalg.det(Vr)
    if np.any(np.abs(det) < 1e-300):
        bad = int(np.flatnonzero(np.abs(det) < 1e-300)[0])
        raise InputError(f"degenerate (zero-area) reference triangle {bad}: {faces[bad].tolist()}",
                         fix="remove degenerate triangles from the mesh")
    Vinv = np.linalg.inv(Vr)
    return triangle_frames(deformed, faces) @ Vinv


def gradient_operator(reference: np.ndarray, faces: np.ndarray,
                      face_weights: np.ndarray | None = None) -> sp.csr_matrix:
    """The per-triangle gradient operator ``G`` (3F, V) on the reference mesh.

    For a per-vertex scalar ``x`` (V,), ``(G x)[3f:3f+3]`` is the gradient of its piecewise-linear
    interpolant on triangle ``f`` (a 3-vector in the triangle's plane), i.e. ``x_b - x_a`` and
    ``x_c - x_a`` mapped through the pseudo-inverse of ``[b - a, c - a]``. Applied to a deformed
    mesh's coordinates (V, 3) it gives the in-plane part of the deformation gradients:
    ``(G X).reshape(F, 3, 3).transpose(0, 2, 1) == T_f P_f``. ``G @ reference`` is ``P_f``.
    ``face_weights`` (F,) multiplies each triangle's rows (e.g. sqrt of areas); default unweighted
    as in Sumner and Popovic 2004.
    """
    ref = np.asarray(reference, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    a = ref[faces[:, 0]]
    E = np.stack([ref[faces[:, 1]] - a, ref[faces[:, 2]] - a], axis=-1)  # (F, 3, 2)
    EtE = np.einsum("fki,fkj->fij", E, E)
    det = EtE[:, 0, 0] * EtE[:, 1, 1] - EtE[:, 0, 1] ** 2
    if np.any(det <= 1e-300):
        bad = int(np.flatnonzero(det <= 1e-300)[0])
        raise InputError(f"degenerate (zero-area) triangle {bad}: {faces[bad].tolist()}",
                         fix="remove degenerate triangles from the mesh")
    pinv = np.linalg.solve(EtE, np.transpose(E, (0, 2, 1)))  # (F, 2, 3): rows for edge b-a and c-a
    if face_weights is not None:
        pinv = pinv * np.asarray(face_weights, dtype=np.float64)[:, None, None]
    F = faces.shape[0]
    rows = (3 * np.arange(F)[:, None] + np.arange(3)[None, :])  # (F, 3)
    vals_b = pinv[:, 0, :]
    vals_c = pinv[:, 1, :]
    vals_a = -(vals_b + vals_c)
    r = np.concatenate([rows, rows, rows], axis=1).ravel()
    c = np.concatenate([np.repeat(faces[:, [0]], 3, 1), np.repeat(faces[:, [1]], 3, 1),
                        np.repeat(faces[:, [2]], 3, 1)], axis=1).ravel()
    v = np.concatenate([vals_a, vals_b, vals_c], axis=1).ravel()
    return sp.csr_matrix((v, (r, c)), shape=(3 * F, ref.shape[0]))


def face_components(n_vertices: int, faces: np.ndarray) -> np.ndarray:
    """(V,) label of the face-connected component of each vertex (vertices in no face get their own)."""
    f = np.asarray(faces, dtype=np.int64)
    r = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    c = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    A = sp.coo_matrix((np.ones(r.size), (r, c)), shape=(n_vertices, n_vertices))
    return csgraph.connected_components(A, directed=False)[1]


def default_support_tol(vertices: np.ndarray) -> float:
    """Displacements at or below this are "static" (zero): 1e-6 of the bounding-box diagonal."""
    v = np.asarray(vertices)
    return 1e-6 * float(np.linalg.norm(v.max(0) - v.min(0)))


def deformation_transfer(
    source_neutral: np.ndarray,
    source_deltas: np.ndarray,
    faces: np.ndarray,
    target_neutral: np.ndarray,
    anchor: np.ndarray | None = None,
    support_tol: float | None = None,
) -> np.ndarray:
    """Transfer expression displacements from a source character to a same-topology target.

    Each target shape minimizes ``sum_f || T_f(target shape) - T_f(source shape) ||^2`` (Sumner and
    Popovic 2004) with the target's 4th vertices eliminated (module docstring): per shape one sparse
    SPD system ``G^T G d = G^T (T_s - I)`` for the target displacement ``d``, with ``G`` built on the
    target neutral, factored once (CHOLMOD) and solved for x, y, z as three right-hand sides.

    Translation freedom and locality: vertices that do not move in the source shape
    (``|delta| <= support_tol``) and ``anchor`` vertices stay exactly static in the target shape (a
    Dirichlet boundary that also fixes the translation and keeps each shape's local support, which
    the personalization's ``D_ki = 0 where D*_ki = 0`` relies on). A mesh component that moves as a
    whole (e.g. the lower teeth in ``jawOpen``) has no static vertex: its mean displacement is set to
    the source's mean displacement scaled by the component's size ratio (target / source RMS radius).

    Parameters
    ----------
    source_neutral : (V, 3) source neutral (any units; the result is in the target's units).
    source_deltas : (K, V, 3) or (V, 3) source displacements.
    faces : (F, 3) triangles shared by both meshes.
    target_neutral : (V, 3) target neutral.
    anchor : optional (A,) vertex ids held static in every shape.
    support_tol : displacement magnitude treated as zero (default :func:`default_support_tol` of the
        source neutral).

    Returns
    -------
    target_deltas : (K, V, 3) (or (V, 3) for a single shape), exactly zero outside each shape's support.
    Identity transfer (target == source) returns the source deltas; a uniformly scaled target gives
    scaled deltas.
    """
    src = np.asarray(source_neutral, dtype=np.float64)
    tgt = np.asarray(target_neutral, dtype=np.float64)
    deltas = np.asarray(source_deltas, dtype=np.float64)
    single = deltas.ndim == 2
    if single:
        deltas = deltas[None]
    faces = np.asarray(faces, dtype=np.int64)
    V = src.shape[0]
    if tgt.shape != src.shape or deltas.shape[1:] != (V, 3):
        raise InputError(
            f"deformation transfer needs the same topology: source neutral {src.shape}, "
            f"target neutral {tgt.shape}, deltas {deltas.shape}",
            fix="both meshes must have the same vertex count and order (template topology)",
        )
    if faces.size and (faces.min() < 0 or faces.max() >= V):
        raise InputError(f"face indices outside [0, {V})")
    tol = default_support_tol(src) if support_tol is None else float(support_tol)

    G = gradient_operator(tgt, faces)
    GtG = (G.T @ G).tocsr()
    Gt = G.T.tocsr()
    Vinv_src = np.linalg.inv(triangle_frames(src, faces))
    comp = face_components(V, faces)
    n_comp = int(comp.max()) + 1
    comp_size = np.bincount(comp, minlength=n_comp)
    fixed_always = np.zeros(V, dtype=bool)
    if anchor is not None:
        fixed_always[np.asarray(anchor, dtype=np.int64)] = True

    out = np.zeros_like(deltas)
    eye = np.eye(3)
    for k in range(deltas.shape[0]):
        dk = deltas[k]
        moving = (np.linalg.norm(dk, axis=1) > tol) & ~fixed_always
        if not moving.any():
            continue
        T = triangle_frames(src + dk, faces) @ Vinv_src  # (F, 3, 3)
        b = (T - eye).transpose(0, 2, 1).reshape(-1, 3)  # rows 3f+j, columns coordinate c
        rhs_all = Gt @ b  # (V, 3)
        # components that move as a whole: pin one vertex, shift afterwards
        moving_count = np.bincount(comp[moving], minlength=n_comp)
        floating = np.flatnonzero((moving_count == comp_size) & (comp_size > 0))
        free = moving.copy()
        pins = []
        for c in floating:
            members = np.flatnonzero(comp == c)
            free[members[0]] = False
            pins.append(members)
        idx = np.flatnonzero(free)
        sol = np.zeros((V, 3))
        if idx.size:
            A = GtG[idx][:, idx]
            sol[idx] = SparseCholesky(A).solve(rhs_all[idx])
        for members in pins:
            s_src = src[members] - src[members].mean(0)
            s_tgt = tgt[members] - tgt[members].mean(0)
            r_src = np.sqrt((s_src**2).sum(1).mean())
            ratio = float(np.sqrt((s_tgt**2).sum(1).mean()) / r_src) if r_src > 0 else 1.0
            sol[members] += ratio * dk[members].mean(0) - sol[members].mean(0)
        out[k] = sol
    return out[0] if single else out
