"""Plausibility options of the Ribera retargeting (rigbuild.retarget.ribera.plausible) and their metrics
(rigbuild.retarget.plausible): exact bounded solves with per-frame bounds, the log sparsity penalty,
antagonist exclusion, the still-region gate, and the parameter checks."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from rigbuild.errors import InputError
from rigbuild.retarget.params import PLAUSIBLE, RetargetParams, RiberaParams, ribera_from_config
from rigbuild.retarget.plausible import ANTAGONISTS, antagonist_frames, antagonist_pairs, plausibility_metrics, shape_region
from rigbuild.retarget.ribera import RiberaRetargeter
from rigbuild.retarget.ribera.bounded import box_qp
from rigbuild.retarget.ribera.plausible import antagonist_pins, marker_ranges, still_upper_bounds, support_masks


def _kkt_violation(A, b, w, lo, hi):
    """Largest violation of the KKT conditions of min 1/2 w^T A w - b^T w, lo <= w <= hi (pinned: none)."""
    g = np.einsum("fkl,fl->fk", A, w) - b
    pinned = hi <= lo
    at_lo = (w <= lo + 1e-12) & ~pinned
    at_hi = (w >= hi - 1e-12) & ~pinned
    free = ~(at_lo | at_hi | pinned)
    bound = np.maximum(np.maximum(lo - w, w - hi), 0).max()
    return max(bound, np.abs(g[free]).max(initial=0), np.maximum(-g[at_lo], 0).max(initial=0),
               np.maximum(g[at_hi], 0).max(initial=0))


@pytest.mark.parametrize("warm", [False, True])
@pytest.mark.parametrize("F", [1, 40])
def test_box_qp_with_per_frame_bounds_and_pinned_shapes_is_exact(warm, F):
    rng = np.random.default_rng(F)
    K = 9
    C = rng.normal(size=(F, 14, K))
    A = np.einsum("fmk,fml->fkl", C, C) + 0.05 * np.eye(K)
    b = rng.normal(size=(F, K)) * 3
    lo = np.zeros((F, K))
    hi = rng.uniform(0.2, 1.0, size=(F, K))
    hi[rng.random((F, K)) < 0.2] = 0.0  # shapes switched off in some frames
    start = np.clip(rng.normal(size=(F, K)), 0, 1) if warm else None
    w, info = box_qp(A, b, lo, hi, passes=3, start=start)
    assert _kkt_violation(A, b, w, lo, hi) < 1e-8
    assert np.all(w[hi <= lo] == 0.0)
    assert info["unconverged"] == 0


def _toy_rig(seed=0, M=12, noise=0.0):
    """Four shapes on two regions (markers 0-5 and 6-11): a pair of exact antagonists (+d, -d) on region 1,
    two shapes on region 2."""
    rng = np.random.default_rng(seed)
    dp = np.zeros((4, M, 3))
    d = rng.normal(size=(6, 3))
    dp[0, :6] = d
    dp[1, :6] = -d + 0.3 * rng.normal(size=(6, 3))
    dp[2, 6:] = rng.normal(size=(6, 3))
    dp[3, 6:] = rng.normal(size=(6, 3))
    return dp


def test_log_sparsity_is_active_and_sparser_than_the_linear_l1():
    rng = np.random.default_rng(1)
    K, M = 12, 20
    dp = rng.normal(size=(K, M, 3))
    W = np.zeros((200, K))
    W[:, 0] = np.linspace(0, 1, 200)
    W[:, 3] = 0.5
    da = np.einsum("fk,kmc->fmc", W, dp) + 0.4 * rng.normal(size=(200, M, 3))
    base = RetargetParams(mu=0.0, lambda_cm=0.01, bounds=(0.0, 1.0), rigid="fixed")
    w_l1 = RiberaRetargeter(dp, np.zeros((K, K)), base).solve(da)
    w_log = RiberaRetargeter(dp, np.zeros((K, K)), replace(base, sparsity="log", sparsity_lambda_cm=0.05,
                                                           coherence_frames=0.0)).solve(da)
    # the linear L1 with the log penalty's slope at 0: as sparse, but it shrinks the shapes that are on
    w_l1s = RiberaRetargeter(dp, np.zeros((K, K)), replace(base, lambda_cm=0.05)).solve(da)
    act = {k: (w > 0.05).sum(1).mean() for k, w in (("l1", w_l1), ("log", w_log), ("l1s", w_l1s),
                                                    ("truth", W))}
    assert act["log"] < act["l1"] - 0.5 and act["log"] < act["truth"] + 0.4
    shrink = {k: abs(w[:, 3].mean() - 0.5) for k, w in (("log", w_log), ("l1s", w_l1s))}
    assert shrink["log"] < 0.05 and shrink["log"] < 0.5 * shrink["l1s"]
    assert np.corrcoef(w_log[:, 0], W[:, 0])[0, 1] > 0.98


def test_antagonists_are_never_on_together():
    rng = np.random.default_rng(2)
    dp = _toy_rig()
    names = ["jawLeft", "jawRight", "eyeBlink_L", "eyeWide_L"]
    assert frozenset(("jawLeft", "jawRight")) in ANTAGONISTS
    pairs = antagonist_pairs(names)
    assert pairs.tolist() == [[0, 1], [2, 3]]
    F = 300
    W = np.zeros((F, 4))
    W[:, 0] = np.clip(np.sin(np.linspace(0, 6, F)), 0, None)
    W[:, 1] = np.clip(-np.sin(np.linspace(0, 6, F)), 0, None)
    W[:, 2] = 0.4
    da = np.einsum("fk,kmc->fmc", W, dp) + 0.3 * rng.normal(size=(F, 12, 3))
    base = RetargetParams(mu=0.0, lambda_cm=0.001, bounds=(0.0, 1.0), rigid="fixed")
    plain = RiberaRetargeter(dp, np.zeros((4, 4)), base, antagonist_pairs=pairs).solve(da)
    # (the push's weight is in mm^2 per unit weight^2 like lambda; these toy shapes move markers by ~1 mm)
    opt = RiberaRetargeter(dp, np.zeros((4, 4)), replace(base, antagonists=True, antagonist_lambda_cm=0.01),
                           antagonist_pairs=pairs).solve(da)
    both = lambda w: (np.minimum(w[:, pairs[:, 0]], w[:, pairs[:, 1]]) > 1e-3).any(1).mean()  # noqa: E731
    assert both(plain) > 0.3  # noise makes the plain solve mix antagonists
    assert both(opt) == 0.0
    for k in (0, 1):  # each shape of the pair follows its truth at least as well as without the option
        r_opt, r_plain = (np.corrcoef(w[:, k], W[:, k])[0, 1] for w in (opt, plain))
        assert r_opt > 0.98 and r_opt >= r_plain
    assert not antagonist_frames(opt, names).any()


def test_antagonist_pins_yield_the_weaker_shape_over_a_window():
    w = np.zeros((30, 2))
    w[:, 0] = 0.8
    w[10:20, 1] = 0.2
    pin = antagonist_pins(w, np.array([[0, 1]]), coherence_frames=2.0)
    assert not pin[:, 0].any()
    assert pin[10:20, 1].all() and pin[6:24, 1].all()  # dilated by 2 * 2 frames
    assert not pin[:5, 1].any()


def test_still_gate_holds_shapes_of_a_motionless_region_at_zero():
    rng = np.random.default_rng(3)
    dp = _toy_rig(seed=3)
    F = 200
    train = np.zeros((F, 4))
    train[:, 0] = np.abs(np.sin(np.linspace(0, 9, F)))
    train[:, 2] = np.abs(np.cos(np.linspace(0, 7, F)))
    da_train = np.einsum("fk,kmc->fmc", train, dp)
    ranges = marker_ranges(da_train)
    sup = support_masks(dp)
    assert sup[2, 6:].any() and not sup[2, :6].any()
    # the take moves region 1 only; region 2's markers carry noise below a quarter of their range
    W = np.zeros((F, 4))
    W[:, 0] = np.abs(np.sin(np.linspace(0, 5, F)))
    da = np.einsum("fk,kmc->fmc", W, dp) + 0.05 * rng.normal(size=(F, 12, 3))
    hi = still_upper_bounds(da, sup, 0.25 * ranges, 1.0, 2.0)
    assert np.all(hi[:, 2:] == 0.0) and hi[:, 0].max() == 1.0
    base = RetargetParams(mu=0.0, lambda_cm=0.0, bounds=(0.0, 1.0), rigid="fixed")
    plain = RiberaRetargeter(dp, np.zeros((4, 4)), base).solve(da)
    gated = RiberaRetargeter(dp, np.zeros((4, 4)), replace(base, still_gate=True), marker_ranges=ranges).solve(da)
    assert (plain[:, 2:] > 1e-3).mean() > 0.2
    assert np.all(gated[:, 2:] == 0.0)
    # (the ramp of the bound trims the shape near zero motion)
    assert np.corrcoef(gated[:, 0], W[:, 0])[0, 1] > 0.97


def test_plausibility_metrics_count_what_they_say():
    names = ["jawLeft", "jawRight", "eyeBlink_L", "browDown_L", "mouthClose"]
    W = np.zeros((10, 5))
    W[:3, 0] = W[:3, 1] = 0.5  # antagonists in 3 of 10 frames
    W[:, 4] = 0.2
    W[5, 2] = 0.3  # an eye shape above 0.2 in one frame
    m = plausibility_metrics(W, names, still_regions=("eyes", "brows"))
    assert m["antagonist_fraction"] == pytest.approx(0.3)
    assert m["worst_antagonist_pair"] == "jawLeft+jawRight"
    assert m["mean_active"] == pytest.approx((3 * 3 + 7 * 1 + 1) / 10)
    assert m["still_fraction"] == pytest.approx(0.1) and m["still_max"] == pytest.approx(0.3)
    assert shape_region("eyeLookUp_R") == "eyes" and shape_region("browInnerUp") == "brows"


def test_plausibility_options_need_bounds_from_zero_and_the_paper_variant_has_none():
    with pytest.raises(InputError, match="need bounds from 0"):
        ribera_from_config({"sparsity": "log", "bounds": None})
    with pytest.raises(InputError, match="sparsity"):
        ribera_from_config({"sparsity": "l0"})
    with pytest.raises(InputError, match="need weight bounds from 0"):
        RiberaRetargeter(np.ones((2, 4, 3)), np.zeros((2, 2)), RetargetParams(antagonists=True))
    p = replace(RiberaParams(), **PLAUSIBLE)
    rp = p.retarget_params("ribera_fit")
    assert rp.sparsity == "log" and rp.antagonists and rp.sparsity_lambda_mm == pytest.approx(60.0)
    paper = p.retarget_params("ribera")
    assert paper.sparsity == "l1" and not paper.antagonists and not paper.still_gate


def test_lambda_is_converted_from_cm_once():
    """Eq. 16 in mm: E_Fit and E_Prior scale by 100 from cm to mm, E_Sparse not: lambda_mm = 100 lambda_cm, and
    the same markers in cm with lambda_cm give the same weights as in mm."""
    rng = np.random.default_rng(5)
    dp_cm = rng.normal(size=(6, 10, 3))
    W = np.clip(rng.normal(0.3, 0.3, size=(50, 6)), 0, 1)
    da_cm = np.einsum("fk,kmc->fmc", W, dp_cm) + 0.05 * rng.normal(size=(50, 10, 3))
    Q_cm = np.eye(6) * 0.1
    p = RetargetParams(mu=0.3, lambda_cm=0.6, bounds=(0.0, 1.0), rigid="fixed")
    assert p.lambda_mm == pytest.approx(60.0)
    w_mm = RiberaRetargeter(dp_cm * 10, Q_cm * 100, p).solve(da_cm * 10)
    # the same problem posed in cm: the solver's mm lambda divided by 100 is the paper's cm value
    w_cm = RiberaRetargeter(dp_cm, Q_cm, replace(p, lambda_cm=0.006)).solve(da_cm)
    np.testing.assert_allclose(w_mm, w_cm, atol=1e-9)


# ------------------------------------------------------------------------------------- Seol's options
@pytest.fixture(scope="module")
def seol_case():
    from rigbuild.assets.head import procedural_head_rig
    from rigbuild.synth.retarget_scenes import synthetic_performance

    head = procedural_head_rig()
    return head, synthetic_performance(head, n_frames=240, fps=60, seed=5, noise_mm=0.2, gap_fraction=0.01)


def test_seol_log_sparsity_and_antagonist_exclusion(seol_case):
    from rigbuild.retarget.seol import retarget_seol

    head, case = seol_case
    common = {"alpha": 1e-4, "weight_bounds": (0.0, 1.5), "sparsity": 0.5, "baselines": False}
    plain = retarget_seol(case["markers"], head, **common).weights
    log = retarget_seol(case["markers"], head, sparsity_mode="log", **common).weights
    excl = retarget_seol(case["markers"], head, sparsity_mode="log", antagonists=True, **common).weights
    # the log penalty has the L1 term's slope at 0 and a smaller one above: the weights that are on shrink less
    on = plain > 0.3
    assert log[on].mean() > plain[on].mean()
    assert not antagonist_frames(excl[1:-1], head.shape_names, level=1e-3).any()
    assert antagonist_frames(log, head.shape_names, level=1e-3).mean() > 0.05
    with pytest.raises(InputError, match="need weight_bounds from 0"):
        from rigbuild.retarget.params import seol_from_config

        seol_from_config({"sparsity_mode": "log"})


def test_stage_job_runs_the_options_from_the_config_block(tmp_path):
    """``params.retarget.ribera`` with the options reaches the solve (rule ``retarget_ribera``): the job's
    weights keep antagonists apart where the plain job does not, and the written params record the options."""
    import json

    from rigbuild.assets.head import procedural_head_rig
    from rigbuild.io.curves import read_weight_curves_csv
    from rigbuild.io.markers import write_markers_npz
    from rigbuild.io.rigs import write_rig_npz
    from rigbuild.retarget.stage import run_ribera, run_seol

    rig = procedural_head_rig()
    names = rig.marker_names
    ds = rig.deltas[:, rig.marker_vertices]
    rom = rig.markers()[None] + np.concatenate([np.zeros((1,) + ds.shape[1:]), ds])
    rng = np.random.default_rng(0)
    W = np.zeros((120, rig.n_shapes))
    k = rig.shape_names.index("jawLeft")
    W[:, k] = 0.5 * (1 - np.cos(np.linspace(0, 2 * np.pi, 120)))
    perf = rig.markers(rig.evaluate(W)) + 0.3 * rng.normal(size=(120, len(names), 3))
    write_markers_npz(tmp_path / "rom.npz", rom, names, 60.0)
    write_markers_npz(tmp_path / "perf.npz", perf, names, 60.0)
    write_rig_npz(tmp_path / "char.npz", rig)
    out = {}
    for label, block in (("plain", {"lambda_cm": 0.006}), ("plausible", {"lambda_cm": 0.006, **PLAUSIBLE})):
        d = tmp_path / label
        paths = {k: str(d / f) for k, f in (("weights", "w.csv"), ("weights_json", "w.json"), ("gltf", "a.gltf"),
                                            ("preview", "p.png"), ("metrics", "m.json"))}
        run_ribera(str(tmp_path / "perf.npz"), [str(tmp_path / "rom.npz")], str(tmp_path / "char.npz"), "rbf", "head",
                   "perf", block, [0], **paths)
        w, shape_names, _ = read_weight_curves_csv(paths["weights"])
        out[label] = (w, json.loads((d / "w.json").read_text()))
    both = {k: antagonist_frames(w, shape_names, level=1e-3).mean() for k, (w, _) in out.items()}
    assert both["plain"] > 0.2 and both["plausible"] == 0.0
    assert out["plausible"][1]["meta"]["params"]["sparsity"] == "log"
    assert out["plausible"][1]["meta"]["params"]["antagonists"] is True
    assert out["plain"][1]["meta"]["params"]["sparsity"] == "l1"
    # the fragments carry the numbers a real capture is judged by (report gates): plausibility and residual
    for label in out:
        frag = json.loads((tmp_path / label / "m.json").read_text())["retarget"]["rbf_baseline"]["head"]
        assert 0.0 <= frag["antagonist_fraction"] <= 1.0
        if label == "plausible":
            assert frag["antagonist_fraction"] == 0.0
        assert 0.1 < frag["marker_residual_mm"] < 1.0  # the 0.3 mm marker noise, per coordinate
        assert frag["mean_active"] > 0
    seol = {k: str(tmp_path / "seol" / f) for k, f in (("weights", "w.csv"), ("weights_json", "w.json"),
                                                        ("gltf", "a.gltf"), ("plot", "v.png"), ("metrics", "m.json"),
                                                        ("system", "s.npz"))}
    run_seol(str(tmp_path / "perf.npz"), str(tmp_path / "char.npz"), [str(tmp_path / "rom.npz")], [0], "head", "perf",
             {"weight_bounds": [0, 1.5], "sparsity": 0.5, "sparsity_mode": "log", "antagonists": True}, **seol)
    frag = json.loads((tmp_path / "seol" / "m.json").read_text())["retarget"]["seol"]["head"]
    assert frag["antagonist_fraction"] == 0.0 and 0.1 < frag["marker_residual_mm"] < 1.0
