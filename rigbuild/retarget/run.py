"""One retargeting job: an actor's training markers + a performance take -> weight curves on a character.

Used by :func:`rigbuild.retarget.stage.run_ribera` (one Snakemake job per (session, performance, character,
method)), the tests and the benchmark. File I/O stays in the stage runner; this module takes arrays and rigs.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.retarget.common import (
    average_neutral,
    check_frames,
    interpolate_missing_rows,
    lowpass_markers,
    map_markers_to_vertices,
    refit_rig_at_markers,
    reorder_markers,
    stabilize,
)
from rigbuild.retarget.ribera import RetargetParams, RiberaModel, RigAtMarkers, TransferParams, build_model
from rigbuild.rig import Rig


@dataclass
class TrainingSet:
    """The actor's training (ROM) markers: markers (F, M, 3) mm (NaN gaps), names (M,), the first frame of
    each concatenated sequence, and the actor's neutral markers a0 (M, 3)."""

    markers: np.ndarray
    names: list[str]
    segment_starts: np.ndarray
    neutral: np.ndarray


#: a training frame needs this many visible markers (a rigid fit and some expression); fewer: left out
MIN_TRAINING_MARKERS = 4


def make_training_set(
    sequences: Sequence[np.ndarray],
    names: Sequence[Sequence[str]],
    neutral_frames: Sequence[int] | None = None,
    sources: Sequence[str | os.PathLike] | None = None,
) -> TrainingSet:
    """Concatenate training sequences (each (F_i, M_i, 3) with its marker names) in the first one's order.

    ``neutral_frames`` gives one neutral frame per sequence (default: frame 0 of the first sequence only; a
    shorter list covers the first sequences). The actor's neutral ``a0`` is the rigidly aligned mean of these
    frames (:func:`~rigbuild.retarget.common.average_neutral`): each neutral frame's marker noise would
    otherwise become a constant offset of every displacement. Every marker must be visible in at least one
    of them. Frames with fewer than :data:`MIN_TRAINING_MARKERS` visible markers (tracking lost, written as
    gaps) are left out with a warning.
    """
    if not sequences:
        raise InputError("no training sequence given", fix="list the actor's ROM marker files")
    order = [str(n) for n in names[0]]
    mats = []
    for i, (m, n) in enumerate(zip(sequences, names)):
        src = None if sources is None else sources[i]
        mats.append(reorder_markers(m, n, order, what="training sequence", path=src))
    nfs = [0] if neutral_frames is None else [int(v) for v in neutral_frames][: len(mats)]
    picked = []
    for i, nf in enumerate(nfs):
        if not 0 <= nf < mats[i].shape[0]:
            raise InputError(f"neutral frame {nf} outside training sequence {i} ({mats[i].shape[0]} frames)",
                             path=None if sources is None else sources[i])
        picked.append(mats[i][nf])
    picked = np.stack(picked)
    never = ~np.all(np.isfinite(picked), axis=2).any(0)
    if never.any():
        missing = [order[j] for j in np.flatnonzero(never)]
        raise InputError(f"the neutral frame(s) {nfs} have gaps in markers {missing}",
                         path=None if sources is None else sources[0],
                         fix="choose neutral frames where every marker is visible (in at least one of them)")
    a0 = average_neutral(picked)
    # frames tracking lost (written as gaps) or with too few markers for a rigid fit carry no expression
    kept = [m[np.isfinite(m).all(axis=2).sum(axis=1) >= MIN_TRAINING_MARKERS] for m in mats]
    dropped = sum(m.shape[0] for m in mats) - sum(k.shape[0] for k in kept)
    if dropped:
        logging.getLogger("rigbuild.retarget").warning(
            "training: %d frame(s) with fewer than %d visible markers left out", dropped, MIN_TRAINING_MARKERS)
    kept = [k for k in kept if k.shape[0]]
    starts = np.cumsum([0] + [m.shape[0] for m in kept[:-1]]).astype(np.int64)
    return TrainingSet(np.concatenate(kept), order, starts, a0)


@dataclass
class RetargetResult:
    """weights (F, K); shape_names; stabilized performance markers (F, M, 3); the model; timings (s); frames
    that had too few markers (their weights interpolated); the fit's RMS marker residual (mm, visible markers:
    each frame rigidly aligned to its fitted expression ``a0 + sum_k w_k dp_k``)."""

    weights: np.ndarray
    shape_names: list[str]
    stabilized: np.ndarray
    model: RiberaModel
    timings: dict = field(default_factory=dict)
    empty_frames: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    marker_residual_mm: float = float("nan")


def retarget_performance(
    training: TrainingSet,
    performance: np.ndarray,
    performance_names: Sequence[str],
    character: Rig,
    map_names: Sequence[str],
    map_vertices: np.ndarray,
    method: str = "ribera",
    transfer_params: TransferParams | None = None,
    retarget_params: RetargetParams | None = None,
    contact_pairs: np.ndarray | None = None,
    allow_empty_frames: bool = True,
    performance_path: str | os.PathLike | None = None,
    map_path: str | os.PathLike | None = None,
    workers: int = 1,
    marker_lowpass_hz: float | None = None,
    fps: float | None = None,
    actor_rig: RigAtMarkers | None = None,
) -> RetargetResult:
    """Retarget one performance onto one character.

    training : :class:`TrainingSet`; performance (F, M', 3) mm with NaN gaps and its marker names;
    character : rig (mm); map_names / map_vertices : the character's marker map (marker name -> vertex);
    contact_pairs : (C, 2) indices into ``map_names`` (converted to the training order here).
    Frames with fewer than 3 visible markers raise unless ``allow_empty_frames`` (weights interpolated).
    workers : processes for the transfer's deformation-transfer guesses (the job's threads).
    marker_lowpass_hz, fps : optional zero-phase low-pass of the performance markers (-3 dB frequency;
        :func:`rigbuild.retarget.common.lowpass_markers`) before retargeting; not in the paper (offline only).
    actor_rig : method ``ribera_fit_actor_rig``: the personalized rig at the markers (its guesses g_k).
    """
    t0 = time.perf_counter()
    model = prepare_model(training, character, map_names, map_vertices, method, transfer_params, retarget_params,
                          contact_pairs, map_path, workers, actor_rig)
    t1 = time.perf_counter()
    res = apply_model(model, training, performance, performance_names, allow_empty_frames, performance_path,
                      marker_lowpass_hz, fps)
    res.timings["build_s"] = t1 - t0
    return res


