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

from rigbuild.errors import InputError, RigbuildError


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


def _gradient_coefficients(reference: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per-triangle coefficients of :func:`gradient_operator`: (F, 3, 3) with ``[f, i, j]`` the entry of
    row ``3f + j`` at corner ``i`` (a, b, c) of triangle f. Raises InputError for degenerate triangles."""
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
    return np.stack([-(pinv[:, 0] + pinv[:, 1]), pinv[:, 0], pinv[:, 1]], axis=1)


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
    coef = _gradient_coefficients(ref, faces)  # (F, 3 corners, 3 rows)
    if face_weights is not None:
        coef = coef * np.asarray(face_weights, dtype=np.float64)[:, None, None]
    F = faces.shape[0]
    rows = (3 * np.arange(F)[:, None] + np.arange(3)[None, :])  # (F, 3)
    r = np.concatenate([rows, rows, rows], axis=1).ravel()
    c = np.concatenate([np.repeat(faces[:, [0]], 3, 1), np.repeat(faces[:, [1]], 3, 1),
                        np.repeat(faces[:, [2]], 3, 1)], axis=1).ravel()
    v = coef.reshape(F, 9).ravel()
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
    sample_vertices: np.ndarray | None = None,
    workers: int = 1,
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
    sample_vertices : optional (S,) vertex ids: return the displacements at these vertices only,
        (K, S, 3). Exact, not an approximation: the free vertices of a shape (moving, not anchored)
        split into connected pieces (vertices sharing a triangle) whose systems are independent, and
        only the pieces that contain a sampled vertex (or belong to a mesh component moving as a whole
        that contains one) are solved.
    workers : processes solving the shapes (forked; the shapes are independent systems). The result
        does not depend on it.

    Returns
    -------
    target_deltas : (K, V, 3) (or (V, 3) for a single shape), exactly zero outside each shape's support;
    (K, S, 3) (or (S, 3)) with ``sample_vertices``.
    Identity transfer (target == source) returns the source deltas; a uniformly scaled target gives
    scaled deltas.

    Cost: per shape one CHOLMOD factorization of its free vertices (the Dirichlet set differs per
    shape); the right-hand side is assembled from the triangles touching the solved vertices only.
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
    sample = None
    if sample_vertices is not None:
        sample = np.asarray(sample_vertices, dtype=np.int64).reshape(-1)
        if sample.size and (sample.min() < 0 or sample.max() >= V):
            raise InputError(f"sample vertices outside [0, {V})", fix="pass vertex ids of the mesh")
    tol = default_support_tol(src) if support_tol is None else float(support_tol)
    fixed_always = np.zeros(V, dtype=bool)
    if anchor is not None:
        fixed_always[np.asarray(anchor, dtype=np.int64)] = True
    if sample is None:
        out = _transfer(src, tgt, deltas, faces, fixed_always, tol, None, workers)
        return out[0] if single else out
    if sample.size == 0:
        out = np.zeros((deltas.shape[0], 0, 3))
        return out[0] if single else out
    # mesh components without a sampled vertex cannot influence the samples: drop them first
    comp = face_components(V, faces)
    keep_v = np.isin(comp, comp[sample])
    new_id = np.cumsum(keep_v) - 1
    keep_f = keep_v[faces[:, 0]]  # a triangle lies in one component
    out = _transfer(src[keep_v], tgt[keep_v], deltas[:, keep_v], new_id[faces[keep_f]], fixed_always[keep_v],
                    tol, new_id[sample], workers)
    return out[0] if single else out


def _transfer(src: np.ndarray, tgt: np.ndarray, deltas: np.ndarray, faces: np.ndarray, fixed_always: np.ndarray,
              tol: float, sample: np.ndarray | None, workers: int = 1) -> np.ndarray:
    """The work of :func:`deformation_transfer`: src, tgt (V, 3), deltas (K, V, 3), faces (F, 3), fixed_always
    (V,) bool (anchors), tol (support tolerance), sample (S,) vertex ids or None, workers (processes).
    Returns (K, V or S, 3)."""
    V = src.shape[0]
    coef = _gradient_coefficients(tgt, faces)  # (F, 3 corners, 3 rows)
    # G^T G (lower triangle, COO) assembled from the per-triangle 3x3 corner blocks
    blk = np.einsum("fij,fkj->fik", coef, coef).reshape(-1)
    bi = np.repeat(faces, 3, axis=1).reshape(-1)
    bj = np.tile(faces, (1, 3)).reshape(-1)
    low = bi >= bj
    GtG = sp.coo_matrix((blk[low], (bi[low], bj[low])), shape=(V, V)).tocsr()
    GtG.sum_duplicates()
    Lc = GtG.tocoo()
    l_rows, l_cols, l_vals = Lc.row.astype(np.int64), Lc.col.astype(np.int64), Lc.data
    off = l_rows != l_cols
    e_rows, e_cols = l_rows[off], l_cols[off]  # vertex adjacency (sharing a triangle)
    frames_src = triangle_frames(src, faces)
    # (T_f - I)^T = V_f^-T dV_f^T with dV_f = V~_f - V_f, so the right-hand side G^T (T - I) needs only
    # W = coef V^-T per triangle: rhs[corner i of f] += sum_l W[f, i, l] dV_f[:, l]
    W = np.einsum("fij,flj->fil", coef, np.linalg.inv(frames_src))
    n_src = frames_src[..., 2]
    edges_src = np.stack([frames_src[..., 0], frames_src[..., 1]], axis=1)  # (F, 2, 3): b - a, c - a
    slots = 3 * faces[:, :, None] + np.arange(3)  # (F, 3 corners, 3 coordinates) into rhs.ravel()
    order_rank = _fill_reducing_rank(l_vals, l_rows, l_cols, V)
    comp = face_components(V, faces)
    n_comp = int(comp.max()) + 1
    comp_size = np.bincount(comp, minlength=n_comp)
    first = np.full(n_comp, V, dtype=np.int64)  # pinned vertex of a component moving as a whole
    np.minimum.at(first, comp, np.arange(V))
    magnitude = np.sqrt(np.einsum("kvc,kvc->kv", deltas, deltas))
    sample_comps = None if sample is None else np.unique(comp[sample])

    local = np.full(V, -1, dtype=np.int64)
    n_out = sample.size if sample is not None else V

    def solve_shape(k: int) -> np.ndarray:
        """(V or S, 3) target displacement of shape k."""
        dk = deltas[k]
        moving = (magnitude[k] > tol) & ~fixed_always
        if not moving.any():
            return np.zeros((n_out, 3))
        # components that move as a whole: pin one vertex, shift afterwards
        moving_count = np.bincount(comp[moving], minlength=n_comp)
        floating = np.flatnonzero((moving_count == comp_size) & (comp_size > 0))
        if sample_comps is not None:
            floating = np.intersect1d(floating, sample_comps)  # the others are not sampled
        free = moving.copy()
        free[first[floating]] = False
        if sample is not None:
            free = _pieces_reaching(free, e_rows, e_cols, sample, comp, floating, V)
        idx = np.flatnonzero(free)
        sol = np.zeros((V, 3))
        if idx.size:
            touch = np.flatnonzero(free[faces].any(1))
            fs = faces[touch]
            dkf = dk[fs]  # (Fs, 3 corners, 3)
            e1 = dkf[:, 1] - dkf[:, 0]
            e2 = dkf[:, 2] - dkf[:, 0]
            n = np.cross(edges_src[touch, 0] + e1, edges_src[touch, 1] + e2)
            dn = n / np.maximum(np.sqrt(np.sqrt(np.einsum("fc,fc->f", n, n)))[:, None], 1e-300) - n_src[touch]
            Wt = W[touch]
            contrib = (Wt[:, :, 0, None] * e1[:, None] + Wt[:, :, 1, None] * e2[:, None]
                       + Wt[:, :, 2, None] * dn[:, None])  # (Fs, 3 corners, 3 coordinates)
            slot = slots[touch].reshape(-1)
            rhs = np.bincount(slot, weights=contrib.reshape(-1), minlength=3 * V).reshape(V, 3)
            local[idx] = np.arange(idx.size)
            keep = free[l_rows] & free[l_cols]
            A = (l_vals[keep], local[l_rows[keep]], local[l_cols[keep]], idx.size)
            sol[idx] = _ordered_cholesky_solve(A, np.argsort(order_rank[idx]), rhs[idx])
            local[idx] = -1
        for c in floating:
            members = np.flatnonzero(comp == c)
            s_src = src[members] - src[members].mean(0)
            s_tgt = tgt[members] - tgt[members].mean(0)
            r_src = np.sqrt((s_src**2).sum(1).mean())
            ratio = float(np.sqrt((s_tgt**2).sum(1).mean()) / r_src) if r_src > 0 else 1.0
            sol[members] += ratio * dk[members].mean(0) - sol[members].mean(0)
        return sol if sample is None else sol[sample]

    moving_counts = ((magnitude > tol) & ~fixed_always).sum(axis=1)
    return _map_shapes(solve_shape, deltas.shape[0], (n_out, 3), moving_counts, workers)


_FORKED_SHAPE_SOLVER = None  # the per-shape closure a forked worker inherits (see _map_shapes)


def _solve_shapes_in_worker(ks: list[int]) -> list[np.ndarray]:
    return [_FORKED_SHAPE_SOLVER(k) for k in ks]


def _map_shapes(solve_shape, n_shapes: int, out_shape: tuple[int, int], cost: np.ndarray,
                workers: int) -> np.ndarray:
    """(K, *out_shape) of ``solve_shape(k)`` for every shape, in ``workers`` forked processes when > 1.

    CHOLMOD (through cvxopt) holds the GIL, so threads would not overlap; forked workers inherit the
    precomputed operators without copying or pickling them and return only their shapes. Shapes are
    dealt to the workers largest first (``cost`` (K,), e.g. support sizes) to balance them. Falls back to
    one process where ``fork`` is unavailable."""
    import multiprocessing as mp

    global _FORKED_SHAPE_SOLVER
    out = np.zeros((n_shapes,) + tuple(out_shape))
    workers = int(min(max(workers, 1), n_shapes))
    if workers > 1 and "fork" in mp.get_all_start_methods():
        loads = np.zeros(workers)
        chunks: list[list[int]] = [[] for _ in range(workers)]
        for k in np.argsort(-np.asarray(cost), kind="stable"):
            w = int(np.argmin(loads))
            chunks[w].append(int(k))
            loads[w] += float(cost[k]) + 1.0
        _FORKED_SHAPE_SOLVER = solve_shape
        try:
            with mp.get_context("fork").Pool(workers) as pool:
                results = pool.map(_solve_shapes_in_worker, chunks)
        finally:
            _FORKED_SHAPE_SOLVER = None
        for ks, res in zip(chunks, results):
            for k, r in zip(ks, res):
                out[k] = r
        return out
    for k in range(n_shapes):
        out[k] = solve_shape(k)
    return out


def _fill_reducing_rank(vals: np.ndarray, rows: np.ndarray, cols: np.ndarray, n: int) -> np.ndarray:
    """(n,) position of each unknown in an AMD ordering of the whole (n, n) lower-triangle pattern; the
    restriction of this order to a subset of the unknowns orders that subset's principal submatrix (as
    good as a fresh AMD ordering on mesh systems, at a fraction of the symbolic analysis time)."""
    import cvxopt
    import cvxopt.amd

    if vals.size == 0:
        return np.arange(n, dtype=np.int64)
    perm = np.array(cvxopt.amd.order(cvxopt.spmatrix(vals, rows, cols, (n, n))), dtype=np.int64).ravel()
    rank = np.empty(n, dtype=np.int64)
    rank[perm] = np.arange(n)
    return rank


def _ordered_cholesky_solve(A: tuple, perm: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Solve SPD ``A X = B`` with CHOLMOD using the given fill-reducing permutation (no ordering search).

    A : lower-triangle triplet ``(values, rows, cols, n)``; perm : (n,) permutation; B : (n, r)."""
    import cvxopt
    import cvxopt.cholmod as cholmod

    vals, rows, cols, n = A
    Ac = cvxopt.spmatrix(vals, rows, cols, (int(n), int(n)))
    saved = dict(cholmod.options)
    cholmod.options["nmethods"] = 1
    try:
        symbolic = cholmod.symbolic(Ac, p=cvxopt.matrix(perm.astype(np.int64)), uplo="L")
    finally:
        cholmod.options.clear()
        cholmod.options.update(saved)
    try:
        cholmod.numeric(Ac, symbolic)
    except ArithmeticError as exc:
        raise RigbuildError(f"deformation transfer: sparse system is not positive definite "
                            f"(CHOLMOD failed at column {exc.args[0]})") from None
    X = cvxopt.matrix(np.asfortranarray(B, dtype=np.float64))
    cholmod.solve(symbolic, X)
    return np.array(X, dtype=np.float64).reshape(B.shape)


