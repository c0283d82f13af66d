"""The report's pass / warn / fail, its summary and verdict, its compact tables and its limits
(rigbuild.report: thresholds, summary, html, grids, params, table)."""

from __future__ import annotations

import html as htmllib
import json
import re

import numpy as np
import pytest

from rigbuild.errors import InputError
from rigbuild.io.metrics import flatten_metrics
from rigbuild.paths import PROJECT_ROOT
from rigbuild.report.html import build_report
from rigbuild.report.params import from_config
from rigbuild.report.summary import STAGES, summarize, worst
from rigbuild.report.table import format_metrics_table
from rigbuild.report.thresholds import DEFAULT_THRESHOLDS, limits_text, rule_for, split_headline, status

STATUSES = ("pass", "warn", "fail")
DEMO_METRICS = PROJECT_ROOT / "benchmarks" / "out" / "metrics-demo.json"


def _value(rule, want: str) -> float:
    """A value of ``rule`` with status ``want``: the pass limit itself (limits are inclusive), the warn limit,
    or just beyond it."""
    direction, ok, warn = rule
    beyond = warn * 1.5 + 0.1 if direction == "max" else warn - 0.1
    return {"pass": ok, "warn": warn, "fail": beyond}[want]


def _nest(flat: dict) -> dict:
    out: dict = {}
    for key, v in flat.items():
        *parents, leaf = key.split(".")
        d = out
        for p in parents:
            d = d.setdefault(p, {})
        d[leaf] = v
    return out


@pytest.fixture
def every_headline():
    """metrics.json with every headline key (``*`` as ``template``), cycling pass / warn / fail, and a few keys
    without threshold."""
    flat, expected = {}, {}
    for i, (pattern, rule) in enumerate(DEFAULT_THRESHOLDS.items()):
        key = pattern.replace("*", "template")
        want = STATUSES[i % 3]
        flat[key] = _value(rule, want)
        expected[key] = want
    flat.update({"calibration.n_cameras": 6, "tracking.visible_corr_mean_error_mm": 0.1,
                 "tracking.sequences.rom00.mean_error_mm": 9.0, "personalization.residual_reduction_weighted": 0.9,
                 "retarget.ribera_paper.template.mean_correlation": 0.1,
                 "retarget.seol_paper.template.weight_min": -1.0})
    return _nest(flat), expected


def _judged_rows(text: str) -> dict[str, tuple[str, str, str]]:
    """stage-relative key -> (value text, status, limits) of every gate / ground-truth row of the page."""
    out = {}
    for m in re.finditer(r'<tr><td>([^<]+)</td><td class="num (\w*)">(.*?)</td><td><span class="badge (\w+)">'
                         r'.*?</span></td><td>(.*?)</td></tr>', text):
        out[htmllib.unescape(m.group(1))] = (m.group(3), m.group(2), htmllib.unescape(m.group(5)))
    return out


def _section(page: str, sec: str) -> str:
    return page.split(f'<section id="{sec}">', 1)[1].split("</section>", 1)[0]


def test_every_headline_key_renders_its_status_and_limits(tmp_path, every_headline):
    metrics, expected = every_headline
    page = build_report(tmp_path, "s1", metrics)
    for stage in STAGES:
        rows = _judged_rows(_section(page, stage.id))
        for key, want in expected.items():
            if not key.startswith(stage.prefix + "."):
                continue
            short = key[len(stage.prefix) + 1:]
            assert short in rows, key
            _, cell, limits = rows[short]
            assert cell == want, (key, cell, want)
            direction, ok, warn = rule_for(key)
            op = "≤" if direction == "max" else "≥"
            assert limits == f"pass {op} {ok:g}, warn {op} {warn:g}", (key, limits)
    # keys without a threshold are in the grids or the scalar list, with no status colour
    assert '<td class="num " title="tracking.sequences.rom00.mean_error_mm">9</td>' in page
    assert '<td class="num " title="calibration.n_cameras">6</td>' in page
    assert "ribera_paper / template" in page and "seol_paper / template" in page


