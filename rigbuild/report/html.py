"""Build the self-contained HTML session report.

Every stage section shows its headline numbers from ``metrics.json`` (the keys with a threshold,
:mod:`rigbuild.report.thresholds`, overridable in the config) first, each with pass / warn / fail and its
limits, the rest folded below them, and the pictures the stage wrote. Images
are embedded as base64 so the file opens offline; rule timings come from Snakemake ``benchmark:`` files.
"""

from __future__ import annotations

import base64
import csv
import html
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

from rigbuild.report.thresholds import limits_text, missing_headline, rule_for, split_headline, status
from rigbuild.io.metrics import flatten_metrics
from rigbuild.progress import progress


@dataclass
class Section:
    """A report section: ``stage`` is the metrics.json key; ``images`` glob patterns under results/<s>/."""

    id: str
    title: str
    stage: str | Sequence[str]
    images: Sequence[str]
    caption: str
    max_images: int = 12


SECTIONS = [
    Section("calibration", "Calibration", "calibration", ["calib/residuals.png", "calib/camera_layout.png"],
            "Reprojection residuals per camera and the camera layout. Re-shoot cameras whose RMS fails."),
    Section("reconstruction", "Reconstruction", "reconstruction", ["reconstruct/*/coverage.png"],
            "Per-frame coverage of the multi-view stereo (fraction of the face seen by 2+ views)."),
    Section("tracking", "Tracking", "tracking",
            ["track/*/residuals.png", "track/*/overlay/*.png"],
            "Tracking residual over time and the tracked mesh over the images. Lost frames are listed in the metrics."),
    Section("personalization", "Personalization", "personalization",
            ["personalize/convergence.png", "personalize/heatmaps/*.png"],
            "EM objective per iteration (must not increase) and per-shape change against the initial rig."),
    Section("retargeting", "Retargeting", ["retarget"],
            ["retarget/*/*/*/velocity_error.png", "retarget/*/*/*/preview.png"],
            "Velocity error of the spacetime solve against its per-frame baselines (Seol), and actor and "
            "character side by side at the most active frames.", max_images=24),
]

_CSS = """
body{font-family:system-ui,sans-serif;margin:2em;max-width:1200px;color:#222}
h1{margin-bottom:0} .sub{color:#666;margin-top:.2em}
section{border-top:2px solid #ddd;margin-top:2em;padding-top:.5em}
table{border-collapse:collapse;margin:.5em 0} td,th{padding:3px 10px;border-bottom:1px solid #eee;text-align:left}
td.num{text-align:right;font-variant-numeric:tabular-nums}
.pass{background:#d8f5d0}.warn{background:#fff2c2}.fail{background:#ffd0d0}
.badge{padding:1px 8px;border-radius:8px;font-weight:600}
figure{display:inline-block;margin:6px;vertical-align:top} figure img{max-width:560px;border:1px solid #ccc}
figcaption{font-size:12px;color:#555;max-width:560px;word-break:break-all}
.summary span{margin-right:1em}
details{margin:.5em 0} summary{cursor:pointer;color:#444}
"""


def _img_tag(path: Path) -> str:
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    mime = "image/png" if path.suffix.lower() == ".png" else "image/jpeg"
    return f'<img alt="{html.escape(path.name)}" src="data:{mime};base64,{data}">'


def _row(key: str, value: Any, thresholds: Mapping | None, with_limits: bool) -> tuple[str, str]:
    """(status, one table row) of a flat metric; ``value`` None: a headline the run did not measure."""
    if value is None:
        st, text = "", "<em>not measured</em>"
    else:
        st = status(key, value, thresholds)
        text = f"{value:.4g}" if isinstance(value, float) else html.escape(str(value))
    badge = f'<span class="badge {st}">{st}</span>' if st else ""
    limits = f"<td>{html.escape(limits_text(rule_for(key, thresholds), '≤', '≥'))}</td>" if with_limits else ""
    return st, f'<tr><td>{html.escape(key)}</td><td class="num">{text}</td><td>{badge}</td>{limits}</tr>'


