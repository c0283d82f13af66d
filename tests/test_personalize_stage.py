"""The personalization stage end to end on a small synthetic session (tracked = ground-truth meshes)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rigbuild.errors import InputError
from rigbuild.io.atomic import save_npz
from rigbuild.io.gltf import read_gltf_rig
from rigbuild.io.rigs import read_obj_folder_rig, read_rig_npz, write_rig_npz
from rigbuild.personalize.stage import neutral_frame_mask, run_personalization, split_params
from rigbuild.rig import Rig

from test_personalize_em import scene

NAMES = ["browUp", "smile", "jawOpen", "cheekPuff"]


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("pz")
    verts, faces, D0, actor, W, Rs, ts, seq, frames = scene()
    template = Rig(verts, D0, NAMES, faces, name="template")
    sess = root / "session"
    gt = sess / "ground_truth"
    write_rig_npz(gt / "actor_rig.npz", Rig(verts, actor, NAMES, faces, name="actor"))
    tracks = {}
    for s in np.unique(seq):
        name = f"rom{s:02d}"
        sel = seq == s
        fr = np.arange(sel.sum())
        save_npz(gt / "rom" / f"{name}.npz", vertices=frames[sel].astype(np.float32), weights=W[sel].astype(np.float32),
                 shape_names=np.asarray(NAMES), frames=fr)
        p = root / "results" / "track" / name / "vertices.npz"
        save_npz(p, vertices=frames[sel].astype(np.float32), confidence=np.ones(frames[sel].shape[:2], np.float32),
                 frames=fr)
        tracks[name] = p
    cfg = {"held_out_sequences": ["rom05"], "lambda_r": 10.0, "lambda_d": 0.05, "lambda_unit_mm": 1.0, "support_tol_mm": 1e-6,
           "min_confident_vertices": 10, "max_iterations": 15}
    out = root / "results" / "personalize"
    metrics_path = root / "results" / "metrics.json"
    m = run_personalization(tracks, template, out, cfg, metrics_path, sess, {n: 0 for n in tracks})
    return dict(root=root, out=out, metrics=m, metrics_path=metrics_path, template=template, actor=actor,
                tracks=tracks, sess=sess)


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
    assert (out / "convergence.png").stat().st_size > 1000
    assert sorted(p.name for p in (out / "heatmaps").glob("*.png")) == sorted([f"{n}.png" for n in NAMES] + ["overview.png"])
    obj = json.loads((out / "objective.json").read_text())
    J = [o["total"] for o in obj["objective"]]
    assert np.all(np.diff(J) <= 1e-9 * J[0])


def test_metrics_against_ground_truth(session):
    m = session["metrics"]
    merged = json.loads(session["metrics_path"].read_text())["personalization"]
    for key in ("residual_reduction", "heldout_residual_reduction", "shape_error_reduction", "weight_mae",
                "min_shape_cosine"):
        assert key in merged and merged[key] == pytest.approx(m[key])
    assert m["objective_monotone"] is True
    assert m["residual_reduction"] >= 0.5
    assert m["heldout_residual_reduction"] >= 0.4
    assert m["shape_error_reduction"] >= 0.3
    assert m["weight_mae"] <= 0.05
    assert m["min_shape_cosine"] >= 0.9


def test_bad_inputs_name_the_problem(session, tmp_path):
    t = session["template"]
    bad = tmp_path / "vertices.npz"
    save_npz(bad, vertices=np.zeros((3, t.n_vertices - 1, 3), np.float32))
    tracks = dict(session["tracks"])
    tracks["rom00"] = bad
    with pytest.raises(InputError, match="topology differs") as e:
        run_personalization(tracks, t, tmp_path / "out", {"min_confident_vertices": 10})
    assert str(bad) in str(e.value)
    with pytest.raises(InputError, match="unknown key"):
        split_params({"lambda_x": 1})
    with pytest.raises(InputError, match="held-out sequence"):
        run_personalization(session["tracks"], t, tmp_path / "out", {"held_out_sequences": ["nope"]})
    params, _ = split_params({"gauge": "rom_peak", "gauge_max_weight": 2.5})
    assert params.gauge == "rom_peak" and params.gauge_max_weight == 2.5
    with pytest.raises(InputError, match="unknown gauge 'peak'"):
        run_personalization(session["tracks"], t, tmp_path / "out", {"gauge": "peak", "min_confident_vertices": 10})


def test_tracks_in_a_rotated_world_get_rotated_initial_shapes(tmp_path):
    """Tracked meshes in the calibrated cameras' world (here turned 160 degrees about y and moved, as a camera
    facing the actor is): D* is the template's shapes turned into that world (deformation gradients are in world
    axes, so an unaligned transfer would move the mouth along the template's axes), and the fit is as good as
    in the template's own world."""
    import cv2

    verts, faces, D0, actor, W, Rs, ts, seq, frames = scene()
    template = Rig(verts, D0, NAMES, faces, name="template")
    R = cv2.Rodrigues(np.array([0.0, 1.0, 0.1]) / np.linalg.norm([0.0, 1.0, 0.1]) * np.radians(160))[0]
    t = np.array([5.0, -20.0, 450.0])
    tracks = {}
    for s in np.unique(seq)[:3]:
        sel = seq == s
        p = tmp_path / "track" / f"rom{s:02d}" / "vertices.npz"
        save_npz(p, vertices=(frames[sel] @ R.T + t).astype(np.float32),
                 confidence=np.ones(frames[sel].shape[:2], np.float32), frames=np.arange(sel.sum()))
        tracks[p.parent.name] = p
    cfg = {"lambda_r": 10.0, "lambda_d": 0.05, "lambda_unit_mm": 1.0, "support_tol_mm": 1e-6, "min_confident_vertices": 10,
           "max_iterations": 5}
    m = run_personalization(tracks, template, tmp_path / "out", cfg, None, None, {n: 0 for n in tracks})
    initial = read_rig_npz(tmp_path / "out" / "initial_rig.npz")
    Dw = D0 @ R.T
    cos = [float(np.sum(a * b) / (np.linalg.norm(a) * np.linalg.norm(b))) for a, b in zip(initial.deltas, Dw)]
    assert min(cos) > 0.97, cos
    assert m["residual_reduction"] >= 0.5


def test_neutral_frame_mask_marks_each_sequences_named_neutral_frame():
    data = {"a": {"vertices": np.zeros((4, 2, 3)), "frames": np.array([10, 11, 12, 13])},
            "b": {"vertices": np.zeros((3, 2, 3)), "frames": None},
            "c": {"vertices": np.zeros((2, 2, 3)), "frames": np.array([0, 1])}}
    m = neutral_frame_mask(data, ["a", "b", "c"], {"a": 11, "b": 0})
    np.testing.assert_array_equal(m, [False, True, False, False, True, False, False, False, False])
    assert not neutral_frame_mask(data, ["a"], None).any()
