"""The personalization stage end to end on a small synthetic session (tracked = ground-truth meshes), and its
ground-truth evaluation (rule eval_personalize) on the stage's outputs."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from rigbuild.errors import InputError
from rigbuild.eval.personalization import evaluate_personalization, run_eval_personalize
from rigbuild.io.atomic import save_npz
from rigbuild.io.gltf import read_gltf_rig
from rigbuild.io.rigs import read_obj_folder_rig, read_rig_npz
from rigbuild.personalize.params import PersonalizeConfig, from_config
from rigbuild.personalize.stage import neutral_frame_mask, run_personalization
from rigbuild.rig import Rig

from personalize_scene import write_tracked_session
from test_personalize_em import scene

NAMES = ["browUp", "smile", "jawOpen", "cheekPuff"]
#: the ground-truth keys of personalization.* (written by rule eval_personalize, never by the stage)
GT_KEYS = {"shape_error_initial_mm", "shape_error_final_mm", "shape_error_reduction", "shape_error_initial_raw_mm",
           "shape_error_final_raw_mm", "shape_error_reduction_raw", "shape_scale_p10", "shape_scale_median",
           "shape_scale_p90", "weight_mae", "weight_mae_raw", "min_shape_cosine", "min_shape_cosine_initial",
           "mean_shape_cosine", "heldout_weight_mae", "heldout_weight_mae_raw",
           "expression_error_initial_mm", "expression_error_final_mm", "expression_error_reduction",
           "heldout_expression_error_initial_mm", "heldout_expression_error_final_mm",
           "heldout_expression_error_reduction"}
CFG = {"lambda_r": 10.0, "lambda_d": 0.05, "lambda_unit_mm": 1.0, "support_tol_mm": 1e-6, "min_confident_vertices": 10}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("pz")
    verts, faces, D0, actor, W, Rs, ts, seq, frames = scene()
    template = Rig(verts, D0, NAMES, faces, name="template")
    s = write_tracked_session(root, template, actor, W, seq, frames)
    out = root / "results" / "personalize"
    m = run_personalization(s["tracks"], template, out, {"held_out_sequences": ["rom05"], "max_iterations": 15, **CFG},
                            {n: 0 for n in s["tracks"]})
    metrics_path = root / "results" / "eval" / "personalization_metrics.json"
    gt = run_eval_personalize(s["gt"], out / "weights.npz", out / "fit.npz", None, metrics_path)
    return dict(root=root, out=out, metrics=m, gt=gt, metrics_path=metrics_path, template=template, actor=actor,
                tracks=s["tracks"], sess=s["session"])


def test_outputs_exist_and_reload(session):
    out = session["out"]
    rig = read_rig_npz(out / "rig.npz")
    assert rig.shape_names == NAMES and rig.n_vertices == session["template"].n_vertices
    with np.load(out / "rig.npz") as z:
        assert {"neutral", "deltas", "shape_names", "faces"} <= set(z.files)
    obj = read_obj_folder_rig(out / "rig_obj")
    np.testing.assert_allclose(obj.deltas, rig.deltas, atol=1e-4)
    g = read_gltf_rig(out / "rig.gltf")
    assert g.shape_names == NAMES
    np.testing.assert_allclose(g.deltas, rig.deltas, atol=1e-3)
    with np.load(out / "weights.npz") as z:
        assert z["weights"].shape == (60, 4) and z["rotation"].shape == (60, 3, 3)
        assert z["heldout_weights"].shape == (12, 4)
        assert set(z["sequence"]) == {f"rom{s:02d}" for s in range(5)}
        np.testing.assert_array_equal(z["heldout_frame"], np.arange(12))
    M = np.asarray(json.loads((out / "head_frame.json").read_text())["capture_to_head"])
    with np.load(out / "fit.npz") as z:  # the fit in the capture frame, the rig files in the head frame
        assert z["deltas"].dtype == np.float64 and z["weights"].shape == (60, 4)
        np.testing.assert_allclose(z["deltas"] @ M[:3, :3].T, rig.deltas, atol=1e-4)
    assert (out / "convergence.png").stat().st_size > 1000
    assert sorted(p.name for p in (out / "heatmaps").glob("*.png")) == sorted([f"{n}.png" for n in NAMES] + ["overview.png"])
    obj = json.loads((out / "objective.json").read_text())
    J = [o["total"] for o in obj["objective"]]
    assert np.all(np.diff(J) <= 1e-9 * J[0])


def test_stage_fragment_has_no_ground_truth_keys_and_the_evaluation_has_them(session):
    fragment = json.loads((session["out"] / "personalize_metrics.json").read_text())
    assert set(fragment) == {"personalization"}
    stage = fragment["personalization"]
    assert stage == pytest.approx(session["metrics"])
    assert not GT_KEYS & set(stage)
    assert {"residual_reduction", "heldout_residual_reduction", "objective_monotone"} <= set(stage)
    ev = json.loads(session["metrics_path"].read_text())
    assert set(ev) == {"personalization"} and set(ev["personalization"]) == GT_KEYS
    assert ev["personalization"] == pytest.approx(session["gt"])


def test_metrics_against_ground_truth(session):
    m, gt = session["metrics"], session["gt"]
    assert m["objective_monotone"] is True
    obj = json.loads((session["out"] / "objective.json").read_text())["objective"]
    assert m["residual_final_mm"] == obj[-1]["rms_unweighted_mm"]
    assert m["residual_final_weighted_mm"] == obj[-1]["rms_mm"]
    assert m["residual_reduction"] >= 0.5
    assert m["heldout_residual_reduction"] >= 0.4
    assert gt["shape_error_reduction_raw"] >= 0.3
    # the rigs posed by their own fits against the true meshes (the tracked frames here are the truth)
    assert gt["expression_error_final_mm"] < gt["expression_error_initial_mm"]
    assert gt["expression_error_reduction"] >= 0.5 and gt["heldout_expression_error_reduction"] >= 0.4
    assert gt["weight_mae_raw"] <= 0.05
    assert gt["min_shape_cosine"] >= 0.9


def test_residuals_are_headlined_unweighted_with_the_weighted_ones_beside():
    """``residual_*`` are the plain RMS over the confident vertices (objective.json's ``rms_unweighted_mm``),
    ``*_weighted`` the confidence-weighted RMS of the EM's data term (``rms_mm``); same for held-out frames.
    Confidences below 1 on half the vertices make the two differ."""
    from rigbuild.personalize.em import PersonalizationResult
    from rigbuild.personalize.stage import stage_metrics

    obj = [{"iteration": 0, "total": 10.0, "rms_mm": 0.8, "rms_unweighted_mm": 1.0},
           {"iteration": 3, "total": 4.0, "rms_mm": 0.2, "rms_unweighted_mm": 0.5}]
    res = PersonalizationResult(neutral=np.zeros((3, 3)), deltas=np.zeros((1, 3, 3)), weights=np.zeros((2, 1)),
                                rotations=np.zeros((2, 3, 3)), translations=np.zeros((2, 3)),
                                kept=np.array([True, True]), objective=obj, residual_initial_mm=0.8,
                                residual_final_mm=0.2, residual_initial_unweighted_mm=1.0,
                                residual_final_unweighted_mm=0.5, n_free_variables=9,
                                timings={"total_s": 1.0, "qp_median_ms": 0.1})
    ho = {"initial": {"rms_mm": 0.4, "rms_unweighted_mm": 2.0}, "final": {"rms_mm": 0.1, "rms_unweighted_mm": 1.5}}
    m = stage_metrics(res, ho)
    assert m["residual_initial_mm"] == 1.0 and m["residual_final_mm"] == 0.5
    assert m["residual_reduction"] == pytest.approx(0.5)
    assert m["residual_initial_weighted_mm"] == 0.8 and m["residual_final_weighted_mm"] == 0.2
    assert m["residual_reduction_weighted"] == pytest.approx(0.75)
    assert m["heldout_residual_initial_mm"] == 2.0 and m["heldout_residual_final_mm"] == 1.5
    assert m["heldout_residual_reduction"] == pytest.approx(0.25)
    assert m["heldout_residual_initial_weighted_mm"] == 0.4 and m["heldout_residual_final_weighted_mm"] == 0.1
    assert m["heldout_residual_reduction_weighted"] == pytest.approx(0.75)
    assert not any(k.endswith("unweighted") or "_unweighted_" in k for k in m)


def test_evaluation_reads_only_the_declared_ground_truth(session, tmp_path):
    """Rule eval_personalize declares ground_truth/actor_rig.npz and rom/<seq>.npz (and cameras.json, read only
    with calibrated cameras): with a copy holding just those files the metrics are the same."""
    gt = tmp_path / "ground_truth"
    (gt / "rom").mkdir(parents=True)
    shutil.copy(session["sess"] / "ground_truth" / "actor_rig.npz", gt)
    for name in session["tracks"]:
        shutil.copy(session["sess"] / "ground_truth" / "rom" / f"{name}.npz", gt / "rom")
    out = session["out"]
    assert evaluate_personalization(gt, out / "weights.npz", out / "fit.npz") == session["gt"]


def test_stage_code_never_reads_ground_truth():
    root = Path(__file__).resolve().parents[1]
    files = sorted((root / "rigbuild" / "personalize").glob("*.py")) + [root / "scripts" / "personalize.py"]
    for f in files:
        text = f.read_text()
        assert not re.search(r"rigbuild\.(eval|synth)\b|ground_truth", text), f


def test_unknown_key_fails_with_did_you_mean():
    with pytest.raises(InputError, match=r"unknown key 'params.personalize.lamda_s' \(did you mean 'lambda_s'\?\)"):
        from_config({"lamda_s": 0.1})
    with pytest.raises(InputError, match=r"'params.personalize.held_out_sequence' \(did you mean 'held_out_sequences'"):
        from_config({"held_out_sequence": ["rom05"]})


def test_params_are_typed_and_checked():
    cfg = from_config({"gauge": "rom_peak", "gauge_max_weight": 2.5, "held_out_sequences": ["rom11"],
                       "template_rig": "ict"})
    assert isinstance(cfg, PersonalizeConfig)
    assert cfg.em.gauge == "rom_peak" and cfg.em.gauge_max_weight == 2.5
    assert cfg.held_out_sequences == ("rom11",) and cfg.template_rig == "ict" and cfg.fit_region == "face"
    assert from_config(None) == PersonalizeConfig()
    for bad, msg in [({"gauge": "peak"}, "unknown gauge 'peak'"), ({"fit_region": "head"}, "unknown fit_region"),
                     ({"lambda_unit_mm": 0.0}, "lambda_unit_mm must be a positive"),
                     ({"lambda_unit_mm": -10.0}, "lambda_unit_mm must be a positive"),
                     ({"qp_method": "osqp"}, "unknown qp_method"), ({"gauge_max_weight": 0.5}, "gauge_max_weight"),
                     ({"held_out_sequences": "rom05"}, "held_out_sequences must be a list")]:
        with pytest.raises(InputError, match=msg):
            from_config(bad)


def test_bad_inputs_name_the_problem(session, tmp_path):
    t = session["template"]
    bad = tmp_path / "vertices.npz"
    save_npz(bad, vertices=np.zeros((3, t.n_vertices - 1, 3), np.float32))
    tracks = dict(session["tracks"])
    tracks["rom00"] = bad
    with pytest.raises(InputError, match="topology differs") as e:
        run_personalization(tracks, t, tmp_path / "out", {"min_confident_vertices": 10})
    assert str(bad) in str(e.value)
    with pytest.raises(InputError, match="held-out sequence"):
        run_personalization(session["tracks"], t, tmp_path / "out", {"held_out_sequences": ["nope"]})
    with pytest.raises(InputError, match="unknown gauge 'peak'"):
        run_personalization(session["tracks"], t, tmp_path / "out", {"gauge": "peak", "min_confident_vertices": 10})


def test_tracks_in_a_rotated_world_get_rotated_initial_shapes(tmp_path):
    """Tracked meshes in the calibrated cameras' world (here turned 160 degrees about y and moved, as a camera
    facing the actor is): D* is the template's shapes turned into that world (deformation gradients are in world
    axes, so an unaligned transfer would move the mouth along the template's axes), and the fit is as good as
    in the template's own world. The evaluation maps the shapes back with the cameras."""
    import cv2

    from rigbuild.camera import Camera, look_at

    verts, faces, D0, actor, W, Rs, ts, seq, frames = scene()
    template = Rig(verts, D0, NAMES, faces, name="template")
    R = cv2.Rodrigues(np.array([0.0, 1.0, 0.1]) / np.linalg.norm([0.0, 1.0, 0.1]) * np.radians(160))[0]
    t = np.array([5.0, -20.0, 450.0])
    cams = []
    for i, c in enumerate([(-200.0, 0.0, 500.0), (0.0, 50.0, 520.0), (200.0, 0.0, 500.0), (0.0, -150.0, 480.0)]):
        Rc, tc = look_at(np.array(c), np.zeros(3))
        cams.append(Camera(f"cam{i}", 640, 480, np.array([[800, 0, 320], [0, 800, 240], [0, 0, 1.0]]), np.zeros(5), Rc, tc))
    keep = seq < 3
    s = write_tracked_session(tmp_path, template, actor, W[keep], seq[keep], frames[keep], world=(R, t), cameras=cams)
    m = run_personalization(s["tracks"], template, tmp_path / "out", {"max_iterations": 5, **CFG},
                            {n: 0 for n in s["tracks"]})
    def cosines(A, B):
        return [float(np.sum(a * b) / (np.linalg.norm(a) * np.linalg.norm(b))) for a, b in zip(A, B)]

    with np.load(tmp_path / "out" / "fit.npz") as z:  # D* in the cameras' world
        assert min(cosines(z["initial_deltas"], D0 @ R.T)) > 0.97
    # the rig files are in the template's head frame: the shapes turned back, the neutral on the template's
    initial = read_rig_npz(tmp_path / "out" / "initial_rig.npz")
    assert min(cosines(initial.deltas, D0)) > 0.97
    rig = read_rig_npz(tmp_path / "out" / "rig.npz")
    assert np.abs(rig.neutral - verts).max() < 0.5
    assert min(cosines(rig.deltas, D0)) > 0.9
    assert m["residual_reduction"] >= 0.5
    out = tmp_path / "out"
    mapped = evaluate_personalization(s["gt"], out / "weights.npz", out / "fit.npz", s["cameras"])
    assert mapped["min_shape_cosine"] >= 0.9 and mapped["shape_error_reduction_raw"] > 0
    # the rigs are posed in the cameras' world and mapped into the ground truth's with the camera similarity
    assert mapped["expression_error_reduction"] >= 0.5 and mapped["expression_error_final_mm"] < 0.1
    unmapped = evaluate_personalization(s["gt"], out / "weights.npz", out / "fit.npz")
    assert unmapped["min_shape_cosine"] < mapped["min_shape_cosine"]


def test_neutral_frame_mask_marks_each_sequences_named_neutral_frame():
    data = {"a": {"vertices": np.zeros((4, 2, 3)), "frames": np.array([10, 11, 12, 13])},
            "b": {"vertices": np.zeros((3, 2, 3)), "frames": None},
            "c": {"vertices": np.zeros((2, 2, 3)), "frames": np.array([0, 1])}}
    m = neutral_frame_mask(data, ["a", "b", "c"], {"a": 11, "b": 0})
    np.testing.assert_array_equal(m, [False, True, False, False, True, False, False, False, False])
    assert not neutral_frame_mask(data, ["a"], None).any()