def prepare_model(
    training: TrainingSet,
    character: Rig,
    map_names: Sequence[str],
    map_vertices: np.ndarray,
    method: str = "ribera",
    transfer_params: TransferParams | None = None,
    retarget_params: RetargetParams | None = None,
    contact_pairs: np.ndarray | None = None,
    map_path: str | os.PathLike | None = None,
    workers: int = 1,
    actor_rig: RigAtMarkers | None = None,
) -> RiberaModel:
    """The retargeting model of :func:`retarget_performance` (the transfer), to apply to several takes with
    :func:`apply_model`. Arguments as there; ``actor_rig`` becomes the guesses g_k of method
    ``ribera_fit_actor_rig`` in the frame of the training neutral (:func:`~rigbuild.retarget.ribera.rig_marker_guesses`,
    markers matched by the training sequence's names, shapes by the character's)."""
    vids = map_markers_to_vertices(training.names, map_names, map_vertices, character.name, map_path)
    pairs = None
    if contact_pairs is not None and len(contact_pairs):
        pos = {n: i for i, n in enumerate(training.names)}
        pairs = np.array([[pos[map_names[a]], pos[map_names[b]]] for a, b in contact_pairs
                          if map_names[a] in pos and map_names[b] in pos], dtype=np.int64).reshape(-1, 2)
    check_frames(training.markers, what="training sequence", allow_empty=True)
    guesses = None
    if actor_rig is not None:
        from rigbuild.retarget.ribera import rig_marker_guesses

        guesses = rig_marker_guesses(actor_rig, training.neutral, training.names, character.shape_names)
    return build_model(character, vids, training.neutral, training.markers, method, transfer_params,
                       retarget_params, training.segment_starts, contact_pairs=pairs, workers=workers,
                       rig_guesses=guesses)


def refine_model_on_take(model: RiberaModel, markers: np.ndarray, weights: np.ndarray
                         ) -> tuple[RiberaModel, np.ndarray]:
    """Beyond the paper (``model.params.take_refine_iterations`` rounds, 0: the model and weights as given): the
    EM's shape step on the whole take (:func:`rigbuild.retarget.common.refit_rig_at_markers`): the actor
    blendshapes at the markers (``a0``, ``dp``) re-estimated from the take's frames stabilized against their
    fitted expressions and the solved weights, held to E_Align's by ``take_refine_prior`` frames, then the take
    solved again from them. markers (F, M, 3) mm (head motion, NaN gaps), weights (F, K) from ``model.retarget``.
    Returns (the refined model, its weights (F, K))."""
    from dataclasses import replace

    a0, dp = model.a0, model.dp
    for _ in range(int(model.params.take_refine_iterations)):
        expr = model.a0[None] + np.einsum("fk,kmc->fmc", weights, model.dp)
        stable, _, _ = stabilize(markers, expr)
        b0, D = refit_rig_at_markers(a0, dp, stable, weights, model.params.take_refine_prior)
        model = replace(model, a0=b0, dp=D)
        weights = model.retarget(markers)
    return model, weights


def apply_model(
    model: RiberaModel,
    training: TrainingSet,
    performance: np.ndarray,
    performance_names: Sequence[str],
    allow_empty_frames: bool = True,
    performance_path: str | os.PathLike | None = None,
    marker_lowpass_hz: float | None = None,
    fps: float | None = None,
) -> RetargetResult:
    """One performance through a prepared model (:func:`prepare_model`); arguments as in
    :func:`retarget_performance`."""
    t1 = time.perf_counter()
    perf = reorder_markers(performance, performance_names, training.names, what="performance", path=performance_path)
    if marker_lowpass_hz is not None:
        perf = lowpass_markers(perf, fps, marker_lowpass_hz)
    ok = check_frames(perf, what="performance", path=performance_path, allow_empty=allow_empty_frames)
    w = np.zeros((perf.shape[0], model.dp.shape[0]))
    w[ok] = model.retarget(perf[ok])
    model, w[ok] = refine_model_on_take(model, perf[ok], w[ok])
    w = interpolate_missing_rows(w, ok)
    t2 = time.perf_counter()
    stable, _, _ = stabilize(perf, training.neutral, model.rigidity)
    expr = model.a0[None] + np.einsum("fk,kmc->fmc", w, model.dp)
    fitted, _, _ = stabilize(perf[ok], expr[ok])
    d2 = np.sum((fitted - expr[ok]) ** 2, axis=2)
    residual = float(np.sqrt(np.nanmean(d2))) if np.isfinite(d2).any() else float("nan")
    return RetargetResult(w, list(model.shape_names), stable, model,
                          {"build_s": 0.0, "retarget_s": t2 - t1, "frames": int(perf.shape[0])},
                          np.flatnonzero(~ok), residual)
