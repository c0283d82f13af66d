"""The personalized rig feeding retargeting: markers placed on the actor's own rig, actor weights solved from it.

Ma et al. 2016 personalize a rig so that "rigs personalized to different actors behave consistently"; here a
performance's markers are read through that rig:

1. **Marker map** (:func:`fit_marker_map`): each marker's own point on the rig's skin, a triangle, barycentric
   coordinates and an offset along the triangle's normal (a marker sits on a stalk or a bead above the skin).
   The rigid pose of the take, the expression of a few of its frames and each marker's closest point on the
   posed rig are alternated (the barycentric coordinates of a closest point on a posed rig are the same skin
   point on its neutral: one topology), so the take need not start at neutral and hand-placed markers land where
   they were placed, not on a template vertex.
2. **Actor weights** (:func:`solve_actor_weights`): per frame, rigid head motion and weights in ``bounds`` of
   the rig's shapes sampled at the markers (:func:`sample_rig_at_markers`), the personalization's weight step
   (Ma et al. eq. 3-4: ``||x(w) - p||^2 + lambda_s (1^T w)^2``) in marker space, with the retargeting's temporal
   term ``lambda_t ||w_f - w_(f-1)||^2`` and L1 sparsity ``lambda_l1 1^T w``. Gauss-Newton sweeps over all
   frames at once: the rigid motion eliminated, then the weights by exact box QPs, one per frame
   (:func:`rigbuild.geometry.box_qp.solve_box_qp_batched`) or, with the temporal term, one over every frame with
   a block tridiagonal Hessian (:func:`rigbuild.geometry.block_tridiagonal.solve_box_qp_block_tridiagonal`).
   Optionally (:func:`solve_actor_weights_refined`, beyond the issue's solve) the EM's shape step in marker space
   (:func:`refine_rig_at_markers`) alternates with it: the rig at the markers is re-estimated from the take's own
   frames, held to the personalized rig by a prior.
3. **Semantic transfer** (:func:`semantic_transfer`): a character whose shape names match the actor rig's takes
   the actor weights by name (the baseline of the ``*_actor_rig`` paths).

Units: mm. Shapes: F frames, M markers, K shapes, V vertices.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.geometry.block_tridiagonal import solve_box_qp_block_tridiagonal
from rigbuild.geometry.box_qp import solve_box_qp_batched
from rigbuild.geometry.mesh import closest_surface_points, points_on_surface
from rigbuild.geometry.rigid import fit_rigid_motion_batched
from rigbuild.progress import progress
from rigbuild.retarget.common import refit_rig_at_markers

log = logging.getLogger(__name__)


@dataclass
class MarkerMap:
    """Markers on a rig's skin: names (M,), face_ids (M,) triangles of the rig, barycentric (M, 3),
    normal_offset (M,) mm along the triangle's normal; surface_rms_mm: RMS distance of the placing frames'
    markers to their points on the posed rig (mm); placed (M,) bool: the marker was seen in a placing frame
    (an unplaced one keeps its starting point, e.g. its template vertex; None: all placed)."""

    names: list[str]
    face_ids: np.ndarray
    barycentric: np.ndarray
    normal_offset: np.ndarray
    surface_rms_mm: float = float("nan")
    placed: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.placed is None:
            self.placed = np.ones(len(self.names), dtype=bool)

    def points(self, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """The markers (..., M, 3) on a mesh (..., V, 3) of the rig's topology (offsets included)."""
        return points_on_surface(vertices, faces, self.face_ids, self.barycentric, self.normal_offset)

    def to_json(self) -> dict:
        """``marker_map.json``'s ``markers``: name -> {face, barycentric, normal_offset_mm, placed}."""
        return {n: {"face": int(f), "barycentric": [float(b) for b in bc], "normal_offset_mm": float(o),
                    "placed": bool(pl)}
                for n, f, bc, o, pl in zip(self.names, self.face_ids, self.barycentric, self.normal_offset, self.placed)}

    @classmethod
    def from_json(cls, markers: dict, path=None) -> "MarkerMap":
        try:
            names = list(markers)
            faces = np.array([int(markers[n]["face"]) for n in names], dtype=np.int64)
            bary = np.array([[float(b) for b in markers[n]["barycentric"]] for n in names]).reshape(-1, 3)
            off = np.array([float(markers[n].get("normal_offset_mm", 0.0)) for n in names])
            placed = np.array([bool(markers[n].get("placed", True)) for n in names], dtype=bool)
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"malformed marker map ({e})", path=path,
                             fix='expected {"markers": {"<name>": {"face": f, "barycentric": [a, b, c]}}}') from None
        return cls(names, faces, bary, off, placed=placed)