def _pieces_reaching(free: np.ndarray, e_rows: np.ndarray, e_cols: np.ndarray, sample: np.ndarray,
                     comp: np.ndarray, floating: np.ndarray, V: int) -> np.ndarray:
    """(V,) bool: the free vertices connected (through edges (e_rows, e_cols) between free vertices) to a
    sampled vertex or to any vertex of a floating mesh component that contains a sampled vertex."""
    seeds = np.zeros(V, dtype=bool)
    seeds[sample] = True
    if floating.size:
        hit = np.intersect1d(floating, comp[sample])
        if hit.size:
            seeds |= np.isin(comp, hit)
    seeds &= free
    if not seeds.any():
        return seeds
    both = free[e_rows] & free[e_cols]
    r, c = e_rows[both], e_cols[both]
    # a super node V joined to every seed; everything reachable from it is kept
    sv = np.flatnonzero(seeds)
    graph = sp.csr_matrix((np.ones(r.size + sv.size), (np.r_[r, np.full(sv.size, V)], np.r_[c, sv])),
                          shape=(V + 1, V + 1))
    order = csgraph.breadth_first_order(graph, V, directed=False, return_predecessors=False)
    keep = np.zeros(V + 1, dtype=bool)
    keep[order] = True
    return keep[:V] & free


