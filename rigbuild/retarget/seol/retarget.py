"""Spacetime expression cloning end to end (Seol et al. 2012, all sections): :func:`retarget_seol`."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field, fields, replace
from typing import Mapping, Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.retarget.common import bridge_rigid_motion, lowpass_markers
from rigbuild.retarget.params import DEFAULT_ALPHA, GAP_MODES, RIGID_WEIGHTS, SCALE_MATCH_MODES, SeolParams
from rigbuild.retarget.proportion import proportion_match
from rigbuild.retarget.seol.baselines import (solve_perframe_prior, solve_perframe_range,
                                             solve_perframe_unconstrained, velocity_error_per_frame)
from rigbuild.retarget.seol.checks import _frame_indices
from rigbuild.retarget.seol.head_motion import (bridge_sparse_frames, fill_marker_gaps, head_motion_about_pivot,
                                               min_visible_markers, refine_head_motion, remove_head_motion)
from rigbuild.retarget.seol.prior import alpha_from_corner_hz, build_pca_prior, sparse_combination_weights
from rigbuild.retarget.seol.scale_match import RbfWarp
from rigbuild.retarget.seol.sobolev import sobolev_beta, sobolev_beta_from_corner_hz
from rigbuild.retarget.seol.system import BOUNDED_MAX_PASSES, SeolSystem
from rigbuild.rig import Rig

@dataclass
class SeolResult:
    """weights (F, K) of the spacetime solution; shape_names; head_rotation (F, 3, 3) and
    head_translation (F, 3) = pivot translation of the source head (re-apply with
    :func:`apply_head_motion` about ``target_pivot``); system for edits; baselines {name: (F, K)};
    velocity_error {name: (F,)} per-frame curves (fig. 11) for "spacetime" and every baseline."""

    weights: np.ndarray
    shape_names: list[str]
    head_rotation: np.ndarray
    head_translation: np.ndarray
    source_pivot: np.ndarray
    target_pivot: np.ndarray
    system: SeolSystem
    warp: RbfWarp
    baselines: dict[str, np.ndarray] = field(default_factory=dict)
    velocity_error: dict[str, np.ndarray] = field(default_factory=dict)
    alpha: float = DEFAULT_ALPHA
    actor_space: object | None = None  # :class:`~rigbuild.retarget.seol.actor_space.ActorExpressionSpace` or None


def target_marker_blendshapes(target: Rig, marker_names: Sequence[str] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The target's neutral markers (M, 3) and marker deltas (K, M, 3), in ``marker_names`` order
    (default: the rig's marker order), mm."""
    rig = target if target.units == "mm" else target.to_units("mm")
    idx = _marker_vertex_ids(rig, marker_names)
    return rig.neutral[idx], rig.deltas[:, idx, :]


def _marker_vertex_ids(rig: Rig, marker_names: Sequence[str] | None) -> np.ndarray:
    """(M,) vertex ids of ``marker_names`` on ``rig`` (default: the rig's marker order)."""
    if rig.marker_vertices.size == 0:
        raise InputError(f"target rig '{rig.name}' has no marker set", fix="attach the marker set (Rig.with_markers)")
    if marker_names is None:
        return np.asarray(rig.marker_vertices)
    pos = {n: i for i, n in enumerate(rig.marker_names)}
    missing = [n for n in marker_names if n not in pos]
    if missing:
        raise InputError(f"markers {missing} are not on target rig '{rig.name}'",
                         fix="use a marker map whose names exist on the target rig")
    return np.asarray(rig.marker_vertices)[[pos[n] for n in marker_names]]


