"""Compact metric tables: the per-sequence and per-character keys as one grid (rows: sequence or method and
character, columns: metric) instead of one row per key.

``tracking.sequences.rom00.median_residual_mm`` is row ``rom00``, column ``median_residual_mm``;
``retarget.ribera.template.weight_mae`` is row ``ribera / template``, column ``weight_mae``;
``calibration.camera_rms_px.cam00`` is row ``cam00``, column ``camera_rms_px``. Every other key
of a stage is a scalar, listed as ``key: value``.
"""

from __future__ import annotations

import html
import re
from typing import Any, Mapping

from rigbuild.report.thresholds import limits_text, rule_for, status

#: stage prefix -> regex of a grid key: (row, column); calibration's per-camera keys are ``<metric>.<camera>``
GRID_KEYS = {
    "retarget": re.compile(r"^retarget\.(?P<row>[^.]+\.[^.]+)\.(?P<col>[^.]+)$"),
    "calibration": re.compile(r"^calibration\.(?P<col>[^.]+)\.(?P<row>[^.]+)$"),
}
SEQUENCE_KEY = re.compile(r"^(?P<stage>[^.]+)\.sequences\.(?P<row>[^.]+)\.(?P<col>[^.]+)$")


def split_grid(flat: Mapping[str, Any], prefix: str) -> tuple[dict[str, dict[str, str]], dict[str, Any]]:
    """(row -> column -> key, the other keys -> value) of a stage's flat metrics."""
    grid: dict[str, dict[str, str]] = {}
    rest: dict[str, Any] = {}
    pattern = GRID_KEYS.get(prefix, SEQUENCE_KEY)
    for key, value in flat.items():
        m = pattern.match(key)
        if m:
            grid.setdefault(m.group("row").replace(".", " / "), {})[m.group("col")] = key
        else:
            rest[key] = value
    return grid, rest


def fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return "—" if value is None else html.escape(str(value))


def _cell(key: str, value: Any, thresholds: Mapping | None) -> str:
    st = status(key, value, thresholds)
    rule = rule_for(key, thresholds)
    title = f' title="{html.escape(key)}: {html.escape(limits_text(rule))}"' if rule else f' title="{html.escape(key)}"'
    return f'<td class="num {st}"{title}>{fmt(value)}</td>'


def grid_html(flat: Mapping[str, Any], grid: Mapping[str, Mapping[str, str]], thresholds: Mapping | None,
              row_label: str) -> str:
    """One table: a row per grid row, a column per metric (first-seen order); cells with a limit coloured."""
    if not grid:
        return ""
    cols: list[str] = []
    for row in grid.values():
        cols += [c for c in row if c not in cols]
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = []
    for name, row in grid.items():
        cells = "".join(_cell(row[c], flat[row[c]], thresholds) if c in row else "<td></td>" for c in cols)
        body.append(f"<tr><th>{html.escape(name)}</th>{cells}</tr>")
    return (f'<div class="scroll"><table class="grid"><tr><th>{html.escape(row_label)}</th>{head}</tr>'
            f'{"".join(body)}</table></div>')


def scalars_html(values: Mapping[str, Any], thresholds: Mapping | None) -> str:
    """The stage's other keys as a compact multi-column list of ``key value`` cells."""
    if not values:
        return ""
    items = "".join(f'<tr><td>{html.escape(k)}</td>{_cell(k, v, thresholds)}</tr>' for k, v in sorted(values.items()))
    return f'<table class="scalars">{items}</table>'