def deformation_transfer_aligned(
    source_neutral: np.ndarray,
    source_deltas: np.ndarray,
    faces: np.ndarray,
    target_neutral: np.ndarray,
    align_vertices: np.ndarray | None = None,
    workers: int = 1,
) -> np.ndarray:
    """:func:`deformation_transfer` onto a target that lives in another world frame (e.g. a tracked neutral in
    the calibrated cameras' frame while the template rig is in its own).

    Deformation gradients are expressed in world axes, so transferring them onto a rotated target would move
    its vertices along the source's axes (a template's ``mouthLeft`` would move the actor's mouth to wherever
    the template's +x points in the target's world). The source is first placed on the target by the
    least-squares similarity over ``align_vertices`` (default all; e.g. the face region) and its displacements
    rotated and scaled with it. Returns (K, V, 3) target displacements in the target's frame; equals
    :func:`deformation_transfer` when the similarity is the identity.
    """
    from rigbuild.geometry.rigid import apply_rigid, fit_similarity

    src = np.asarray(source_neutral, dtype=np.float64)
    tgt = np.asarray(target_neutral, dtype=np.float64)
    v = np.arange(src.shape[0]) if align_vertices is None else np.asarray(align_vertices, dtype=np.int64)
    s, R, t = fit_similarity(src[v], tgt[v])
    deltas = s * np.asarray(source_deltas, dtype=np.float64) @ R.T
    return deformation_transfer(apply_rigid(src, R, t, s), deltas, faces, tgt, workers=workers)
