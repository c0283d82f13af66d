"""Ground-truth evaluation of spacetime expression cloning (Seol et al. 2012) on synthetic sessions.

:func:`synthetic_performance` builds the paper's capture protocol on a synthetic actor (neutral face
at the start and the end, speech-like weights, smooth head motion, marker noise, optional gaps);
:func:`seol_metrics` scores a :class:`~rigbuild.retarget.seol.SeolResult` and its sec. 7 baselines
against the ground-truth weights: the fig. 11 velocity error, per-shape correlation, MAE and weight
range per method.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from rigbuild.retarget.common import active_shapes, mean_correlation, observable_shapes, weight_mae
from rigbuild.retarget.seol import SeolResult
from rigbuild.rig import Rig

#: metric-name prefixes per method, as written to metrics.json (``retarget.<prefix>.<character>.*``)
METHOD_KEYS = {
    "spacetime": "seol",
    "no_constraint": "noconst",
    "perframe_range": "perframe_range",
    "perframe_prior": "perframe_prior",
    "spacetime_paper": "seol_paper",
}


def neutral_envelope(n_frames: int, ramp_frames: int) -> np.ndarray:
    """(F,) 0 at the first and last frame, smoothstep up to 1 over ``ramp_frames`` frames at each end."""
    i = np.arange(n_frames, dtype=np.float64)
    x = np.clip(np.minimum(i, n_frames - 1 - i) / max(ramp_frames, 1), 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def synthetic_performance(
    template: Rig,
    n_frames: int = 600,
    fps: float = 60.0,
    seed: int = 0,
    noise_mm: float = 0.05,
    gap_fraction: float = 0.0,
    head_motion: bool = True,
    ramp_frames: int = 30,
    actor_kwargs: Mapping | None = None,
) -> dict:
    """A synthetic performance of an actor derived from ``template`` (which carries the marker set).

    Returns ``{"actor": Rig, "info": dict, "weights": (F, K) ground truth, "markers": (F, M, 3) mm
    world space, "R": (F, 3, 3), "t": (F, 3), "fps"}``. Weights start and end at neutral (the
    paper's actors hold a neutral face at both ends, sec. 3.1).
    """
    from rigbuild.synth.actor import make_actor_rig
    from rigbuild.synth.motion import make_head_motion, make_performance_weights, markers_from_rig

    actor, info = make_actor_rig(template, seed=seed, **dict(actor_kwargs or {}))
    W = make_performance_weights(template.shape_names, n_frames, fps, seed=seed + 1)
    W = W * neutral_envelope(n_frames, ramp_frames)[:, None]
    R = t = None
    if head_motion:
        R, t = make_head_motion(n_frames, seed=seed + 2)
    X = markers_from_rig(actor, W, R, t, noise_mm=noise_mm, gap_fraction=gap_fraction, seed=seed + 3)
    return {"actor": actor, "info": info, "weights": W, "markers": X, "R": R, "t": t, "fps": fps}


def evaluated_shapes(actor: Rig, weights_true: np.ndarray, marker_vertices: np.ndarray | None = None) -> np.ndarray:
    """(K,) bool: shapes that move during the performance and that the marker set can observe on the
    actor (a marker moves >= 1 mm at weight 1), the shapes a correlation is meaningful for."""
    mv = actor.marker_vertices if marker_vertices is None else np.asarray(marker_vertices)
    return active_shapes(weights_true) & observable_shapes(actor.deltas[:, mv])


def seol_metrics(result: SeolResult, weights_true: np.ndarray, shapes: np.ndarray) -> dict[str, dict[str, float]]:
    """Per method (``spacetime`` and each baseline): ``velocity_error`` (sum of fig. 11, mm^2),
    ``velocity_error_per_frame`` (mean, mm^2), ``mean_correlation`` over ``shapes``, ``mae``,
    ``weight_min``, ``weight_max``."""
    out: dict[str, dict[str, float]] = {}
    methods = {"spacetime": result.weights, **result.baselines}
    for name, W in methods.items():
        ve = result.velocity_error[name]
        out[name] = {
            "velocity_error": float(ve.sum()),
            "velocity_error_per_frame": float(ve[1:].mean()) if ve.size > 1 else 0.0,
            "mean_correlation": mean_correlation(W, weights_true, shapes),
            "mae": weight_mae(W, weights_true, shapes),
            "weight_min": float(W.min()),
            "weight_max": float(W.max()),
        }
    return out


def flat_metric_keys(per_method: Mapping[str, Mapping[str, float]], character: str) -> dict[str, float]:
    """``{"seol.<character>.velocity_error": ..., "perframe_prior.<character>.velocity_error": ...}``
    (to merge under the ``retarget`` stage of metrics.json)."""
    flat: dict[str, float] = {}
    for method, values in per_method.items():
        prefix = METHOD_KEYS.get(method, method)
        for k, v in values.items():
            flat[f"{prefix}.{character}.{k}"] = v
    return flat