def test_the_summary_row_of_each_stage_is_its_worst_status_and_the_verdict_the_worst_stage():
    flat = {
        "calibration.rms_px": 0.1,                                # pass (<= 0.2)
        "calibration.rotation_error_deg": 0.05,                   # warn (ground truth)
        "tracking.sequences.rom00.median_residual_mm": 0.3,       # pass
        "tracking.sequences.rom01.median_residual_mm": 0.7,       # warn: the worst sequence is the number
        "tracking.lost_frames": 0,                                # pass
        "personalization.residual_final_mm": 0.4,                 # pass
        "personalization.residual_reduction": 0.2,                # fail (>= 0.3 to warn)
        "retarget.seol.template.mean_correlation": 0.95,          # pass (ground truth)
        "retarget.seol.template.n_frames": 300,
    }
    rows, verdict = summarize(flat)
    by = {r.stage.id: r for r in rows}
    assert verdict == "fail"
    cal = by["calibration"]
    assert cal.status == "warn" and cal.number.key == "calibration.rms_px" and cal.number.status == "pass"
    assert cal.missing_gates == ["calibration.heldout_reprojection_rms_px", "calibration.n_gate_failures",
                                 "calibration.n_plausibility_flags"]
    assert [j.key for j in cal.truth] == ["calibration.rotation_error_deg"]
    assert by["reconstruction"].status == "" and by["reconstruction"].number is None
    trk = by["tracking"]
    assert trk.status == "warn" and trk.number.key == "tracking.sequences.rom01.median_residual_mm"
    assert [j.key for j in trk.gates] == ["tracking.sequences.rom01.median_residual_mm",
                                         "tracking.sequences.rom00.median_residual_mm", "tracking.lost_frames"]
    per = by["personalization"]
    assert per.status == "fail" and per.number.key == "personalization.residual_final_mm"
    assert per.missing_gates == ["personalization.heldout_residual_final_mm",
                                 "personalization.heldout_residual_reduction"]
    ret = by["retargeting"]
    assert ret.status == "pass" and ret.number.key == "retarget.seol.template.mean_correlation" and not ret.gates
    assert worst(["pass", "", "warn"]) == "warn" and worst([]) == ""
    # the calibration's own RMS / convergence gates (params.calibrate): any failure fails
    assert [status("calibration.n_gate_failures", n) for n in (0, 1)] == ["pass", "fail"]
    # lost frames: none passes, up to two warn, more fail
    assert [status("tracking.lost_frames", n) for n in (0, 2, 3)] == ["pass", "warn", "fail"]


def test_the_page_opens_with_the_verdict_and_one_row_per_stage_with_its_limit(tmp_path):
    flat = {"calibration.rms_px": 0.1, "tracking.lost_frames": 3, "tracking.sequences.rom00.median_residual_mm": 0.2}
    page = build_report(tmp_path, "s1", _nest(flat))
    head = page.split('<section id="summary">', 1)[1].split("</section>", 1)[0]
    assert '<span class="badge fail">session fail · 3 of 5 stages not measured</span>' in head
    assert "no ground truth (a real capture): judged by its gates alone" in head
    assert "capture gates (no ground truth needed): 2 pass, 1 fail, 13 not measured" in head
    rows = re.findall(r'<tr><th><a href="#(\w+)">', head)
    assert rows == ["calibration", "reconstruction", "tracking", "personalization", "retargeting"]
    cal = head.split('href="#calibration"', 1)[1].split("</tr>", 1)[0]
    assert ('<td>rms_px</td><td class="num pass">0.1</td><td>pass ≤ 0.2, warn ≤ 0.5</td>' in cal)
    trk = head.split('href="#tracking"', 1)[1].split("</tr>", 1)[0]
    assert '<span class="badge fail">fail</span>' in trk and "sequences.rom00.median_residual_mm" in trk
    assert page.index('id="summary"') < page.index('id="calibration"')
    # a real capture lists no ground-truth goal as "not measured"; its missing gates are listed
    assert "rotation_error_deg" not in page and "heldout_reprojection_rms_px" in page


def test_a_session_with_ground_truth_lists_its_unmeasured_goals(tmp_path):
    page = build_report(tmp_path, "s1", {"tracking": {"mean_error_mm": 0.2, "lost_frames": 0},
                                         "personalization": {"residual_reduction": 0.6}})
    trk = _section(page, "tracking")
    for key in ("p95_error_mm", "end_drift_mm", "visible_mean_error_mm"):
        assert f"<tr><td>{key}</td><td><em>not measured</em></td>" in trk, key
    assert "No metrics for this stage." in _section(page, "calibration")
    assert "ground truth: 1 pass" in page
    assert '<span class="badge pass">session pass · 3 of 5 stages not measured</span>' in page


