"""Build the session report: the technician's decision page, one HTML file that works offline.

Top of the page (visible without scrolling at 1400x900): the session verdict and one row per stage with its
pass / warn / fail, the number that matters with its limit beside it (:mod:`rigbuild.report.summary`), its
gates (judged without ground truth) and its worst ground-truth number. Below: the 3D view (the personalized
rig with one slider per shape, each retargeted take played on its character; :mod:`rigbuild.report.viewer`),
then one section per stage with its pictures (downscaled JPEG) and, collapsed, every metric: gates, ground
truth, per-sequence / per-character grids, the rest; rule timings last.
"""

from __future__ import annotations

import csv
import html
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from rigbuild.io.metrics import flatten_metrics
from rigbuild.progress import progress
from rigbuild.report.grids import fmt, grid_html, scalars_html, split_grid
from rigbuild.report.images import figure
from rigbuild.report.summary import STAGES, Judged, StageSummary, counts, summarize
from rigbuild.report.thresholds import limits_text, missing_headline
from rigbuild.retarget.methods import PRIMARY_RIBERA_METHOD

ASSETS = Path(__file__).parent


@dataclass
class Pictures:
    """A section's pictures: ``shown`` open under the heading, ``more`` folded as thumbnails. Each entry is
    (glob under results/<s>/, at most this many files per folder)."""

    shown: Sequence[tuple[str, int]]
    more: Sequence[tuple[str, int]] = ()
    caption: str = ""


#: the stages' pictures (globs under results/<s>/)
PICTURES = {
    "calibration": Pictures([("calib/residuals.png", 1), ("calib/camera_layout.png", 1)],
                            [("calib/detections/*.jpg", 64)],
                            "Reprojection residuals per camera and the camera layout: re-shoot cameras whose RMS "
                            "fails; below, the board detections per camera."),
    "reconstruction": Pictures([("reconstruct/*/coverage.png", 1)],
                               [("reconstruct/*/renders/*.png", 8), ("reconstruct/*/coverage/*.png", 2)],
                               "Per-frame coverage of the multi-view stereo (fraction of the face seen by 2+ "
                               "views); below, depth and mesh renders and the first frames' coverage per sequence."),
    "tracking": Pictures([("track/*/residuals.png", 1)], [("track/*/overlay/*.jpg", 24)],
                         "Tracking residual over time per sequence; below, the tracked mesh over every camera's "
                         "image (first, most deformed and last frame)."),
    "personalization": Pictures([("personalize/convergence.png", 1), ("personalize/heatmaps/overview.png", 1)],
                                [("personalize/heatmaps/*.png", 200)],
                                "EM objective per iteration (must not increase) and the change of every shape "
                                "against the initial rig; below, one heat map per shape."),
    "retargeting": Pictures([("retarget/{primary}/*/*/preview.png", 8)],
                            [("retarget/*/*/*/preview.png", 64), ("retarget/*/*/*/velocity_error.png", 64)],
                            "Actor and character side by side at the most active frames (the primary Ribera "
                            "variant, {primary}); below, every method's previews and Seol's velocity error "
                            "against its per-frame baselines."),
}

_CSS = (ASSETS / "report.css").read_text(encoding="utf-8")


def _badge(st: str, text: str | None = None) -> str:
    return f'<span class="badge {st or "none"}">{html.escape(text or st or "not measured")}</span>'


def _short(key: str, prefix: str) -> str:
    return key[len(prefix) + 1:] if key.startswith(prefix + ".") else key


def _counts_text(judged: Sequence[Judged], missing: int = 0) -> str:
    c = counts(judged)
    parts = [f"{n} {s}" for s, n in c.items() if n]
    if missing:
        parts.append(f"{missing} not measured")
    return ", ".join(parts) or "none"