def retarget_seol(
    source_markers: np.ndarray,
    target: Rig,
    marker_names: Sequence[str] | None = None,
    source_neutral: np.ndarray | None = None,
    params: SeolParams | None = None,
    *,
    fps: float | None = None,
    beta: np.ndarray | None = None,
    prior_training: np.ndarray | None = None,
    remove_head: bool = True,
    baselines: bool = True,
    source_path: str | os.PathLike | None = None,
    actor_rig=None,
    **options,
) -> SeolResult:
    """Retarget a marker performance onto a blendshape target (Seol et al. 2012, all sections).

    Parameters
    ----------
    source_markers : (F, M, 3) mm, world space (or head-stabilized with ``remove_head=False``), NaN
        for gaps; markers in the order of ``marker_names``.
    target : the target rig with a marker set; markers are picked by ``marker_names`` (default: the
        rig's own marker order, which must then match the source's).
    source_neutral : (M, 3) the actor's neutral markers; default the first frame (the paper's actor
        holds a neutral face at the start). Used for Procrustes (sec. 3.1), the RBF (sec. 3.2) and as
        the origin of the displacements ``S``.
    params : :class:`~rigbuild.retarget.params.SeolParams` (``params.retarget.seol``; default: the paper's
        settings); ``**options`` override single fields (``alpha=1e-4, gaps="interpolate"``). Its fields:

        - ``alpha`` (eq. 4) or ``prior_corner_hz`` (the prior strength as a corner frequency,
          :func:`alpha_from_corner_hz`; independent of units, marker count and frame rate; needs ``fps``);
        - ``boundary_frames``, ``boundary_values`` (``"neutral"``: all weights 0 there, the paper's protocol;
          ``"perframe"``: the Range-PF per-frame solution, for takes that do not start and end on a
          neutral face) and ``pins`` ``{frame: {shape: value}}`` or ``{frame: (K,) weights}``;
        - ``rigid_weights``: ``"rigidity"`` (markers the target's shapes move little count more in
          Procrustes, :func:`rigbuild.retarget.common.rigidity_weights` of the scale-matched shapes) or
          ``"uniform"`` (the paper); ``head_refine_iterations``: Gauss-Newton refinements of the head motion
          jointly with per-frame weights (:func:`refine_head_motion`; 0 = the paper's plain Procrustes);
        - ``sobolev`` / ``sobolev_corner_hz``: the sec. 7.1 term (:func:`sobolev_beta`,
          :func:`sobolev_beta_from_corner_hz`), used when ``beta`` is not given;
        - ``gaps``: ``"mask"`` (marker gaps left out of every energy term, of the head-motion fits and of
          the baselines; :class:`SeolSystem` ``visibility``) or ``"interpolate"`` (filled linearly in time
          first; the paper does not discuss gaps, and interpolation invents motion during a gap);
        - ``prior_combinations``, ``prior_combination_density``: a sparse-combination training set of the
          PCA prior (:func:`sparse_combination_weights`), used when ``prior_training`` is not given;
        - ``scale_match``: how the target's marker blendshapes are carried into the source's proportions
          (:mod:`rigbuild.retarget.proportion`): ``"rbf"`` (sec. 3.2, the paper: ``d(n + b) - d(n)``),
          ``"deformation"`` (the target's blendshapes deformation-transferred onto the RBF-warped target
          mesh), ``"jacobian"``, ``"local_affine"``, ``"affine"`` or ``"none"`` (the target's own marker
          deltas); ``scale_match_kernel``: the RBF's ``phi`` (``"r"`` the paper, ``"r3"``, ``"tps"``);
        - ``marker_lowpass_hz``: zero-phase low-pass of the source markers before anything else
          (:func:`rigbuild.retarget.common.lowpass_markers`; needs ``fps``; not in the paper: its velocity
          matching passes marker noise into the weights wherever the prior is weaker than the data);
        - ``weight_bounds`` (lo, hi): the spacetime solution kept in the rig's weight range
          (:meth:`SeolSystem.solve_bounded`; the paper's is unconstrained); ``sparsity``: an L1 term
          ``sparsity * sum |w|`` (mm^2 per unit weight; Ribera et al. 2017's E_Sparse, not in the paper;
          needs ``weight_bounds`` from 0);
        - ``alpha_perframe``, ``weight_range``: the "Prior PF" and "Range PF" baselines (sec. 7).
    fps : frames per second of the take (for ``prior_corner_hz``, ``sobolev_corner_hz``, the low-pass).
    beta : Sobolev weights (M,) or (F, M) (sec. 7.1), overriding ``sobolev`` / ``sobolev_corner_hz``.
    prior_training : (N, K) extra target weight vectors ("animations of the target") added to the PCA
        training set after the neutral and the one-shape-per-frame set; overrides ``prior_combinations``.
    remove_head : remove the head motion (sec. 3.1); False for head-stabilized markers.
    baselines : also compute the sec. 7 per-frame baselines and all velocity-error curves.
    source_path : the take's file, named in errors and warnings.
    actor_rig : :class:`~rigbuild.retarget.ribera.RigAtMarkers`, the actor's personalized rig at the markers
        (method ``seol_actor_rig``): the source side comes from it (:mod:`rigbuild.retarget.seol.actor_space`):
        the source neutral is the rig's neutral Kabsch-fitted onto ``source_neutral``, and each character shape
        with a rig shape of the same name is matched as that rig shape (rotated into the take's frame) instead
        of ``scale_match``'s neutral-guessed map; ``result.actor_space`` keeps it. None: the paper's calibration.

    Occlusion gaps: head motion is fitted on each frame's visible markers and bridged over frames with fewer
    than half of them (:func:`min_visible_markers`, :func:`remove_head_motion`); such frames' markers are
    then filled by interpolation in time
    (:func:`bridge_sparse_frames`) so the movement matching stays connected across them; other gaps follow
    ``gaps``.

    With ``weight_bounds`` or ``sparsity`` the spacetime solve is no longer the paper's: the "perframe_prior"
    baseline then gets the same bounds and sparsity (the comparison isolates the movement matching, as in
    fig. 11), and the paper's unconstrained spacetime solution is added as ``baselines["spacetime_paper"]``.

    Returns :class:`SeolResult`.
    """
    p = _with_options(params, options)
    X, Y, n_tgt, d_star, warp, space = _matched_source_and_target(source_markers, target, marker_names,
                                                                  source_neutral, p, fps, actor_rig)
    F, M, _ = X.shape
    K = d_star.shape[0]
    B = d_star.reshape(K, -1).T
    R, t, stab = _stabilized(X, Y, B, d_star, p, remove_head, source_path)
    stab = bridge_sparse_frames(stab, source_path, min_visible_markers(M))
    vis = np.all(np.isfinite(stab), axis=2)
    if vis.all():
        vis = None
    S = (stab - Y[None]).reshape(F, -1)
    src_pivot = Y.mean(0)
    head_d = head_motion_about_pivot(R, t, src_pivot)
    mnames = list(marker_names) if marker_names is not None else list(target.marker_names)
    if prior_training is None and int(p.prior_combinations or 0) > 0:
        prior_training = sparse_combination_weights(K, int(p.prior_combinations), float(p.prior_combination_density))
    P, pp, alpha = _prior(d_star, B, prior_training, p, fps)
    if beta is None:
        beta = _sobolev_from_params(p, mnames, F, fps)
    names = list(target.shape_names)
    system = SeolSystem(B=B, S=S, prior_P=P, prior_p=pp, alpha=alpha, beta=beta, ridge=SPACETIME_RIDGE,
                        shape_names=names, marker_names=mnames, visibility=vis,
                        bounds=None if p.weight_bounds is None else tuple(p.weight_bounds),
                        sparsity=float(p.sparsity or 0.0))
    S = system.S  # gaps zeroed (ignored through visibility)
    mask, vals = _boundary_pins(system, p, B, S, vis, F)
    W = _solve_spacetime(system, mask, vals, p)
    result = SeolResult(weights=W, shape_names=names, head_rotation=R, head_translation=head_d,
                        source_pivot=src_pivot, target_pivot=n_tgt.mean(0), system=system, warp=warp,
                        alpha=float(alpha), actor_space=space)
    result.velocity_error["spacetime"] = velocity_error_per_frame(W, B, S, vis)
    if baselines:
        _add_baselines(result, system, B, S, P, pp, p, mask, vals, vis)
    return result


