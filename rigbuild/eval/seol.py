"""Ground-truth evaluation of spacetime expression cloning (Seol et al. 2012) on synthetic performances
(:func:`rigbuild.synth.retarget_scenes.synthetic_performance`).

:func:`seol_metrics` scores a :class:`~rigbuild.retarget.seol.SeolResult` and its sec. 7 baselines
against the ground-truth weights: the fig. 11 velocity error, per-shape correlation, MAE and weight
range per method.
"""

from __future__ import annotations

import numpy as np

from rigbuild.eval.retarget import active_shapes, mean_correlation, observable_shapes, weight_mae
from rigbuild.retarget.seol import SeolResult
from rigbuild.rig import Rig


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
