"""The report's pass / warn / fail for every headline key (rigbuild.report: thresholds, html, table)."""

from __future__ import annotations

import html as htmllib
import re

import pytest

from rigbuild.io.metrics import flatten_metrics
from rigbuild.report.html import build_report
from rigbuild.report.table import format_metrics_table
from rigbuild.report.thresholds import DEFAULT_THRESHOLDS, limits_text, rule_for, split_headline, status

STATUSES = ("pass", "warn", "fail")


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
    """metrics.json with every headline key (``*`` as the character ``template``), cycling pass / warn / fail,
    and a few keys without threshold."""
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


def _rows(text: str) -> dict[str, tuple[str, str, str | None]]:
    """key -> (value text, status, limits or None) of every metric row of the page."""
    out = {}
    for m in re.finditer(r'<tr><td>([^<]+)</td><td class="num">(.*?)</td><td>(.*?)</td>(?:<td>(.*?)</td>)?</tr>', text):
        badge = re.search(r'class="badge (\w+)"', m.group(3))
        out[htmllib.unescape(m.group(1))] = (m.group(2), badge.group(1) if badge else "",
                                             None if m.group(4) is None else htmllib.unescape(m.group(4)))
    return out


def test_every_headline_key_renders_its_status_and_limits(tmp_path, every_headline):
    metrics, expected = every_headline
    page = build_report(tmp_path, "s1", metrics)
    rows = _rows(page)
    for key, want in expected.items():
        assert key in rows, key
        _, st, limits = rows[key]
        assert st == want, (key, st, want)
        direction, ok, warn = rule_for(key)
        op = "≤" if direction == "max" else "≥"
        assert limits == f"pass {op} {ok:g}, warn {op} {warn:g}", (key, limits)
    # keys without a threshold: no status, no limits column, folded under <details>
    for key in ("calibration.n_cameras", "tracking.visible_corr_mean_error_mm",
                "tracking.sequences.rom00.mean_error_mm", "personalization.residual_reduction_weighted",
                "retarget.ribera_paper.template.mean_correlation"):
        assert rows[key][1] == "" and rows[key][2] is None, key
    n = {s: sum(1 for w in expected.values() if w == s) for s in STATUSES}
    assert f'<span>{n["pass"]} pass</span><span>{n["warn"]} warn</span><span>{n["fail"]} fail</span>' in page
    assert "<span>0 not measured</span>" in page and 'session fail' in page


def test_each_section_lists_its_headline_keys_first_and_folds_the_rest(tmp_path, every_headline):
    metrics, expected = every_headline
    page = build_report(tmp_path, "s1", metrics)
    for sec in ("calibration", "reconstruction", "tracking", "personalization", "retargeting"):
        body = page.split(f'<section id="{sec}">', 1)[1].split("</section>", 1)[0]
        head, _, folded = body.partition("<details>")
        assert '<table class="headline">' in head and "<th>limits</th>" in head
        head_keys = list(_rows(head))
        assert head_keys and all(k in expected for k in head_keys), (sec, head_keys)
        assert all(k not in expected for k in _rows(folded)), sec
        # in the threshold table's order
        order = [k.replace("*", "template") for k in DEFAULT_THRESHOLDS]
        assert head_keys == sorted(head_keys, key=order.index)
    tracking = page.split('<section id="tracking">', 1)[1].split("</section>", 1)[0]
    assert list(_rows(tracking.partition("<details>")[0])) == [
        "tracking.mean_error_mm", "tracking.p95_error_mm", "tracking.end_drift_mm", "tracking.visible_mean_error_mm",
        "tracking.visible_p95_error_mm", "tracking.visible_end_drift_mm"]
    assert "<summary>2 more metrics</summary>" in tracking


def test_a_headline_goal_without_a_number_is_shown_not_measured(tmp_path):
    page = build_report(tmp_path, "s1", {"tracking": {"mean_error_mm": 0.2, "lost_frames": 0},
                                         "personalization": {"residual_reduction": 0.6}})
    rows = _rows(page)
    assert rows["tracking.mean_error_mm"][1] == "pass"
    for key in ("tracking.p95_error_mm", "tracking.end_drift_mm", "tracking.visible_mean_error_mm",
                "personalization.heldout_residual_reduction", "personalization.heldout_expression_error_reduction"):
        assert rows[key][0] == "<em>not measured</em>" and rows[key][1] == "" and rows[key][2], key
    assert "calibration.rms_px" not in rows  # a stage with no metrics at all says so once
    assert "No metrics for this stage." in page
    n_missing = sum(1 for k in DEFAULT_THRESHOLDS if k.startswith(("tracking.", "personalization."))) - 2
    assert n_missing == 5 + 7  # tracking: 6 headline keys, 1 measured; personalization: 8, 1 measured
    assert f"<span>{n_missing} not measured</span>" in page and "session pass" in page


def test_thresholds_new_and_renamed_keys_keep_the_goals():
    t = DEFAULT_THRESHOLDS
    for k in ("mean_error_mm", "p95_error_mm", "end_drift_mm"):
        assert t[f"tracking.visible_{k}"] == t[f"tracking.{k}"]
    assert t["tracking.mean_error_mm"] == ("max", 0.5, 1.0)
    assert t["personalization.residual_reduction"] == ("min", 0.5, 0.3)
    assert t["personalization.heldout_residual_reduction"] == ("min", 0.4, 0.2)
    assert t["personalization.heldout_expression_error_reduction"] == ("min", 0.4, 0.2)
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