#: Tikhonov weight of the spacetime system (:class:`SeolSystem` ``ridge``)
SPACETIME_RIDGE = 1e-6


#: neighbourhood size of ``scale_match = "local_affine"``
SCALE_MATCH_NEIGHBORS = 12


def _with_options(params: SeolParams | None, options: Mapping) -> SeolParams:
    """``params`` (default :class:`SeolParams`) with single fields overridden (unknown names fail)."""
    from rigbuild.params import check_keys

    base = params if params is not None else SeolParams()
    check_keys(options, [f.name for f in fields(SeolParams)], "retarget_seol")
    return replace(base, **options) if options else base


def _matched_source_and_target(source_markers, target: Rig, marker_names, source_neutral, p: SeolParams,
                               fps: float | None, actor_rig=None):
    """Source markers (F, M, 3) (low-passed), the source neutral Y (M, 3), the target's neutral markers and its
    marker blendshapes carried into the source's proportions (sec. 3.2): n_tgt (M, 3), d_star (K, M, 3), warp, and
    the actor's expression space (None without ``actor_rig``: then Y is ``source_neutral``)."""
    X = np.asarray(source_markers, dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != 3:
        raise InputError(f"source markers must be (F, M, 3), got {X.shape}")
    F, M, _ = X.shape
    if F < 2:
        raise InputError(f"the performance has {F} frame(s); spacetime retargeting needs at least 2")
    if p.marker_lowpass_hz is not None:
        X = lowpass_markers(X, fps, float(p.marker_lowpass_hz))
    n_tgt, d_tgt = target_marker_blendshapes(target, marker_names)
    if n_tgt.shape[0] != M:
        raise InputError(f"{M} source markers but {n_tgt.shape[0]} target markers",
                         fix="pass marker_names so both sides use the same markers")
    if source_neutral is None:
        source_neutral = fill_marker_gaps(X)[0] if not np.all(np.isfinite(X[0])) else X[0]
    Y = np.asarray(source_neutral, dtype=np.float64)
    if Y.shape != (M, 3) or not np.all(np.isfinite(Y)):
        raise InputError(f"source neutral must be a finite ({M}, 3) array, got {Y.shape}")
    if p.scale_match not in SCALE_MATCH_MODES:
        raise InputError(f"scale_match '{p.scale_match}' unknown", fix=f"use one of {list(SCALE_MATCH_MODES)}")
    space = None
    if actor_rig is not None:
        from rigbuild.retarget.seol.actor_space import actor_expression_space

        mnames = list(marker_names) if marker_names is not None else list(target.marker_names)
        space = actor_expression_space(actor_rig, Y, mnames, list(target.shape_names))
        Y = space.neutral
    if space is not None and space.covered.all():  # every shape from the actor's rig: no guessed map needed
        from rigbuild.retarget.proportion import fit_proportion_map

        warp = fit_proportion_map(n_tgt, Y, p.scale_match_kernel)  # kept for the record (SeolResult.warp)
        d_star = space.deltas.copy()
    else:
        mesh = mvid = None
        if p.scale_match == "deformation":
            mesh = target if target.units == "mm" else target.to_units("mm")
            mvid = _marker_vertex_ids(mesh, marker_names)
        _, d_star, warp = proportion_match(n_tgt, d_tgt, Y, p.scale_match, p.scale_match_kernel,
                                           SCALE_MATCH_NEIGHBORS, mesh=mesh, marker_vertices=mvid)
        if space is not None:
            from rigbuild.retarget.seol.actor_space import actor_space_blendshapes

            d_star = actor_space_blendshapes(space, d_star)
    if p.gaps not in GAP_MODES:
        raise InputError(f"gaps '{p.gaps}' unknown", fix="use 'mask' or 'interpolate'")
    if p.gaps == "interpolate":
        X = fill_marker_gaps(X)
    return X, Y, n_tgt, d_star, warp, space


def _stabilized(X: np.ndarray, Y: np.ndarray, B: np.ndarray, d_star: np.ndarray, p: SeolParams,
                remove_head: bool, path: str | os.PathLike | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Head motion (sec. 3.1): R (F, 3, 3), t (F, 3) and the stabilized markers (F, M, 3)."""
    F = X.shape[0]
    if not remove_head:
        return np.broadcast_to(np.eye(3), (F, 3, 3)).copy(), np.zeros((F, 3)), X
    if p.rigid_weights not in RIGID_WEIGHTS:
        raise InputError(f"rigid_weights '{p.rigid_weights}' unknown", fix=f"use one of {list(RIGID_WEIGHTS)}")
    rigid_weights = None
    if p.rigid_weights == "rigidity":
        from rigbuild.retarget.common import rigidity_weights

        rigid_weights = rigidity_weights(d_star)
    need = min_visible_markers(X.shape[1])
    _, R, t = remove_head_motion(X, Y, rigid_weights, path, need)
    if int(p.head_refine_iterations) > 0:
        _, R, t = refine_head_motion(X, Y, B, R, t, rigid_weights, int(p.head_refine_iterations))
        # frames with too few markers keep the bridged head motion (their refinement is underdetermined)
        R, t = bridge_rigid_motion(R, t, np.all(np.isfinite(X), axis=2).sum(1) >= need)
    return R, t, np.einsum("fji,fmj->fmi", R, X - t[:, None, :])


def _prior(d_star: np.ndarray, B: np.ndarray, prior_training: np.ndarray | None, p: SeolParams,
           fps: float | None) -> tuple[np.ndarray, np.ndarray, float]:
    """The sec. 5 PCA prior's quadratic form (P (K, K), p (K,)) and the prior weight alpha.

    The training "animation": the neutral, then one blendshape per frame, then ``prior_training``. Without
    the neutral frame the centred PCA has near-zero eigenvalues along directions where all shapes agree,
    which makes the neutral itself implausible and drives large cancelling weights."""
    K = d_star.shape[0]
    flat = d_star.reshape(K, -1)
    train = np.vstack([np.zeros((1, flat.shape[1])), flat])
    if prior_training is not None:
        pt = np.asarray(prior_training, dtype=np.float64)
        if pt.ndim != 2 or pt.shape[1] != K:
            raise InputError(f"prior training weights must be (N, {K}), got {pt.shape}")
        train = np.vstack([train, pt @ flat])
    P, pp = build_pca_prior(train).quadratic(B)
    alpha = float(p.alpha)
    if p.prior_corner_hz is not None:
        if not fps or fps <= 0:
            raise InputError("prior_corner_hz needs the take's fps", fix="pass fps=<frames per second>")
        alpha = alpha_from_corner_hz(float(p.prior_corner_hz), B, P, float(fps))
    return P, pp, alpha


def _sobolev_from_params(p: SeolParams, marker_names: Sequence[str], n_frames: int,
                         fps: float | None) -> np.ndarray | None:
    """Sec. 7.1 weights from ``sobolev`` (regions, frames) and ``sobolev_corner_hz`` (their maximum), or None."""
    beta = None
    if p.sobolev:
        sob = p.sobolev
        beta = sobolev_beta(marker_names, sob.get("regions", {}), n_frames if sob.get("frames") else None,
                            sob.get("frames"))
    if p.sobolev_corner_hz is not None:
        if not fps:
            raise InputError("sobolev_corner_hz needs the take's fps", fix="pass fps=<frames per second>")
        uniform = sobolev_beta_from_corner_hz(len(marker_names), float(p.sobolev_corner_hz), float(fps))
        beta = uniform if beta is None else np.maximum(beta, uniform)
    return beta


def _boundary_pins(system: SeolSystem, p: SeolParams, B: np.ndarray, S: np.ndarray, vis: np.ndarray | None,
                   n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Pin mask and values (F, K) of the boundary frames and the extra pins."""
    pins = {int(f): v for f, v in (p.pins or {}).items()}
    if p.boundary_values == "neutral":
        return system.pins_for(p.boundary_frames, pins)
    if p.boundary_values == "perframe":
        fr = _frame_indices(p.boundary_frames, n_frames, "boundary frames")
        lim = tuple(p.weight_range) if p.weight_bounds is None else tuple(p.weight_bounds)
        bpins = {int(f): v for f, v in zip(fr, solve_perframe_range(
            B, S[fr], lim, visibility=None if vis is None else vis[fr]))}
        return system.pins_for((), {**bpins, **pins})
    raise InputError(f"boundary_values '{p.boundary_values}' unknown", fix="use 'neutral' or 'perframe'")


def _bounded(system: SeolSystem, mask: np.ndarray, vals: np.ndarray, linear: np.ndarray | None = None) -> np.ndarray:
    W, passes = system.solve_bounded(mask, vals, max_iterations=BOUNDED_MAX_PASSES, linear=linear)
    if passes > BOUNDED_MAX_PASSES:
        logging.getLogger("rigbuild.retarget.seol").warning(
            "bounded spacetime solve: no exact KKT point after %d active-set passes; the interior-point weights "
            "(within %s, tolerance 1e-10) are used", BOUNDED_MAX_PASSES, list(system.bounds))
    return W


def _solve_spacetime(system: SeolSystem, mask: np.ndarray, vals: np.ndarray, p: SeolParams | None = None
                     ) -> np.ndarray:
    """The spacetime solution (F, K): unconstrained, or within ``system.bounds`` (active set), with the
    plausibility options of ``p`` (``sparsity_mode: log``, ``antagonists``; need ``weight_bounds`` from 0):
    the log penalty by majorize-minimize passes (each the exact bounded solve with the linear term
    :func:`rigbuild.retarget.ribera.plausible.reweighted_slopes` of the last weights, slope ``sparsity`` at 0),
    with the antagonist penalty ``antagonist_weight w_a w_b`` linearized alongside
    (:func:`~rigbuild.retarget.ribera.plausible.antagonist_slopes`), then antagonist pairs excluded by pinning the
    weaker at 0 (:func:`~rigbuild.retarget.ribera.plausible.antagonist_pins`)."""
    if system.bounds is None:
        return system.solve(mask, vals)
    W = _bounded(system, mask, vals)
    if p is None or (p.sparsity_mode == "l1" and not p.antagonists):
        return W
    from rigbuild.retarget.plausible import antagonist_pairs
    from rigbuild.retarget.ribera.plausible import (ANTAGONIST_ROUNDS, REWEIGHT_PASSES, antagonist_pins,
                                                    antagonist_slopes, reweighted_slopes)

    linear = None
    pairs = antagonist_pairs(system.shape_names)
    push = p.antagonists and pairs.size and p.antagonist_weight > 0
    if p.sparsity_mode == "log" or push:
        base = np.full(W.shape, system.sparsity)  # the L1 term is already in the system: add the difference
        for _ in range(REWEIGHT_PASSES):
            linear = (reweighted_slopes(W, system.sparsity, float(p.sparsity_eps), float(p.coherence_frames)) - base
                      if p.sparsity_mode == "log" else np.zeros(W.shape))
            if push:
                linear = linear + antagonist_slopes(W, pairs, float(p.antagonist_weight), float(p.coherence_frames))
            W = _bounded(system, mask, vals, linear)
    if p.antagonists and pairs.size:
        mask, vals = mask.copy(), vals.copy()
        for _ in range(ANTAGONIST_ROUNDS):
            pin = antagonist_pins(W, pairs, float(p.coherence_frames)) & ~mask
            if not pin.any():
                break
            mask |= pin
            vals[pin] = 0.0
            W = _bounded(system, mask, vals, linear)
    return W


def _add_baselines(result: SeolResult, system: SeolSystem, B: np.ndarray, S: np.ndarray, P: np.ndarray, pp: np.ndarray,
                   p: SeolParams, mask: np.ndarray, vals: np.ndarray, vis: np.ndarray | None) -> None:
    """The sec. 7 per-frame baselines (and the paper's unconstrained spacetime solve when the spacetime
    solve is bounded) with their velocity-error curves, added to ``result``."""
    result.baselines["no_constraint"] = solve_perframe_unconstrained(B, S, vis)
    result.baselines["perframe_range"] = solve_perframe_range(B, S, tuple(p.weight_range), visibility=vis)
    result.baselines["perframe_prior"] = solve_perframe_prior(B, S, P, pp, float(p.alpha_perframe),
                                                              visibility=vis, bounds=system.bounds,
                                                              sparsity=system.sparsity)
    if system.bounds is not None:
        paper = replace(system, bounds=None, sparsity=0.0, visibility=vis)
        result.baselines["spacetime_paper"] = paper.solve(mask, vals)
    for name, Wb in result.baselines.items():
        result.velocity_error[name] = velocity_error_per_frame(Wb, B, S, vis)
