"""A plain-text metrics table with pass/warn/fail marks and limits (``rigbuild eval``)."""

from __future__ import annotations

from typing import Any, Mapping

from rigbuild.io.metrics import flatten_metrics
from rigbuild.report.thresholds import limits_text, rule_for, split_headline, status


def format_metrics_table(metrics: Mapping[str, Any], thresholds: Mapping | None = None) -> tuple[str, int]:
    """Return (table text, number of failing metrics): the headline keys (those with a threshold) first in
    the threshold table's order with their status and limits, then every other key sorted."""
    flat = flatten_metrics(metrics)
    head, rest = split_headline(flat, thresholds)
    width = max((len(k) for k in flat), default=10)
    lines = [f"{'metric':<{width}}  {'value':>12}  {'status':<6}  limits", "-" * (width + 44)]
    n_fail = 0
    for key in head + rest:
        value = flat[key]
        st = status(key, value, thresholds)
        n_fail += st == "fail"
        text = f"{value:12.4g}" if isinstance(value, float) else f"{str(value):>12}"
        lines.append(f"{key:<{width}}  {text}  {st:<6}  {limits_text(rule_for(key, thresholds))}".rstrip())
        if key in head and key == head[-1] and rest:
            lines.append("-" * (width + 44))
    return "\n".join(lines), n_fail


def format_summary(metrics: Mapping[str, Any], thresholds: Mapping | None = None) -> tuple[str, str]:
    """(text, verdict): the report's summary as plain text, one line per stage (status, the number that matters
    with its limit, gate and ground-truth counts), the session verdict first."""
    from rigbuild.report.summary import counts, summarize

    rows, verdict = summarize(flatten_metrics(metrics), thresholds)
    lines = [f"session {verdict or 'not measured'}"]
    for r in rows:
        n = r.number
        number = "nothing measured with a limit" if n is None else (
            f"{n.key} = {n.value:.4g}" + (f" ({limits_text(n.rule)})" if n.rule else "")
            + ("" if n in r.gates else " [ground truth]"))
        g, t = counts(r.gates), counts(r.truth)
        gates = ", ".join(f"{v} {k}" for k, v in g.items() if v) or "none"
        truth = ", ".join(f"{v} {k}" for k, v in t.items() if v) or "none"
        lines.append(f"  {r.stage.title:<16} {r.status or '-':<5} {number}; gates: {gates}"
                     + (f", {len(r.missing_gates)} not measured" if r.missing_gates else "") + f"; ground truth: {truth}")
    return "\n".join(lines), verdict
