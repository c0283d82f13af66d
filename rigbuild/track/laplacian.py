"""Laplacian mesh deformation with barycentric constraints (Ma et al. 2016, section 2.2, eq. 1).

Energy, per coordinate (x, y, z solved as three right-hand sides of one factorization)::

    E(p) = ||L p - delta||^2 + lambda ||M B p - M c||^2 + eps ||p - prior||^2

``L`` is libigl's cotangent Laplacian of the tracking mesh (sign flipped so its diagonal is positive),
``delta`` the rest-pose Laplacian coordinates ``L p_rest`` rotated per vertex by the rotation that
best maps the rest 1-ring onto the current estimate's 1-ring (Botsch & Sorkine 2008, rotation-aware
Laplacian coordinates), ``B`` one row per match holding its barycentric coordinates ``(alpha, beta,
gamma)`` in its triangle, ``M`` the diagonal per-match quality weights and ``c`` the constraint
positions (mm). ``eps`` is a tiny Tikhonov weight (default 1e-6) that only keeps the system definite
where a component has no constraint; it does not change constrained solutions measurably.

The normal equations ``(L^T L + lambda B^T M^2 B + eps I) p = L^T delta + lambda B^T M^2 c + eps prior``
have the sparsity of ``L^T L`` whatever the constraints are (a barycentric row couples the three
corners of one triangle, which are 1-ring neighbours), so the CHOLMOD symbolic analysis is done once
per mesh (:class:`LaplacianSolver`) and every solve only refactors numerically.

Matches are represented as in the paper (after Kobbelt et al. 1999): a world point ``u`` is a base
point ``b`` on the surface (triangle + barycentrics) plus a displacement ``h`` along the interpolated
normal ``n`` (:func:`normal_displacement`); the constraint for its matched point ``u'`` on the target
is ``c = u' - h n`` (:func:`displaced_targets`).
"""

from __future__ import annotations

from dataclasses import dataclass

import igl
import numpy as np
import scipy.sparse as sp
from cvxopt import cholmod, matrix, spmatrix

from rigbuild.errors import InputError
from rigbuild.geometry.mesh import vertex_normals  # noqa: F401 (re-exported)

cholmod.options["supernodal"] = 2


