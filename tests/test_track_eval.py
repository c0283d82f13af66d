"""Exact tests of the tracking error measures (rigbuild.eval.tracking)."""

from __future__ import annotations

import numpy as np
import pytest

from rigbuild.eval.tracking import session_tracking_metrics, surface_anchors, tracking_summary


def _mesh():
    V = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0]], float)
    F = np.array([[0, 1, 2], [1, 3, 2]])
    return V, F


def test_vertex_and_correspondence_errors_exact():
    V, F = _mesh()
    truth = np.stack([V, V + [0, 0, 2.0], V + [1.0, 0, 0]])
    # registration slid every vertex by 0.5 mm along x (tangential error), tracking then exact on the surface
    reg = V + np.array([[0.5, 0, 0], [-0.5, 0, 0], [0.5, 0, 0], [-0.5, 0, 0]])  # stays on the surface
    tracked = np.stack([reg, reg + [0, 0, 2.0], reg + [1.0, 0, 0]])
    s = tracking_summary(tracked, truth, F, np.arange(4), reg, V)
    assert s["mean_error_mm"] == pytest.approx(0.5)
    assert s["end_error_mm"] == pytest.approx(0.5)
    assert s["corr_mean_error_mm"] == pytest.approx(0.0, abs=1e-9)
    # now a drift of 0.3 mm in z at the last frame only
    tracked[2] += [0, 0, 0.3]
    s = tracking_summary(tracked, truth, F, np.arange(4), reg, V)
    assert s["corr_end_error_mm"] == pytest.approx(0.3)
    assert s["corr_per_frame_mean_mm"][0] == pytest.approx(0.0, abs=1e-9)
    m = session_tracking_metrics({"a": s, "b": s})
    assert m["end_drift_mm"] == pytest.approx(np.linalg.norm([0.5, 0, 0.3]))
    assert m["corr_end_drift_mm"] == pytest.approx(0.3)


def test_surface_anchors_exact():
    V, F = _mesh()
    tri, bary = surface_anchors(np.array([[2.0, 3.0, 1.0], [9.0, 8.0, -2.0]]), V, F)
    np.testing.assert_allclose(np.einsum("nk,nkd->nd", bary, V[F[tri]]), [[2, 3, 0], [9, 8, 0]], atol=1e-12)
