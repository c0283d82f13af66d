"""Personalization on the ICT topology (53 shapes, 26,719 vertices, face region 0-9408).

The fast test runs the whole EM on a small ROM of a synthetic ICT actor with a subset of shapes (the
full-size code path: DT onto the actor's neutral, face-region fitting, ICT supports). The realistic
acceptance run (all 53 shapes, config/ict.yaml's ROM) is marked slow; its numbers are printed by
benchmarks/bench_personalize.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from rigbuild.eval.personalization import personalization_metrics
from rigbuild.geometry.deformation_transfer import deformation_transfer
from rigbuild.personalize.em import PersonalizeParams, fit_weights_and_rigid, personalize

from personalize_scene import make_rom_scene

SUBSET = ["jawOpen", "mouthSmile_L", "mouthSmile_R", "browInnerUp_L", "browInnerUp_R", "eyeBlink_L",
          "mouthPucker", "cheekPuff_L"]


def run(template, n_seq, frames, held, ict_folder, seed, params):
    sc = make_rom_scene(template, n_sequences=n_seq, frames_per_sequence=frames, seed=seed,
                        identity_folder=ict_folder)
    fit = sc.sequence_ids < n_seq - held
    fr = template.face_region
    b0 = sc.vertices[0]
    Dstar = deformation_transfer(template.neutral, template.deltas, template.faces, b0)
    res = personalize(b0, Dstar, template.faces, sc.vertices[fit], None, sc.sequence_ids[fit], params,
                      template.shape_names, fit_vertices=fr)
    h0 = fit_weights_and_rigid(b0, Dstar, sc.vertices[~fit], None, sc.sequence_ids[~fit], params, vertices=fr)
    h1 = fit_weights_and_rigid(res.neutral, res.deltas, sc.vertices[~fit], None, sc.sequence_ids[~fit], params,
                               vertices=fr)
    m = personalization_metrics(Dstar, res.deltas, sc.actor.deltas, res.weights, sc.weights[fit],
                                res.residual_initial_mm, res.residual_final_mm, fr, h0["rms_mm"], h1["rms_mm"])
    return res, m, b0, Dstar


def test_ict_subset_personalization(ict_rig, ict_folder):
    tpl = ict_rig.subset(SUBSET)
    res, m, b0, Dstar = run(tpl, 6, 8, 1, ict_folder, 5, PersonalizeParams(max_iterations=8))
    J = [o["total"] for o in res.objective]
    assert np.all(np.diff(J) <= 1e-9 * J[0])
    assert res.neutral.shape == tpl.neutral.shape and res.deltas.shape == tpl.deltas.shape
    # outside the fitted region + ring nothing changes
    outside = np.setdiff1d(np.arange(tpl.n_vertices), res.active_vertices)
    np.testing.assert_array_equal(res.neutral[outside], b0[outside])
    np.testing.assert_array_equal(res.deltas[:, outside], Dstar[:, outside])
    assert res.n_free_variables > 0 and np.abs(res.deltas - Dstar).max() > 0.1
    print(m)
    assert m["residual_reduction"] >= 0.5
    assert m["heldout_residual_reduction"] >= 0.2
    assert m["weight_mae_raw"] <= 0.05
    assert m["min_shape_cosine"] >= 0.9


@pytest.mark.slow
def test_ict_realistic_acceptance(ict_rig, ict_folder):
    """config/ict.yaml's actor and ROM: 12 sequences x 15 frames, the last held out, rom_peak gauge.

    The ROM here is performed at full intensity (make_rom_weights' default: every shape peaks at weight 1), so the
    ROM-peak gauge fixes each shape's amplitude and the raw shape error can be bounded. On the proving ground's ROM
    (peaks 0.5-1.0) no ROM-peak gauge passes 0.29 raw (the actor's exact shapes, scaled so, score 0.284:
    ``acceptance_bound_rom_peak_gauge`` in benchmarks/out/personalize.json, which also holds the gauge-invariant
    numbers of the paper's EM on that ROM)."""
    res, m, _, _ = run(ict_rig, 12, 15, 1, ict_folder, 11, PersonalizeParams(gauge="rom_peak"))
    print(m)
    assert m["residual_reduction"] >= 0.5
    assert m["min_shape_cosine"] >= 0.9
    assert m["weight_mae_raw"] <= 0.05
    assert m["heldout_residual_reduction"] >= 0.4
    assert m["shape_error_reduction_raw"] >= 0.4
