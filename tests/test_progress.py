"""rigbuild.progress: silent (the iterable itself) off a terminal; a tqdm bar on one, yielding the same items.

Also checks that the long loops wrapped with it (reconstruct per-view map, personalization weight sweeps,
report sections) give identical results with and without a terminal, and that the bar really draws there.
"""

from __future__ import annotations

import io
import logging
import sys

import numpy as np

from rigbuild.progress import progress


class FakeTTY:
    """A stderr stand-in that claims to be a terminal and records what is written to it."""

    def __init__(self) -> None:
        self.chunks: list[str] = []
        self.encoding = "utf-8"

    def isatty(self) -> bool:
        return True

    def write(self, s: str) -> int:
        self.chunks.append(s)
        return len(s)

    def flush(self) -> None:
        pass

    @property
    def text(self) -> str:
        return "".join(self.chunks)


class NotATTY(io.StringIO):
    def isatty(self) -> bool:
        return False


def test_off_a_terminal_the_same_items_come_out_and_progress_lines_are_logged(monkeypatch, caplog):
    monkeypatch.setattr(sys, "stderr", NotATTY())
    import rigbuild.progress as P

    items = [3, 1, 4, 1, 5]
    with caplog.at_level(logging.INFO, logger=P.LOGGER):
        assert list(progress(items, "digits", unit="digit")) == items
    lines = [r.getMessage() for r in caplog.records if r.name == P.LOGGER]
    assert lines[0].startswith("digits: digit 1/5 (20%)") and lines[-1].startswith("digits: digit 5/5 (100%)")
    assert len(lines) == 2  # first and last: the five items took less than LOG_INTERVAL_S
    caplog.clear()
    gen = (i for i in range(3))
    with caplog.at_level(logging.INFO, logger=P.LOGGER):
        assert list(progress(gen, "gen")) == [0, 1, 2]
    assert [r.getMessage().split(",")[0] for r in caplog.records] == ["gen: step 1"]
    assert sys.stderr.getvalue() == ""  # nothing is drawn: the lines go to the logger only


def test_progress_line_estimates_the_time_left():
    from rigbuild.progress import progress_line

    assert progress_line("ROM images", 3, 12, "sequence", 60.0) == \
        "ROM images: sequence 3/12 (25%), 60 s, about 180 s left"
    assert progress_line("x", 4, None, "frame", 2.0) == "x: frame 4, 2 s"


def test_run_logged_shows_progress_lines_with_the_job_label(tmp_path, monkeypatch):
    from types import SimpleNamespace

    from rigbuild.logs import run_logged

    err = NotATTY()
    monkeypatch.setattr(sys, "stderr", err)
    job = SimpleNamespace(log=[str(tmp_path / "job.log")], rule="track_sequence",
                          wildcards={"session": "demo", "seq": "rom01"})
    run_logged(job, lambda smk: list(progress(range(3), "frames", unit="frame")))
    shown = err.getvalue().splitlines()
    assert shown[0].startswith("[track_sequence session=demo seq=rom01] frames: frame 1/3")
    assert "frames: frame 3/3 (100%)" in (tmp_path / "job.log").read_text()


def test_on_a_terminal_a_bar_is_drawn_and_the_same_items_come_out(monkeypatch):
    tty = FakeTTY()
    monkeypatch.setattr(sys, "stderr", tty)
    items = [3, 1, 4, 1, 5, 9, 2, 6]
    wrapped = progress(items, "counting things", unit="thing")
    assert wrapped is not items
    assert list(wrapped) == items
    assert "counting things" in tty.text
    assert "0/8" in tty.text  # the bar knows the total (len of the list)
    # generators (no len) with an explicit total, and numpy arrays
    n0 = len(tty.chunks)
    assert list(progress((i * i for i in range(5)), "squares", total=5)) == [0, 1, 4, 9, 16]
    assert len(tty.chunks) > n0 and "squares" in tty.text
    arr = np.array([7, 8, 9])
    out = list(progress(arr, "array"))
    np.testing.assert_array_equal(out, arr)
    assert "array" in tty.text


def test_reconstruct_view_map_same_results_with_a_bar(monkeypatch):
    from rigbuild.reconstruct.filter import _map_views

    def fn(k):
        return k * 10 + 1

    expected = [fn(k) for k in range(5)]
    tty = FakeTTY()
    monkeypatch.setattr(sys, "stderr", tty)
    for threads in (1, 2):
        assert _map_views(fn, 5, threads, desc="stereo depth maps") == expected
        assert _map_views(fn, 5, threads) == expected
    assert tty.text.count("stereo depth maps") >= 2  # one bar per call with a desc (both thread modes)


def _tiny_blendshape_frames():
    rng = np.random.default_rng(3)
    neutral = rng.normal(size=(40, 3)) * 20.0
    deltas = rng.normal(size=(3, 40, 3)) * 2.0
    W = rng.uniform(0, 1, size=(6, 3))
    frames = neutral[None] + np.einsum("fk,kvc->fvc", W, deltas)
    return neutral, deltas, frames, W


def test_personalize_weight_sweep_same_results_with_a_bar(monkeypatch):
    from rigbuild.personalize.em import PersonalizeParams, fit_weights_and_rigid

    neutral, deltas, frames, W = _tiny_blendshape_frames()
    p = PersonalizeParams(lambda_unit_mm=1.0)  # 40 vertices: the regularisers stated in mm
    monkeypatch.setattr(sys, "stderr", NotATTY())
    quiet = fit_weights_and_rigid(neutral, deltas, frames, params=p, sweeps=3)
    assert sys.stderr.getvalue() == ""
    tty = FakeTTY()
    monkeypatch.setattr(sys, "stderr", tty)
    shown = fit_weights_and_rigid(neutral, deltas, frames, params=p, sweeps=3)
    assert "weight fits" in tty.text
    np.testing.assert_array_equal(shown["weights"], quiet["weights"])
    np.testing.assert_array_equal(shown["rotations"], quiet["rotations"])
    assert shown["energy"] == quiet["energy"]
    # and the fit is right (exact data, lambda_s/lambda_t regularisers are small): not a vacuous comparison
    np.testing.assert_allclose(quiet["weights"], W, atol=0.05)


def test_report_same_html_with_a_bar(monkeypatch, tmp_path):
    from rigbuild.report.html import build_report

    metrics = {"calibrate": {"rms_px": 0.31}}
    monkeypatch.setattr(sys, "stderr", NotATTY())
    quiet = build_report(tmp_path, "s1", metrics)
    tty = FakeTTY()
    monkeypatch.setattr(sys, "stderr", tty)
    shown = build_report(tmp_path, "s1", metrics)
    assert shown == quiet and "rigbuild session report: s1" in quiet
    assert "report sections" in tty.text
