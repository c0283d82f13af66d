"""Marker-space retargeting with range-of-motion alignment and a geometric prior (Ribera et al. 2017).

Notation (paper section 3): the character has neutral marker positions ``s0`` (M, 3) and sparse delta
blendshapes ``ds`` (K, M, 3) (its deltas at the marker vertices); the actor has neutral markers ``a0``
(M, 3) and a training (range-of-motion) sequence ``a`` (F, M, 3). Blendshape transfer (section 4) computes
personalized sparse actor blendshapes ``dp`` (K, M, 3); retargeting (section 5) finds per-frame weights
``w`` (K,) from actor marker displacements ``da = a_f - a0`` with the character's dense deltas in the
geometric prior.

Section 4 terms, all implemented here:

- correlations ``c_kf`` (eq. 5) :func:`correlations`; trust values ``t_k`` (eq. 6) :func:`trust_values`;
  contrast enhancement (eq. 7-8, r = 15) :func:`enhance_similarity`;
- key expression extraction (3-frame Gaussian low-pass, summed rows, local peaks) :func:`key_expressions`;
- soft masks ``u_k`` (eq. 10) :func:`soft_masks`; E_Match (eq. 10);
- E_Mesh (eq. 11): thin-plate RBF initial guesses ``g_k`` (:func:`fit_thin_plate_rbf`, :func:`rbf_transfer`),
  cotangent Laplacian of a triangulation of the markers in a 2D parameterization with extra eyelid / lip
  contact edges (:func:`marker_triangulation`, :func:`marker_laplacian`);
- E_CEG (eq. 12-13): signed graph Laplacian of the between-blendshape correlations
  (:func:`cross_expression_laplacian`);
- alpha = 0.01, beta = 0.1; three sparse (MK x MK) systems, one per coordinate, sharing one CHOLMOD
  factorization (:func:`transfer_blendshapes`).

Section 5: ``E_Fit + mu E_Prior + lambda E_Sparse`` (eq. 16) with ``E_Prior = (1/N) |L dV w|^2`` on the full
character mesh (``L dV`` precomputed, :func:`prior_matrix`) solved by iteratively reweighted least squares
with optional weight bounds (:class:`RiberaRetargeter`).

Units. Everything here works in mm. The paper recommends mu = 0.3 and lambda = 0.6 "for markers in cm and
the face rig uniformly scaled to roughly match the actor's head". E_Fit and E_Prior are squared lengths and
E_Sparse is unit-free, so in mm the same balance needs ``lambda_mm = lambda_cm * 100`` (mu unchanged), and
the prior is evaluated on the character scaled by ``head_scale`` = RMS radius of the actor's neutral markers
/ RMS radius of the character's (:func:`head_scale`). :class:`RetargetParams` takes the paper's values and
converts them. E_Align's alpha and beta need no conversion: E_Match, E_Mesh and E_CEG are all squared marker
displacements (cotangent and CEG weights are dimensionless), so 0.01 / 0.1 mean the same in mm.

Beyond the paper (options; the faithful path stays):

- ``RetargetParams.rigid = "joint"`` (default): E_Fit also minimizes over a residual small rigid motion of
  each stabilized frame (eliminated exactly, :class:`RiberaRetargeter`); a rigid fit to the neutral alone
  absorbs part of every expression. ``"fixed"``: the stabilized frame as is.
- ``TransferParams.match = "fit"`` (method ``ribera_fit``, :func:`fit_match_transfer`): E_Match matches every
  training frame with all shapes at their solved (sparse) activations instead of eq. 10's similarity-weighted
  mean of masked keys, which shrinks the shapes.
- ``TransferParams.guess = "deformation"`` (and method ``deformation``, the guesses used directly): g_k by
  deformation transfer onto the character's neutral warped into the actor's proportions
  (:func:`deformation_guesses`), instead of the pointwise thin-plate RBF.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial import Delaunay, cKDTree

from rigbuild.errors import InputError
from rigbuild.rig import Rig
from rigbuild.geometry.rigid import fit_similarity
from rigbuild.retarget.common import stabilize, visible_mask
from rigbuild.retarget.methods import RIBERA_METHODS
from rigbuild.retarget.params import (  # noqa: F401  (re-exported: the solver's parameter classes)
    CM2_TO_MM2,
    PAPER_ALPHA,
    PAPER_BETA,
    PAPER_LAMBDA_CM,
    PAPER_MU,
    PAPER_R,
    RetargetParams,
    TransferParams,
)
from rigbuild.retarget.proportion import ProportionMap, fit_proportion_map, transfer_displacements_mesh


# ======================================================================== RBF initial guess (sec. 4.4)
def fit_thin_plate_rbf(centres: np.ndarray, values: np.ndarray) -> ProportionMap:
    """3D thin-plate (biharmonic, ``phi(r) = r``) RBF interpolant with an affine part,
    ``f(x) = sum_i lambda_i |x - c_i| + A x + b`` with ``f(c_i) = y_i``; centres, values : (M, 3) mm.
    (:func:`rigbuild.retarget.proportion.fit_proportion_map` with kernel ``r``; M >= 4, coplanar markers
    get the minimum-norm affine part.)"""
    return fit_proportion_map(centres, values, kernel="r", allow_coplanar=True)


def rbf_transfer(s0: np.ndarray, ds: np.ndarray, a0: np.ndarray) -> np.ndarray:
    """Initial guesses ``dg`` (K, M, 3): the RBF mapping ``s0 -> a0`` applied to the character's shapes.

    ``dg_k = f(s0 + ds_k) - f(s0)`` (= ``f(s0 + ds_k) - a0``), the RBF proportion matching of Seol 2012 /
    Orvalho 2008 used as the initial guess in E_Mesh and as the RBF-transfer baseline.
    """
    f = fit_thin_plate_rbf(s0, a0)
    base = f(s0)
    return f(s0[None] + ds) - base[None]


# ======================================================================== marker mesh (sec. 4.4)
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


# ======================================================================== similarity (sec. 4.1)
def _unit_rows(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(x, axis=1)
    return x / np.maximum(n, 1e-12)[:, None], n


def correlations(da: np.ndarray, ds: np.ndarray) -> np.ndarray:
    """Eq. 5: ``c_kf = da_f . ds_k / (|da_f| |ds_k|)`` (K, F), over the markers visible in frame f.

    da : (F, M, 3) actor marker displacements from the neutral (NaN gaps); ds : (K, M, 3).
    """
    vis = visible_mask(da).astype(np.float64)  # (F, M)
    a = np.nan_to_num(da).reshape(da.shape[0], -1)
    s = ds.reshape(ds.shape[0], -1)
    num = s @ a.T  # (K, F)
    a_norm = np.sqrt((a * a).sum(1))  # (F,)
    s_norm = np.sqrt(np.einsum("kmc,kmc->km", ds, ds) @ vis.T)  # (K, F) over visible markers
    den = s_norm * a_norm[None]
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.where(den > 1e-12, num / np.where(den > 1e-12, den, 1.0), 0.0)
    return c


def shape_correlation_matrix(ds: np.ndarray) -> np.ndarray:
    """(K, K) signed Pearson correlations (eq. 5 form) between sparse blendshapes ds (K, M, 3)."""
    u, n = _unit_rows(ds.reshape(ds.shape[0], -1))
    C = u @ u.T
    C[n < 1e-12] = 0.0
    C[:, n < 1e-12] = 0.0
    return C


def trust_values(ds: np.ndarray) -> np.ndarray:
    """Eq. 6 trust values t_k (K,) in [0, 1].

    Shapes are sorted by total displacement ``d_k = |ds_k|`` (largest first); ``t_k = 1 - r_k / max r``
    with ``r_k`` the sum of positive correlations with the shapes of larger displacement.
    """
    d = np.linalg.norm(ds.reshape(ds.shape[0], -1), axis=1)
    order = np.argsort(-d, kind="stable")
    Cs = np.maximum(shape_correlation_matrix(ds)[np.ix_(order, order)], 0.0)
    r_sorted = np.tril(Cs, -1).sum(1)
    rmax = r_sorted.max()
    t_sorted = 1.0 - r_sorted / rmax if rmax > 0 else np.ones_like(r_sorted)
    t = np.empty_like(t_sorted)
    t[order] = t_sorted
    return t


def contrast(c: np.ndarray, r: float = PAPER_R) -> np.ndarray:
    """Eq. 7: ``b(c) = e^{rc} / (e^{r/2} + e^{rc})`` (a sigmoid centred at 0.5), computed stably."""
    return 0.5 * (1.0 + np.tanh(0.5 * r * (np.asarray(c, float) - 0.5)))


def enhance_similarity(c: np.ndarray, t: np.ndarray, r: float = PAPER_R) -> np.ndarray:
    """Eq. 8: ``c~_kf = (1 - t_k) c+_kf + t_k b(c+_kf)`` for c (K, F), t (K,)."""
    cp = np.maximum(c, 0.0)
    return (1.0 - t)[:, None] * cp + t[:, None] * contrast(cp, r)


def key_expressions(similarity: np.ndarray, segment_starts: np.ndarray | None = None) -> np.ndarray:
    """Section 4.2: key frames of the training sequence (sorted frame indices).

    Each row of ``similarity`` (K, F) is low-pass filtered with a 3-frame Gaussian kernel (1, 2, 1) / 4,
    the rows are summed, and the local peaks (strictly above the previous frame, not below the next) of
    the cumulative curve (with positive similarity) are returned. ``segment_starts``: first frame of each concatenated sequence (the
    filter does not cross sequence boundaries; default: one sequence).
    """
    K, F = similarity.shape
    starts = np.array([0] if segment_starts is None else segment_starts, dtype=np.int64)
    bounds = list(starts) + [F]
    keys = []
    for s, e in zip(bounds[:-1], bounds[1:]):
        x = similarity[:, s:e]
        if x.shape[1] == 0:
            continue
        pad = np.pad(x, ((0, 0), (1, 1)), mode="edge")
        filt = 0.25 * pad[:, :-2] + 0.5 * pad[:, 1:-1] + 0.25 * pad[:, 2:]
        cum = filt.sum(0)
        n = cum.size
        if n == 1:
            keys.append(np.array([s]))
            continue
        prev = np.r_[-np.inf, cum[:-1]]
        nxt = np.r_[cum[1:], -np.inf]
        peaks = np.flatnonzero((cum > prev) & (cum >= nxt) & (cum > 0))
        keys.append(peaks + s)
    return np.concatenate(keys) if keys else np.zeros(0, dtype=np.int64)


def soft_masks(ds: np.ndarray) -> np.ndarray:
    """Eq. 10 soft masks u_k (K, M): ``|ds_k^m| / max_m |ds_k^m|`` (0 for a shape that moves no marker)."""
    n = np.linalg.norm(ds, axis=2)
    mx = n.max(1, keepdims=True)
    return np.where(mx > 1e-12, n / np.maximum(mx, 1e-12), 0.0)


def cross_expression_laplacian(C: np.ndarray) -> np.ndarray:
    """Eq. 12 signed graph Laplacian G (K, K) of the cross-expression graph with edge weights C (K, K).

    ``(G x)_k = (1 / sum_{l != k} |c_kl|) sum_{l != k} c_kl (x_l - x_k)``.
    """
    W = np.array(C, dtype=np.float64)
    np.fill_diagonal(W, 0.0)
    n = np.abs(W).sum(1)
    Wn = np.where(n[:, None] > 1e-12, W / np.maximum(n, 1e-12)[:, None], 0.0)
    return Wn - np.diag(Wn.sum(1))


# ======================================================================== transfer (sec. 4.6)
@dataclass
class TransferResult:
    """Output of :func:`transfer_blendshapes`. Shapes: K shapes, M markers, F training frames."""

    dp: np.ndarray  # (K, M, 3) personalized sparse actor blendshapes
    dg: np.ndarray  # (K, M, 3) RBF initial guesses
    keys: np.ndarray  # (F',) key frame indices into the training sequence
    similarity: np.ndarray  # (K, F) enhanced similarity c~
    trust: np.ndarray  # (K,)
    masks: np.ndarray  # (K, M)
    triangulation: MarkerTriangulation
    info: dict = field(default_factory=dict)


def _cholmod_solve(A: sp.spmatrix, B: np.ndarray) -> np.ndarray:
    """Solve SPD ``A X = B`` (B: (n, r)) with cvxopt's CHOLMOD (one factorization, r right-hand sides)."""
    import cvxopt
    import cvxopt.cholmod

    A = sp.tril(A).tocoo()
    Ac = cvxopt.spmatrix(A.data.tolist(), A.row.tolist(), A.col.tolist(), A.shape)
    X = cvxopt.matrix(np.asfortranarray(B, dtype=np.float64))
    cvxopt.cholmod.options["supernodal"] = 2
    cvxopt.cholmod.linsolve(Ac, X, uplo="L")
    return np.array(X).reshape(B.shape)


