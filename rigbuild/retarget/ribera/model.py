"""The end-to-end Ribera model: transfer (sec. 4) + prior (sec. 5) prepared once, then performances
retargeted with head motion removed (:class:`RiberaModel`, :func:`build_model`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigbuild.errors import InputError
from rigbuild.retarget.common import stabilize
from rigbuild.retarget.methods import RIBERA_FIT_METHODS, RIBERA_METHODS, RIBERA_RIG_METHODS
from rigbuild.retarget.params import RetargetParams, TransferParams
from rigbuild.retarget.ribera.guesses import RigMarkerGuesses, combine_guesses, deformation_guesses, rbf_transfer
from rigbuild.retarget.plausible import antagonist_pairs
from rigbuild.retarget.ribera.plausible import marker_ranges
from rigbuild.retarget.ribera.prior import head_scale, prior_matrix
from rigbuild.retarget.ribera.retargeter import RiberaRetargeter
from rigbuild.retarget.ribera.transfer import TransferResult, training_displacements, transfer_blendshapes
from rigbuild.rig import Rig

@dataclass
class RiberaModel:
    """Everything needed to retarget performances of one actor onto one character.

    a0 : (M, 3) actor neutral (mm); dp : (K, M, 3) actor blendshapes used in E_Fit; Q : (K, K) prior;
    rigidity : (M,) stabilization weights; shape_names : K names; transfer : the transfer result (None for
    the ``rbf`` and ``deformation`` baselines); marker_range : (M,) each marker's range over the training
    sequence (mm; the still-region option's noise level, :func:`.plausible.marker_ranges`; None without
    training markers: the option is then off).
    """

    a0: np.ndarray
    dp: np.ndarray
    Q: np.ndarray
    rigidity: np.ndarray
    shape_names: list[str]
    params: RetargetParams
    transfer: TransferResult | None = None
    marker_range: np.ndarray | None = None  # (M,) training range of each marker (mm; the still-region test)

    def retargeter(self) -> RiberaRetargeter:
        return RiberaRetargeter(self.dp, self.Q, self.params, reference=self.a0,
                                antagonist_pairs=antagonist_pairs(self.shape_names), marker_ranges=self.marker_range)

    def retarget(self, markers: np.ndarray, retargeter: RiberaRetargeter | None = None) -> np.ndarray:
        """Weights (F, K) for raw performance markers (F, M, 3) mm with head motion and NaN gaps.

        Head motion is removed per frame (weighted rigid fit to ``a0`` with the rigidity weights), then
        ``refine_rigid`` times re-fitted against the fitted expression ``a0 + P w`` with uniform weights; with
        ``params.rigid = "joint"`` each solve also fits the remaining small rigid motion. The plausibility
        options (:mod:`.plausible`) run on the last solve only.
        """
        rt = retargeter or self.retargeter()
        stable, _, _ = stabilize(markers, self.a0, self.rigidity)
        w = rt.solve(stable - self.a0[None], plain=self.params.refine_rigid > 0)  # options on the last solve
        for _ in range(self.params.refine_rigid):
            expr = self.a0[None] + np.einsum("fk,kmc->fmc", w, self.dp)
            stable, _, _ = stabilize(markers, expr)
            w = rt.solve(stable - self.a0[None], start=w)  # warm start: same minimizer, fewer passes
        return w


#: the methods :func:`build_model` prepares (the registry: :mod:`rigbuild.retarget.methods`)
METHODS = tuple(RIBERA_METHODS)


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
    rig_guesses: RigMarkerGuesses | None = None,
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
        :func:`fit_match_transfer`), ``"ribera_fit_actor_rig"`` (``ribera_fit`` with the guesses g_k, E_Mesh's
        reference, from the actor's personalized rig: ``rig_guesses``), ``"ribera_fit_template_rig"`` (the same
        from the template rig the personalization starts from), ``"rbf"`` (baseline: the thin-plate RBF guesses ``g_k`` used directly), ``"deformation"`` (the
        deformation-transfer guesses of :func:`deformation_guesses` used directly).
    segment_starts : first frame of each concatenated training sequence.
    transfer_params.guess : g_k of ``"ribera"`` / ``"ribera_activation"`` (``"rbf"`` as in the paper, or
        ``"deformation"``).

    workers : processes for the deformation-transfer guesses (the job's threads; same result).
    rig_guesses : methods ``"ribera_fit_actor_rig"`` / ``"ribera_fit_template_rig"`` only: the personalized /
        template rig at the markers in ``a0``'s frame
        (:func:`rigbuild.retarget.ribera.guesses.rig_marker_guesses`, the character's shape order); g_k of a
        shape and marker it covers is the rig's, the others keep the ``transfer_params.guess`` guess. Everything
        ``ribera_fit`` derives from g_k (E_Mesh, the transfer's starting point and Tikhonov reference, the
        rigidity weights of the stabilization) then derives from these.

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
    if method in RIBERA_RIG_METHODS:
        if rig_guesses is None:
            raise InputError(f"method '{method}' needs its rig at the markers (rig_guesses)",
                             fix="give the job the rig and the take's marker map on it")
        if rig_guesses.dg.shape != ds.shape:
            raise InputError(f"rig guesses {rig_guesses.dg.shape} do not match the character's {ds.shape}")
        covered = bool(rig_guesses.shapes.all() and rig_guesses.markers.all())
        fallback = None if covered else (deformation_guesses(ch, vertex_ids, a0, workers) if use_dt
                                         else rbf_transfer(s0, ds, a0))
        dg = combine_guesses(rig_guesses, fallback)
    else:
        dg = deformation_guesses(ch, vertex_ids, a0, workers) if use_dt else rbf_transfer(s0, ds, a0)
    rigidity = rigidity_weights(dg)
    marker_range = da = None
    if training is not None:
        da = training_displacements(np.asarray(training, float), a0, rigidity)
        marker_range = marker_ranges(da)
    if method in ("rbf", "deformation"):
        dp = dg
    else:
        if training is None:
            raise InputError(f"method '{method}' needs the actor's training (ROM) markers")
        if method == "ribera_activation":
            tp = TransferParams(**{**tp.__dict__, "match": "activation"})
        if method in RIBERA_FIT_METHODS:
            tp = TransferParams(**{**tp.__dict__, "match": "fit"})
        transfer = transfer_blendshapes(s0, ds, a0, da, tp, uv=uv, contact_pairs=contact_pairs,
                                        segment_starts=segment_starts, dg=dg, prior=Q)
        dp = transfer.dp
        if rig_guesses is not None and method in RIBERA_RIG_METHODS:
            transfer.info["rig_guess_shapes"] = int(rig_guesses.shapes.sum())
            transfer.info["rig_guess_markers"] = int(rig_guesses.markers.sum())
            transfer.info["rig_alignment_rms_mm"] = float(rig_guesses.alignment_rms_mm)
    return RiberaModel(a0, dp, Q, rigidity, list(ch.shape_names), rp, transfer, marker_range)
