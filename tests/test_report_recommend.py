"""The report's choice of retargeting path (rigbuild/report/recommend.py): analytic metric sets."""

import math

from rigbuild.report.recommend import method_rows, recommend


def test_ground_truth_picks_the_highest_mean_correlation():
    flat = {"retarget.ribera_fit.a.mean_correlation": 0.6, "retarget.ribera_fit.b.mean_correlation": 0.8,
            "retarget.seol.a.mean_correlation": 0.65, "retarget.seol.b.mean_correlation": 0.70,
            "retarget.ribera.a.mean_correlation": 0.99,  # the primary variant reported twice: not a method
            "retarget.actor_rig_weights.mean_correlation": 0.99,  # per take, no character
            "retarget.noconst.a.velocity_error": 3.0,  # a Seol baseline without weights metrics
            "retarget.ribera_fit.a.weight_mae": 0.1}
    rows = method_rows(flat)
    assert [r["method"] for r in rows] == ["ribera_fit", "seol"]
    assert math.isclose(rows[0]["mean_correlation"], 0.7) and rows[0]["characters"] == 2
    assert math.isnan(rows[1]["weight_mae"])
    best, basis = recommend(rows)
    assert best == "ribera_fit" and "ground-truth" in basis


def test_without_ground_truth_the_most_plausible_weights_win():
    flat = {"retarget.ribera_fit.a.antagonist_fraction": 0.3, "retarget.ribera_fit.a.mean_active": 4.0,
            "retarget.seol.a.antagonist_fraction": 0.1, "retarget.seol.a.mean_active": 9.0,
            "retarget.deformation_baseline.a.antagonist_fraction": 0.1,
            "retarget.deformation_baseline.a.mean_active": 6.0}
    best, basis = recommend(method_rows(flat))
    assert best == "deformation_baseline" and "no ground truth" in basis
    assert recommend([]) == (None, "no retargeting numbers")