def kron_sum_solve(
    d: np.ndarray, C: np.ndarray, Bk: np.ndarray, R: np.ndarray, tol: float = 1e-10, max_iter: int = 200
) -> np.ndarray:
    """Solve ``(diag(d) + I_K (x) C + Bk (x) I_M) x = r`` for every coordinate, exploiting the Kronecker sum.

    This is the E_Align system of :func:`align_system` in the ordering ``index = k * M + m``: d (K, M)
    diagonal (E_Match, epsilon), C (M, M) = ``alpha/M L^T L`` (E_Mesh), Bk (K, K) = ``beta/M G^T G``
    (E_CEG); R (K, M, 3) right-hand sides, one per coordinate. When ``d`` is constant over markers the
    matrix is a Kronecker sum ``B (x) I + I (x) C`` and is solved exactly by diagonalizing B (K x K) and C
    (M x M); otherwise that Kronecker sum (with ``d`` averaged over markers) preconditions conjugate
    gradients. Returns x (K, M, 3).
    """
    K, M = d.shape
    dbar = d.mean(1)
    lam, U = np.linalg.eigh(Bk + np.diag(dbar))
    sig, V = np.linalg.eigh(C)
    denom = lam[:, None] + sig[None, :]

    Ut, Vt = U.T, V.T

    def precond(X: np.ndarray) -> np.ndarray:  # X (3, K, M)
        return U @ ((Ut @ X @ V) / denom) @ Vt

    def matvec(X: np.ndarray) -> np.ndarray:
        return d * X + X @ C + Bk @ X

    R = np.ascontiguousarray(np.moveaxis(R, 2, 0))
    x = precond(R)
    if np.allclose(d, dbar[:, None], rtol=1e-12, atol=0.0):
        return np.moveaxis(x, 0, 2)
    r = R - matvec(x)
    z = precond(r)
    p = z.copy()
    rz = (r * z).sum((1, 2))
    rnorm0 = np.sqrt((R * R).sum((1, 2))) + 1e-300
    for _ in range(max_iter):
        Ap = matvec(p)
        step = rz / np.maximum((p * Ap).sum((1, 2)), 1e-300)
        x += step[:, None, None] * p
        r -= step[:, None, None] * Ap
        if np.all(np.sqrt((r * r).sum((1, 2))) <= tol * rnorm0):
            break
        z = precond(r)
        rz_new = (r * z).sum((1, 2))
        p = z + (rz_new / np.maximum(rz, 1e-300))[:, None, None] * p
        rz = rz_new
    return np.moveaxis(x, 0, 2)