def sample_rig_at_markers(neutral: np.ndarray, deltas: np.ndarray, faces: np.ndarray,
                          marker_map: MarkerMap) -> tuple[np.ndarray, np.ndarray]:
    """The rig at the markers: neutral (M, 3) mm (with each marker's normal offset) and shape offsets
    (K, M, 3) mm (the barycentric blend of the vertex offsets; the offset's direction follows the neutral).

    neutral (V, 3), deltas (K, V, 3) mm, faces (T, 3)."""
    b0 = marker_map.points(neutral, faces)
    tri = np.asarray(faces, dtype=np.int64)[marker_map.face_ids]
    D = np.einsum("kmjc,mj->kmc", np.asarray(deltas, dtype=np.float64)[:, tri], marker_map.barycentric)
    return b0, D


def vertex_marker_map(names: Sequence[str], vertices: np.ndarray, faces: np.ndarray) -> MarkerMap:
    """A map putting each marker exactly on a vertex (barycentric one-hot on a triangle using it)."""
    F = np.asarray(faces, dtype=np.int64)
    v = np.asarray(vertices, dtype=np.int64)
    owner = np.full(max(int(F.max()), int(v.max(initial=0))) + 1, -1, dtype=np.int64)
    corner = np.zeros_like(owner)
    for j in (2, 1, 0):
        owner[F[:, j]] = np.arange(F.shape[0])
        corner[F[:, j]] = j
    if np.any(owner[v] < 0):
        raise InputError("a marker vertex is on no triangle of the rig", fix="use a marker set on the rig's skin")
    bary = np.zeros((v.size, 3))
    bary[np.arange(v.size), corner[v]] = 1.0
    return MarkerMap(list(names), owner[v], bary, np.zeros(v.size))


# ------------------------------------------------------------------------------------------- the solve
#: most active-set passes of a temporal weight step (:func:`solve_box_qp_block_tridiagonal`)
TEMPORAL_MAX_PASSES = 100


@dataclass
class ActorWeights:
    """weights (F, K) in the rig's shape order; rotations (F, 3, 3), translations (F, 3) mm: the head pose
    ``p = R (b0 + D w) + t``; residual_mm (F,) RMS marker residual per frame (NaN: no marker);
    observable (K,) bool: the shapes solved (the others are 0); sweeps: Gauss-Newton sweeps run;
    converged: the last sweep moved no weight more than ``tol`` (and every QP converged)."""

    weights: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    residual_mm: np.ndarray
    observable: np.ndarray
    sweeps: int
    converged: bool