def _summary_row(s: StageSummary) -> str:
    st = s.stage
    n = s.number
    if n is None:
        number = '<td colspan="3"><em>nothing measured with a limit</em></td>'
    else:
        tag = "" if n in s.gates else ' <span class="gt">ground truth</span>'
        number = (f'<td>{html.escape(_short(n.key, st.prefix))}{tag}</td><td class="num {n.status}">{fmt(n.value)}</td>'
                  f"<td>{html.escape(limits_text(n.rule, '≤', '≥'))}</td>")
    gates = _counts_text(s.gates, len(s.missing_gates))
    if s.missing_gates:
        names = ", ".join(_short(g, st.prefix) for g in s.missing_gates)
        gates = f'<span title="not measured: {html.escape(names)}">{gates}</span>'
    if s.truth:
        w = s.truth[0]
        truth = (f"{_counts_text(s.truth)}; worst {html.escape(_short(w.key, st.prefix))} "
                 f"<b class=\"{w.status}\">{fmt(w.value)}</b> ({html.escape(limits_text(w.rule, '≤', '≥'))})")
    else:
        truth = "—"
    return (f'<tr><th><a href="#{st.id}">{st.title}</a></th><td>{_badge(s.status)}</td>{number}'
            f"<td>{gates}</td><td>{truth}</td></tr>")


def summary_html(rows: Sequence[StageSummary], verdict: str, session: str, limits_note: str) -> str:
    """The verdict line and the per-stage table."""
    gates = [j for r in rows for j in r.gates]
    truth = [j for r in rows for j in r.truth]
    n_missing = sum(len(r.missing_gates) for r in rows)
    gt = (f"ground truth: {_counts_text(truth)}" if truth
          else "no ground truth (a real capture): judged by its gates alone")
    unmeasured = sum(1 for r in rows if not r.status)
    text = f"session {verdict or 'not measured'}"
    if verdict and unmeasured:  # a pass over what was measured is not a pass of the stages that were not
        text += f" · {unmeasured} of {len(rows)} stages not measured"
    badge = _badge(verdict, text)
    return (f'<section id="summary"><h1>{html.escape(session)} {badge}</h1>'
            f'<p class="sub">capture gates (no ground truth needed): {_counts_text(gates, n_missing)} · {gt} · '
            f"{html.escape(limits_note)}</p>"
            '<table class="summary"><tr><th>stage</th><th>status</th><th>the number that matters</th><th>value</th>'
            "<th>limit</th><th>capture gates</th><th>vs ground truth</th></tr>"
            + "".join(_summary_row(r) for r in rows) + "</table></section>")


def _judged_table(judged: Sequence[Judged], missing: Sequence[str], prefix: str, title: str) -> str:
    if not judged and not missing:
        return ""
    rows = [f'<tr><td>{html.escape(_short(j.key, prefix))}</td><td class="num {j.status}">{fmt(j.value)}</td>'
            f"<td>{_badge(j.status, None if j.status else 'no limit')}</td>"
            f"<td>{html.escape(limits_text(j.rule, '≤', '≥'))}</td></tr>" for j in judged]
    rows += [f"<tr><td>{html.escape(_short(k, prefix))}</td><td><em>not measured</em></td><td></td><td></td></tr>"
             for k in missing]
    return (f'<table class="judged"><tr><th>{title}</th><th>value</th><th>status</th><th>limit</th></tr>'
            f'{"".join(rows)}</table>')


def metrics_html(flat: Mapping[str, Any], s: StageSummary, thresholds: Mapping | None, has_truth: bool) -> str:
    """A stage's metrics, folded: gates, ground-truth keys (missing ones listed when the session has ground
    truth), the per-sequence / per-character grid and the other keys."""
    prefix = s.stage.prefix
    own = {k: v for k, v in flat.items() if k.startswith(prefix + ".")}
    if not own:
        return "<p><em>No metrics for this stage.</em></p>"
    missing = [k for k in missing_headline(own, (prefix + ".",), thresholds)
               if not any(k == g for g in s.stage.gates)] if has_truth else []
    shown = {j.key for j in s.gates + s.truth}
    grid, rest = split_grid({k: v for k, v in own.items() if k not in shown}, prefix)
    row_label = {"retarget": "method / character", "calibration": "camera"}.get(prefix, "sequence")
    body = (_judged_table(s.gates, s.missing_gates, prefix, "capture gate")
            + _judged_table(s.truth, missing, prefix, "vs ground truth")
            + grid_html(flat, grid, thresholds, row_label) + scalars_html(rest, thresholds))
    return f"<details><summary>metrics ({len(own)})</summary>{body}</details>"


