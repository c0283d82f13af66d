"""The painted dot pattern (rigbuild.dots): exact spacing properties of the stencil on the procedural head."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from rigbuild.dots import dot_stencil, painted_dot_vertices, stencil_candidates
from rigbuild.errors import InputError


@pytest.fixture(scope="module")
def head():
    from rigbuild.io.rigs import load_rig

    return load_rig("procedural")


def _dist(a, b):
    return np.linalg.norm(a[:, None] - b[None], axis=2)


def test_stencil_spacing_and_coverage_exact(head):
    s = 14.0
    st = dot_stencil(head, s)
    P = head.neutral
    mk = head.marker_vertices
    assert st.size > 10
    assert np.isin(st, stencil_candidates(head)).all()
    assert not np.isin(st, mk).any()
    d = _dist(P[st], P[st])
    np.fill_diagonal(d, np.inf)
    assert d.min() >= s  # no two stencil dots closer than the spacing
    assert _dist(P[st], P[mk]).min() >= s  # nor a stencil dot and a marker
    cand = stencil_candidates(head)
    assert _dist(P[cand], P[np.concatenate([mk, st])]).min(1).max() < s  # every candidate within reach of a dot
    np.testing.assert_array_equal(st, dot_stencil(head, s))  # deterministic
    assert dot_stencil(head, 20.0).size < st.size


def test_painted_dot_vertices_markers_first(head):
    np.testing.assert_array_equal(painted_dot_vertices(head), head.marker_vertices)
    dv = painted_dot_vertices(head, 16.0)
    np.testing.assert_array_equal(dv[:head.marker_vertices.size], head.marker_vertices)
    np.testing.assert_array_equal(dv[head.marker_vertices.size:], dot_stencil(head, 16.0))


def test_stencil_keeps_clear_of_lips_and_eyes(head):
    cand = stencil_candidates(head, lip_clearance_mm=8.0, eye_clearance_mm=7.0)
    lm = head.landmarks
    P = head.neutral
    assert _dist(P[cand], P[lm[48:68]]).min() >= 8.0
    assert _dist(P[cand], P[lm[36:48]]).min() >= 7.0


def test_stencil_bad_input(head):
    with pytest.raises(InputError, match="positive number"):
        dot_stencil(head, 0.0)
    with pytest.raises(InputError, match="positive number"):
        dot_stencil(head, float("nan"))
    bare = replace(head.copy(), marker_names=[], marker_vertices=np.zeros(0, np.int64))
    with pytest.raises(InputError, match="no markers"):
        dot_stencil(bare, 14.0)