def _metric_rows(metrics: Mapping[str, Any], stages: Sequence[str], thresholds: Mapping | None) -> tuple[str, dict]:
    """A section's metrics: the headline keys (those with a threshold, :func:`split_headline`) first with their
    status and limits, headline goals the run has no number for marked "not measured", and every other key
    folded in a ``<details>`` table. Returns (HTML, counts of pass / warn / fail / missing headline keys)."""
    flat = flatten_metrics({k: v for k, v in metrics.items() if k in stages})
    counts = {"pass": 0, "warn": 0, "fail": 0, "missing": 0}
    if not flat:
        return "<p><em>No metrics for this stage.</em></p>", counts
    head, rest = split_headline(flat, thresholds)
    missing = missing_headline(flat, tuple(f"{s}." for s in stages), thresholds)
    rows = []
    for key in head + missing:
        st, row = _row(key, flat.get(key) if key in head else None, thresholds, True)
        if st:
            counts[st] += 1
        counts["missing"] += key in missing
        rows.append(row)
    out = ""
    if rows:
        out = ('<table class="headline"><tr><th>headline metric</th><th>value</th><th>status</th><th>limits</th></tr>'
               + "".join(rows) + "</table>")
    if rest:
        body = "".join(_row(k, flat[k], thresholds, False)[1] for k in rest)
        out += (f"<details><summary>{len(rest)} more metrics</summary><table><tr><th>metric</th><th>value</th>"
                f"<th>status</th></tr>{body}</table></details>")
    return out, counts


def _timings(results_dir: Path) -> str:
    rows = []
    for tsv in sorted((results_dir / "benchmarks").glob("*.tsv")):
        with open(tsv) as fh:
            rec = next(csv.DictReader(fh, delimiter="\t"), None)
        if rec:
            rows.append((tsv.stem, float(rec.get("s", "nan")), rec.get("max_rss", "")))
    if not rows:
        return "<p><em>No rule timings recorded.</em></p>"
    total = sum(r[1] for r in rows)
    body = "".join(f'<tr><td>{html.escape(n)}</td><td class="num">{s:.1f}</td><td class="num">{m}</td></tr>'
                   for n, s, m in rows)
    return (f"<p>{len(rows)} jobs, {total:.0f} s of job time in total.</p><table><tr><th>rule (job)</th>"
            f"<th>seconds</th><th>max RSS (MB)</th></tr>{body}</table>")


def build_report(results_dir: str | os.PathLike, session: str, metrics: Mapping[str, Any],
                 thresholds: Mapping | None = None) -> str:
    """The report HTML text for one session's results folder."""
    results_dir = Path(results_dir)
    parts, totals = [], {"pass": 0, "warn": 0, "fail": 0, "missing": 0}
    nav = []
    for sec in progress(SECTIONS, "report sections", unit="section"):
        stages = [sec.stage] if isinstance(sec.stage, str) else list(sec.stage)
        table, counts = _metric_rows(metrics, stages, thresholds)
        for k in totals:
            totals[k] += counts[k]
        figs = []
        for pattern in sec.images:
            for p in sorted(results_dir.glob(pattern))[: sec.max_images]:
                rel = p.relative_to(results_dir)
                figs.append(f"<figure>{_img_tag(p)}<figcaption>{html.escape(str(rel))}</figcaption></figure>")
        verdict = "fail" if counts["fail"] else "warn" if counts["warn"] else "pass" if counts["pass"] else ""
        badge = f' <span class="badge {verdict}">{verdict}</span>' if verdict else ""
        nav.append(f'<a href="#{sec.id}">{sec.title}</a>')
        parts.append(f'<section id="{sec.id}"><h2>{sec.title}{badge}</h2><p>{html.escape(sec.caption)}</p>'
                     f'{table}<div>{"".join(figs) or "<p><em>No pictures for this stage.</em></p>"}</div></section>')
    parts.append(f'<section id="timings"><h2>Timings</h2>{_timings(results_dir)}</section>')
    nav.append('<a href="#timings">Timings</a>')
    overall = "fail" if totals["fail"] else "warn" if totals["warn"] else "pass"
    summary = (f'<p class="summary"><span class="badge {overall}">session {overall}</span>'
               f'<span>{totals["pass"]} pass</span><span>{totals["warn"]} warn</span><span>{totals["fail"]} fail</span>'
               f'<span>{totals["missing"]} not measured</span></p>')
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>rigbuild report: {html.escape(session)}</title>"
            f"<style>{_CSS}</style></head><body><h1>rigbuild session report: {html.escape(session)}</h1>"
            f"<p class='sub'>{' · '.join(nav)}</p>{summary}{''.join(parts)}</body></html>\n")


def write_report(metrics_json: str | os.PathLike, results_dir: str | os.PathLike, session: str,
                 report_params: Mapping[str, Any] | None, out_html: str | os.PathLike) -> None:
    """Rule ``report``: read ``metrics.json``, build the page with ``params.report``'s thresholds, write it."""
    from rigbuild.io.atomic import write_text
    from rigbuild.io.metrics import read_metrics
    from rigbuild.report.params import from_config

    params = from_config(report_params)
    write_text(out_html, build_report(results_dir, session, read_metrics(metrics_json), params.thresholds))