# ----------------------------------------------------------------------------- surface points
def barycentric_matrix(faces: np.ndarray, tri: np.ndarray, bary: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """Barycentric equation matrix ``B`` (N, V): row i has ``bary[i]`` at the corners of ``faces[tri[i]]``.

    faces : (F, 3) int; tri : (N,) triangle ids; bary : (N, 3) barycentric coordinates (sum 1).
    """
    tri = np.asarray(tri, dtype=np.int64)
    bary = np.asarray(bary, dtype=np.float64).reshape(-1, 3)
    n = tri.shape[0]
    rows = np.repeat(np.arange(n), 3)
    cols = np.asarray(faces, dtype=np.int64)[tri].reshape(-1)
    return sp.csr_matrix((bary.reshape(-1), (rows, cols)), shape=(n, n_vertices))


def interpolate(values: np.ndarray, faces: np.ndarray, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Barycentric interpolation of per-vertex ``values`` (V, D) at surface points -> (N, D)."""
    corners = np.asarray(values)[np.asarray(faces)[np.asarray(tri, dtype=np.int64)]]  # (N, 3, D)
    return np.einsum("nk,nkd->nd", np.asarray(bary, dtype=np.float64).reshape(-1, 3), corners)


def interpolated_normals(normals: np.ndarray, faces: np.ndarray, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Phong-interpolated unit normals (N, 3) at surface points."""
    n = interpolate(normals, faces, tri, bary)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def normal_displacement(
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray,
    points: np.ndarray,
    tri: np.ndarray,
    bary0: np.ndarray | None = None,
    iterations: int = 5,
    tolerance: float = 0.05,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Base points of world points along the interpolated normal field (Kobbelt et al. 1999).

    Solves ``u = alpha a + beta b + gamma c + h n(alpha, beta, gamma)`` in the given triangle by fixed-point
    iteration on the normal (each step an exact 3x3 solve for ``alpha, beta, h``).

    vertices : (V, 3) mm; faces : (F, 3); normals : (V, 3) unit vertex normals; points : (N, 3) mm;
    tri : (N,) triangle of each point (e.g. from a rendered id buffer or a closest-point query);
    bary0 : (N, 3) starting barycentrics (default: the centroid).
    tolerance : how far outside the triangle (in barycentric units) a base point may fall and still be valid.

    Returns bary (N, 3) (clamped into the triangle), h (N,) signed normal displacement in mm, valid (N,) bool.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)[np.asarray(tri, dtype=np.int64)]
    u = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    na, nb, nc = normals[f[:, 0]], normals[f[:, 1]], normals[f[:, 2]]
    if bary0 is None:
        bary = np.full((u.shape[0], 3), 1.0 / 3.0)
    else:
        bary = np.asarray(bary0, dtype=np.float64).reshape(-1, 3).copy()
    h = np.zeros(u.shape[0])
    ok = np.ones(u.shape[0], dtype=bool)
    for _ in range(max(1, iterations)):
        n = bary[:, :1] * na + bary[:, 1:2] * nb + bary[:, 2:] * nc
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        A = np.stack([a - c, b - c, n], axis=2)  # columns
        det = np.linalg.det(A)
        ok = np.abs(det) > 1e-12
        A[~ok] = np.eye(3)
        sol = np.linalg.solve(A, (u - c)[:, :, None])[:, :, 0]
        bary = np.stack([sol[:, 0], sol[:, 1], 1.0 - sol[:, 0] - sol[:, 1]], axis=1)
        h = sol[:, 2]
    valid = ok & np.all(bary >= -tolerance, axis=1)
    bary = np.clip(bary, 0.0, None)
    bary /= np.maximum(bary.sum(1, keepdims=True), 1e-12)
    return bary, h, valid


def displaced_targets(targets: np.ndarray, h: np.ndarray, normals_at_base: np.ndarray) -> np.ndarray:
    """Barycentric constraint positions ``c_j = u_j - h_i n_i`` (N, 3): equal normal displacement on source
    and target (paper section 2.2). targets (N, 3) mm, h (N,) mm, normals_at_base (N, 3) unit."""
    return np.asarray(targets, dtype=np.float64) - np.asarray(h)[:, None] * np.asarray(normals_at_base)


# ----------------------------------------------------------------------------- Laplacian
def cotangent_laplacian(vertices: np.ndarray, faces: np.ndarray) -> sp.csc_matrix:
    """(V, V) cotangent Laplacian ``L = -igl.cotmatrix`` (positive diagonal, rows sum to 0)."""
    L = -igl.cotmatrix(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64))
    L = sp.csc_matrix(L)
    if not np.all(np.isfinite(L.data)):
        raise InputError("tracking mesh has degenerate triangles (non-finite cotangent weights)",
                         fix="remove zero-area triangles from the template")
    return L


def fit_vertex_rotations(
    rest: np.ndarray, current: np.ndarray, edges: np.ndarray, edge_weights: np.ndarray, workers: int = 1
) -> np.ndarray:
    """Per-vertex rotations (V, 3, 3) best mapping the rest 1-ring edges onto the current ones (ARAP local step).

    rest, current : (V, 3); edges : (E, 2) directed vertex pairs (i, j) (both directions listed);
    edge_weights : (E,) non-negative weights. ``R_i = argmin sum_j w_ij ||R (r_j - r_i) - (p_j - p_i)||^2``.
    ``workers`` threads share the SVDs.
    """
    i, j = edges[:, 0], edges[:, 1]
    e0 = (rest[j] - rest[i]) * edge_weights[:, None]
    return rotations_from_covariances(edge_covariances(np.asarray(current, dtype=np.float64), edges, e0,
                                                       vertex_edge_incidence(edges, rest.shape[0])), workers)


def vertex_edge_incidence(edges: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(V, E) 0/1 matrix summing the directed edges (E, 2) over their first vertex."""
    E = edges.shape[0]
    return sp.csr_matrix((np.ones(E), (edges[:, 0], np.arange(E))), shape=(n_vertices, E))


def edge_covariances(current: np.ndarray, edges: np.ndarray, weighted_rest_edges: np.ndarray,
                     incidence: sp.csr_matrix) -> np.ndarray:
    """Per-vertex ``S_i = sum_j (p_j - p_i) (w_ij (r_j - r_i))^T`` (V, 3, 3); weighted_rest_edges (E, 3),
    incidence from :func:`vertex_edge_incidence`."""
    e1 = current[edges[:, 1]] - current[edges[:, 0]]
    outer = (e1[:, :, None] * weighted_rest_edges[:, None, :]).reshape(-1, 9)
    return np.asarray(incidence @ outer).reshape(-1, 3, 3)


def rotations_from_covariances(S: np.ndarray, workers: int = 1) -> np.ndarray:
    """Closest rotations (V, 3, 3) to S (V, 3, 3) (``U W^T`` of the SVD, last column of U flipped where that
    is a reflection). ``workers`` threads take contiguous blocks (LAPACK releases the GIL)."""
    if workers > 1 and S.shape[0] >= 2048:
        from concurrent.futures import ThreadPoolExecutor

        blocks = np.array_split(S, workers)
        with ThreadPoolExecutor(max_workers=workers) as pool:
            return np.concatenate(list(pool.map(rotations_from_covariances, blocks)))
    U, _, Wt = np.linalg.svd(S)
    d = np.sign(np.linalg.det(U @ Wt))
    d[d == 0] = 1.0
    U[:, :, 2] *= d[:, None]
    return U @ Wt


@dataclass
class SolveReport:
    """Diagnostics of one solve: per-match residual ``|B p - c|`` (N,) mm and the energy terms."""

    residual_mm: np.ndarray
    laplacian_energy: float
    data_energy: float


class LaplacianSolver:
    """Precomputed Laplacian deformation of one tracking mesh (factor once, solve many).

    Parameters
    ----------
    rest_vertices : (V, 3) mm, the rest pose whose Laplacian coordinates are preserved (the actor's
        registered neutral).
    faces : (F, 3) triangles of the tracking mesh (every vertex referenced).
    eps : Tikhonov weight towards the prior (keeps the system definite; default 1e-6).
    """

    def __init__(self, rest_vertices: np.ndarray, faces: np.ndarray, eps: float = 1e-6):
        self.rest = np.asarray(rest_vertices, dtype=np.float64).copy()
        self.faces = np.asarray(faces, dtype=np.int64)
        self.n = self.rest.shape[0]
        if self.faces.size == 0 or self.faces.max() >= self.n:
            raise InputError("tracking mesh faces reference missing vertices")
        self.eps = float(eps)
        self.L = cotangent_laplacian(self.rest, self.faces)
        self.delta_rest = self.L @ self.rest  # (V, 3) rest Laplacian coordinates
        LtL = (self.L.T @ self.L).tocsc()
        # fixed sparsity: L^T L + I (triangle corner pairs are already in L's pattern)
        pattern = (LtL + sp.eye(self.n, format="csc")).tocsc()
        pattern.sort_indices()
        self._lower = sp.tril(pattern, format="csc")
        self._lower.sort_indices()
        self._lower.data[:] = 0.0
        base = sp.tril(LtL + self.eps * sp.eye(self.n), format="csc")
        self._base_data = self._scatter_values(base.tocoo())
        # column-major keys of the lower pattern for scattering B^T W B entries
        cols = np.repeat(np.arange(self.n), np.diff(self._lower.indptr))
        self._keys = cols.astype(np.int64) * self.n + self._lower.indices.astype(np.int64)
        coo = self._lower.tocoo()
        self._cvx_I = matrix(coo.row.astype(np.int64))
        self._cvx_J = matrix(coo.col.astype(np.int64))
        self._symbolic = cholmod.symbolic(self._to_cvx(self._base_data))
        # edges for rotation fitting (positive cot weights of the rest mesh)
        Lc = self.L.tocoo()
        off = Lc.row != Lc.col
        self.edges = np.stack([Lc.row[off], Lc.col[off]], axis=1)
        self.edge_weights = np.maximum(-Lc.data[off], 1e-6)
        self._incidence = vertex_edge_incidence(self.edges, self.n)
        self._rest_edges_w = (self.rest[self.edges[:, 1]] - self.rest[self.edges[:, 0]]) * self.edge_weights[:, None]
        self.workers = 1  # threads of the rotation fits (rotated_delta)

    # -------------------------------------------------------------- internals
    def _scatter_values(self, coo: sp.coo_matrix) -> np.ndarray:
        """Sum the entries of a lower-triangular COO matrix into the fixed pattern's data order."""
        keys = coo.col.astype(np.int64) * self.n + coo.row.astype(np.int64)
        if not hasattr(self, "_keys"):
            cols = np.repeat(np.arange(self.n), np.diff(self._lower.indptr))
            self._keys = cols.astype(np.int64) * self.n + self._lower.indices.astype(np.int64)
        pos = np.searchsorted(self._keys, keys)
        if np.any(pos >= self._keys.size) or np.any(self._keys[np.minimum(pos, self._keys.size - 1)] != keys):
            raise ValueError("constraint couples vertices that share no triangle")
        return np.bincount(pos, weights=coo.data, minlength=self._keys.size)

    def _to_cvx(self, data: np.ndarray) -> spmatrix:
        return spmatrix(matrix(np.ascontiguousarray(data, dtype=np.float64)), self._cvx_I, self._cvx_J, size=(self.n, self.n))

    # -------------------------------------------------------------- public
    def rotated_delta(self, current: np.ndarray) -> np.ndarray:
        """Rest Laplacian coordinates rotated by per-vertex rotations fitted to ``current`` (V, 3)."""
        S = edge_covariances(np.asarray(current, dtype=np.float64), self.edges, self._rest_edges_w, self._incidence)
        R = rotations_from_covariances(S, self.workers)
        return np.einsum("vij,vj->vi", R, self.delta_rest)

    def solve(
        self,
        tri: np.ndarray,
        bary: np.ndarray,
        targets: np.ndarray,
        weights: np.ndarray,
        lam: float,
        delta: np.ndarray | None = None,
        prior: np.ndarray | None = None,
    ) -> tuple[np.ndarray, SolveReport]:
        """Minimize eq. 1 for the vertex positions ``p`` (V, 3) mm.

        tri (N,), bary (N, 3): the matches' base points on the tracking mesh; targets (N, 3) mm: ``c``;
        weights (N,): quality weights (the diagonal of ``M``); lam: ``lambda``; delta (V, 3): Laplacian
        coordinates to preserve (default: the rest pose's); prior (V, 3): where the Tikhonov term pulls
        (default: the rest pose).
        """
        tri = np.asarray(tri, dtype=np.int64)
        targets = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        if not (tri.shape[0] == targets.shape[0] == w.shape[0] == np.asarray(bary).reshape(-1, 3).shape[0]):
            raise ValueError("tri, bary, targets and weights differ in length")
        if tri.size == 0 or not np.any(w > 0):
            raise ValueError("no weighted constraints")
        delta = self.delta_rest if delta is None else np.asarray(delta, dtype=np.float64)
        prior = self.rest if prior is None else np.asarray(prior, dtype=np.float64)
        B = barycentric_matrix(self.faces, tri, bary, self.n)
        W2 = sp.diags(lam * w * w)
        BtWB = (B.T @ W2 @ B).tocoo()
        low = BtWB.row >= BtWB.col
        data = self._base_data + self._scatter_values(
            sp.coo_matrix((BtWB.data[low], (BtWB.row[low], BtWB.col[low])), shape=BtWB.shape)
        )
        A = self._to_cvx(data)
        F = cholmod.symbolic(A) if self._symbolic is None else self._symbolic
        cholmod.numeric(A, F)
        rhs = self.L.T @ delta + B.T @ (W2 @ targets) + self.eps * prior
        X = matrix(np.ascontiguousarray(rhs))
        cholmod.solve(F, X)
        p = np.array(X).reshape(self.n, 3)
        res = np.linalg.norm(B @ p - targets, axis=1)
        lap = float(np.sum((self.L @ p - delta) ** 2))
        dat = float(lam * np.sum((w * res) ** 2))
        return p, SolveReport(res, lap, dat)
