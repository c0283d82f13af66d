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


#: what the quality gate does when it fails: fail the job (after writing every output) or only warn
GATES = ("fail", "warn")
#: how the bundle weighs the corners: equally, or by the noise of corners seen at the same angle to the board
NOISE_MODELS = ("none", "view_angle")
#: how known intrinsics (session.yaml ``intrinsics:`` or ``calib_intrinsics/<cam>/`` images) enter the rig fit
KNOWN_INTRINSICS = ("fixed", "prior")


@dataclass
class CalibrationOptions:
    """Parameters (``config["params"]["calibrate"]``).

    min_corners : images with fewer detected corners are dropped (and listed).
    min_images : QA gate: usable images each camera needs.
    max_rms_px : QA gate: largest allowed per-camera reprojection RMS after the adjustment.
    gate : ``fail`` (default): a failed RMS / convergence gate writes every output, then fails the job;
        ``warn``: it is logged and reported (status fail) and the pipeline goes on.
    robust_loss, robust_scale_px : loss (``soft_l1``, ``huber``, ``cauchy``, ``linear``) and scale (px), or
        ``auto``: a first adjustment at 1 px, then a second one at 3 times the corners' noise estimated from its
        residuals (:func:`rigbuild.calibrate.bundle.robust_noise_px`), so that a corner is down-weighted from
        about 3 sigma on, whatever the detector's accuracy.
    noise_model : ``none``: every corner weighs the same; ``view_angle``: a first adjustment, then the corners
        are binned by their angle to the board and each weighed by the inverse noise variance of its bin's
        residuals, and the adjustment is repeated (:func:`rigbuild.calibrate.bundle.view_angle_weights`).
    fix_k3 : hold k3 = 0 (4-parameter Brown model) - for narrow lenses or few images.
    fix_tangential : hold p1 = p2 = 0.
    fix_principal_point : hold the principal point at the image centre.
    fix_aspect_ratio : hold fx = fy.
    known_intrinsics : ``fixed``: given or separately calibrated intrinsics are held in the rig fit;
        ``prior``: they are Gaussian priors (sigmas below) and the rig footage refines them.
    prior_focal_pct, prior_principal_px, prior_distortion : prior sigmas (% of the focal length, px, unitless).
    reference_camera : world-frame camera (None = first camera).
    max_iterations : iteration cap of the adjustment (Levenberg-Marquardt steps); it stops earlier at
        ``tolerance`` (relative cost decrease or relative step); not converged by the cap = a gate failure.
    subpix_window : corner refinement half-window, px (None = the detector's default per board type:
        0 = none for ChArUco (OpenCV's own refinement), a fifth of the corner spacing (5..21 px) for
        chessboards; see :func:`rigbuild.calibrate.detect.detect_board`).
    face_on_subpix_deg, face_on_subpix_blur_px, face_on_subpix_window : a second sub-pixel pass for ChArUco
        corners whose board is seen within ``face_on_subpix_deg`` of face-on (0 = off), on the image blurred
        by ``face_on_subpix_blur_px`` (px), half-window ``face_on_subpix_window`` times the corner's local
        spacing (:func:`rigbuild.calibrate.detect.refine_face_on`).
    heldout_every : every n-th board pose (in view-key order, the n-th, 2n-th, ...) is left out of a second
        fit whose cameras triangulate and reproject its corners (``heldout_reprojection_rms_px``); 0 = off.
        The delivered calibration uses every pose.
    min_board_poses : plausibility flag: a camera seen in fewer board poses.
    """

    min_corners: int = 8
    min_images: int = 4
    max_rms_px: float = 0.5
    gate: str = "fail"
    robust_loss: str = "soft_l1"
    robust_scale_px: float | str = 1.0
    noise_model: str = "none"
    fix_k3: bool = False
    fix_tangential: bool = False
    fix_principal_point: bool = False
    fix_aspect_ratio: bool = False
    known_intrinsics: str = "fixed"
    prior_focal_pct: float = 1.0
    prior_principal_px: float = 10.0
    prior_distortion: float = 0.05
    reference_camera: str | None = None
    max_iterations: int = 1000
    tolerance: float = 1e-10
    subpix_window: int | None = None
    face_on_subpix_deg: float = 0.0
    face_on_subpix_blur_px: float = 1.0
    face_on_subpix_window: float = 0.1
    heldout_every: int = 4
    min_board_poses: int = 10


def _one_of(p, name: str, choices) -> None:
    if getattr(p, name) not in choices:
        raise InputError(f"field '{WHERE}.{name}': unknown value {getattr(p, name)!r}", path="config",
                         fix=f"use one of {', '.join(choices)}")


def from_config(values: Mapping[str, Any] | None) -> CalibrationOptions:
    """``config["params"]["calibrate"]`` -> :class:`CalibrationOptions`; InputError (with "did you mean")
    on an unknown key or a bad value."""
    p = from_mapping(CalibrationOptions, values, WHERE)
    _one_of(p, "robust_loss", ROBUST_LOSSES)
    _one_of(p, "noise_model", NOISE_MODELS)
    if p.robust_scale_px != "auto" and (isinstance(p.robust_scale_px, bool) or
                                        not isinstance(p.robust_scale_px, (int, float)) or not p.robust_scale_px > 0):
        raise InputError(f"field '{WHERE}.robust_scale_px': must be a number of pixels > 0 or 'auto', got "
                         f"{p.robust_scale_px!r}", path="config")
    _one_of(p, "gate", GATES)
    _one_of(p, "known_intrinsics", KNOWN_INTRINSICS)
    if p.subpix_window is not None and (not isinstance(p.subpix_window, int) or p.subpix_window < 0):
        raise InputError(f"field '{WHERE}.subpix_window': must be a whole number of pixels >= 0 or null, "
                         f"got {p.subpix_window!r}", path="config")
    checks = {"face_on_subpix_deg": (lambda v: 0 <= v < 90, "an angle in degrees, 0 <= angle < 90 (0 = off)"),
              "face_on_subpix_blur_px": (lambda v: v >= 0, "a blur in pixels >= 0"),
              "face_on_subpix_window": (lambda v: 0 < v <= 0.5, "a fraction of the corner spacing in (0, 0.5]")}
    for name, (ok, text) in checks.items():
        v = getattr(p, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not ok(v):
            raise InputError(f"field '{WHERE}.{name}': must be {text}, got {v!r}", path="config")
    for name in ("max_iterations", "heldout_every", "min_board_poses"):
        v = getattr(p, name)
        if not isinstance(v, int) or v < (1 if name == "max_iterations" else 0):
            raise InputError(f"field '{WHERE}.{name}': must be a whole number >= "
                             f"{1 if name == 'max_iterations' else 0}, got {v!r}", path="config")
    if not p.tolerance > 0:
        raise InputError(f"field '{WHERE}.tolerance': must be > 0, got {p.tolerance!r}", path="config")
    return p
