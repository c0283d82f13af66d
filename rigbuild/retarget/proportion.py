"""Scale-proportion matching: carry a target character's marker displacements into the source's
(the actor's) proportions, shared by both retargeting methods (Seol et al. 2012 sec. 3.2; Ribera et
al. 2017 can reuse it).

A *proportion map* is the interpolating RBF ``f(x) = sum_i w_i phi(|x - c_i|) + a_0 + A x`` from the
target's neutral markers ``c_i`` to the source's neutral markers (:func:`fit_proportion_map`). Seol
et al. use ``phi(r) = r``; ``r^3`` and the thin-plate ``r^2 log r`` are C^1 alternatives (``phi(r) = r``
has a cusp at every centre, so ``f(c_i + d) - f(c_i)`` carries a term ``w_i |d|`` that ignores the
direction of ``d``).

:func:`transfer_displacements` turns target marker deltas ``d`` (K, M, 3) into source-proportioned ones:

``"rbf"`` (the paper)       ``f(n + d) - f(n)``;
``"jacobian"``              ``J_f(n_i) d_i``, the map's Jacobian at each marker. For ``phi(r) = r`` the
                            centre's own term has no derivative at ``r = 0``; it is *left out*, which
                            equals the central-difference limit ``(f(c + e d) - f(c - e d)) / 2e`` (the
                            one-sided limit would be ``J d + w_i |d|``, i.e. ``"rbf"`` for small ``d``);
``"local_affine"``          the linear part of the least-squares affine map of each marker's ``k``
                            nearest target-neutral neighbours onto their source positions, applied to
                            ``d_i``;
``"affine"``                the linear part ``A`` of the RBF's polynomial, applied to every ``d``;
``"none"``                  ``d`` unchanged.

All of these map each marker's displacement pointwise. A character whose expressions were built by
deformation transfer (Sumner and Popovic 2004; how studios build stylized rigs, and how
``rigbuild.synth.characters`` builds them) has displacements whose *spatial gradient* equals the
template's, not displacements equal to ``J d``; no pointwise map undoes that (a jaw rotation about a
hinge that moved, a lip roll on a wider mouth). :func:`transfer_displacements_mesh` (``"deformation"``)
is the inverse that does: the RBF warps the whole target neutral mesh into the source's proportions
(a proxy of the actor's face) and the target's blendshapes are deformation-transferred onto that proxy,
then sampled at the markers. It needs the target's mesh (any :class:`~rigbuild.rig.Rig`).

Units: mm throughout (any consistent unit works; nothing depends on it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.distance import cdist

from rigbuild.errors import InputError
from rigbuild.retarget.params import SCALE_MATCH_KERNELS as KERNELS
from rigbuild.retarget.params import SCALE_MATCH_MARKER_MODES as MARKER_MODES
from rigbuild.retarget.params import SCALE_MATCH_MODES as MODES


def rbf_kernel(r: np.ndarray, kernel: str = "r") -> np.ndarray:
    """``phi(r)`` elementwise for r (...) >= 0: ``"r"`` r, ``"r3"`` r^3, ``"tps"`` r^2 log r (0 at 0)."""
    r = np.asarray(r, dtype=np.float64)
    if kernel == "r":
        return r
    if kernel == "r3":
        return r**3
    if kernel == "tps":
        return np.where(r > 0, r * r * np.log(np.maximum(r, 1e-300)), 0.0)
    raise InputError(f"RBF kernel '{kernel}' unknown", fix=f"use one of {KERNELS}")


def _kernel_slope_over_r(r: np.ndarray, kernel: str) -> np.ndarray:
    """``phi'(r) / r`` (so ``grad_x phi(|x - c|) = phi'(r)/r (x - c)``); 0 at r = 0 for every kernel
    (for ``"r"`` this leaves the singular self term out, see the module docstring)."""
    rs = np.maximum(r, 1e-300)
    if kernel == "r":
        return np.where(r > 0, 1.0 / rs, 0.0)
    if kernel == "r3":
        return 3.0 * r
    if kernel == "tps":
        return np.where(r > 0, 2.0 * np.log(rs) + 1.0, 0.0)
    raise InputError(f"RBF kernel '{kernel}' unknown", fix=f"use one of {KERNELS}")


@dataclass
class ProportionMap:
    """``f(x) = sum_i w_i phi(|x - c_i|) + a_0 + A x``: centers (n, 3) mm; weights (n, 3); affine (4, 3)
    rows ``[a_0; A^T]`` (so ``a_0 + x @ affine[1:]``); kernel in :data:`KERNELS`."""

    centers: np.ndarray
    weights: np.ndarray
    affine: np.ndarray
    kernel: str = "r"

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Map points (..., 3) mm -> (..., 3) mm (chunked: any number of points)."""
        x = np.asarray(x, dtype=np.float64)
        flat = x.reshape(-1, 3)
        out = np.empty_like(flat)
        step = max(1, 2_000_000 // max(len(self.centers), 1))
        for s in range(0, len(flat), step):
            p = flat[s:s + step]
            r = cdist(p, self.centers)  # exact differences (no |x|^2 - 2 x.c + |c|^2 cancellation)
            out[s:s + step] = rbf_kernel(r, self.kernel) @ self.weights + self.affine[0] + p @ self.affine[1:]
        return out.reshape(x.shape)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """Jacobians ``J[n] = df/dx`` (N, 3, 3) at points x (N, 3); at a centre the centre's own term
        is left out for ``phi(r) = r`` (central-difference limit)."""
        p = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        diff = p[:, None, :] - self.centers[None]
        g = _kernel_slope_over_r(np.linalg.norm(diff, axis=2), self.kernel)
        return np.einsum("nj,njk,jo->nok", g, diff, self.weights) + self.affine[1:].T[None]


def fit_proportion_map(target_neutral: np.ndarray, source_neutral: np.ndarray, kernel: str = "r",
                       allow_coplanar: bool = False) -> ProportionMap:
    """Fit the interpolating RBF + linear polynomial with ``f(target_i) = source_i``.

    target_neutral, source_neutral : (M, 3) corresponding neutral markers (mm), M >= 4 non-coplanar.
    Solves ``[[Phi, P], [P^T, 0]] [w; a] = [source; 0]``; the side conditions make ``f`` reproduce
    affine maps exactly (then ``w = 0``). Returns a :class:`ProportionMap`. ``allow_coplanar``: coplanar
    markers leave the affine part's out-of-plane column undetermined; take the minimum-norm least-squares
    solution instead of raising.
    """
    c = np.asarray(target_neutral, dtype=np.float64)
    y = np.asarray(source_neutral, dtype=np.float64)
    if c.shape != y.shape or c.ndim != 2 or c.shape[1] != 3:
        raise InputError(f"RBF: centers {c.shape} and targets {y.shape} must both be (n, 3)")
    if kernel not in KERNELS:
        raise InputError(f"RBF kernel '{kernel}' unknown", fix=f"use one of {KERNELS}")
    n = c.shape[0]
    coplanar = n >= 4 and np.linalg.matrix_rank(c - c.mean(0)) < 3
    if n < 4 or (coplanar and not allow_coplanar):
        raise InputError("RBF: need at least 4 non-coplanar corresponding markers",
                         fix="map more markers between the source and the target")
    Phi = rbf_kernel(np.linalg.norm(c[:, None, :] - c[None], axis=2), kernel)
    P = np.hstack([np.ones((n, 1)), c])
    A = np.zeros((n + 4, n + 4))
    A[:n, :n] = Phi
    A[:n, n:] = P
    A[n:, :n] = P.T
    rhs = np.zeros((n + 4, 3))
    rhs[:n] = y
    sol = np.linalg.lstsq(A, rhs, rcond=None)[0] if coplanar else np.linalg.solve(A, rhs)
    return ProportionMap(centers=c, weights=sol[:n], affine=sol[n:], kernel=kernel)


def local_affine_linear_parts(target_neutral: np.ndarray, source_neutral: np.ndarray, k: int = 12) -> np.ndarray:
    """(M, 3, 3) linear parts ``A_i`` of the least-squares affine maps ``source_j ~ A_i target_j + b_i``
    over the ``k`` nearest target-neutral markers ``j`` of each marker ``i`` (itself included)."""
    from scipy.spatial import cKDTree

    c = np.asarray(target_neutral, dtype=np.float64)
    y = np.asarray(source_neutral, dtype=np.float64)
    M = c.shape[0]
    k = int(min(max(k, 4), M))
    _, nb = cKDTree(c).query(c, k=k)
    X = np.concatenate([np.ones((M, k, 1)), c[nb]], axis=2)  # (M, k, 4)
    XtX = np.einsum("mka,mkb->mab", X, X) + 1e-9 * np.eye(4)
    Xty = np.einsum("mka,mkc->mac", X, y[nb])
    sol = np.linalg.solve(XtX, Xty)  # (M, 4, 3)
    return sol[:, 1:, :].transpose(0, 2, 1)


def polar_rotation(A: np.ndarray) -> np.ndarray:
    """(3, 3) rotation ``R`` of the polar decomposition ``A = R S`` (``S`` symmetric positive
    semi-definite) of a (3, 3) linear map: identity for any pure stretch, ``R`` for ``s R``."""
    U, _, Vt = np.linalg.svd(np.asarray(A, dtype=np.float64))
    if np.linalg.det(U @ Vt) < 0:
        U[:, -1] *= -1
    return U @ Vt


def transfer_displacements(pmap: ProportionMap, target_neutral: np.ndarray, target_deltas: np.ndarray,
                           mode: str = "rbf", source_neutral: np.ndarray | None = None,
                           k_neighbors: int = 12) -> np.ndarray:
    """Target marker displacements in the source's proportions (module docstring for the modes).

    pmap : the map from :func:`fit_proportion_map` (target neutral -> source neutral).
    target_neutral : (M, 3) mm; target_deltas : (K, M, 3) mm (or (M, 3) for one shape).
    mode : one of :data:`MARKER_MODES` (``"deformation"`` is :func:`transfer_displacements_mesh`).
    source_neutral : (M, 3), only for ``"local_affine"`` (default ``pmap(target_neutral)``).
    Returns (K, M, 3) (or (M, 3)) mm.
    """
    n = np.asarray(target_neutral, dtype=np.float64)
    d = np.asarray(target_deltas, dtype=np.float64)
    single = d.ndim == 2
    if single:
        d = d[None]
    if d.shape[1:] != n.shape:
        raise InputError(f"target deltas {d.shape} do not match the target neutral markers {n.shape}")
    if mode == "rbf":
        out = pmap(n[None] + d) - pmap(n)[None]
    elif mode == "jacobian":
        out = np.einsum("mok,smk->smo", pmap.jacobian(n), d)
    elif mode == "local_affine":
        y = pmap(n) if source_neutral is None else np.asarray(source_neutral, dtype=np.float64)
        out = np.einsum("mok,smk->smo", local_affine_linear_parts(n, y, k_neighbors), d)
    elif mode == "affine":
        out = d @ pmap.affine[1:]
    elif mode == "none":
        out = d.copy()
    elif mode == "deformation":
        raise InputError("scale_match 'deformation' needs the target's mesh",
                         fix="call transfer_displacements_mesh with the target rig's neutral, deltas and faces")
    else:
        raise InputError(f"scale_match '{mode}' unknown", fix=f"use one of {MODES}")
    return out[0] if single else out


def transfer_displacements_mesh(pmap: ProportionMap, target_mesh_neutral: np.ndarray, target_mesh_deltas: np.ndarray,
                                faces: np.ndarray, marker_vertices: np.ndarray, workers: int = 1) -> np.ndarray:
    """``"deformation"``: the target's blendshapes deformation-transferred onto the source-proportioned
    proxy ``pmap(target_mesh_neutral)``, sampled at the markers.

    target_mesh_neutral : (V, 3) mm; target_mesh_deltas : (K, V, 3) mm; faces : (F, 3) triangles;
    marker_vertices : (M,) vertex ids of the markers (in the order of ``pmap.centers``).
    workers : processes for the per-shape solves (see ``deformation_transfer``).
    The rotation of the map (:func:`polar_rotation` of the RBF's linear part ``A``: identity for any
    pure stretch, unlike a Kabsch fit of anisotropically scaled point sets, which turns them) is factored out first, so that the transfer sees only the change of scale and
    proportions (deformation transfer copies gradients in world axes: a proxy rotated against the
    target would get un-rotated expressions); the result is rotated back. A similarity map therefore gives ``s R d`` and the
    identity map returns ``d``. Returns (K, M, 3) mm.
    """
    from rigbuild.geometry.deformation_transfer import deformation_transfer

    nv = np.asarray(target_mesh_neutral, dtype=np.float64)
    dv = np.asarray(target_mesh_deltas, dtype=np.float64)
    mv = np.asarray(marker_vertices, dtype=np.int64)
    if dv.ndim != 3 or dv.shape[1:] != nv.shape:
        raise InputError(f"target mesh deltas {dv.shape} do not match the neutral {nv.shape}")
    if mv.shape != (pmap.centers.shape[0],):
        raise InputError(f"{mv.size} marker vertices for a proportion map of {pmap.centers.shape[0]} markers")
    proxy = pmap(nv)
    R = polar_rotation(pmap.affine[1:].T)
    proxy_aligned = proxy @ R  # R^T x: source proportions in the target's orientation
    # only the markers are read: solve just the pieces of each shape's support that reach them (exact)
    moved = deformation_transfer(nv, dv, faces, proxy_aligned, sample_vertices=mv, workers=workers)
    return moved @ R.T


def proportion_match(target_neutral: np.ndarray, target_deltas: np.ndarray, source_neutral: np.ndarray,
                     mode: str = "rbf", kernel: str = "r", k_neighbors: int = 12, mesh=None,
                     marker_vertices: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, ProportionMap]:
    """Fit the map and transfer in one call.

    target_neutral : (M, 3); target_deltas : (K, M, 3); source_neutral : (M, 3) (mm).
    mode : :data:`MODES`; kernel : :data:`KERNELS`; mesh : for ``"deformation"`` a
    :class:`~rigbuild.rig.Rig` (or an object with ``neutral``, ``deltas``, ``faces``) whose vertices
    ``marker_vertices`` are the markers. Returns ``n* = f(n)`` (M, 3) (= source_neutral up to
    round-off), the transferred deltas (K, M, 3) and the map.
    """
    pmap = fit_proportion_map(target_neutral, source_neutral, kernel)
    n_star = pmap(np.asarray(target_neutral, dtype=np.float64))
    if mode == "deformation":
        if mesh is None or marker_vertices is None:
            raise InputError("scale_match 'deformation' needs the target's mesh and marker vertex ids",
                             fix="pass mesh=<target Rig> and marker_vertices")
        d_star = transfer_displacements_mesh(pmap, mesh.neutral, mesh.deltas, mesh.faces, marker_vertices)
    else:
        d_star = transfer_displacements(pmap, target_neutral, target_deltas, mode, source_neutral, k_neighbors)
    return n_star, d_star, pmap
