"""Pass / warn / fail thresholds for the metrics in ``metrics.json`` (the stage issues' acceptance lines).

A threshold is ``(direction, pass_value, warn_value)``: for ``"max"`` a value <= pass passes, <= warn
warns, else fails; for ``"min"`` the reverse. The config's ``params.report.thresholds`` overrides
entries (same keys). Keys may contain one ``*`` matching a character name.
"""

from __future__ import annotations

import fnmatch
from typing import Any, Mapping

DEFAULT_THRESHOLDS: dict[str, tuple[str, float, float]] = {
    "calibration.rms_px": ("max", 0.2, 0.5),
    "calibration.focal_error_pct": ("max", 0.1, 0.5),
    "calibration.center_error_mm": ("max", 0.3, 1.0),
    "calibration.rotation_error_deg": ("max", 0.02, 0.1),
    "reconstruction.median_error_mm": ("max", 0.2, 0.4),
    "reconstruction.p90_error_mm": ("max", 0.6, 1.2),
    "reconstruction.completeness": ("min", 0.95, 0.85),
    "tracking.mean_error_mm": ("max", 0.5, 1.0),
    "tracking.p95_error_mm": ("max", 1.5, 3.0),
    "tracking.end_drift_mm": ("max", 0.3, 0.6),
    "personalization.residual_reduction": ("min", 0.5, 0.3),
    "personalization.heldout_residual_reduction": ("min", 0.4, 0.2),
    "personalization.shape_error_reduction": ("min", 0.4, 0.2),
    "personalization.weight_mae": ("max", 0.05, 0.1),
    "personalization.min_shape_cosine": ("min", 0.9, 0.8),
    "retarget.ribera.*.weight_mae": ("max", 0.05, 0.1),
    "retarget.ribera.*.mean_correlation": ("min", 0.9, 0.8),
    "retarget.seol.*.mean_correlation": ("min", 0.9, 0.8),
}


def status(key: str, value: Any, thresholds: Mapping[str, tuple[str, float, float]] | None = None) -> str:
    """``"pass"``, ``"warn"``, ``"fail"`` or ``""`` (no threshold / not a number) for a flat metric key."""
    table = dict(DEFAULT_THRESHOLDS)
    table.update(thresholds or {})
    rule = table.get(key)
    if rule is None:
        for pattern, r in table.items():
            if "*" in pattern and fnmatch.fnmatchcase(key, pattern):
                rule = r
                break
    if rule is None or not isinstance(value, (int, float)) or isinstance(value, bool):
        return ""
    direction, ok, warn = rule
    if direction == "max":
        return "pass" if value <= ok else "warn" if value <= warn else "fail"
    return "pass" if value >= ok else "warn" if value >= warn else "fail"
