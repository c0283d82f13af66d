"""Ground-truth evaluation of retargeted weight curves (synthetic sessions; characters share the actor's
ARKit shape names, so the actor's ground-truth weights apply).

Metrics per (method, character): ``weight_mae`` over the shapes the markers can observe (a shape that
moves no marker by 1 mm at weight 1 is reported separately in ``unobservable_mae``), ``mean_correlation``:
mean per-shape Pearson correlation over active observable shapes (ground truth varies by >= 0.05).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.retarget.common import (
    active_shapes,
    mean_correlation,
    observable_shapes,
    per_shape_correlation,
    weight_mae,
)

#: method name -> metric prefix in metrics.json (``retarget.<prefix>.<character>.*``)
#: metrics.json prefix (``retarget.<prefix>.<character>.*``) of each method's own numbers
METHOD_KEYS = {"ribera": "ribera_faithful", "ribera_activation": "ribera_activation", "ribera_fit": "ribera_fit",
               "rbf": "rbf_baseline", "deformation": "deformation_baseline", "parallel": "parallel", "seol": "seol"}
#: the Ribera 2017 variant whose numbers are also reported as ``retarget.ribera.*`` (the issue's keys);
#: config ``params.retarget.ribera.primary`` chooses another (``ribera`` = the paper as written)
PRIMARY_RIBERA_METHOD = "ribera_fit"
RIBERA_VARIANTS = ("ribera", "ribera_activation", "ribera_fit")


def metric_prefixes(method: str, primary: str = PRIMARY_RIBERA_METHOD) -> list[str]:
    """metrics.json prefixes under which ``method``'s numbers are merged: its own key, plus ``ribera``
    when it is the primary Ribera variant."""
    if primary not in RIBERA_VARIANTS:
        raise InputError(f"params.retarget.ribera.primary '{primary}' is not a Ribera variant", path="config",
                         fix=f"use one of {list(RIBERA_VARIANTS)}")
    return [METHOD_KEYS[method]] + (["ribera"] if method == primary else [])


def align_to_truth(weights: np.ndarray, names: Sequence[str], true_weights: np.ndarray,
                   true_names: Sequence[str]) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Columns of both weight arrays for the shape names they share (estimated order kept)."""
    tn = [str(n) for n in true_names]
    shared = [n for n in names if n in tn]
    if not shared:
        raise InputError("the character shares no shape name with the ground truth",
                         fix="evaluate characters with the actor's (ARKit) shape names")
    if weights.shape[0] != true_weights.shape[0]:
        raise InputError(f"{weights.shape[0]} retargeted frames vs {true_weights.shape[0]} ground-truth frames")
    a = weights[:, [list(names).index(n) for n in shared]]
    b = true_weights[:, [tn.index(n) for n in shared]]
    return a, b, shared


def retarget_metrics(weights: np.ndarray, names: Sequence[str], true_weights: np.ndarray,
                     true_names: Sequence[str], actor_sparse_deltas: np.ndarray) -> dict:
    """Metrics of weights (F, K) against ground truth (F, K').

    actor_sparse_deltas : (K', M, 3) mm, the actor's ground-truth shapes at the marker vertices, in
    ``true_names`` order (defines which shapes the markers observe).
    """
    a, b, shared = align_to_truth(np.asarray(weights, float), list(names), np.asarray(true_weights, float), true_names)
    tn = [str(n) for n in true_names]
    obs_all = observable_shapes(actor_sparse_deltas)
    obs = np.array([obs_all[tn.index(n)] for n in shared])
    act = active_shapes(b) & obs
    r = per_shape_correlation(a, b)
    return {
        "weight_mae": weight_mae(a, b, obs),
        "mean_correlation": mean_correlation(a, b, act),
        "unobservable_mae": weight_mae(a, b, ~obs) if (~obs).any() else float("nan"),
        "n_observable": int(obs.sum()),
        "n_active": int(act.sum()),
        "unobservable_shapes": [n for n, o in zip(shared, obs) if not o],
        "per_shape_correlation": {n: (None if np.isnan(v) else float(v)) for n, v in zip(shared, r)},
    }


def synthetic_retarget_scene(template, seed: int = 0, identity_folder=None, n_rom_sequences: int | None = None,
                             rom_frames: int = 20, rom_coverage: int = 2, perf_frames: int = 450, fps: float = 30.0,
                             noise_mm: float = 0.2, gap_fraction: float = 0.01) -> dict:
    """A ground-truth retargeting scene on ``template`` (a Rig with a marker set, mm).

    The actor (:func:`rigbuild.synth.actor.make_actor_rig`) performs a range-of-motion training set
    (``n_rom_sequences`` x ``rom_frames``, default one sequence per shape, each shape peaking in
    ``rom_coverage`` sequences) and a speech-like performance, both with head motion, marker noise and gaps.
    Returns a dict: actor, info, training (F, M, 3), segment_starts, rom_weights, neutral (M, 3),
    performance (F', M, 3), weights (F', K) ground truth, fps.
    """
    from rigbuild.synth.actor import make_actor_rig
    from rigbuild.synth.motion import make_head_motion, make_performance_weights, make_rom_weights, markers_from_rig

    actor, info = make_actor_rig(template, seed=seed, identity_folder=identity_folder)
    names = actor.shape_names
    n_seq = n_rom_sequences or len(names)
    seqs = make_rom_weights(names, n_seq, rom_frames, seed=seed + 5, coverage=rom_coverage)
    W = np.concatenate(seqs)
    starts = np.cumsum([0] + [len(s) for s in seqs[:-1]]).astype(np.int64)
    R, t = make_head_motion(len(W), seed=seed + 6, max_rotation_deg=2.0, max_translation_mm=3.0)
    train = markers_from_rig(actor, W, R, t, noise_mm=noise_mm, gap_fraction=gap_fraction, seed=seed + 7)
    train[0] = markers_from_rig(actor, W[:1], noise_mm=noise_mm, seed=seed + 8)[0]  # a clean neutral frame 0
    Wp = make_performance_weights(names, perf_frames, fps, seed=seed + 9)
    R2, t2 = make_head_motion(perf_frames, seed=seed + 10)
    perf = markers_from_rig(actor, Wp, R2, t2, noise_mm=noise_mm, gap_fraction=gap_fraction, seed=seed + 11)
    return {"actor": actor, "info": info, "training": train, "segment_starts": starts, "rom_weights": W,
            "neutral": train[0].copy(), "performance": perf, "weights": Wp, "fps": fps}