def _pictures(results_dir: Path, patterns: Sequence[tuple[str, int]], width: int, quality: int,
              skip: set[Path]) -> list[str]:
    figs = []
    for pattern, per_folder in patterns:
        taken: dict[Path, int] = {}
        for p in sorted(results_dir.glob(pattern)):
            if p in skip or taken.get(p.parent, 0) >= per_folder:
                continue
            taken[p.parent] = taken.get(p.parent, 0) + 1
            skip.add(p)
            figs.append(figure(p, str(p.relative_to(results_dir)), width, quality))
    return figs


def pictures_html(results_dir: Path, pics: Pictures, width: int, quality: int, primary: str) -> str:
    seen: set[Path] = set()
    shown = _pictures(results_dir, [(g.format(primary=primary), n) for g, n in pics.shown], width, quality, seen)
    more = _pictures(results_dir, [(g.format(primary=primary), n) for g, n in pics.more], max(160, width // 2),
                     quality, seen)
    out = f'<div class="figs">{"".join(shown)}</div>' if shown else "<p><em>No pictures for this stage.</em></p>"
    if more:
        out += f'<details><summary>{len(more)} more pictures</summary><div class="figs small">{"".join(more)}</div></details>'
    return out


def timings_html(results_dir: Path) -> str:
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
    return (f"<details><summary>{len(rows)} jobs, {total:.0f} s of job time in total</summary><table><tr>"
            f"<th>rule (job)</th><th>seconds</th><th>max RSS (MB)</th></tr>{body}</table></details>")


def retarget_choice_html(flat: Mapping[str, Any]) -> str:
    """The retargeting section's table of methods and the one to use (:mod:`rigbuild.report.recommend`)."""
    from rigbuild.report.recommend import method_rows, recommend

    rows = method_rows(flat)
    if not rows:
        return ""
    best, basis = recommend(rows)
    cols = ("mean_correlation", "weight_mae", "antagonist_fraction", "mean_active")
    body = "".join(
        f'<tr{" class=best" if r["method"] == best else ""}><th>{html.escape(r["method"])}'
        f'{" ✓" if r["method"] == best else ""}</th><td class="num">{r["characters"]}</td>'
        + "".join(f'<td class="num">{fmt(r[c]) if np.isfinite(r[c]) else "—"}</td>' for c in cols) + "</tr>"
        for r in rows)
    return (f'<p class="choice">Use <b>{html.escape(str(best))}</b> on this session ({html.escape(basis)}).</p>'
            '<table class="choice"><tr><th>method</th><th>characters</th><th>mean correlation</th><th>weight MAE</th>'
            f"<th>antagonists active together</th><th>shapes active per frame</th></tr>{body}</table>")


def build_report(results_dir: str | os.PathLike, session: str, metrics: Mapping[str, Any],
                 thresholds: Mapping | None = None, *, three_js: str | None = None, image_width: int = 560,
                 jpeg_quality: int = 80, limits_note: str = "limits: the defaults",
                 assets: dict[str, str] | None = None, inline_limit_mb: float = 5.0,
                 primary: str = PRIMARY_RIBERA_METHOD) -> str:
    """The report HTML text for one session's results folder.

    thresholds: the limit overrides in force (config and session); three_js: the text of three.min.js (None:
    the page has no 3D view); image_width / jpeg_quality: the embedded pictures; assets: when given and the
    page would exceed ``inline_limit_mb`` MB, it receives the 3D view's files (name -> text) for the folder
    beside the page (:data:`rigbuild.report.viewer.ASSETS_FOLDER`) and the page loads them from there;
    primary: the Ribera variant reported as ``retarget.ribera.*`` (``params.retarget.ribera.primary``)."""
    from rigbuild.report.viewer import viewer_data, viewer_html

    results_dir = Path(results_dir)
    flat = flatten_metrics(metrics)
    rows, verdict = summarize(flat, thresholds)
    has_truth = any(r.truth for r in rows)
    parts = [summary_html(rows, verdict, session, limits_note), ""]
    data = viewer_data(results_dir) if three_js is not None else None
    for s in progress(rows, "report sections", unit="section"):
        st, pics = s.stage, PICTURES[s.stage.id]
        caption = html.escape(pics.caption.format(primary=primary))
        choice = retarget_choice_html(flat) if st.id == "retargeting" else ""
        parts.append(f'<section id="{st.id}"><h2>{st.title} {_badge(s.status)}</h2><p>{caption}</p>{choice}'
                     f"{pictures_html(results_dir, pics, image_width, jpeg_quality, primary)}"
                     f"{metrics_html(flat, s, thresholds, has_truth)}</section>")
    parts.append(f'<section id="timings"><h2>Timings</h2>{timings_html(results_dir)}</section>')
    nav = " · ".join(f'<a href="#{s.stage.id}">{s.stage.title}</a>' for s in rows) + ' · <a href="#timings">Timings</a>'

    def page(viewer: str) -> str:
        parts[1] = f'<section id="viewer"><h2>Rig and takes in 3D</h2>{viewer}</section>' if viewer else ""
        return (f"<!DOCTYPE html><html><head><meta charset='utf-8'>"
                f"<title>rigbuild session report: {html.escape(session)}</title><style>{_CSS}</style></head><body>"
                '<pre id="rb-errors" hidden data-count="0"></pre><pre id="rb-selfcheck" hidden></pre>'
                f"<script>{(ASSETS / 'errors.js').read_text(encoding='utf-8')}</script>"
                f"<p class='top'>rigbuild session report · {nav}</p>{''.join(parts)}</body></html>\n")

    text = page(viewer_html(data, three_js) if data is not None else "")
    if data is not None and assets is not None and len(text.encode("utf-8")) > inline_limit_mb * 1e6:
        text = page(viewer_html(data, three_js, assets))
    return text


def limits_note(report_params: Any, session: str) -> str:
    """Which limits the page applies: the defaults, the config's overrides, the session's."""
    n_cfg = len(report_params.thresholds)
    n_ses = len(report_params.sessions.get(session, {}).get("thresholds", {}))
    parts = ["limits: the defaults (rigbuild/report/thresholds.py)"]
    if n_cfg:
        parts.append(f"{n_cfg} from params.report.thresholds")
    if n_ses:
        parts.append(f"{n_ses} from params.report.sessions.{session}")
    return ", ".join(parts)


def write_report(metrics_json: str | os.PathLike, results_dir: str | os.PathLike, session: str,
                 report_params: Mapping[str, Any] | None, out_html: str | os.PathLike,
                 assets_dir: str | os.PathLike | None = None, primary: str = PRIMARY_RIBERA_METHOD) -> None:
    """Rule ``report``: read ``metrics.json``, build the page with the config's and the session's limits and
    the installed three.js (InputError with the install command when it is missing), write it, and the 3D
    view's files into ``assets_dir`` (default ``report_files/`` beside the page) when they do not fit inline
    (else a README saying so: the folder is always there, a declared output)."""
    from rigbuild.assets.web import asset_path
    from rigbuild.io.atomic import write_text
    from rigbuild.io.metrics import read_metrics
    from rigbuild.report.params import from_config
    from rigbuild.report.viewer import ASSETS_FOLDER

    p = from_config(report_params)
    three = asset_path("three.min.js").read_text(encoding="utf-8")
    assets: dict[str, str] = {}
    page = build_report(results_dir, session, read_metrics(metrics_json), p.for_session(session), three_js=three,
                        image_width=p.image_width, jpeg_quality=p.jpeg_quality, limits_note=limits_note(p, session),
                        assets=assets, inline_limit_mb=p.inline_limit_mb, primary=primary)
    folder = Path(assets_dir) if assets_dir is not None else Path(out_html).parent / ASSETS_FOLDER
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in assets.items():
        write_text(folder / name, text)
    if not assets:
        write_text(folder / "README.txt", f"{Path(out_html).name} is self-contained: its 3D view fits inline "
                   f"(under params.report.inline_limit_mb = {p.inline_limit_mb:g} MB), so this folder holds nothing else.\n")
    write_text(out_html, page)
