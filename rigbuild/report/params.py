"""``config["params"]["report"]``: the report's parameters (pass / warn / fail limits over the defaults)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

from rigbuild.errors import InputError
from rigbuild.params import from_mapping


@dataclass
class ReportParams:
    """thresholds : metric key (one ``*`` may stand for a character) -> [direction, pass, warn], where direction
    is ``max`` (a value <= pass passes) or ``min``; overrides :data:`rigbuild.report.thresholds.DEFAULT_THRESHOLDS`."""

    thresholds: dict[str, Any] = field(default_factory=dict)


def from_config(values: Mapping[str, Any] | None) -> ReportParams:
    p = from_mapping(ReportParams, values, "params.report")
    for key, rule in p.thresholds.items():
        ok = (isinstance(rule, (list, tuple)) and len(rule) == 3 and rule[0] in ("max", "min")
              and all(isinstance(v, (int, float)) for v in rule[1:]))
        if not ok:
            raise InputError(f"params.report.thresholds.{key} is {rule!r}", path="config",
                             fix="give [max|min, pass_value, warn_value], e.g. [max, 0.2, 0.5]")
    p.thresholds = {k: tuple(v) for k, v in p.thresholds.items()}
    return p
