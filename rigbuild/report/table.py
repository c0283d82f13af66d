"""A plain-text metrics table with pass/warn/fail marks (``rigbuild eval``)."""

from __future__ import annotations

from typing import Any, Mapping

from rigbuild.report.thresholds import status
from rigbuild.io.metrics import flatten_metrics


def format_metrics_table(metrics: Mapping[str, Any], thresholds: Mapping | None = None) -> tuple[str, int]:
    """Return (table text, number of failing metrics)."""
    flat = flatten_metrics(metrics)
    width = max((len(k) for k in flat), default=10)
    lines = [f"{'metric':<{width}}  {'value':>12}  status", "-" * (width + 22)]
    n_fail = 0
    for key in sorted(flat):
        value = flat[key]
        st = status(key, value, thresholds)
        n_fail += st == "fail"
        if isinstance(value, float):
            text = f"{value:12.4g}"
        else:
            text = f"{str(value):>12}"
        lines.append(f"{key:<{width}}  {text}  {st}")
    return "\n".join(lines), n_fail