def test_per_sequence_and_per_character_keys_are_grids_and_the_demo_page_is_compact(tmp_path):
    metrics = json.loads(DEMO_METRICS.read_text())
    flat = flatten_metrics(metrics)
    page = build_report(tmp_path, "demo", metrics)
    trk = _section(page, "tracking")
    grid = trk.split('<table class="grid">', 1)[1].split("</table>", 1)[0]
    assert re.findall(r"<tr><th>(rom\d+)</th>", grid) == ["rom00", "rom01", "rom02", "rom03"]
    assert "<th>mean_error_mm</th>" in grid and "<th>lost_frames</th>" in grid
    cam = _section(build_report(tmp_path, "c", {"calibration": {"camera_rms_px": {"cam00": 0.1, "cam01": 0.2},
                                                                "heldout_camera_rms_px": {"cam01": 0.3}}}), "calibration")
    cam = cam.split('<table class="grid">', 1)[1].split("</table>", 1)[0]
    assert re.findall(r"<tr><th>(cam\d+)</th>", cam) == ["cam00", "cam01"] and "<th>heldout_camera_rms_px</th>" in cam
    ret = _section(page, "retargeting").split('<table class="grid">', 1)[1].split("</table>", 1)[0]
    assert "<tr><th>ribera / template</th>" in ret and "<tr><th>seol / sculpted</th>" in ret
    # one table row per sequence / method+character: a third of a row per key or less (committed demo: 691 keys, 198 rows)
    assert len(flat) > 500 and page.count("<tr") < len(flat) / 3
    # every key is on the page: a grid or list cell titled with it, or a gate / ground-truth row naming it
    for key in flat:
        stage, short = key.split(".", 1)
        assert f'title="{key}' in page or f"<tr><td>{short}</td>" in page, key


def test_per_session_limits_override_the_configs_which_override_the_defaults():
    p = from_config({"thresholds": {"calibration.rms_px": ["max", 0.3, 0.6]},
                     "sessions": {"s2": {"thresholds": {"calibration.rms_px": ["max", 0.1, 0.2],
                                                         "tracking.lost_frames": ["max", 1, 4]}}}})
    assert p.for_session("s1") == {"calibration.rms_px": ("max", 0.3, 0.6)}
    assert p.for_session("s2") == {"calibration.rms_px": ("max", 0.1, 0.2), "tracking.lost_frames": ("max", 1, 4)}
    assert status("calibration.rms_px", 0.25, p.for_session("s1")) == "pass"
    assert status("calibration.rms_px", 0.25, p.for_session("s2")) == "fail"
    assert status("calibration.rms_px", 0.25) == "warn"
    with pytest.raises(InputError, match="params.report.sessions.s2.thresholds.calibration.rms_px"):
        from_config({"sessions": {"s2": {"thresholds": {"calibration.rms_px": ["max", "a", 0.2]}}}})
    with pytest.raises(InputError, match="did you mean 'thresholds'"):
        from_config({"sessions": {"s2": {"threshold": {}}}})
    with pytest.raises(InputError, match="params.report.thresholds.x"):
        from_config({"thresholds": {"x": ["less", 1, 2]}})
    with pytest.raises(InputError, match="did you mean 'sessions'"):
        from_config({"session": {}})


def test_thresholds_new_and_renamed_keys_keep_the_goals():
    t = DEFAULT_THRESHOLDS
    for k in ("mean_error_mm", "p95_error_mm", "end_drift_mm"):
        assert t[f"tracking.visible_{k}"] == t[f"tracking.{k}"]
    assert t["tracking.mean_error_mm"] == ("max", 0.5, 1.0)
    assert t["personalization.residual_reduction"] == ("min", 0.5, 0.3)
    assert t["personalization.heldout_residual_reduction"] == ("min", 0.4, 0.2)
    assert t["personalization.heldout_expression_error_reduction"] == ("min", 0.4, 0.2)
    assert t["calibration.heldout_reprojection_rms_px"] == ("max", 0.5, 1.0)
    # a tracked sequence's residual to its scan passes below the tracking goal and warns up to the tracker's
    # lost-frame residual (params.track lost_residual_mm = 1.0)
    assert t["tracking.sequences.*.median_residual_mm"] == ("max", 0.5, 1.0)
    assert not any(k.startswith("tracking.mask_") or k.endswith("_unweighted") for k in t)
    # the limits are inclusive; a pattern matches one character; an override takes the key's place
    assert status("tracking.mean_error_mm", 0.5) == "pass" and status("tracking.mean_error_mm", 0.5001) == "warn"
    assert status("retarget.ribera.stylized.mean_correlation", 0.85) == "warn"
    assert status("retarget.ribera_fit.stylized.mean_correlation", 0.1) == ""
    over = {"tracking.mean_error_mm": ("max", 2.0, 3.0), "tracking.lips_mean_error_mm": ["max", 1.0, 2.0]}
    assert status("tracking.mean_error_mm", 1.5, over) == "pass"
    head, rest = split_headline({"tracking.lips_mean_error_mm": 0.5, "tracking.mean_error_mm": 1.0, "a.b": 1}, over)
    assert head == ["tracking.mean_error_mm", "tracking.lips_mean_error_mm"] and rest == ["a.b"]
    assert limits_text(("min", 0.9, 0.8)) == "pass >= 0.9, warn >= 0.8" and limits_text(None) == ""


