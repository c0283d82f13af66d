"""Automatic neutral registration: template neutral -> actor's neutral reconstruction (Ma et al. 2016 s. 2.2).

1. **Landmark-driven similarity.** The painted dots (triangulated, unlabeled) are labeled by aligning the
   template's marker set to them (similarity ICP from a few starting rotations + optimal assignment),
   then :func:`rigbuild.geometry.fit_similarity` on the labeled pairs places the template.
2. **Non-rigid registration.** Laplacian-regularized deformation (:class:`LaplacianSolver`, rotated
   Laplacian coordinates) with three data terms, re-linearized every iteration:
   closest point (true point-to-plane to the scan, distance- and normal-gated, solved with x/y/z coupled by
   :func:`solve_point_to_plane` so vertices slide freely along the scan and their tangential placement is
   the Laplacian's smooth interpolation of the dots' correspondences; only vertices that a view's depth map
   observes get the term, :func:`observed_views`), landmark points (triangulated dots at the marker
   vertices) and the projective image term (each 2-D dot detection constrains its marker vertex to the
   camera ray through it; linearized as the ray's closest point).
   The schedule loosens the regularization (lambda grows) while the closest-point gate shrinks.

With ``params.coarse = "landmarks"`` the first level is the triangulated face landmarks instead of the dot
labeling (:func:`landmark_observations`, :func:`_landmark_alignment_from_landmarks`); the dots are then unlabeled
features that pull the closest point of the current mesh (:func:`_feature_terms`).

No hand-placed points: everything derives from the dot detections (or the landmarks) and the scan.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from rigbuild.errors import InputError
from rigbuild.geometry.rigid import apply_rigid, fit_similarity
from rigbuild.rig import Rig
from rigbuild.track.laplacian import LaplacianSolver, barycentric_matrix
from rigbuild.track.mesh import TrackingMesh, build_tracking_mesh
from rigbuild.track.params import RegistrationParams


@dataclass
class RayObservations:
    """2-D detections of marker vertices as world rays (the projective image term).

    marker : (N,) index into the rig's marker list; origin : (N, 3) camera centres mm; direction : (N, 3)
    unit world ray directions through the detections.
    """

    marker: np.ndarray
    origin: np.ndarray
    direction: np.ndarray


@dataclass
class LandmarkObservations:
    """Triangulated face landmarks for the ``landmarks`` coarse level.

    points : (L, 3) mm; vertices : (L, 3) template vertex ids and bary : (L, 3) barycentrics of each
    landmark's surface point on the template (a landmark table, :mod:`rigbuild.track.landmark_table`);
    weight : (L,) reliability in (0, 1].
    """

    points: np.ndarray
    vertices: np.ndarray
    bary: np.ndarray
    weight: np.ndarray


def landmark_observations(X: np.ndarray, table: dict, n_vertices: int) -> LandmarkObservations:
    """The valid rows of triangulated landmarks ``X`` (468, 3) (NaN = lost) with a landmark table
    (its ``faces`` and ``bary``; :func:`rigbuild.track.landmark_table.load_table`) checked against the
    template's vertex count ``n_vertices``."""
    faces = np.asarray(table["faces"], np.int64)
    if faces.max() >= n_vertices:
        raise InputError(f"the landmark table is for a {table.get('rig', '?')} template, not one with {n_vertices} "
                         "vertices", fix="use the ict template with registration.coarse: landmarks, or make a table "
                         "for this template (python -m rigbuild.track.landmark_table)")
    ok = np.isfinite(np.asarray(X, float)[:, 0])
    return LandmarkObservations(np.asarray(X, float)[ok], faces[ok], np.asarray(table["bary"], float)[ok],
                                np.asarray(table["reliability"], float)[ok])


@dataclass
class NeutralRegistration:
    """Result: ``vertices`` (V, 3) mm actor neutral in template topology; ``markers`` (M, 3) the marker
    vertices on it; ``similarity`` (s, R, t) template -> world; ``dot_labels`` (D,) index of the dot
    matched to each painted dot vertex (the markers first; -1 none); per-iteration ``history`` of residuals (mm)."""

    vertices: np.ndarray
    markers: np.ndarray
    similarity: tuple[float, np.ndarray, np.ndarray]
    dot_labels: np.ndarray
    scan_rms_mm: float  # point-to-plane RMS of the face region to the scan
    dot_rms_mm: float
    history: list[dict] = field(default_factory=list)
    #: the ``landmarks`` coarse level and the ``dots`` level with ``dot_surface_points``: every detected dot within
    #: the last gate of the registered neutral gets its own surface location: (K, 3) template vertex ids of its
    #: triangle, (K, 3) barycentrics, (K,) dot index; else None
    dot_surface: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


def require_markers(template: Rig) -> None:
    """Raise :class:`InputError` if the template has no usable marker/landmark vertices."""
    if template.marker_vertices.size < 4:
        raise InputError(
            f"template rig '{template.name}' defines {template.marker_vertices.size} marker vertices; tracking "
            "needs at least 4 face features (the painted dots at the rig's marker vertices)",
            fix="give the template a marker set (rig.json 'markers', rigbuild/assets/marker_sets/<rig>.json) or use a rig "
                "whose markers are defined",
        )


