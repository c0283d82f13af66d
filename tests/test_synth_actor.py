"""Synthetic actor (rigbuild.synth.actor): identity range and expressions the template does not span."""

from __future__ import annotations

import numpy as np
import pytest

from rigbuild.synth.actor import (make_actor_rig, novel_displacement, out_of_span_fraction, sample_identity,
                                  shape_region_weight)
from test_synth_motion import _grid_rig


@pytest.fixture(scope="module")
def head():
    from rigbuild.io.rigs import load_rig

    return load_rig("procedural")


def test_default_actor_unchanged():
    """The opt-in options off reproduce the actor of the code before them (values from that code, rtol 1e-9)."""
    a, info = make_actor_rig(_grid_rig(), seed=3)
    assert float(a.deltas.sum()) == pytest.approx(824.3293695601276, rel=1e-9)
    assert float(np.abs(a.deltas).sum()) == pytest.approx(851.5966651318311, rel=1e-9)
    assert float(a.neutral.sum()) == pytest.approx(77.11313706203009, rel=1e-9)
    b, _ = make_actor_rig(_grid_rig(), seed=3, identity_sigma=None, expression_novelty=None)
    assert np.array_equal(a.deltas, b.deltas) and np.array_equal(a.neutral, b.neutral)
    assert "novelty_fraction" not in info


def test_identity_coefficients_bounded_by_sigma():
    rng = np.random.default_rng(0)
    u = sample_identity(rng, 20000, 2.0, "uniform")
    assert np.abs(u).max() <= 2.0 and np.abs(u).max() > 1.99
    assert u.std() == pytest.approx(2.0 / np.sqrt(3), rel=0.02)  # U(-2, 2)
    c = sample_identity(rng, 20000, 2.0, "clipped_normal")
    assert np.abs(c).max() == 2.0 and np.mean(np.abs(c) == 2.0) == pytest.approx(0.0455, abs=0.006)  # P(|z|>2)
    with pytest.raises(ValueError):
        sample_identity(rng, 3, -1.0)
    with pytest.raises(ValueError):
        sample_identity(rng, 3, 1.0, "gamma")


@pytest.mark.data
def test_ict_identity_at_two_sigma(ict_rig, ict_folder):
    actor, info = make_actor_rig(ict_rig, seed=4, identity_folder=ict_folder, identity_sigma=2.0, n_identity_modes=5)
    coeffs = np.asarray(info["identity"])
    assert coeffs.shape == (5,) and np.abs(coeffs).max() <= 2.0
    assert np.abs(actor.neutral - ict_rig.neutral).max() > 1.0  # mm: a different face


def _novelty_checks(rig, seed):
    plain, _ = make_actor_rig(rig, seed=seed)
    actor, info = make_actor_rig(rig, seed=seed, expression_novelty=(0.15, 0.30))
    added = actor.deltas - plain.deltas  # crosstalk and everything else identical: the novel fields alone
    frac = np.asarray(info["novelty_fraction"])
    moving = np.linalg.norm(rig.deltas.reshape(rig.n_shapes, -1), axis=1) > 0
    assert np.all((frac[moving] >= 0.15) & (frac[moving] <= 0.30))
    assert np.all(info["novelty_out_of_span"][moving] > 0.999)
    for k in np.flatnonzero(moving):
        # |novel| = f_k |scaled, tilted delta| (the actor delta before crosstalk)
        base = plain.deltas[k] - _crosstalk(rig, plain, k, info)
        assert np.linalg.norm(added[k]) == pytest.approx(frac[k] * np.linalg.norm(base), rel=1e-9)
        # inside the shape's own region only
        region = shape_region_weight(rig.deltas[k]) > 0
        assert np.all(added[k][~region] == 0)
        # no template shape spans it: orthogonal to every template delta restricted to the region
        D = rig.deltas[:, region].reshape(rig.n_shapes, -1).T
        assert out_of_span_fraction(added[k][region].reshape(-1), D) > 0.999
        assert np.abs(D.T @ added[k][region].reshape(-1)).max() <= 1e-8 * np.linalg.norm(added[k]) * np.abs(D).max() * D.shape[0]
    return actor, frac


def _crosstalk(rig, plain, k, info):
    """The crosstalk added to actor shape k (``info["crosstalk"]``: (shape, source, amount))."""
    out = np.zeros_like(rig.deltas[k])
    for target, source, a in info["crosstalk"]:
        if target == rig.shape_names[k]:
            out += a * rig.deltas[rig.shape_index(source)]
    return out


def test_expression_novelty_outside_template_span_grid():
    _novelty_checks(_grid_rig(), seed=2)


def test_expression_novelty_outside_template_span_head(head):
    actor, frac = _novelty_checks(head, seed=1)
    assert 0.2 < float(np.median(frac[frac > 0])) < 0.25  # U(0.15, 0.30)


def test_novel_displacement_is_smooth(head):
    """The novel field varies on the scale of the shape, not of the mesh: its mean change along an edge over its
    mean magnitude is within 2.5x the template delta's own and under 0.4x that of white noise on the region."""
    f = head.faces
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])

    def roughness(x):
        m = np.linalg.norm(x, axis=1) > 0
        e = edges[m[edges[:, 0]] | m[edges[:, 1]]]
        return np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1).mean() / np.linalg.norm(x[m], axis=1).mean()

    k = head.shape_index("jawOpen")
    n, oos = novel_displacement(head.neutral, head.deltas[k], head.deltas, np.random.default_rng(0))
    assert oos > 0.999 and np.linalg.norm(n) == pytest.approx(1.0)
    s = shape_region_weight(head.deltas[k])
    white = s[:, None] * np.random.default_rng(1).normal(size=n.shape)
    assert roughness(n) < 2.5 * roughness(head.deltas[k])
    assert roughness(n) < 0.4 * roughness(white)