def test_text_table_shows_headline_keys_first_with_limits(every_headline):
    metrics, expected = every_headline
    text, n_fail = format_metrics_table(metrics)
    lines = text.splitlines()[2:]
    keys = [ln.split()[0] for ln in lines if not ln.startswith("-")]
    assert keys[: len(expected)] == [k.replace("*", "template") for k in DEFAULT_THRESHOLDS]
    assert set(keys) == set(flatten_metrics(metrics))
    assert n_fail == sum(1 for w in expected.values() if w == "fail")
    row = next(ln for ln in lines if ln.startswith("tracking.visible_mean_error_mm "))
    assert row.split()[2] == expected["tracking.visible_mean_error_mm"] and row.endswith("pass <= 0.5, warn <= 1")


def test_pictures_are_embedded_downscaled_as_jpeg(tmp_path):
    import cv2

    from rigbuild.report.images import jpeg_bytes

    img = np.zeros((500, 1000, 3), np.uint8)
    img[:, 500:] = 200
    (tmp_path / "calib").mkdir()
    cv2.imwrite(str(tmp_path / "calib" / "residuals.png"), img)
    out = cv2.imdecode(np.frombuffer(jpeg_bytes(tmp_path / "calib" / "residuals.png", 400, 80), np.uint8), 1)
    assert out.shape == (200, 400, 3) and abs(int(out[100, 300, 0]) - 200) <= 3
    page = build_report(tmp_path, "s1", {"calibration": {"rms_px": 0.1}}, image_width=400)
    assert page.count("data:image/jpeg;base64,") == 1 and "data:image/png" not in page
    assert "calib/residuals.png</figcaption>" in _section(page, "calibration")
    assert '<a href="calib/residuals.png"><img' in page  # the thumbnail links to the full-size file beside the page


def test_a_gate_measured_without_a_limit_is_shown_but_judges_nothing(tmp_path):
    flat = {"retarget.ribera.template.marker_residual_mm": 0.2, "retarget.ribera.template.n_frames": 9}
    rows, verdict = summarize(flat)
    ret = next(r for r in rows if r.stage.id == "retargeting")
    assert ret.status == "" and ret.number.key == "retarget.ribera.template.marker_residual_mm" and ret.number.rule is None
    assert verdict == ""
    page = build_report(tmp_path, "s1", _nest(flat))
    assert '<span class="badge none">session not measured</span>' in page
    assert ('<tr><td>ribera.template.marker_residual_mm</td><td class="num ">0.2</td><td><span class="badge none">'
            'no limit</span>' in _section(page, "retargeting"))


def test_the_text_summary_has_one_line_per_stage_and_the_verdict_first():
    from rigbuild.report.table import format_summary

    text, verdict = format_summary(_nest({"calibration.rms_px": 0.3, "calibration.rotation_error_deg": 0.01,
                                          "tracking.sequences.rom00.median_residual_mm": 0.2}))
    lines = text.splitlines()
    assert verdict == "warn" and lines[0] == "session warn" and len(lines) == 6
    assert lines[1] == ("  Calibration      warn  calibration.rms_px = 0.3 (pass <= 0.2, warn <= 0.5); gates: 1 warn, "
                        "3 not measured; ground truth: 1 pass")
    assert lines[2].startswith("  Reconstruction   -     nothing measured with a limit; gates: none, 1 not measured")