def match_terms(da_keys: np.ndarray, sim_keys: np.ndarray, masks: np.ndarray,
                activations: np.ndarray | None = None, targets: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """E_Match's normal-equation pieces: the diagonal d (K, M) and right-hand side b (K, M, 3).

    Faithful (eq. 10): ``(1/F) sum_f sum_k c~_kf |dp_k - diag(u_k) da_f|^2`` over visible markers.
    With ``activations`` h (K, F') and ``targets`` r (K, F', M, 3): the activation-aware option
    ``(1/F) sum c~_kf |diag(u_k) (h_kf dp_k - r_kf)|^2`` (the mask as a residual weight).
    """
    Fk = max(da_keys.shape[0], 1)
    vis = visible_mask(da_keys).astype(np.float64)  # (F', M)
    if activations is None:
        d_match = (sim_keys @ vis) / Fk
        b_match = np.einsum("kf,km,fmc->kmc", sim_keys, masks, np.nan_to_num(da_keys)) / Fk
    else:
        h = activations
        u2 = masks * masks
        d_match = ((sim_keys * h * h) @ vis) * u2 / Fk
        b_match = np.einsum("kf,km,kfmc->kmc", sim_keys * h, u2, np.nan_to_num(targets) * vis[None, :, :, None]) / Fk
    return d_match, b_match


def align_terms(
    ds: np.ndarray,
    dg: np.ndarray,
    da_keys: np.ndarray,
    sim_keys: np.ndarray,
    masks: np.ndarray,
    lap: sp.spmatrix,
    params: TransferParams,
    activations: np.ndarray | None = None,
    targets: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The E_Align normal equations in Kronecker form: d (K, M), C (M, M), Bk (K, K), R (K, M, 3).

    ``A = diag(d) + I_K (x) C + Bk (x) I_M`` (one matrix for x, y and z); see :func:`align_system` for the
    terms. :func:`kron_sum_solve` solves it.
    """
    K, M, _ = ds.shape
    d_match, b_match = match_terms(da_keys, sim_keys, masks, activations, targets)
    L = lap.toarray() if sp.issparse(lap) else np.asarray(lap)
    C = (params.alpha / M) * (L.T @ L)
    G = cross_expression_laplacian(shape_correlation_matrix(ds))
    Bk = (params.beta / M) * (G.T @ G)
    ref = ds if params.ceg_reference == "character" else dg
    R = (b_match + params.epsilon * dg + np.einsum("kmc,mn->knc", dg, C) + np.einsum("kl,lmc->kmc", Bk, ref))
    return d_match + params.epsilon, C, Bk, R


def align_system(
    s0: np.ndarray,
    ds: np.ndarray,
    dg: np.ndarray,
    da_keys: np.ndarray,
    sim_keys: np.ndarray,
    masks: np.ndarray,
    lap: sp.spmatrix,
    params: TransferParams,
    activations: np.ndarray | None = None,
    targets: np.ndarray | None = None,
) -> tuple[sp.csr_matrix, np.ndarray]:
    """Normal equations of E_Align (eq. 4) = E_Match + alpha E_Mesh + beta E_CEG (+ epsilon |dp - dg|^2).

    Unknown ordering ``index = k * M + m``; the same (MK x MK) matrix serves x, y and z. da_keys (F', M, 3)
    (NaN gaps), sim_keys (K, F'), masks (K, M), lap (M, M). Returns A (MK, MK) and B (MK, 3).

    With ``activations`` h (K, F') and ``targets`` r (K, F', M, 3) the match term becomes the activation-aware
    ``(1/F) sum c~_kf |h_kf dp_k - diag(u_k) r_kf|^2`` (see :func:`transfer_blendshapes`, ``match``).
    """
    K, M, _ = ds.shape
    d_match, b_match = match_terms(da_keys, sim_keys, masks, activations, targets)
    LtL = (lap.T @ lap).tocsr()
    G = cross_expression_laplacian(shape_correlation_matrix(ds))
    GtG = G.T @ G
    IK = sp.identity(K, format="csr")
    IM = sp.identity(M, format="csr")
    A = (
        sp.diags(d_match.ravel() + params.epsilon)
        + (params.alpha / M) * sp.kron(IK, LtL, format="csr")
        + (params.beta / M) * sp.kron(sp.csr_matrix(GtG), IM, format="csr")
    )
    ref = ds if params.ceg_reference == "character" else dg
    B = np.empty((K * M, 3))
    for c in range(3):
        g = dg[..., c]
        B[:, c] = (
            b_match[..., c].ravel()
            + params.epsilon * g.ravel()
            + (params.alpha / M) * (LtL @ g.T).T.ravel()
            + (params.beta / M) * (GtG @ ref[..., c]).ravel()
        )
    return A.tocsr(), B


def training_displacements(
    training: np.ndarray, a0: np.ndarray, rigidity: np.ndarray | None = None, stabilize_frames: bool = True
) -> np.ndarray:
    """Actor displacements ``da_f = a_f - a0`` (F, M, 3) of a training sequence with head motion removed."""
    if stabilize_frames:
        training, _, _ = stabilize(training, a0, rigidity)
    return training - a0[None]


def transfer_blendshapes(
    s0: np.ndarray,
    ds: np.ndarray,
    a0: np.ndarray,
    da: np.ndarray,
    params: TransferParams | None = None,
    uv: np.ndarray | None = None,
    contact_pairs: np.ndarray | None = None,
    segment_starts: np.ndarray | None = None,
    dg: np.ndarray | None = None,
    prior: np.ndarray | None = None,
) -> TransferResult:
    """Automatic blendshape transfer (section 4): personalized sparse actor blendshapes.

    Parameters
    ----------
    s0 : (M, 3) character neutral markers; ds : (K, M, 3) character sparse blendshapes (character units).
    a0 : (M, 3) actor neutral markers (mm); da : (F, M, 3) stabilized training displacements (mm, NaN gaps).
    params : :class:`TransferParams`. uv, contact_pairs : see :func:`marker_triangulation`.
    segment_starts : first frame of each concatenated training sequence (for the key-frame filter).

    ``params.match = "faithful"`` minimizes eq. 4 exactly as written. Its weak spot (the paper's sec. 6.3
    notes it): eq. 10's minimizer is a similarity-weighted *mean* of masked key expressions; every key with a
    positive similarity (partial activations, mixtures, near-neutral frames) pulls ``dp_k`` toward a smaller
    shape, and ``diag(u_k)`` damps the actor's data where the character's shape falls off, so the shapes
    shrink. ``match = "activation"`` is one offered option: the
    activation of every shape in every key is solved jointly with the shapes (alternating, starting from the
    RBF guesses; :func:`key_activations`) and the match term becomes
    ``(1/F) sum_f sum_k c~_kf |diag(u_k) (h_kf dp_k - r_kf)|^2`` - the key expression minus what the other
    shapes explain, compared at the shape's activation, with the soft mask as a residual weight. The
    correlations, trust, contrast enhancement, key extraction, E_Mesh and E_CEG are unchanged.
    ``match = "fit"`` (:func:`fit_match_transfer`) matches all training frames with the whole blendshape model
    at sparse activations solved with the section-5 energy.
    ``prior`` (K, K): the E_Prior form for those activations (default none); ``dg``: initial guesses g_k
    (default :func:`rbf_transfer`).

    Returns
    -------
    :class:`TransferResult` with ``dp`` (K, M, 3) in mm.
    """
    params = params or TransferParams()
    if params.match not in ("faithful", "activation", "fit"):
        raise InputError(f"unknown match '{params.match}'", fix="use faithful, activation or fit")
    s0 = np.asarray(s0, float)
    ds = np.asarray(ds, float)
    a0 = np.asarray(a0, float)
    K, M, _ = ds.shape
    if a0.shape != (M, 3) or da.ndim != 3 or da.shape[1:] != (M, 3):
        raise InputError(f"marker count mismatch: character {M}, actor neutral {a0.shape}, training {da.shape}")
    dg = rbf_transfer(s0, ds, a0) if dg is None else np.asarray(dg, float)
    # correlations in the actor's frame: rotate the character's displacements by the s0 -> a0 rotation
    _, Rsa, _ = fit_similarity(s0, a0)
    ds_rot = ds @ Rsa.T
    c = correlations(da, ds_rot)
    t = trust_values(ds)
    sim = enhance_similarity(c, t, params.r)
    keys = key_expressions(sim, segment_starts)
    masks = soft_masks(ds)
    tri = marker_triangulation(s0, ds, uv=uv, contact_pairs=contact_pairs)
    lap = marker_laplacian(a0, tri)

    def solve(h=None, r=None) -> np.ndarray:
        if params.solver == "cholmod":
            A, B = align_system(s0, ds_rot, dg, da[keys], sim[:, keys], masks, lap, params, h, r)
            return _cholmod_solve(A, B).reshape(K, M, 3)
        d, C, Bk, R = align_terms(ds_rot, dg, da[keys], sim[:, keys], masks, lap, params, h, r)
        return kron_sum_solve(d, C, Bk, R)

    info = {"n_keys": int(keys.size), "match": params.match}
    if params.match == "activation":
        dp = dg.copy()
        for _ in range(params.match_iterations):
            h, r = key_activations(dp, da[keys])
            dp = solve(h, r)
    elif params.match == "fit":
        frames = keys if params.fit_frames == "keys" else np.arange(da.shape[0])
        Q = np.zeros((K, K)) if prior is None else np.asarray(prior, float)
        dp, h = fit_match_transfer(ds_rot, dg, a0, da[frames], lap, Q, params)
        info["fit_frames"] = int(frames.size)
        info["activations"] = h
    else:
        dp = solve()
    return TransferResult(dp, dg, keys, sim, t, masks, tri, info=info)


def fit_match_transfer(ds: np.ndarray, dg: np.ndarray, a0: np.ndarray, da: np.ndarray, lap: sp.spmatrix,
                       Q: np.ndarray, params: TransferParams) -> tuple[np.ndarray, np.ndarray]:
    """The ``"fit"`` option of E_Align: match the training frames with the blendshape model itself.

    ``E_Match' = (1/F) sum_f |da_f - J xi_f - sum_k h_kf dp_k|^2`` (visible markers; gaps imputed with the
    model's prediction), ``+ fit_alpha E_Mesh + beta E_CEG`` (eq. 11 and 12-13 unchanged, E_Mesh around the
    guesses g_k). The activations h (F, K) of the training frames and their residual rigid motion xi_f are
    the section-5 retargeting solution (E_Fit + fit_mu E_Prior + fit_lambda E_Sparse, joint rigid fit,
    bounds [0, 1]) with the current dp; dp and h alternate ``match_iterations`` times, starting from g_k.
    As for the faithful term, the minimizer over dp is three (MK x MK) systems, here the Kronecker sum
    ``(H^T H / F + beta/M G^T G) (x) I_M + I_K (x) fit_alpha/M L^T L`` (exact eigen-solve).

    Why: eq. 10 compares each shape with whole key expressions (its minimizer is a similarity-weighted mean of
    masked keys, which shrinks shapes whenever keys mix shapes or are partial); here every frame is explained
    by all shapes at once at their solved activations, and the sparse activations (lambda_cm 0.2) keep shapes
    from trading motion (with a box-only activation fit the shapes drift and the transfer ends below g_k).

    ds (K, M, 3) character shapes (actor orientation), dg (K, M, 3) guesses, a0 (M, 3), da (F, M, 3)
    stabilized training displacements (NaN gaps), lap (M, M) marker Laplacian, Q (K, K) prior (actor scale).
    Returns dp (K, M, 3) mm and h (F, K).
    """
    K, M, _ = dg.shape
    F = max(da.shape[0], 1)
    L = lap.toarray() if sp.issparse(lap) else np.asarray(lap)
    C = (params.fit_alpha / M) * (L.T @ L)
    G = cross_expression_laplacian(shape_correlation_matrix(ds))
    Bc = (params.beta / M) * (G.T @ G)
    ref = ds if params.ceg_reference == "character" else dg
    R0 = np.einsum("kmc,mn->knc", dg, C) + np.einsum("kl,lmc->kmc", Bc, ref) + params.epsilon * dg
    d = np.full((K, M), params.epsilon)
    vis = visible_mask(da)
    hp = RetargetParams(mu=params.fit_mu, lambda_cm=params.fit_lambda_cm, bounds=(0.0, 1.0), rigid="joint")
    dp = np.array(dg, dtype=np.float64, copy=True)
    h = np.zeros((da.shape[0], K))
    for it in range(params.match_iterations):
        rt = RiberaRetargeter(dp, Q, hp, reference=a0)
        h = rt.solve(da, start=h if it else None)  # warm start from the last activations (same minimizer)
        x = da - rt.rigid_motion(da, h)
        for _ in range(2):  # gaps: impute with the current model (EM for the least-squares match)
            x = np.where(vis[..., None], x, np.einsum("fk,kmc->fmc", h, dp))
            dp = kron_sum_solve(d, C, Bc + h.T @ h / F, R0 + np.einsum("fk,fmc->kmc", h, x) / F)
    return dp, h


def key_activations(dp: np.ndarray, da_keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Activations of every shape in every key expression and each shape's share of the key expression.

    dp (K, M, 3) current actor blendshapes; da_keys (F', M, 3) key displacements (NaN gaps). The weights
    ``h`` (K, F') in [0, 1] fit all shapes jointly to each key (least squares, bounds [0, 1]); the target of
    shape k in key f is the key minus what the other shapes explain, ``r_kf = da_f - sum_{l != k} h_lf dp_l``
    (K, F', M, 3).
    """
    K = dp.shape[0]
    rt = RiberaRetargeter(dp, np.zeros((K, K)), RetargetParams(mu=0.0, lambda_cm=0.0, bounds=(0.0, 1.0)))
    h = rt.solve(da_keys).T  # (K, F')
    full = np.einsum("kf,kmc->fmc", h, dp)  # (F', M, 3)
    r = da_keys[None] - full[None] + h[:, :, None, None] * dp[:, None]
    return h, r


# ======================================================================== geometric prior (sec. 5)
def mesh_cotangent_laplacian(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """(N, N) cotangent Laplacian of a triangle mesh (libigl ``cotmatrix``; non-finite entries zeroed)."""
    import igl

    L = igl.cotmatrix(np.asarray(vertices, np.float64), np.asarray(faces, np.int64))
    L = sp.csr_matrix(L)
    bad = ~np.isfinite(L.data)
    if bad.any():
        L.data[bad] = 0.0
    return L


def prior_matrix(neutral: np.ndarray, deltas: np.ndarray, faces: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Eq. 15 as a (K, K) quadratic form: ``E_Prior(w) = w^T Q w = (1/N) |L dV w|^2``.

    neutral (N, 3), deltas (K, N, 3) of the character (mm), faces (F, 3). ``L dV`` is precomputed once
    (cotangent Laplacian applied per coordinate); ``scale`` is the uniform scale that brings the rig to the
    actor's head size (the Laplacian's cotangent weights are scale invariant, the deltas scale).
    """
    L = mesh_cotangent_laplacian(neutral, faces)
    K, N, _ = deltas.shape
    Q = np.zeros((K, K))
    for c in range(3):
        LD = L @ deltas[:, :, c].T  # (N, K)
        Q += LD.T @ LD
    return Q * (scale**2) / N


def head_scale(a0: np.ndarray, s0: np.ndarray) -> float:
    """Uniform scale that makes the character's marker set ``s0`` as large as the actor's ``a0`` (RMS radius)."""
    ra = np.sqrt(((a0 - a0.mean(0)) ** 2).sum(1).mean())
    rs = np.sqrt(((s0 - s0.mean(0)) ** 2).sum(1).mean())
    return float(ra / rs) if rs > 0 else 1.0


def _masked_system(A: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Rows/columns of fixed variables of A (F, K, K) replaced by the identity (free: (F, K) bool)."""
    f = free.astype(A.dtype)
    out = A * f[:, :, None]
    out *= f[:, None, :]
    k = np.arange(A.shape[1])
    out[:, k, k] += 1.0 - f
    return out


def _solve_free(A: np.ndarray, b: np.ndarray, free: np.ndarray, fixed_values: np.ndarray) -> np.ndarray:
    """Batched ``A_f w_f = b_f`` over the free variables with the others held at ``fixed_values``.

    A (F, K, K), b (F, K), free (F, K) bool, fixed_values (F, K) (read where not free). Returns w (F, K):
    the fixed values, and on the free set ``w_S = A_SS^-1 (b_S - A_SN w_N)``. Solved as (F, m, m) systems
    with m the largest free count (free variables gathered first, the padding an identity block), which
    for sparse weights is a fraction of the (K, K) cost of :func:`_masked_system`.
    """
    F, K = b.shape
    wf = np.where(free, 0.0, fixed_values)
    rhs = b - (A @ wf[..., None])[..., 0]
    n_free = free.sum(1)
    m = int(n_free.max()) if F else 0
    if m == 0:
        return wf
    order = np.argsort(~free, axis=1, kind="stable")[:, :m]  # free variables first
    valid = np.arange(m)[None, :] < n_free[:, None]
    rows = np.arange(F)[:, None]
    Ar = A[rows[:, :, None], order[:, :, None], order[:, None, :]]
    pair = valid[:, :, None] & valid[:, None, :]
    Ar = np.where(pair, Ar, np.eye(m)[None])
    br = np.where(valid, np.take_along_axis(rhs, order, axis=1), 0.0)
    x = np.linalg.solve(Ar, br[..., None])[..., 0]
    w = wf.copy()
    w[np.broadcast_to(rows, order.shape)[valid], order[valid]] = x[valid]
    return w


def rigid_jacobian(reference: np.ndarray) -> np.ndarray:
    """(M, 3, 6) derivative of the marker positions under a small rigid motion of ``reference`` (M, 3).

    ``x_m(omega, t) ~ x_m + omega x (x_m - c) + t`` with c the centroid: columns 0-2 rotation (rad),
    3-5 translation (mm).
    """
    p = np.asarray(reference, float) - np.asarray(reference, float).mean(0)
    J = np.zeros(p.shape[:1] + (3, 6))
    # omega x p = -[p]_x omega
    J[:, 0, 1], J[:, 0, 2] = p[:, 2], -p[:, 1]
    J[:, 1, 0], J[:, 1, 2] = -p[:, 2], p[:, 0]
    J[:, 2, 0], J[:, 2, 1] = p[:, 1], -p[:, 0]
    J[:, :, 3:] = np.eye(3)
    return J


class RiberaRetargeter:
    """Per-frame weights minimizing eq. 16: ``(1/M)|da - P w|^2 + mu w^T Q w + (lambda/K) |w|_1``.

    dp : (K, M, 3) personalized sparse actor blendshapes (mm); Q : (K, K) prior form from
    :func:`prior_matrix` (already scaled to the actor's head); params : :class:`RetargetParams`.
    Frames with gaps use their visible markers (E_Fit over the visible ones, normalized by their count).

    reference : (M, 3) the actor's neutral markers; with ``params.rigid == "joint"`` E_Fit becomes
    ``min_xi (1/M)|da - P w - J xi|^2`` with J = :func:`rigid_jacobian` (reference) and xi (6,) a residual
    small rigid motion of the stabilized frame. xi is unbounded and unpenalized, so it is eliminated exactly:
    the normal matrix becomes the Schur complement ``P^T P - P^T J (J^T J)^-1 J^T P`` and the right-hand
    side ``P^T da - P^T J (J^T J)^-1 J^T da`` (per visibility pattern); the K x K bounded solve is unchanged.

    Speed (whole sequences and single frames give the same weights): the normal matrix of each visibility
    pattern is built once and cached (:meth:`_pattern_systems`); all frames are solved together, each
    active-set pass only over the free (off-bound) weights (:func:`_solve_free`); ``solve(..., start=w)``
    seeds the active set from a nearby solution (the rigid re-fit in :meth:`RiberaModel.retarget`).
    """

    def __init__(self, dp: np.ndarray, Q: np.ndarray, params: RetargetParams | None = None,
                 reference: np.ndarray | None = None):
        self.params = params or RetargetParams()
        if self.params.rigid not in ("joint", "fixed"):
            raise InputError(f"unknown rigid mode '{self.params.rigid}'", fix="use joint or fixed")
        self.dp = np.asarray(dp, float)
        K, M, _ = self.dp.shape
        self.K, self.M = K, M
        self.P = self.dp.transpose(1, 2, 0).reshape(M * 3, K)  # rows (m, c)
        self.Q = np.asarray(Q, float)
        Pm = self.dp.transpose(1, 2, 0)  # (M, 3, K)
        self.PtP_m = np.einsum("mck,mcl->mkl", Pm, Pm)  # (M,K,K)
        self._PtP = self.PtP_m.sum(0)
        self.joint = reference is not None and self.params.rigid == "joint"
        if self.joint:
            self.J = rigid_jacobian(reference)  # (M, 3, 6)
            self.PtJ_m = np.einsum("mck,mcj->mkj", Pm, self.J)  # (M, K, 6)
            self.JtJ_m = np.einsum("mci,mcj->mij", self.J, self.J)  # (M, 6, 6)
        self._full, self._full_G = self._system(np.ones(M, bool))
        self._cache: dict[bytes, tuple[np.ndarray, np.ndarray | None]] = {}
        lo, hi = (None, None) if self.params.bounds is None else self.params.bounds
        self.lo = -np.inf if lo is None else float(lo)
        self.hi = np.inf if hi is None else float(hi)

    def _system(self, vis: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Normal matrix (K, K) for visible markers ``vis`` (M,) and, for the joint rigid fit, the (K, 6)
        coupling ``G = P^T J (J^T J)^-1`` that the right-hand side needs."""
        n = max(int(vis.sum()), 1)
        hidden = ~vis
        use_hidden = hidden.sum() < vis.sum()

        def vsum(per_marker: np.ndarray) -> np.ndarray:
            return per_marker.sum(0) - per_marker[hidden].sum(0) if use_hidden else per_marker[vis].sum(0)

        PtP = self._PtP - self.PtP_m[hidden].sum(0) if use_hidden else self.PtP_m[vis].sum(0)
        G = None
        if self.joint:
            PtJ, JtJ = vsum(self.PtJ_m), vsum(self.JtJ_m)
            G = np.linalg.solve(JtJ + 1e-12 * np.trace(JtJ) * np.eye(6), PtJ.T).T  # (K, 6)
            PtP = PtP - G @ PtJ.T
            PtP = 0.5 * (PtP + PtP.T)
        return 2.0 * PtP / n + 2.0 * self.params.mu * self.Q, G

    def _rhs(self, da: np.ndarray, vis: np.ndarray, G: np.ndarray | None = None) -> np.ndarray:
        """(F, K) ``(2/M_f) P^T da_f`` over visible markers (minus ``G_f J^T da_f`` for the joint rigid fit;
        G (F, K, 6) or (K, 6))."""
        a3 = np.where(vis[..., None], np.nan_to_num(da), 0.0)
        a = a3.reshape(da.shape[0], -1)
        n = np.maximum(vis.sum(1), 1)
        b = a @ self.P
        if self.joint and G is not None:
            Jta = np.einsum("fmc,mcj->fj", a3, self.J)  # (F, 6)
            b = b - (np.einsum("fkj,fj->fk", G, Jta) if G.ndim == 3 else Jta @ G.T)
        return 2.0 * b / n[:, None]

    def rigid_motion(self, da: np.ndarray, w: np.ndarray) -> np.ndarray:
        """(F, M, 3) the residual rigid motion ``J xi_f`` that the joint fit attributes to each frame of da
        (F, M, 3) (NaN gaps) with weights w (F, K): ``xi_f = (J^T J)^-1 J^T (da_f - P w_f)`` over the visible
        markers (zeros for ``rigid="fixed"``)."""
        if not self.joint:
            return np.zeros(da.shape)
        vis = visible_mask(da)
        res = np.where(vis[..., None], np.nan_to_num(da) - np.einsum("fk,kmc->fmc", w, self.dp), 0.0)
        JtJ = np.einsum("fm,mij->fij", vis.astype(float), self.JtJ_m)
        Jtr = np.einsum("fmc,mcj->fj", res, self.J)
        xi = np.linalg.solve(JtJ + 1e-12 * np.eye(6), Jtr[..., None])[..., 0]
        return np.einsum("mcj,fj->fmc", self.J, xi)

    def _bounded_solve(self, A: np.ndarray, b: np.ndarray, shared: bool = False,
                       start: np.ndarray | None = None) -> np.ndarray:
        """Batched ``min 1/2 w^T A_f w - b_f^T w`` s.t. lo <= w <= hi by a primal active-set method.

        A (F, K, K) SPD, b (F, K); ``shared``: every A_f is the complete-visibility system (one inverse serves
        the unconstrained start). ``start`` (F, K): a previous solution whose active set (variables at a bound) is the first guess instead of
        the unconstrained solution's violations (a warm start; the minimizer is unique, so only the number
        of passes changes). Exact: KKT signs are checked each pass; frames where the fast primal-dual
        passes do not settle finish with :meth:`_primal_active_set`. Each pass solves only the free
        variables (:func:`_solve_free`).
        """
        F, K = b.shape
        if not (np.isfinite(self.lo) or np.isfinite(self.hi)):
            return np.linalg.solve(A, b[..., None])[..., 0]
        self.last_passes = 0
        self.unconverged = 0
        if start is not None:
            at_lo = start <= self.lo
            at_hi = start >= self.hi
            w = np.clip(start, self.lo, self.hi)
            todo = np.arange(F)
        else:
            # start from the unconstrained solution's violations (one shared inverse when every frame is complete)
            if shared and A.shape[0] > 1:
                if not hasattr(self, "_full_inv"):
                    self._full_inv = np.linalg.inv(self._full)
                w = b @ self._full_inv.T
            else:
                w = np.linalg.solve(A, b[..., None])[..., 0]
            at_lo = w < self.lo
            at_hi = w > self.hi
            todo = np.flatnonzero(at_lo.any(1) | at_hi.any(1))
        for _ in range(self.params.active_set_passes):
            if todo.size == 0:
                break
            self.last_passes += 1
            Ab, bb, lo_b, hi_b = A[todo], b[todo], at_lo[todo], at_hi[todo]
            free = ~(lo_b | hi_b)
            wb = _solve_free(Ab, bb, free, np.where(lo_b, self.lo, self.hi))
            grad = (Ab @ wb[..., None])[..., 0] - bb
            release = (lo_b & (grad < -1e-12)) | (hi_b & (grad > 1e-12))
            new_lo = free & (wb < self.lo - 1e-12)
            new_hi = free & (wb > self.hi + 1e-12)
            w[todo] = wb
            at_lo[todo] = (lo_b & ~release) | new_lo
            at_hi[todo] = (hi_b & ~release) | new_hi
            todo = todo[release.any(1) | new_lo.any(1) | new_hi.any(1)]
        if todo.size:
            w[todo] = self._primal_active_set(A[todo], b[todo], np.clip(w[todo], self.lo, self.hi))
        return np.clip(w, self.lo, self.hi)

    def _primal_active_set(self, A: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Batched primal active-set method from a feasible start (cannot cycle; for the few frames where
        the fast primal-dual active set above did not settle). One constraint changes per step."""
        F, K = b.shape
        lo, hi = self.lo, self.hi
        at_lo = w <= lo
        at_hi = w >= hi
        todo = np.arange(F)
        rows = np.arange(F)
        for _ in range(6 * K + 10):
            if todo.size == 0:
                break
            Ab, bb, lo_b, hi_b, wt = A[todo], b[todo], at_lo[todo], at_hi[todo], w[todo]
            free = ~(lo_b | hi_b)
            wb = _solve_free(Ab, bb, free, np.where(lo_b, lo, hi))
            d = wb - wt
            below = free & (wb < lo - 1e-12)
            above = free & (wb > hi + 1e-12)
            infeasible = below.any(1) | above.any(1)
            with np.errstate(divide="ignore", invalid="ignore"):
                alpha = np.where(below, (lo - wt) / d, np.inf)
                alpha = np.minimum(alpha, np.where(above, (hi - wt) / d, np.inf))
            r = rows[: todo.size]
            blk = np.argmin(alpha, axis=1)
            step = np.clip(alpha[r, blk], 0.0, 1.0)
            w_new = np.where(infeasible[:, None], wt + step[:, None] * d, wb)
            lo_new, hi_new = lo_b.copy(), hi_b.copy()
            inf_r = r[infeasible]
            lo_new[inf_r, blk[infeasible]] |= below[inf_r, blk[infeasible]]
            hi_new[inf_r, blk[infeasible]] |= above[inf_r, blk[infeasible]]
            # feasible frames: check multipliers, release the worst
            grad = (Ab @ w_new[..., None])[..., 0] - bb
            viol = np.where(lo_b, -grad, 0.0) + np.where(hi_b, grad, 0.0)  # > 0: wrong sign
            worst = np.argmax(viol, axis=1)
            release = ~infeasible & (viol[r, worst] > 1e-10)
            rel_r = r[release]
            lo_new[rel_r, worst[release]] = False
            hi_new[rel_r, worst[release]] = False
            w[todo] = np.clip(w_new, lo, hi)
            at_lo[todo] = lo_new
            at_hi[todo] = hi_new
            todo = todo[infeasible | release]
        self.unconverged = int(todo.size)
        return w

    def _pattern_systems(self, vis: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Normal matrices (F, K, K) and joint-rigid couplings (F, K, 6) (or None) for the visibility rows
        vis (F, M): one :meth:`_system` per distinct pattern, kept in a cache across calls (a take's gap
        patterns recur; one frame at a time then costs no re-assembly)."""
        packed = np.packbits(vis, axis=1)
        keys = [r.tobytes() for r in packed]
        cache = self._cache
        for key, row in zip(keys, vis):
            if key not in cache:
                if len(cache) >= self.CACHE_PATTERNS:
                    cache.clear()
                cache[key] = self._system(row)
        A = np.stack([cache[k][0] for k in keys])
        G = np.stack([cache[k][1] for k in keys]) if self.joint else None
        return A, G

    CACHE_PATTERNS = 1024  # (K, K) + (K, 6) floats each: about 25 MB at K = 53

    def solve(self, da: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
        """Weights (F, K) for stabilized actor displacements da (F, M, 3) (NaN gaps).

        ``start`` (F, K): weights of a nearby problem (e.g. the same frames before a rigid re-fit) whose
        active set seeds the bounded solve (with ``bounds`` and lo >= 0); the result is the same minimizer.
        """
        da = np.asarray(da, float)
        if da.ndim == 2:
            return self.solve(da[None], None if start is None else np.asarray(start)[None])[0]
        F = da.shape[0]
        vis = visible_mask(da)
        partial = ~vis.all(1)
        A = np.broadcast_to(self._full, (F, self.K, self.K))
        G = self._full_G
        if partial.any():
            A = A.copy()
            Ap, Gp = self._pattern_systems(vis[partial])
            A[partial] = Ap
            if self.joint:
                G = np.broadcast_to(self._full_G, (F, self.K, 6)).copy()
                G[partial] = Gp
        b = self._rhs(da, vis, G)
        lam = self.params.lambda_mm / self.K
        shared = not partial.any()
        if self.lo >= 0:
            # with w >= 0 the L1 term is linear, (lambda/K) sum_k w_k: exact, no reweighting needed
            return self._bounded_solve(A, b - lam, shared, start=start)
        w = self._bounded_solve(A, b, shared)
        if lam > 0:
            diag_idx = np.arange(self.K)
            for _ in range(self.params.irls_iterations):
                Ai = A.copy()
                Ai[:, diag_idx, diag_idx] += lam / (np.abs(w) + self.params.irls_eps)
                w = self._bounded_solve(Ai, b)
        return w

    def solve_frame(self, da: np.ndarray) -> np.ndarray:
        """Weights (K,) for one stabilized frame da (M, 3)."""
        return self.solve(np.asarray(da, float)[None])[0]


# ======================================================================== end-to-end model
@dataclass
class RiberaModel:
    """Everything needed to retarget performances of one actor onto one character.

    a0 : (M, 3) actor neutral (mm); dp : (K, M, 3) actor blendshapes used in E_Fit; Q : (K, K) prior;
    rigidity : (M,) stabilization weights; shape_names : K names; transfer : the transfer result (None for
    the ``rbf`` and ``deformation`` baselines).
    """

    a0: np.ndarray
    dp: np.ndarray
    Q: np.ndarray
    rigidity: np.ndarray
    shape_names: list[str]
    params: RetargetParams
    transfer: TransferResult | None = None

    def retargeter(self) -> RiberaRetargeter:
        return RiberaRetargeter(self.dp, self.Q, self.params, reference=self.a0)

    def retarget(self, markers: np.ndarray, retargeter: RiberaRetargeter | None = None) -> np.ndarray:
        """Weights (F, K) for raw performance markers (F, M, 3) mm with head motion and NaN gaps.

        Head motion is removed per frame (weighted rigid fit to ``a0`` with the rigidity weights), then
        ``refine_rigid`` times re-fitted against the fitted expression ``a0 + P w`` with uniform weights; with
        ``params.rigid = "joint"`` each solve also fits the remaining small rigid motion.
        """
        rt = retargeter or self.retargeter()
        stable, _, _ = stabilize(markers, self.a0, self.rigidity)
        w = rt.solve(stable - self.a0[None])
        for _ in range(self.params.refine_rigid):
            expr = self.a0[None] + np.einsum("fk,kmc->fmc", w, self.dp)
            stable, _, _ = stabilize(markers, expr)
            w = rt.solve(stable - self.a0[None], start=w)  # warm start: same minimizer, fewer passes
        return w


#: the methods :func:`build_model` prepares (the registry: :mod:`rigbuild.retarget.methods`)
METHODS = tuple(RIBERA_METHODS)


def deformation_guesses(character: Rig, vertex_ids: np.ndarray, a0: np.ndarray, workers: int = 1) -> np.ndarray:
    """Initial guesses g_k (K, M, 3) mm by deformation transfer (``TransferParams.guess = "deformation"``).

    The thin-plate RBF that maps the character's neutral markers onto the actor's ``a0`` (M, 3) warps the
    character's whole neutral mesh into the actor's proportions; the character's blendshapes are
    deformation-transferred (Sumner and Popovic 2004) onto that proxy and sampled at ``vertex_ids`` (M,).
    Unlike the pointwise RBF guess, this carries a shape's spatial gradients (a jaw hinge that moved, a lip
    roll on a wider mouth) into the new proportions. Uses ``rigbuild.retarget.proportion``. Only the marker
    vertices are solved for (``deformation_transfer(..., sample_vertices=...)``: the support pieces that reach
    a marker; exact, not a truncation). ``workers``: processes for the per-shape solves (same result).
    """
    vid = np.asarray(vertex_ids, dtype=np.int64)
    pmap = fit_proportion_map(character.neutral[vid], np.asarray(a0, float), "r")
    return transfer_displacements_mesh(pmap, character.neutral, character.deltas, character.faces, vid, workers)


def build_model(
    character: Rig,
    vertex_ids: np.ndarray,
    a0: np.ndarray,
    training: np.ndarray | None,
    method: str = "ribera",
    transfer_params: TransferParams | None = None,
    retarget_params: RetargetParams | None = None,
    segment_starts: np.ndarray | None = None,
    uv: np.ndarray | None = None,
    contact_pairs: np.ndarray | None = None,
    workers: int = 1,
) -> RiberaModel:
    """Prepare retargeting of an actor's markers onto ``character``.

    Parameters
    ----------
    character : the character rig (mm), any topology and shape set.
    vertex_ids : (M,) character vertex of each actor marker (see ``common.map_markers_to_vertices``).
    a0 : (M, 3) actor neutral markers (mm).
    training : (F, M, 3) the actor's training (ROM) markers (mm, NaN gaps, head motion allowed); unused by
        the ``"rbf"`` and ``"deformation"`` baselines.
    method : ``"ribera"`` (section 4 transfer as written), ``"ribera_activation"`` (the activation-aware
        E_Match option, see :func:`transfer_blendshapes`), ``"ribera_fit"`` (the ROM-fit E_Match option,
        :func:`fit_match_transfer`),
        ``"rbf"`` (baseline: the thin-plate RBF guesses ``g_k`` used directly), ``"deformation"`` (the
        deformation-transfer guesses of :func:`deformation_guesses` used directly).
    segment_starts : first frame of each concatenated training sequence.
    transfer_params.guess : g_k of ``"ribera"`` / ``"ribera_activation"`` (``"rbf"`` as in the paper, or
        ``"deformation"``).

    workers : processes for the deformation-transfer guesses (the job's threads; same result).

    All methods retarget with the same section-5 energy (E_Fit + mu E_Prior + lambda E_Sparse).
    """
    from rigbuild.retarget.common import character_sparse_blendshapes, rigidity_weights

    if method not in METHODS:
        raise InputError(f"unknown retargeting method '{method}'", fix=f"use one of {', '.join(METHODS)}")
    rp = retarget_params or RetargetParams()
    tp = transfer_params or TransferParams()
    ch = character.to_units("mm") if character.units != "mm" else character
    s0, ds = character_sparse_blendshapes(ch, vertex_ids)
    a0 = np.asarray(a0, float)
    scale = head_scale(a0, s0)
    Q = prior_matrix(ch.neutral, ch.deltas, ch.faces, scale)
    transfer = None
    if tp.guess not in ("rbf", "deformation"):
        raise InputError(f"unknown initial guess '{tp.guess}'", fix="use rbf or deformation")
    use_dt = method == "deformation" or (method != "rbf" and tp.guess == "deformation")
    dg = deformation_guesses(ch, vertex_ids, a0, workers) if use_dt else rbf_transfer(s0, ds, a0)
    rigidity = rigidity_weights(dg)
    if method in ("rbf", "deformation"):
        dp = dg
    else:
        if training is None:
            raise InputError(f"method '{method}' needs the actor's training (ROM) markers")
        da = training_displacements(np.asarray(training, float), a0, rigidity)
        if method == "ribera_activation":
            tp = TransferParams(**{**tp.__dict__, "match": "activation"})
        if method == "ribera_fit":
            tp = TransferParams(**{**tp.__dict__, "match": "fit"})
        transfer = transfer_blendshapes(s0, ds, a0, da, tp, uv=uv, contact_pairs=contact_pairs,
                                        segment_starts=segment_starts, dg=dg, prior=Q)
        dp = transfer.dp
    return RiberaModel(a0, dp, Q, rigidity, list(ch.shape_names), rp, transfer)
