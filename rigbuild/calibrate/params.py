"""Parameters of the calibrate stage (``config["params"]["calibrate"]``): one typed definition, checked at
DAG start (:func:`rigbuild.params.validate_params`) and used by the runner (:mod:`rigbuild.calibrate.stage`).

Cheap to import (no OpenCV / scipy): rules/common.smk imports it before any job runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from rigbuild.errors import InputError
from rigbuild.params import from_mapping

#: robust losses of the bundle adjustment (:func:`rigbuild.calibrate.bundle.robust_weights`)
ROBUST_LOSSES = ("linear", "soft_l1", "huber", "cauchy")

WHERE = "params.calibrate"


@dataclass
class CalibrationOptions:
    """Parameters (``config["params"]["calibrate"]``).

    min_corners : images with fewer detected corners are dropped (and listed).
    min_images : QA gate: usable images each camera needs.
    max_rms_px : QA gate: largest allowed per-camera reprojection RMS after the adjustment.
    robust_loss, robust_scale_px : loss (``soft_l1``, ``huber``, ``cauchy``, ``linear``) and scale (px).
    fix_k3 : hold k3 = 0 (4-parameter Brown model) - for narrow lenses or few images.
    reference_camera : world-frame camera (None = first camera).
    max_iterations : iteration cap of the adjustment (Levenberg-Marquardt steps).
    subpix_window : corner refinement half-window, px (None = the detector's default per board type:
        0 = none for ChArUco, 5 for chessboards; see :func:`rigbuild.calibrate.detect.detect_board`).
    """

    min_corners: int = 8
    min_images: int = 4
    max_rms_px: float = 0.5
    robust_loss: str = "soft_l1"
    robust_scale_px: float = 1.0
    fix_k3: bool = False
    reference_camera: str | None = None
    max_iterations: int = 100
    subpix_window: int | None = None


def from_config(values: Mapping[str, Any] | None) -> CalibrationOptions:
    """``config["params"]["calibrate"]`` -> :class:`CalibrationOptions`; InputError (with "did you mean")
    on an unknown key or a bad value."""
    p = from_mapping(CalibrationOptions, values, WHERE)
    if p.robust_loss not in ROBUST_LOSSES:
        raise InputError(f"field '{WHERE}.robust_loss': unknown loss {p.robust_loss!r}", path="config",
                         fix=f"use one of {', '.join(ROBUST_LOSSES)}")
    if p.subpix_window is not None and (not isinstance(p.subpix_window, int) or p.subpix_window < 0):
        raise InputError(f"field '{WHERE}.subpix_window': must be a whole number of pixels >= 0 or null, "
                         f"got {p.subpix_window!r}", path="config")
    return p