def _rotation_candidates(src: np.ndarray, dst: np.ndarray) -> list[np.ndarray]:
    """Starting rotations: identity plus every proper rotation taking src's principal axes onto dst's
    (all 6 axis pairings x signs: a face's width and height spread alike, and spurious dots or missing
    markers can swap the order of its principal axes)."""
    from itertools import permutations, product

    def axes(p):
        c = p - p.mean(0)
        _, _, vt = np.linalg.svd(c, full_matrices=False)
        return vt  # rows = principal axes

    A, B = axes(src), axes(dst)
    out = [np.eye(3)]
    for perm in permutations(range(3)):
        P = np.eye(3)[list(perm)]
        for signs in product((1.0, -1.0), repeat=3):
            R = B.T @ np.diag(signs) @ P @ A
            if np.linalg.det(R) > 0:
                out.append(R)
    return out


def label_dots(template_markers: np.ndarray, dots: np.ndarray, gate_mm: float = 6.0,
               iterations: int = 30) -> tuple[np.ndarray, tuple[float, np.ndarray, np.ndarray], float]:
    """Assign unlabeled 3-D dots to the template's markers.

    template_markers (M, 3) mm, dots (D, 3) mm. Similarity ICP (nearest neighbours, trimmed) from each
    candidate rotation; the best final fit is refined with an optimal one-to-one assignment
    (Hungarian, :func:`relabel_dots`) gated at ``gate_mm``, alternated with the similarity and then an
    affine map fitted to the pairs (the actor's proportions move some markers past the gate of a
    similarity). Returns labels (M,) dot index per marker or -1, the similarity
    (s, R, t) mapping template -> dots, and the RMS of the labeled pairs (mm).
    """
    tm = np.asarray(template_markers, dtype=np.float64)
    dots = np.asarray(dots, dtype=np.float64)
    if dots.shape[0] < 4:
        raise InputError(f"only {dots.shape[0]} painted dots were found on the neutral frame (need >= 4)",
                         fix="check the dot detector thresholds (track.dots) and that the actor's dots are visible")
    # the candidate alignments come from the dots near the bulk of them (dark spots in the hair or on the
    # background would tilt the principal axes and the scale); all dots are labeled at the end
    all_dots = dots
    rad = np.linalg.norm(dots - np.median(dots, axis=0), axis=1)
    core = rad <= 2.0 * np.median(rad)
    if core.sum() >= max(4, tm.shape[0] // 2):
        dots = dots[core]
    tree = cKDTree(dots)
    dc, tc = dots.mean(0), tm.mean(0)
    s0 = np.sqrt(((dots - dc) ** 2).sum(1).mean() / max(((tm - tc) ** 2).sum(1).mean(), 1e-12))
    best = None
    for R0 in _rotation_candidates(tm, dots):
        s, R, t = s0, R0, dc - s0 * R0 @ tc
        for _ in range(iterations):
            x = apply_rigid(tm, R, t, s)
            d, j = tree.query(x)
            keep = d <= max(np.percentile(d, 80), 1e-9)
            if keep.sum() < 4:
                break
            s, R, t = fit_similarity(tm[keep], dots[j[keep]])
        x = apply_rigid(tm, R, t, s)
        d, _ = tree.query(x)
        back, _ = cKDTree(x).query(dots)  # two-sided: a fit that shrinks onto a few dots leaves the rest far
        # (the nearest dots only on the way back: some dark spots are not painted dots)
        back = np.sort(back)[:max(int(np.ceil(0.7 * back.size)), min(back.size, tm.shape[0]) // 2)]
        score = float(np.mean(np.minimum(d, 3 * gate_mm)) + np.mean(np.minimum(back, 3 * gate_mm)))
        if best is None or score < best[0]:
            best = (score, s, R, t)
    _, s, R, t = best
    dots = all_dots
    labels = np.full(tm.shape[0], -1, dtype=np.int64)
    x = apply_rigid(tm, R, t, s)
    for it in range(4):
        labels = relabel_dots(x, dots, gate_mm)
        ok = labels >= 0
        if ok.sum() < 4:
            raise InputError(f"only {int(ok.sum())} dots could be matched to the template's markers",
                             fix="the neutral frame must show the actor's painted dots in a neutral pose")
        s, R, t = fit_similarity(tm[ok], dots[labels[ok]])
        x = apply_rigid(tm, R, t, s)
        if ok.sum() >= 12 and it >= 1:  # the actor's proportions: an affine map once enough pairs hold it
            A, b = fit_affine(tm[ok], dots[labels[ok]])
            x = tm @ A.T + b
    m = labels >= 0
    rms = float(np.sqrt(np.mean(np.sum((apply_rigid(tm[m], R, t, s) - dots[labels[m]]) ** 2, axis=1))))
    return labels, (float(s), R, t), rms


def relabel_dots(marker_positions: np.ndarray, dots: np.ndarray, gate_mm: float) -> np.ndarray:
    """One-to-one assignment of dots to markers at their current estimated positions.

    marker_positions (M, 3) mm (NaN rows: not assignable), dots (D, 3) mm. Optimal assignment (Hungarian)
    of the pairwise distances; pairs farther than ``gate_mm`` are dropped. Returns labels (M,): the dot
    index of each marker or -1.
    """
    x = np.asarray(marker_positions, dtype=np.float64)
    dots = np.asarray(dots, dtype=np.float64)
    labels = np.full(x.shape[0], -1, dtype=np.int64)
    if dots.shape[0] == 0 or x.shape[0] == 0:
        return labels
    cost = np.linalg.norm(x[:, None, :] - dots[None, :, :], axis=2)
    cost[~np.isfinite(cost)] = np.inf
    big = 10.0 * gate_mm
    rows, cols = linear_sum_assignment(np.minimum(cost, big))
    ok = cost[rows, cols] <= gate_mm
    labels[rows[ok]] = cols[ok]
    return labels


def fit_affine(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares affine map ``dst ~ A src + b`` (src, dst (N, 3), N >= 4). Returns A (3, 3), b (3,)."""
    X = np.hstack([src, np.ones((src.shape[0], 1))])
    sol, *_ = np.linalg.lstsq(X, dst, rcond=None)
    return sol[:3].T, sol[3]


def closest_point_targets(points: np.ndarray, normals: np.ndarray, tree: cKDTree, scan_points: np.ndarray,
                          scan_normals: np.ndarray, gate_mm: float, max_angle_deg: float = 60.0
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point-to-plane closest-point targets on a scan.

    points, normals (N, 3) current mesh vertices and unit normals; the scan as a KD-tree of
    ``scan_points`` (S, 3) with unit ``scan_normals``. Returns targets (N, 3) (the mesh point projected onto
    the tangent plane of its nearest scan point), weights (N,) in [0, 1] (0 = rejected by the distance
    gate or normal compatibility) and distances (N,) mm.
    """
    d, j = tree.query(points)
    q, n = scan_points[j], scan_normals[j]
    off = np.einsum("nd,nd->n", q - points, n)
    targets = points + off[:, None] * n
    cos = np.einsum("nd,nd->n", normals, n)
    w = np.where((d <= gate_mm) & (cos >= np.cos(np.radians(max_angle_deg))), 1.0, 0.0) * np.clip(cos, 0, 1)
    return targets, w, d


def solve_point_to_plane(
    solver: LaplacianSolver,
    delta: np.ndarray,
    tri: np.ndarray,
    bary: np.ndarray,
    targets: np.ndarray,
    weights: np.ndarray,
    plane_vertices: np.ndarray,
    plane_points: np.ndarray,
    plane_normals: np.ndarray,
    plane_weights: np.ndarray,
    lam: float,
    prior: np.ndarray,
) -> np.ndarray:
    """Laplacian deformation with point and point-to-plane constraints (coordinates coupled).

    Minimizes ``||L p - delta||^2 + lam sum_i w_i^2 ||B_i p - c_i||^2
    + lam sum_j v_j^2 (n_j . (p_{k_j} - q_j))^2 + eps ||p - prior||^2`` over p (T, 3) mm.
    The point-to-plane term leaves a vertex free to slide along the scan, so its tangential position is
    decided by the Laplacian (smooth interpolation of the dots' correspondences) instead of being held where
    the previous iterate put it. The plane term couples x, y and z, so the system has 3T unknowns
    (ordered x block, y block, z block) and is factored per call with CHOLMOD.

    solver : the :class:`LaplacianSolver` of the mesh (L, eps); delta (T, 3): Laplacian coordinates to keep;
    tri (N,), bary (N, 3), targets (N, 3), weights (N,): point constraints; plane_vertices (P,) vertex ids,
    plane_points (P, 3) mm and unit plane_normals (P, 3) of the scan, plane_weights (P,); lam: data weight;
    prior (T, 3). Returns p (T, 3) mm.
    """
    from cvxopt import cholmod, matrix, spmatrix

    import scipy.sparse as sp

    T = solver.n
    L = solver.L
    base = (L.T @ L).tocsr() + solver.eps * sp.eye(T, format="csr")
    rhs = L.T @ delta + solver.eps * prior
    if np.asarray(tri).size:
        B = barycentric_matrix(solver.faces, tri, bary, T)
        W2 = sp.diags(lam * np.asarray(weights, float) ** 2)
        base = base + (B.T @ W2 @ B).tocsr()
        rhs = rhs + B.T @ (W2 @ np.asarray(targets, float))
    k = np.asarray(plane_vertices, dtype=np.int64)
    n = np.asarray(plane_normals, dtype=np.float64)
    v2 = lam * np.asarray(plane_weights, dtype=np.float64) ** 2
    off = np.einsum("pd,pd->p", n, np.asarray(plane_points, dtype=np.float64))
    rows, cols, vals = [], [], []
    for a in range(3):
        for b in range(3):
            rows.append(a * T + k)
            cols.append(b * T + k)
            vals.append(v2 * n[:, a] * n[:, b])
    plane = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * T, 3 * T))
    A = (sp.kron(sp.eye(3), base) + plane).tocoo()
    low = A.row >= A.col
    b = rhs.T.reshape(-1).copy()  # x block, y block, z block
    for a in range(3):
        np.add.at(b, a * T + k, v2 * off * n[:, a])
    Ac = spmatrix(matrix(A.data[low].astype(np.float64)), matrix(A.row[low].astype(np.int64)),
                  matrix(A.col[low].astype(np.int64)), size=(3 * T, 3 * T))
    X = matrix(b)
    cholmod.linsolve(Ac, X)
    return np.array(X).reshape(3, T).T


def observed_views(points: np.ndarray, normals: np.ndarray, depth_views: list, tolerance_mm: float) -> np.ndarray:
    """Number of views (N,) in which each mesh point is observed: it faces the camera and the view's depth
    map at its projection agrees with its camera depth within ``tolerance_mm``.

    points, normals (N, 3) mm / unit; depth_views : list of (Camera, depth (H, W) camera-z mm, NaN = none).
    """
    from rigbuild.track.features import sample_bilinear

    n = np.zeros(points.shape[0], dtype=np.int64)
    for cam, depth in depth_views:
        z = points @ cam.R[2] + cam.t[2]
        facing = np.einsum("nd,nd->n", normals, cam.center - points) > 0
        zs = sample_bilinear(depth, cam.project(points))
        n += facing & (np.abs(zs - z) <= tolerance_mm)
    return n


def ray_targets(points: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Closest points (N, 3) on rays ``origin + s direction`` (unit directions) to ``points`` (N, 3)."""
    s = np.einsum("nd,nd->n", points - origin, direction)
    return origin + s[:, None] * direction


class _DotTerms(NamedTuple):
    """The dot and ray constraints of one labeling: ``has_dot`` (D,) which painted dots are constrained;
    dot_tri (K,), dot_bary (K, 3), dot_targets (K, 3) mm; the rays' tracking-mesh vertices r_local (Q,),
    their r_tri (Q,), r_bary (Q, 3), r_origin (Q, 3) mm and unit r_dir (Q, 3) (None without rays)."""

    has_dot: np.ndarray
    dot_tri: np.ndarray
    dot_bary: np.ndarray
    dot_targets: np.ndarray
    r_local: np.ndarray
    r_tri: np.ndarray | None
    r_bary: np.ndarray | None
    r_origin: np.ndarray | None
    r_dir: np.ndarray | None
    dot_w: np.ndarray | None = None  # (K,) per-constraint weights (None: params.dot_weight for all)


def _dot_terms(labels: np.ndarray, dots: np.ndarray, rays: RayObservations | None, mk_local: np.ndarray,
               mesh: TrackingMesh, ray_labels_are_dots: bool) -> _DotTerms:
    """Dot and ray constraints of a labeling (labels (D,): the dot index of each painted dot vertex or -1;
    mk_local (D,): their tracking-mesh ids, -1 off the mesh)."""
    has_dot = (labels >= 0) & (mk_local >= 0)
    dot_tri, dot_bary = mesh.vertex_points(mk_local[has_dot])
    ray = (np.zeros(0, dtype=np.int64),) + (None,) * 4
    if rays is not None and rays.marker.size:
        if ray_labels_are_dots:
            dot_to_marker = np.full(dots.shape[0], -1, dtype=np.int64)
            dot_to_marker[labels[labels >= 0]] = np.flatnonzero(labels >= 0)
            r_marker = dot_to_marker[rays.marker]
        else:
            r_marker = np.asarray(rays.marker, dtype=np.int64)
        r_ok = (r_marker >= 0)
        r_ok[r_ok] &= mk_local[r_marker[r_ok]] >= 0
        r_local = mk_local[r_marker[r_ok]]
        ray = (r_local,) + mesh.vertex_points(r_local) + (rays.origin[r_ok], rays.direction[r_ok])
    return _DotTerms(has_dot, dot_tri, dot_bary, dots[labels[has_dot]], *ray)


def _landmark_alignment(template: Rig, dots: np.ndarray, dot_vertices: np.ndarray, affine: bool
                        ) -> tuple[np.ndarray, tuple[float, np.ndarray, np.ndarray], np.ndarray]:
    """Label the dots and place the template on them: labels (D,), the similarity (s, R, t) and the
    aligned template neutral (V, 3) mm (similarity, then the landmark-driven affine refinement when
    ``affine``: it captures anisotropic proportions)."""
    labels, (s, R, t), _ = label_dots(template.neutral[dot_vertices], dots)
    aligned_full = apply_rigid(template.neutral, R, t, s)
    if affine:
        lab = labels >= 0
        A, b = fit_affine(template.neutral[dot_vertices][lab], dots[labels[lab]])
        aligned_full = template.neutral @ A.T + b
    return labels, (s, R, t), aligned_full


def _dot_rms(p: np.ndarray, mk_local: np.ndarray, terms: _DotTerms, faces: np.ndarray | None = None) -> float:
    """RMS (mm) of the constrained painted dot vertices of ``p`` (T, 3) to their dots; with ``faces`` (the
    ``landmarks`` level) of every constraint's surface point (landmarks and unlabeled dots) to its target."""
    if faces is not None:
        at = np.einsum("nk,nkd->nd", terms.dot_bary, p[faces[terms.dot_tri]])
        return float(np.sqrt(np.mean(np.sum((at - terms.dot_targets) ** 2, 1)))) if len(at) else float("nan")
    return float(np.sqrt(np.mean(np.sum((p[mk_local[terms.has_dot]] - terms.dot_targets) ** 2, 1))))


def site_positions(p: np.ndarray, mk_local: np.ndarray) -> np.ndarray:
    """The painted dot vertices' positions (D, 3) mm on tracking-mesh vertices ``p`` (T, 3); rows of vertices off the
    tracking mesh (``mk_local`` -1) are NaN, which :func:`relabel_dots` never assigns."""
    return np.where((mk_local >= 0)[:, None], p[np.maximum(mk_local, 0)], np.nan)


def smooth_stencil_offsets(sites: np.ndarray, offsets: np.ndarray, sigma_mm: float, outlier_mads: float = 3.0,
                           weights: np.ndarray | None = None, anchor: np.ndarray | None = None) -> np.ndarray:
    """The smooth part of the offsets of matched dots from their stencil sites.

    sites (N, 3) mm: the sites on the current mesh; offsets (N, 3) mm: each matched dot minus its site. A hand
    places each dot a few mm off its site in a random direction, while the mesh's own error varies slowly over
    the face: a Gaussian-weighted mean over sites (``sigma_mm``, 3-D distance) keeps the slow part and averages
    the placement error down. Matches whose offset departs from their neighbours' mean by more than
    ``outlier_mads`` x 1.4826 x the median departure of the matches (a false detection, a dot given to the
    wrong site) are left out of the mean (one pass). ``weights`` (N,): each row's weight in the means;
    ``anchor`` (N,) bool: rows that are no matches (fixed points) and are never left out nor counted in the
    median. Returns (N, 3) mm."""
    x = np.asarray(sites, np.float64).reshape(-1, 3)
    r = np.asarray(offsets, np.float64).reshape(-1, 3)
    if len(x) == 0:
        return r.copy()
    w = np.exp(-cdist(x, x, "sqeuclidean") / (2.0 * sigma_mm**2))
    if weights is not None:
        w = w * np.asarray(weights, np.float64)[None, :]
    fixed = np.zeros(len(x), bool) if anchor is None else np.asarray(anchor, bool)
    mean = w @ r / np.maximum(w.sum(1, keepdims=True), 1e-12)
    dev = np.linalg.norm(r - mean, axis=1)
    mad = np.median(dev[~fixed]) if (~fixed).any() else 0.0
    keep = fixed | (dev <= outlier_mads * max(1.4826 * mad, 1e-6))
    wk = w * keep[None, :]
    return wk @ r / np.maximum(wk.sum(1, keepdims=True), 1e-12)


def _stencil_warp(p: np.ndarray, mesh: TrackingMesh, mk_local: np.ndarray, dots: np.ndarray,
                  params: RegistrationParams, anchors: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                  ) -> np.ndarray:
    """Slide the tracking-mesh vertices ``p`` (T, 3) mm along the surface by the smooth part of the painted dots'
    offsets from their stencil sites (dots matched one to one within ``stencil_gate_mm``;
    :func:`smooth_stencil_offsets` at the sites, spread to every vertex by the same Gaussian), times
    ``stencil_warp``; the normal part is left to the scan. ``anchors``: (points (A, 3) mm on the mesh, their
    offsets (A, 3) mm, weights (A,)) taking part in the mean beside the dots (weight 1 each)."""
    from rigbuild.track.laplacian import vertex_normals

    at = site_positions(p, mk_local)
    labels = relabel_dots(at, dots, params.stencil_gate_mm)
    has = (labels >= 0) & (mk_local >= 0)
    if has.sum() < 4:
        return p
    x, r, sw = at[has], dots[labels[has]] - at[has], np.ones(int(has.sum()))
    fixed = np.zeros(len(x), bool)
    if anchors is not None:
        x, r, sw = (np.concatenate([a, b]) for a, b in zip((x, r, sw), anchors))
        fixed = np.concatenate([fixed, np.ones(len(anchors[0]), bool)])
    field = smooth_stencil_offsets(x, r, params.stencil_smoothing_mm, weights=sw, anchor=fixed)
    w = np.exp(-cdist(p, x, "sqeuclidean") / (2.0 * params.stencil_smoothing_mm**2)) * sw[None, :]
    cover = np.minimum(w.sum(1, keepdims=True), 1.0)
    move = (w @ field) / np.maximum(w.sum(1, keepdims=True), 1e-12) * cover  # fades out away from the dots
    n = vertex_normals(p, mesh.faces)
    move -= np.sum(move * n, 1, keepdims=True) * n
    return p + params.stencil_warp * move


def _with_stencil_prior(terms: _DotTerms, p: np.ndarray, mesh: TrackingMesh, mk_local: np.ndarray,
                        dots: np.ndarray, params: RegistrationParams) -> _DotTerms:
    """``terms`` plus the stencil prior: dots matched one to one to the painted dot vertices of ``p`` (gate
    ``stencil_gate_mm``) pull those vertices with ``stencil_prior_weight``."""
    at = site_positions(p, mk_local)
    labels = relabel_dots(at, dots, params.stencil_gate_mm)
    has = (labels >= 0) & (mk_local >= 0)
    tri, bary = mesh.vertex_points(mk_local[has])
    return terms._replace(dot_tri=np.concatenate([terms.dot_tri, tri]), dot_bary=np.concatenate([terms.dot_bary, bary]),
                          dot_targets=np.concatenate([terms.dot_targets, dots[labels[has]]]),
                          dot_w=np.concatenate([terms.dot_w, np.full(int(has.sum()), params.stencil_prior_weight)]))


#: reliable landmarks needed for the affine refinement of the landmark alignment (46 of the ICT table's 468 are
#: reliable at 0.2: a similarity, 4.0 mm face error, beat the affine, 5.3 mm, on a rendered ICT actor)
AFFINE_MIN_LANDMARKS = 100


def _landmark_alignment_from_landmarks(template: Rig, lm: LandmarkObservations, params: RegistrationParams
                                       ) -> tuple[tuple[float, np.ndarray, np.ndarray], np.ndarray]:
    """Place the template on the triangulated landmarks: weighted similarity on the reliable ones, then (with
    ``params.affine`` and >= :data:`AFFINE_MIN_LANDMARKS` of them) an affine map (with fewer, the landmarks'
    few-mm noise makes the 12 parameters worse than the similarity). Returns (s, R, t) and the aligned
    neutral (V, 3)."""
    P = np.einsum("nk,nkd->nd", lm.bary, template.neutral[lm.vertices])
    keep = lm.weight >= params.landmark_min_reliability
    if keep.sum() < 4:
        raise InputError(f"only {int(keep.sum())} reliable face landmarks were triangulated on the neutral frame",
                         fix="check that at least two cameras see the whole face, or use registration.coarse: dots")
    s, R, t = fit_similarity(P[keep], lm.points[keep], lm.weight[keep])
    aligned = apply_rigid(template.neutral, R, t, s)
    if params.affine and keep.sum() >= AFFINE_MIN_LANDMARKS:
        A, b = fit_affine(P[keep], lm.points[keep])
        aligned = template.neutral @ A.T + b
    return (s, R, t), aligned


def _similarity_icp(template: Rig, sim: tuple[float, np.ndarray, np.ndarray], aligned: np.ndarray, tree: cKDTree,
                    scan_points: np.ndarray, iterations: int = 15, keep_pct: float = 90.0
                    ) -> tuple[tuple[float, np.ndarray, np.ndarray], np.ndarray]:
    """Refine the landmark similarity on the scan: trimmed closest-point similarity ICP of the face region (the
    ``keep_pct`` % nearest pairs), started from the landmarks' pose. The face's shape fixes the pose better than
    the landmarks' few-mm noise: on a rendered ICT actor (bench_track's, seed 5) the template's face error after
    the similarity went from 4.0 to 2.2 mm (keeping the landmarks in the fit at equal total weight: 3.3 mm;
    70 % of the pairs: 2.6 mm; the registration's face error 2.7 -> 1.65 mm). A detector's landmarks share a
    bias of a few mm (the whole set sits off the skin points the table names, while their residual to the
    similarity is small), which the scan's shape corrects. An affine ``aligned`` (many reliable landmarks)
    is kept as it is."""
    s, R, t = sim
    if not np.allclose(aligned, apply_rigid(template.neutral, R, t, s)):
        return sim, aligned
    P0 = template.neutral[template.face_vertices]
    for _ in range(iterations):
        d, j = tree.query(apply_rigid(P0, R, t, s))
        keep = d <= max(np.percentile(d, keep_pct), 1e-9)
        s, R, t = fit_similarity(P0[keep], scan_points[j[keep]])
    return (s, R, t), apply_rigid(template.neutral, R, t, s)


def _feature_terms(p: np.ndarray, mesh: TrackingMesh, lm_tri: np.ndarray, lm_bary: np.ndarray, lm: LandmarkObservations,
                   dots: np.ndarray, params: RegistrationParams, gate_mm: float) -> _DotTerms:
    """The ``landmarks`` level's constraints at the current tracking-mesh vertices ``p``: every landmark's table
    point (lm_tri, lm_bary on the tracking mesh) to its triangulated position (weight landmark_weight x
    reliability), every dot within ``gate_mm`` of the mesh to it from its closest mesh point
    (feature_dot_weight)."""
    from rigbuild.track.matches import closest_surface_points

    tri, bary, d = closest_surface_points(dots, p, mesh.faces)
    ok = d <= gate_mm
    none = np.zeros(0, np.int64)
    return _DotTerms(np.zeros(0, bool), np.concatenate([lm_tri, tri[ok]]), np.concatenate([lm_bary, bary[ok]]),
                     np.concatenate([lm.points, dots[ok]]), none, None, None, None, None,
                     np.concatenate([params.landmark_weight * lm.weight,
                                     np.full(int(ok.sum()), params.feature_dot_weight)]))


def _nonrigid_step(p: np.ndarray, it: int, params: RegistrationParams, solver: LaplacianSolver,
                   mesh: TrackingMesh, tree: cKDTree, scan_points: np.ndarray, scan_normals: np.ndarray,
                   terms: _DotTerms, mk_local: np.ndarray, depth_views: list | None,
                   faces: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """One non-rigid iteration ``it`` from the tracking-mesh vertices ``p`` (T, 3) mm: closest points on the
    scan (lambda and gate from their schedules), the dot and ray terms, one Laplacian solve. Returns the new
    vertices and the iteration's history row."""
    from rigbuild.track.laplacian import vertex_normals

    face = mesh.face_local
    lam_schedule, gate_schedule_mm = params.lam_schedule, params.gate_schedule_mm
    a = it / max(params.iterations - 1, 1)
    lam = lam_schedule[0] * (lam_schedule[1] / lam_schedule[0]) ** a
    gate = gate_schedule_mm[0] * (gate_schedule_mm[1] / gate_schedule_mm[0]) ** a
    nrm = vertex_normals(p, mesh.faces)
    tgt, w, dist = closest_point_targets(p[face], nrm[face], tree, scan_points, scan_normals, gate,
                                         params.max_normal_angle_deg)
    if depth_views:
        w = w * (observed_views(p[face], nrm[face], depth_views, max(gate, params.visibility_mm)) > 0)
    cp_tri, cp_bary = mesh.vertex_points(face)
    tris = [cp_tri, terms.dot_tri]
    barys = [cp_bary, terms.dot_bary]
    tgts = [tgt, terms.dot_targets]
    ws = [w, np.full(terms.dot_tri.size, params.dot_weight) if terms.dot_w is None else terms.dot_w]
    if terms.r_local.size:
        tris.append(terms.r_tri)
        barys.append(terms.r_bary)
        tgts.append(ray_targets(p[terms.r_local], terms.r_origin, terms.r_dir))
        ws.append(np.full(terms.r_local.size, params.ray_weight))
    delta = solver.rotated_delta(p) if params.rotate_delta else solver.delta_rest
    if params.point_to_plane:
        _, j = tree.query(p[face])
        p = solve_point_to_plane(solver, delta, np.concatenate(tris[1:]), np.concatenate(barys[1:]),
                                 np.concatenate(tgts[1:]), np.concatenate(ws[1:]), face[w > 0], tgt[w > 0],
                                 scan_normals[j[w > 0]], w[w > 0], lam, prior=p)
    else:
        p, rep = solver.solve(np.concatenate(tris), np.concatenate(barys), np.concatenate(tgts),
                              np.concatenate(ws), lam, delta=delta, prior=p)
    valid = w > 0
    row = {"iteration": it, "lambda": lam, "gate_mm": gate,
           "scan_median_mm": float(np.median(dist[valid])) if valid.any() else float("nan"),
           "closest_points": int(valid.sum()), "dot_rms_mm": _dot_rms(p, mk_local, terms, faces)}
    return p, row


def register_neutral(
    template: Rig,
    scan_points: np.ndarray,
    scan_normals: np.ndarray,
    dots: np.ndarray,
    rays: RayObservations | None = None,
    params: RegistrationParams | None = None,
    *,
    mesh: TrackingMesh | None = None,
    depth_views: list | None = None,
    dot_vertices: np.ndarray | None = None,
    landmarks: LandmarkObservations | None = None,
) -> NeutralRegistration:
    """Register the template's neutral to the actor's neutral scan.

    template : Rig in mm with marker vertices (the painted dots); scan_points, scan_normals (S, 3): the
    reconstructed neutral surface (mm, unit normals, e.g. the fused mesh's vertices); dots (D, 3) mm:
    triangulated dot centres (unlabeled); rays : 2-D dot detections as rays; their ``marker`` field holds a
    dot index (``params.ray_labels_are_dots``) that is converted to a marker index through the labeling.
    params : :class:`~rigbuild.track.params.RegistrationParams` (schedules, weights, options; default the
    defaults). mesh : the template's tracking mesh (built when None).
    depth_views : (camera, depth map) pairs; when given, the closest-point term is applied only to vertices
    observed in at least one view (:func:`observed_views`, ``params.visibility_mm``).
    dot_vertices : (D,) template vertices of the painted dots (:func:`rigbuild.dots.painted_dot_vertices`:
    the markers and the stencil dots); default: the markers.
    landmarks : the triangulated face landmarks, required by ``params.coarse = "landmarks"``.

    Returns :class:`NeutralRegistration` (vertices in full template topology).
    """
    params = params or RegistrationParams()
    require_markers(template)
    scan_points = np.asarray(scan_points, dtype=np.float64)
    scan_normals = np.asarray(scan_normals, dtype=np.float64)
    if scan_points.shape[0] < 100:
        raise InputError(f"the neutral scan has only {scan_points.shape[0]} points",
                         fix="check the reconstruction of the neutral frame (depth maps / fused mesh)")
    mesh = mesh or build_tracking_mesh(template.neutral, template.faces, template.face_region)
    dot_vertices = template.marker_vertices if dot_vertices is None else np.asarray(dot_vertices, np.int64)
    if params.coarse == "landmarks":
        if landmarks is None:
            raise InputError("registration.coarse is 'landmarks' but no face landmarks were given",
                             fix="pass the triangulated landmarks (track_neutral_frame does) or use coarse: dots")
        return _register_from_landmarks(template, scan_points, scan_normals, dots, landmarks, params, mesh,
                                        depth_views, dot_vertices)
    labels, (s, R, t), aligned_full = _landmark_alignment(template, dots, dot_vertices, params.affine)
    rest = mesh.local(aligned_full)
    solver = LaplacianSolver(rest, mesh.faces)
    tree = cKDTree(scan_points)
    mk_local = mesh.full_to_local[dot_vertices]
    terms = _dot_terms(labels, dots, rays, mk_local, mesh, params.ray_labels_are_dots)
    p = rest.copy()
    history = []
    for it in range(params.iterations):
        if it in params.relabel_at:
            # the painted dots sit at the markers of the actor's surface: once the mesh has taken the scan's
            # shape its markers are near their dots, so dots the first (affine) labeling could not reach or
            # confused are assigned again, one to one, with a tighter gate
            at = site_positions(p, mk_local)
            labels = relabel_dots(at, dots, params.relabel_gate_mm)
            terms = _dot_terms(labels, dots, rays, mk_local, mesh, params.ray_labels_are_dots)
        p, row = _nonrigid_step(p, it, params, solver, mesh, tree, scan_points, scan_normals, terms, mk_local,
                                depth_views)
        history.append(row)
    if params.stencil_warp > 0:
        p = _stencil_warp(p, mesh, mk_local, dots, params)
        at = site_positions(p, mk_local)
        labels = relabel_dots(at, dots, params.relabel_gate_mm)  # the labels of the warped mesh
    full = mesh.to_full(p, aligned_full)
    return NeutralRegistration(
        vertices=full, markers=full[template.marker_vertices], similarity=(s, R, t), dot_labels=labels,
        scan_rms_mm=_scan_rms(p, mesh, tree, scan_points, scan_normals, params),
        dot_rms_mm=_dot_rms(p, mk_local, terms), history=history,
        dot_surface=dot_surface_points(p, mesh, dots, params.gate_schedule_mm[1],
                                       stencil_matched_dots(p, mk_local, dots, params.dot_surface_stencil_gate_mm))
        if params.dot_surface_points else None,
    )


def dot_surface_points(p: np.ndarray, mesh: TrackingMesh, dots: np.ndarray, gate_mm: float,
                       keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each detected dot's own point on the registered neutral: the closest surface point of ``p`` (T, 3) mm (the
    tracking mesh) to each of ``dots`` (D, 3) mm, kept within ``gate_mm`` (dots on the skin, not on hair, the
    background or the eyes) and, given ``keep`` (D,) bool, only where it is set. Returns (K, 3) template vertex
    ids of its triangle, (K, 3) barycentrics, (K,) dot indices (:attr:`NeutralRegistration.dot_surface`)."""
    from rigbuild.track.matches import closest_surface_points

    tri, bary, dist = closest_surface_points(np.asarray(dots, np.float64).reshape(-1, 3), p, mesh.faces)
    ok = dist <= gate_mm
    if keep is not None:
        ok &= np.asarray(keep, bool)
    on = np.flatnonzero(ok)
    return mesh.vertex_ids[mesh.faces[tri[on]]], bary[on], on


def stencil_matched_dots(p: np.ndarray, mk_local: np.ndarray, dots: np.ndarray, gate_mm: float) -> np.ndarray | None:
    """(D,) bool: the ``dots`` (D, 3) mm matched one to one (:func:`relabel_dots`) to a stencil site of the
    registered tracking mesh ``p`` (T, 3) mm (``mk_local``: the sites' local vertex ids, -1 = off the mesh) within
    ``gate_mm``; None for ``gate_mm`` <= 0 (every dot)."""
    if gate_mm <= 0:
        return None
    labels = relabel_dots(site_positions(p, mk_local), dots, gate_mm)
    keep = np.zeros(len(dots), bool)
    keep[labels[labels >= 0]] = True
    return keep


def _scan_rms(p: np.ndarray, mesh: TrackingMesh, tree: cKDTree, scan_points: np.ndarray, scan_normals: np.ndarray,
              params: RegistrationParams) -> float:
    """Point-to-plane RMS (mm) of the face region of ``p`` to the scan, at the last iteration's gate."""
    from rigbuild.track.laplacian import vertex_normals

    face = mesh.face_local
    nrm = vertex_normals(p, mesh.faces)
    tgt, w, _ = closest_point_targets(p[face], nrm[face], tree, scan_points, scan_normals,
                                      params.gate_schedule_mm[1])
    dist = np.linalg.norm(tgt - p[face], axis=1)
    return float(np.sqrt(np.mean(dist[w > 0] ** 2))) if np.any(w > 0) else float("nan")


def _register_from_landmarks(template: Rig, scan_points: np.ndarray, scan_normals: np.ndarray, dots: np.ndarray,
                             lm: LandmarkObservations, params: RegistrationParams, mesh: TrackingMesh,
                             depth_views: list | None, dot_vertices: np.ndarray) -> NeutralRegistration:
    """:func:`register_neutral` with the ``landmarks`` coarse level (see :class:`RegistrationParams`)."""
    from rigbuild.track.matches import closest_surface_points

    (s, R, t), aligned_full = _landmark_alignment_from_landmarks(template, lm, params)
    tree = cKDTree(scan_points)
    (s, R, t), aligned_full = _similarity_icp(template, (s, R, t), aligned_full, tree, scan_points)
    rest = mesh.local(aligned_full)
    solver = LaplacianSolver(rest, mesh.faces)
    # the table's surface points on the tracking mesh (landmarks on untracked parts are dropped)
    at = np.einsum("nk,nkd->nd", lm.bary, aligned_full[lm.vertices])
    lm_tri, lm_bary, d = closest_surface_points(at, rest, mesh.faces)
    on = d < 1e-4
    lm = LandmarkObservations(lm.points[on], lm.vertices[on], lm.bary[on], lm.weight[on])
    lm_tri, lm_bary = lm_tri[on], lm_bary[on]
    mk_local = mesh.full_to_local[dot_vertices]
    dots = np.asarray(dots, np.float64).reshape(-1, 3)
    p = rest.copy()
    history = []
    for it in range(params.iterations):
        a = it / max(params.iterations - 1, 1)
        gate = params.gate_schedule_mm[0] * (params.gate_schedule_mm[1] / params.gate_schedule_mm[0]) ** a
        terms = _feature_terms(p, mesh, lm_tri, lm_bary, lm, dots, params, gate)
        if params.stencil_prior_weight > 0 and it >= min(params.relabel_at, default=0):
            terms = _with_stencil_prior(terms, p, mesh, mk_local, dots, params)
        p, row = _nonrigid_step(p, it, params, solver, mesh, tree, scan_points, scan_normals, terms, mk_local,
                                depth_views, faces=mesh.faces)
        row["landmarks"], row["dots_used"] = int(lm_tri.size), int(terms.dot_tri.size - lm_tri.size)
        history.append(row)
    if params.stencil_warp > 0:
        lm_at = np.einsum("nk,nkd->nd", lm_bary, p[mesh.faces[lm_tri]])
        # the landmarks are fitted already: zero offsets there, weighed by their reliability
        anchors = (lm_at, np.zeros_like(lm_at), params.stencil_landmark_weight * lm.weight)
        p = _stencil_warp(p, mesh, mk_local, dots, params, anchors)
    full = mesh.to_full(p, aligned_full)
    at_dots = site_positions(p, mk_local)
    labels = relabel_dots(at_dots, dots, params.relabel_gate_mm)  # read off the mesh, for the sequence tracker
    return NeutralRegistration(
        vertices=full, markers=full[template.marker_vertices], similarity=(s, R, t), dot_labels=labels,
        scan_rms_mm=_scan_rms(p, mesh, tree, scan_points, scan_normals, params),
        dot_rms_mm=_dot_rms(p, mk_local, terms, mesh.faces), history=history,
        dot_surface=dot_surface_points(p, mesh, dots, params.gate_schedule_mm[1],
                                       stencil_matched_dots(p, mk_local, dots, params.dot_surface_stencil_gate_mm)),
    )