def _grams(D: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """(F, K, K) ``sum_m v_fm D_m^T D_m`` per frame, computed once per distinct visibility pattern."""
    patterns, inverse = np.unique(visible, axis=0, return_inverse=True)
    per_pattern = np.einsum("kmc,pm,lmc->pkl", D, patterns.astype(np.float64), D, optimize=True)
    return per_pattern[np.asarray(inverse).reshape(-1)]


def _rotation_exp(omega: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrices (F, 3, 3) of axis-angle vectors (F, 3)."""
    ang = np.linalg.norm(omega, axis=1)
    Kx = np.zeros((omega.shape[0], 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -omega[:, 2], omega[:, 1], -omega[:, 0]
    Kx -= Kx.transpose(0, 2, 1)
    safe = np.maximum(ang, 1e-12)
    a = np.where(ang > 1e-12, np.sin(ang) / safe, 1.0)[:, None, None]
    b = np.where(ang > 1e-12, (1 - np.cos(ang)) / safe**2, 0.5)[:, None, None]
    return np.eye(3) + a * Kx + b * Kx @ Kx


def _frame_energy(model: np.ndarray, R: np.ndarray, t: np.ndarray, Pz: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """(F,) data term ``sum_m v ||R y + t - p||^2`` (mm^2) of posed models ``y`` (F, M, 3)."""
    d = model @ R.transpose(0, 2, 1) + t[:, None] - Pz
    return np.where(vis, (d * d).sum(2), 0.0).sum(1)


_CYCLIC = ((0, 1, 2), (1, 2, 0), (2, 0, 1))


def _rigid_blocks(y: np.ndarray, v: np.ndarray, base: np.ndarray,
                  D: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton blocks of the rigid unknowns z = (omega, tau) for residuals ``base + D w + omega x y + tau``
    weighted by the visibility ``v`` (F, M): ``Hzz`` (F, 6, 6), ``Hzw`` (F, 6, K), ``gz`` (F, 6). y, base
    (F, M, 3) mm (base already zero where v = 0), D (K, M, 3). Closed forms (``d r / d omega_i = e_i x y``),
    no (F, 3M, 6) Jacobian."""
    F = y.shape[0]
    yv = y * v[..., None]
    c = yv.sum(1)  # (F, 3)
    n = v.sum(1)
    Hzz = np.zeros((F, 6, 6))
    Hzz[:, :3, :3] = (np.einsum("fm,fm->f", v, (y * y).sum(2))[:, None, None] * np.eye(3)
                      - np.einsum("fmi,fmj->fij", yv, y))
    eye3 = np.eye(3)
    for i in range(3):
        Hzz[:, i, 3:] = np.cross(eye3[i], c)
    Hzz[:, 3:, :3] = Hzz[:, :3, 3:].transpose(0, 2, 1)
    Hzz[:, 3:, 3:] = n[:, None, None] * eye3
    Hzw = np.empty((F, 6, D.shape[0]))
    gz = np.empty((F, 6))
    for i, j, k in _CYCLIC:  # (y x D)_i = y_j D_k - y_k D_j
        Hzw[:, i] = yv[:, :, j] @ D[:, :, k].T - yv[:, :, k] @ D[:, :, j].T
        gz[:, i] = (yv[:, :, j] * base[:, :, k] - yv[:, :, k] * base[:, :, j]).sum(1)
    for cc in range(3):
        Hzw[:, 3 + cc] = v @ D[:, :, cc].T
        gz[:, 3 + cc] = base[:, :, cc].sum(1)
    return Hzz, Hzw, gz


def solve_actor_weights(b0: np.ndarray, D: np.ndarray, markers: np.ndarray, lambda_t: float = 0.0,
                        lambda_l1: float = 0.0, lambda_s: float = 0.0, bounds: Sequence[float] = (0.0, 1.0),
                        sweeps: int = 60, tol: float = 1e-4, observable_mm: float = 0.05,
                        contiguous: bool = True, initial: ActorWeights | None = None) -> ActorWeights:
    """Rigid head motion and bounded weights of every frame of a take from a rig sampled at its markers.

    b0 (M, 3) mm, D (K, M, 3) mm (:func:`sample_rig_at_markers`); markers (F, M, 3) mm in any rigid frame
    (NaN: a gap). Minimizes over (R_f, t_f, w_f), ``lo <= w <= hi``::

        sum_f sum_m v_fm ||R_f (b0_m + D_m w_f) + t_f - p_fm||^2 + lambda_s (1^T w_f)^2 + lambda_l1 1^T w_f
            + lambda_t sum_f ||w_f - w_(f-1)||^2     (the last term only when ``contiguous``)

    Each sweep is a joint Gauss-Newton step of every frame, as the personalization's frame fit: the rotation
    linearized about the current one (``R = R0 exp([omega])``, ``t = t0 + R0 tau``), the six rigid unknowns
    eliminated (Schur complement), and the weights from exact box QPs: per frame, or with the temporal term one
    over all frames (block tridiagonal, warm-started from the sweep's weights). The poses start from a batched
    Kabsch fit of the neutral (``initial``: from that solve's weights and poses instead, e.g. a solve of the same
    take with a slightly different rig). A frame with fewer than 3 markers keeps the nearest posed frame's pose;
    one with none takes its weights from the temporal term.
    """
    b0 = np.asarray(b0, dtype=np.float64)
    D = np.asarray(D, dtype=np.float64)
    P = np.asarray(markers, dtype=np.float64)
    F, M = P.shape[:2]
    K = D.shape[0]
    lo, hi = float(bounds[0]), float(bounds[1])
    if b0.shape != (M, 3) or D.shape[1:] != (M, 3):
        raise InputError(f"rig at markers {b0.shape} / {D.shape} does not match the take's {M} markers")
    vis = np.isfinite(P).all(2)
    v = vis.astype(np.float64)
    Pz = np.where(vis[..., None], P, 0.0)
    observable = np.linalg.norm(D, axis=2).max(1) >= observable_mm
    Do = D[observable]
    Ko = Do.shape[0]
    G = _grams(Do, vis)  # (F, Ko, Ko)
    lt = float(lambda_t) if contiguous and F > 1 else 0.0
    nbrs = np.full(F, 2.0)
    nbrs[0] = nbrs[-1] = 1.0 if F > 1 else 0.0
    ridge = 1e-9 * max(1.0, float(np.abs(np.diagonal(G, axis1=1, axis2=2)).max(initial=0.0)))
    reg = lambda_s * np.ones((Ko, Ko)) + ridge * np.eye(Ko)
    posable = vis.sum(1) >= 3
    if not posable.any():
        raise InputError("no frame of the take has 3 visible markers: the head pose cannot be found",
                         fix="check the take's marker labels and gaps")
    idx = np.flatnonzero(posable)
    pos = np.clip(np.searchsorted(idx, np.arange(F)), 0, idx.size - 1)
    right, left = idx[pos], idx[np.maximum(pos - 1, 0)]
    nearest = np.where(np.abs(left - np.arange(F)) < np.abs(right - np.arange(F)), left, right)
    Dflat = Do.reshape(Ko, 3 * M)
    W = np.zeros((F, Ko))
    R, t = fit_rigid_motion_batched(np.broadcast_to(b0, (F, M, 3)), Pz, v)
    R, t = R[nearest], t[nearest]
    if initial is not None:
        W = np.clip(np.asarray(initial.weights, dtype=np.float64)[:, observable], lo, hi)
        R, t = np.array(initial.rotations, dtype=np.float64), np.array(initial.translations, dtype=np.float64)
    U_time = np.broadcast_to(-lt * np.eye(Ko), (max(F - 1, 0), Ko, Ko))  # the temporal term's coupling blocks
    converged_qp = True
    done, moved = 0, np.inf
    for done in range(1, int(sweeps) + 1):
        y0 = b0[None] + (W @ Dflat).reshape(F, M, 3)  # posed model, rig frame
        q = (Pz - t[:, None]) @ R  # markers in the rig frame
        base = (b0[None] - q) * v[..., None]  # residual = base + D w + omega x y0 + tau, (F, M, 3)
        Hzz, Hzw, gz = _rigid_blocks(y0, v, base, Do)
        Hzz = Hzz + (~posable)[:, None, None] * np.eye(6)
        rhs = np.concatenate([Hzw, gz[..., None]], 2) * posable[:, None, None]  # [Hzw gz]
        gw = base.reshape(F, 3 * M) @ Dflat.T
        S = np.linalg.solve(Hzz, rhs)  # Hzz^-1 [Hzw gz]
        Hzw_t = rhs[..., :Ko].transpose(0, 2, 1)
        Hred = G - Hzw_t @ S[..., :Ko] + reg
        fred = gw - (Hzw_t @ S[..., Ko:])[..., 0]
        W_old = W.copy()
        if lt > 0:  # every frame's weights at once: a box QP with a block tridiagonal Hessian
            A = Hred + (lt * nbrs)[:, None, None] * np.eye(Ko)
            W, passes = solve_box_qp_block_tridiagonal(A, U_time, -(fred + lambda_l1), lo, hi, x0=W,
                                                       max_iterations=TEMPORAL_MAX_PASSES)
            converged_qp &= passes <= TEMPORAL_MAX_PASSES
        else:
            W, ok = solve_box_qp_batched(Hred, fred + lambda_l1, lo, hi, x0=W)
            converged_qp &= bool(ok.all())
        z = -(S[..., Ko] + (S[..., :Ko] @ W[..., None])[..., 0]) * posable[:, None]
        R_new = R @ _rotation_exp(z[:, :3])
        t_new = t + (R @ z[:, 3:, None])[..., 0]
        # keep a frame's Gauss-Newton pose only where it lowers the frame's data term (the rotation is linearized)
        y1 = b0[None] + (W @ Dflat).reshape(F, M, 3)
        better = _frame_energy(y1, R_new, t_new, Pz, vis) <= _frame_energy(y1, R, t, Pz, vis)
        R = np.where(better[:, None, None], R_new, R)[nearest]
        t = np.where(better[:, None], t_new, t)[nearest]
        moved = float(np.abs(W - W_old).max(initial=0.0))
        if moved < tol and float(np.abs(z).max(initial=0.0)) < tol:
            break
    model = b0[None] + (W @ Dflat).reshape(F, M, 3)
    with np.errstate(invalid="ignore"):
        residual = np.sqrt(_frame_energy(model, R, t, Pz, vis) / vis.sum(1))
    weights = np.zeros((F, K))
    weights[:, observable] = W
    return ActorWeights(weights, R, t, residual, observable, done, bool(moved < tol and converged_qp))


def refine_rig_at_markers(prior_b0: np.ndarray, prior_D: np.ndarray, markers: np.ndarray, solved: ActorWeights,
                          prior: float) -> tuple[np.ndarray, np.ndarray]:
    """The EM's shape step on a take (:func:`rigbuild.retarget.common.refit_rig_at_markers`): the rig at the
    markers re-estimated from the take's markers (F, M, 3) mm (NaN: a gap), brought into the rig's frame by the
    solved head poses (``q = R_f^T (p - t_f)``), and the solved weights, held to ``prior_b0`` (M, 3), ``prior_D``
    (K, M, 3) mm (the personalized rig's, :func:`sample_rig_at_markers`) by ``prior`` frames. Returns (b0, D) mm."""
    P = np.asarray(markers, dtype=np.float64)
    q = np.einsum("fji,fmj->fmi", solved.rotations, P - solved.translations[:, None])  # NaN gaps stay NaN
    return refit_rig_at_markers(prior_b0, prior_D, q, solved.weights, prior)


def solve_actor_weights_refined(b0: np.ndarray, D: np.ndarray, markers: np.ndarray, iterations: int, prior: float,
                                lambda_t: float = 0.0, **solve_kw) -> tuple[ActorWeights, ActorWeights, np.ndarray,
                                                                            np.ndarray]:
    """:func:`solve_actor_weights`, then ``iterations`` rounds of (:func:`refine_rig_at_markers` held to ``b0``,
    ``D``; the weights and poses solved again from the refined rig, warm-started). Online refinement of the
    personalized rig on the take being solved: where the personalization got a shape wrong at the markers (the
    tracked range of motion's lids and lips), the take's own frames correct it; the prior keeps each shape near
    the personalized one, so the weights keep the personalized rig's meaning.

    The temporal term ``lambda_t`` couples every frame, which makes a solve dearer; it joins the solve from the
    unrefined rig and the final solve from the refined one, each warm-started from the solve without it, while the
    refinement's rounds solve without it (docs/decisions.md).

    Returns (the final solve, the solve from the unrefined rig, refined b0 (M, 3), refined D (K, M, 3));
    ``iterations`` 0 returns the solve from the unrefined rig twice and the rig unchanged."""
    b0, D = np.asarray(b0, dtype=np.float64), np.asarray(D, dtype=np.float64)
    lt = float(lambda_t)
    plain = solve_actor_weights(b0, D, markers, **solve_kw)
    first = plain if lt <= 0 else solve_actor_weights(b0, D, markers, lambda_t=lt, initial=plain, **solve_kw)
    sol, b, d = plain, b0, D
    for _ in range(int(iterations)):
        b, d = refine_rig_at_markers(b0, D, markers, sol, prior)
        sol = solve_actor_weights(b, d, markers, initial=sol, **solve_kw)
    if lt > 0:
        sol = solve_actor_weights(b, d, markers, lambda_t=lt, initial=sol, **solve_kw) if int(iterations) > 0 else first
    return sol, first, b, d


# --------------------------------------------------------------------------------------- the marker map
def solve_frames_point_to_plane(b0: np.ndarray, D: np.ndarray, normals: np.ndarray, markers: np.ndarray,
                                lambda_l1: float = 0.0, bounds: Sequence[float] = (0.0, 1.0),
                                iterations: int = 10, observable_mm: float = 0.05,
                                pose: tuple[np.ndarray, np.ndarray] | None = None) -> ActorWeights:
    """Head pose and weights of a few frames from the markers' distances along the rig's skin normals
    (point-to-plane): ``sum_m v_fm (n_m . (R_f^T (p_fm - t_f) - b0_m - D_m w_f))^2 + lambda_l1 1^T w_f``.

    A marker whose point on the rig is wrong along the skin costs nothing here, so the pose and expression of
    the frames do not bend to fit the map's errors (they would with the full 3D residual, which is what the
    marker map is fitted to correct). b0 (M, 3), D (K, M, 3) mm, normals (M, 3) unit, rig frame; markers
    (F, M, 3) mm, NaN gaps; pose: starting (R (F, 3, 3), t (F, 3)), default a Kabsch fit of ``b0``.
    Joint Gauss-Newton steps with the six rigid unknowns eliminated, the weights by exact box QPs.
    """
    P = np.asarray(markers, dtype=np.float64)
    F, M = P.shape[:2]
    K = D.shape[0]
    vis = np.isfinite(P).all(2)
    v = vis.astype(np.float64)
    Pz = np.where(vis[..., None], P, 0.0)
    n = np.asarray(normals, dtype=np.float64)
    observable = np.linalg.norm(D, axis=2).max(1) >= observable_mm
    Do = D[observable]
    Ko = Do.shape[0]
    Dn = np.einsum("kmc,mc->km", Do, n)  # (Ko, M) each shape's motion along the normals
    G = np.einsum("km,fm,lm->fkl", Dn, v, Dn) + 1e-9 * np.eye(Ko)
    if pose is None:
        R, t = fit_rigid_motion_batched(np.broadcast_to(b0, (F, M, 3)), Pz, v)
    else:
        R, t = np.array(pose[0], dtype=np.float64), np.array(pose[1], dtype=np.float64)
    W = np.zeros((F, Ko))
    steps, settled = 0, False
    for steps in range(1, int(iterations) + 1):
        y = b0[None] + np.einsum("fk,kmc->fmc", W, Do)
        q = (Pz - t[:, None]) @ R
        base = np.einsum("fmc,mc->fm", b0[None] - q, n) * v  # residual = base + Dn w + (y x n).omega + n.tau
        A = np.concatenate([np.cross(y, n[None]), np.broadcast_to(n, (F, M, 3))], 2)  # (F, M, 6)
        Av = A * v[..., None]
        Hzz = np.einsum("fmi,fmj->fij", Av, A) + 1e-9 * np.eye(6)
        Hzw = np.einsum("fmi,km->fik", Av, Dn)
        gz = np.einsum("fmi,fm->fi", Av, base)
        S = np.linalg.solve(Hzz, np.concatenate([Hzw, gz[..., None]], 2))
        Hzw_t = Hzw.transpose(0, 2, 1)
        H = G - Hzw_t @ S[..., :Ko]
        f = base @ Dn.T - (Hzw_t @ S[..., Ko:])[..., 0] + lambda_l1
        W, _ = solve_box_qp_batched(H, f, float(bounds[0]), float(bounds[1]), x0=W)
        z = -(S[..., Ko] + (S[..., :Ko] @ W[..., None])[..., 0])
        R, t = R @ _rotation_exp(z[:, :3]), t + (R @ z[:, 3:, None])[..., 0]
        if float(np.abs(z).max(initial=0.0)) < 1e-6:
            settled = True
            break
    weights = np.zeros((F, K))
    weights[:, observable] = W
    return ActorWeights(weights, R, t, np.full(F, np.nan), observable, steps, settled)


def _placing_frames(visible: np.ndarray, n: int) -> np.ndarray:
    """Up to ``n`` frames spread evenly over the take, each moved to the nearby frame (within half the spacing)
    where most markers are visible."""
    F = visible.shape[0]
    n = min(int(n), F)
    counts = visible.sum(1)
    edges = np.linspace(0, F, n + 1).astype(int)
    picks = [int(a + np.argmax(counts[a:b])) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    return np.array(sorted(set(picks)), dtype=np.int64)


def _triangle_normals(vertices: np.ndarray, faces: np.ndarray, face_ids: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3) of triangles ``face_ids`` of a mesh."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)[face_ids]]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)


def _averaged_map(current: MarkerMap, neutral: np.ndarray, faces: np.ndarray, marker: np.ndarray,
                  points: np.ndarray, offsets: np.ndarray, surface_rms_mm: float) -> MarkerMap:
    """``current`` with each marker moved to the mean of its skin points on the neutral: ``points`` (N, 3) mm on
    the neutral's skin and their normal ``offsets`` (N,) mm, ``marker`` (N,) the marker index of each; the mean
    point is put back on the skin by a closest-point query, the offset is the mean offset. Markers without a
    point keep theirs (``placed`` False)."""
    M = len(current.names)
    acc = np.zeros((M, 3))
    np.add.at(acc, marker, points)
    cnt = np.bincount(marker, minlength=M).astype(np.float64)
    off = np.bincount(marker, weights=offsets, minlength=M)
    seen = cnt > 0
    fid, bc, _ = closest_surface_points(neutral, faces, acc[seen] / cnt[seen, None])
    face_ids, bary, offset = current.face_ids.copy(), current.barycentric.copy(), current.normal_offset.copy()
    face_ids[seen], bary[seen], offset[seen] = fid, bc, off[seen] / cnt[seen]
    return MarkerMap(list(current.names), face_ids, bary, offset, surface_rms_mm, placed=seen)


def fit_marker_map(neutral: np.ndarray, deltas: np.ndarray, faces: np.ndarray, markers: np.ndarray,
                   names: Sequence[str], initial: MarkerMap, n_frames: int = 24, iterations: int = 2,
                   lambda_l1: float = 0.0, bounds: Sequence[float] = (0.0, 1.0),
                   observable_mm: float = 0.05) -> MarkerMap:
    """Each marker's own point on the rig's skin from a take.

    neutral (V, 3), deltas (K, V, 3) mm, faces (T, 3): the rig; markers (F, M, 3) mm (NaN gaps) in any rigid
    frame; initial: the starting map (e.g. :func:`vertex_marker_map` of the rig's marker set). Per iteration:
    the weights and head pose of ``n_frames`` frames spread over the take are solved with the current map
    (:func:`solve_actor_weights`, no temporal term), each visible marker is brought into the rig's frame and
    moved to its closest point on that frame's posed rig, the points are carried to the neutral (same
    triangle and barycentric coordinates, the normal offset kept), averaged over the frames and put back on the
    neutral's skin by a closest-point query. Returns the map after ``iterations`` rounds.
    """
    P = np.asarray(markers, dtype=np.float64)
    neutral = np.asarray(neutral, dtype=np.float64)
    deltas = np.asarray(deltas, dtype=np.float64)
    vis = np.isfinite(P).all(2)
    frames = _placing_frames(vis, n_frames)
    Ps, vs = P[frames], vis[frames]
    current = initial
    pose = None
    for _ in progress(range(int(iterations)), "placing the markers on the rig", unit="round"):
        b0, D = sample_rig_at_markers(neutral, deltas, faces, current)
        normals = _triangle_normals(neutral, faces, current.face_ids)
        sol = solve_frames_point_to_plane(b0, D, normals, Ps, lambda_l1=lambda_l1, bounds=bounds,
                                          observable_mm=observable_mm, pose=pose)
        pose = (sol.rotations, sol.translations)
        marker, pts, offs = [], [], []
        for i in range(frames.size):
            v = vs[i]
            if v.sum() < 3:
                continue
            q = (Ps[i, v] - sol.translations[i]) @ sol.rotations[i]  # rig frame
            posed = neutral + np.einsum("k,kvc->vc", sol.weights[i], deltas)
            fid, bc, dist = closest_surface_points(posed, faces, q)
            marker.append(np.flatnonzero(v))
            pts.append(points_on_surface(neutral, faces, fid, bc))
            offs.append(dist)
        offsets = np.concatenate(offs) if offs else np.zeros(0)
        current = _averaged_map(current, neutral, faces, np.concatenate(marker or [np.zeros(0, np.int64)]),
                                np.concatenate(pts or [np.zeros((0, 3))]), offsets,
                                float(np.sqrt(np.mean(offsets**2))) if offsets.size else float("nan"))
    return current


def _icp_to_surface(neutral: np.ndarray, faces: np.ndarray, P: np.ndarray, vis: np.ndarray, R: np.ndarray,
                    t: np.ndarray, iterations: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Point-to-plane ICP of each frame's markers onto a mesh's skin: the rigid motions ``(R, t)`` (B, 3, 3),
    (B, 3) (mesh -> take, ``p = R x + t``) refined from the given ones so that the visible markers ``P`` (B, M, 3)
    mm (``vis`` (B, M)) brought into the mesh's frame lie on its surface (distance along the closest points'
    normals; sliding along the skin costs nothing, so the pose does not depend on where on the skin a marker is
    assumed to sit). Returns the refined (R, t)."""
    fr, mk = np.nonzero(vis)
    B = P.shape[0]
    for _ in range(int(iterations)):
        q = np.einsum("nji,nj->ni", R[fr], P[fr, mk] - t[fr])  # R^T (p - t): the mesh's frame
        fid, bc, dist = closest_surface_points(neutral, faces, q)
        n = _triangle_normals(neutral, faces, fid)
        c = np.zeros((B, 3))
        np.add.at(c, fr, q)
        c /= np.maximum(np.bincount(fr, minlength=B), 1)[:, None]
        J = np.concatenate([np.cross(q - c[fr], n), n], axis=1)  # d(n . q)/d(omega, v), about the centroid
        A = np.zeros((B, 6, 6))
        np.add.at(A, fr, J[:, :, None] * J[:, None, :])
        g = np.zeros((B, 6))
        np.add.at(g, fr, J * dist[:, None])
        x = -np.linalg.solve(A + 1e-9 * np.eye(6), g[:, :, None])[:, :, 0]  # the points' small motion (mesh frame)
        dR = _rotation_exp(x[:, :3])
        # q' = dR (q - c) + c + v  =>  x_mesh = dR R^T (p - t) + (c - dR c + v): compose into mesh -> take
        shift = c - np.einsum("bij,bj->bi", dR, c) + x[:, 3:]
        Rn = np.einsum("bij,bkj->bik", R, dR)  # (dR R^T)^T = R dR^T
        t = t - np.einsum("bij,bj->bi", Rn, shift)
        R = Rn
    return R, t


def place_markers_on_neutral(neutral: np.ndarray, faces: np.ndarray, markers: np.ndarray, initial: MarkerMap,
                             neutral_fraction: float = 0.05, min_frames: int = 10, iterations: int = 3,
                             trim: float = 2.5) -> MarkerMap:
    """Each marker's own point on the skin of the actor's neutral mesh, from the take's most neutral frames: no
    rig needed (the tracked neutral alone), so the range of motion can be read where the take's hand-placed
    markers sit (:func:`tracked_markers_on_map`) by the retargeting methods that do not use the personalized rig.

    neutral (V, 3) mm, faces (T, 3): the neutral mesh; markers (F, M, 3) mm in any rigid frame (NaN gaps), in
    ``initial``'s marker order; initial : the starting map (e.g. the marker set's vertices,
    :func:`vertex_marker_map`). Per round: every frame with 6 or more visible markers is fitted rigidly onto
    the map's points on the neutral (batched Kabsch, three passes, a marker whose residual exceeds ``trim`` times
    the frame's median residual (and 0.5 mm) left out); the ``neutral_fraction`` of frames with the smallest
    RMS residual (at least ``min_frames``) are the take's closest to the neutral expression; their poses are
    refined by point-to-plane ICP onto the neutral's skin (:func:`_icp_to_surface`: the pose comes from the
    face's shape, not from where the map assumed the markers), their visible markers go to their closest points
    on the skin, averaged per marker and put back on the skin by a closest-point query (the normal offset is
    the mean signed distance). ``surface_rms_mm``: the RMS distance of those frames' markers to the skin in the
    last round. A marker seen in none of the picked frames keeps its starting point (``placed`` False).
    Returns the map after ``iterations`` rounds.
    """
    P = np.asarray(markers, dtype=np.float64)
    neutral = np.asarray(neutral, dtype=np.float64)
    F, M, _ = P.shape
    vis = np.isfinite(P).all(2)
    usable = vis.sum(1) >= 6
    seen_any = vis.any(1)
    if not usable.any():
        raise InputError(f"no frame of the take shows 6 or more of its {M} markers",
                         fix="check the take's marker labels and gaps")
    current = initial
    for _ in range(int(iterations)):
        ref = np.broadcast_to(current.points(neutral, faces), (F, M, 3))
        keep = vis.copy()
        for _ in range(3):
            R, t = fit_rigid_motion_batched(ref, P, keep.astype(np.float64))  # neutral -> take, per frame
            posed = np.einsum("fij,fmj->fmi", R, ref) + t[:, None]
            r = np.linalg.norm(posed - np.where(vis[..., None], P, 0.0), axis=2)
            med = np.zeros(F)  # each frame's median residual over its visible markers
            med[seen_any] = np.nanmedian(np.where(vis[seen_any], r[seen_any], np.nan), axis=1)
            keep = vis & (r <= np.maximum(trim * med, 0.5)[:, None])
        rms = np.where(usable, np.sqrt((np.where(keep, r, 0.0) ** 2).sum(1) / np.maximum(keep.sum(1), 1)), np.inf)
        n = min(max(int(min_frames), int(round(neutral_fraction * usable.sum()))), int(usable.sum()))
        picked = np.argsort(rms, kind="stable")[:n]
        Rp, tp = _icp_to_surface(neutral, faces, P[picked], keep[picked], R[picked], t[picked])
        fr, mk = np.nonzero(vis[picked])
        q = np.einsum("nji,nj->ni", Rp[fr], P[picked][fr, mk] - tp[fr])  # R^T (p - t): into the neutral's frame
        fid, bc, dist = closest_surface_points(neutral, faces, q)
        current = _averaged_map(current, neutral, faces, mk, points_on_surface(neutral, faces, fid, bc), dist,
                                float(np.sqrt(np.mean(dist**2))))
    return current


def marker_map_for_take(rig, names: Sequence[str], path=None) -> MarkerMap:
    """The starting map of a take on ``rig``: its marker set's vertices, for the take's markers ``names``
    (InputError naming the markers the rig's marker set lacks)."""
    index = {n: i for i, n in enumerate(rig.marker_names)}
    missing = [n for n in names if n not in index]
    if missing:
        raise InputError(f"the personalized rig's marker set lacks the take's markers {missing[:6]}"
                         f"{' ...' if len(missing) > 6 else ''} ({len(missing)} of {len(names)})", path=path,
                         fix="give the template rig a marker set whose names match the performance's labels")
    return vertex_marker_map(list(names), rig.marker_vertices[[index[n] for n in names]], rig.faces)


def tracked_markers_on_map(vertices: np.ndarray, faces: np.ndarray, marker_map: MarkerMap,
                           lost: np.ndarray | None = None) -> np.ndarray:
    """A tracked sequence's markers at the marker map's skin points: (F, M, 3) mm from the tracked vertices
    (F, V, 3) of the rig's topology (the map's triangles and barycentric coordinates, its normal offsets along
    each frame's triangle normals); rows of ``lost`` (F,) frames are NaN. The range of motion then shows the
    markers where the performance's markers sit, not at the template's marker vertices."""
    V = np.asarray(vertices, dtype=np.float64)
    if int(marker_map.face_ids.max(initial=-1)) >= np.asarray(faces).shape[0]:
        raise InputError("the marker map names triangles the tracked mesh lacks (another topology)",
                         fix="place the markers on a rig of the tracked topology (the personalized rig)")
    out = marker_map.points(V, faces)
    if lost is not None:
        out[np.asarray(lost, dtype=bool)] = np.nan
    return out


# ------------------------------------------------------------------------------------- semantic transfer
def semantic_transfer(weights: np.ndarray, names: Sequence[str], character_names: Sequence[str]) -> tuple[np.ndarray, list[str]]:
    """The actor weights (F, K) carried to a character by shape name: (F, K_c) in the character's order (a
    character shape the actor rig lacks stays 0) and the names carried. InputError when no name matches."""
    index = {str(n): i for i, n in enumerate(names)}
    shared = [n for n in character_names if str(n) in index]
    if not shared:
        raise InputError(f"no shape name of the character ({', '.join(map(str, list(character_names)[:4]))}, ...) "
                         f"is in the actor rig ({', '.join(map(str, list(names)[:4]))}, ...)",
                         fix="use a character with the template's shape names, or a Ribera or Seol method")
    out = np.zeros((weights.shape[0], len(character_names)))
    for j, n in enumerate(character_names):
        if str(n) in index:
            out[:, j] = weights[:, index[str(n)]]
    return out, shared
