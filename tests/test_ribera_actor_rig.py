"""Ribera's E_Align from the actor's personalized rig (method ``ribera_fit_actor_rig``, issue 26): the initial
guesses g_k are the rig's shapes sampled at the markers and rotated into the actor's marker space (exact on an
analytic rig, with and without a rotation), the transfer starts from and is held to them, the stage reads the
rig and the marker map, and only this method's jobs depend on the personalized rig in the DAG."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from grid_mesh import grid_mesh
from dry_run import jobs_after_touching_the_personalized_rig
from rigbuild.errors import InputError
from rigbuild.retarget import ribera as rb
from rigbuild.retarget.actor_rig import MarkerMap, sample_rig_at_markers, vertex_marker_map
from rigbuild.retarget.methods import METHOD_KEYS, RIBERA_ACTOR_RIG_METHOD, RIBERA_METHODS, RIBERA_TEMPLATE_RIG_METHOD
from rigbuild.rig import Rig


def _grid(n: int = 7, spacing: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """A flat n x n grid (mm) in z = 0 (:func:`grid_mesh.grid_mesh`): vertices (n*n, 3), faces (2(n-1)^2, 3)."""
    return grid_mesh(n, spacing * (n - 1))


def _affine_rig(seed: int = 0):
    """A grid rig whose shape offsets are affine in the position, ``delta_k(x) = A_k x + c_k`` (mm), so the
    barycentric blend at any skin point p is exactly ``A_k p + c_k``; 6 markers on triangles with random
    barycentric coordinates and no normal offset. Returns V, faces, deltas (K, V, 3), A (K, 3, 3), c (K, 3),
    the marker map and the markers' skin points (M, 3)."""
    rng = np.random.default_rng(seed)
    V, faces = _grid()
    K = 4
    A = rng.normal(scale=0.05, size=(K, 3, 3))
    c = rng.normal(scale=2.0, size=(K, 3))
    deltas = np.einsum("kij,vj->kvi", A, V) + c[:, None]
    fid = rng.choice(faces.shape[0], size=6, replace=False)
    bary = rng.dirichlet(np.ones(3), size=6)
    mmap = MarkerMap([f"m{i}" for i in range(6)], fid, bary, np.zeros(6))
    points = np.einsum("mj,mjc->mc", bary, V[faces[fid]])
    return V, faces, deltas, A, c, mmap, points


@pytest.mark.parametrize("rotation", ["identity", "known"])
def test_guesses_are_the_rig_deltas_at_the_markers_rotated_into_the_actor_frame(rotation):
    V, faces, deltas, A, c, mmap, points = _affine_rig()
    b0, D = sample_rig_at_markers(V, deltas, faces, mmap)
    np.testing.assert_allclose(b0, points, atol=1e-12)
    np.testing.assert_allclose(D, np.einsum("kij,mj->kmi", A, points) + c[:, None], atol=1e-12)
    R = np.eye(3) if rotation == "identity" else Rotation.from_rotvec([0.3, -0.8, 0.5]).as_matrix()
    t = np.array([12.0, -40.0, 300.0])
    # the actor's marker space: another marker order, one marker the map lacks ("extra"), the capture frame
    order = [3, 0, 5, 1, 4, 2]
    names = [f"m{i}" for i in order] + ["extra"]
    a0 = np.vstack([points[order] @ R.T + t, [[5.0, 5.0, 5.0]]])
    rig = rb.RigAtMarkers(b0, D, list(mmap.names), ["s0", "s1", "s2", "s3"])
    shape_names = ["s2", "other", "s0", "s3", "s1"]  # the character's order; "other" is not in the rig
    g = rb.rig_marker_guesses(rig, a0[:-1], names[:-1], shape_names)  # every marker on the map: exact
    np.testing.assert_allclose(g.rotation, R, atol=1e-10)
    assert g.alignment_rms_mm < 1e-9
    rig_k = {"s0": 0, "s1": 1, "s2": 2, "s3": 3}
    for j, name in enumerate(shape_names):
        if name in rig_k:
            k = rig_k[name]
            expected = (np.einsum("ij,mj->mi", A[k], points[order]) + c[k]) @ R.T  # R (A_k p + c_k)
            np.testing.assert_allclose(g.dg[j], expected, atol=1e-10)
        else:
            assert not g.shapes[j] and np.all(g.dg[j] == 0)
    assert g.shapes.tolist() == [True, False, True, True, True] and g.markers.all()
    # a marker the map lacks: the rotation from the shared ones, the guess there comes from the fallback
    g2 = rb.rig_marker_guesses(rig, a0, names, shape_names)
    assert g2.markers.tolist() == [True] * 6 + [False]
    np.testing.assert_allclose(g2.rotation, R, atol=1e-10)
    np.testing.assert_allclose(g2.dg[:, :6], g.dg, atol=1e-10)
    fallback = np.full(g2.dg.shape, 7.0)
    dg = rb.combine_guesses(g2, fallback)
    np.testing.assert_allclose(dg[np.ix_(g2.shapes, g2.markers)], g2.dg[np.ix_(g2.shapes, g2.markers)])
    assert np.all(dg[1] == 7.0) and np.all(dg[:, 6] == 7.0)
    with pytest.raises(InputError, match="no other guess"):
        rb.combine_guesses(g2, None)
    with pytest.raises(InputError, match="only 2 of the 3 markers"):
        rb.rig_marker_guesses(rig, a0[[0, 1, 6]], [names[0], names[1], "extra"], shape_names)


def _actor_and_character(scale: float = 1.5):
    """A grid character with four bump shapes and the actor: the same face whose shapes move ``scale`` x as much
    (its personalized rig), markers on every other vertex."""
    V, faces = _grid(9)
    deltas = np.zeros((4, V.shape[0], 3))
    for k, (cx, cy) in enumerate([(20, 20), (60, 20), (20, 60), (60, 60)]):
        inside = (V[:, 0] - cx) ** 2 + (V[:, 1] - cy) ** 2 <= 15.0**2
        deltas[k, inside, k % 2] = 5.0
    mk = np.array([i * 9 + j for i in range(0, 9, 2) for j in range(0, 9, 2)])
    names = [f"m{i}" for i in range(mk.size)]
    shapes = [f"s{k}" for k in range(4)]
    character = Rig(V, deltas, shapes, faces, name="grid", marker_names=names, marker_vertices=mk)
    actor = Rig(V, scale * deltas, shapes, faces, name="actor", marker_names=names, marker_vertices=mk)
    return character, actor


def _rom(actor: Rig, R: np.ndarray, t: np.ndarray, n_frames: int = 24) -> np.ndarray:
    """The actor's ROM markers (F, M, 3) in a capture frame ``x -> R x + t``: frame 0 neutral, then each shape
    alone at full strength and with a second one at half."""
    rng = np.random.default_rng(3)
    K = actor.n_shapes
    W = np.zeros((n_frames, K))
    for f in range(1, n_frames):
        W[f, f % K] = 1.0
        W[f, (f + 1 + rng.integers(K - 1)) % K] = 0.5
    return actor.markers(actor.evaluate(W)) @ R.T + t


def test_transfer_starts_from_and_keeps_the_personalized_rig():
    """When the personalized rig is the actor's true rig, ribera_fit_actor_rig's guesses are its shapes in the
    capture frame and the ROM alignment leaves them there; ribera_fit from the character does not get there."""
    from rigbuild.retarget.run import make_training_set, prepare_model

    character, actor = _actor_and_character(1.5)
    R, t = Rotation.from_rotvec([0.1, 0.4, -0.2]).as_matrix(), np.array([5.0, 80.0, 900.0])
    rom = _rom(actor, R, t)
    names = list(character.marker_names)
    ts = make_training_set([rom], [names], [0])
    mmap = vertex_marker_map(names, actor.marker_vertices, actor.faces)
    b0, D = sample_rig_at_markers(actor.neutral, actor.deltas, actor.faces, mmap)
    rig = rb.RigAtMarkers(b0, D, names, list(actor.shape_names))
    tp = rb.TransferParams(guess="rbf", fit_lambda_cm=0.0, fit_mu=0.0)
    truth = actor.deltas[:, actor.marker_vertices] @ R.T  # the actor's shapes in the capture frame
    model = prepare_model(ts, character, names, character.marker_vertices, RIBERA_ACTOR_RIG_METHOD, tp,
                          rb.RetargetParams(bounds=(0.0, 1.0)), actor_rig=rig)
    np.testing.assert_allclose(model.transfer.dg, truth, atol=1e-8)
    assert model.transfer.info["rig_guess_shapes"] == 4 and model.transfer.info["rig_alignment_rms_mm"] < 1e-8
    err = np.abs(model.dp - truth).max()
    assert err < 1e-3, err
    plain = prepare_model(ts, character, names, character.marker_vertices, "ribera_fit", tp,
                          rb.RetargetParams(bounds=(0.0, 1.0)))
    assert np.abs(plain.dp - truth).max() > 100 * max(err, 1e-6)
    with pytest.raises(InputError, match="needs its rig at the markers"):
        prepare_model(ts, character, names, character.marker_vertices, RIBERA_ACTOR_RIG_METHOD, tp)


def test_template_rig_guesses_read_the_rom_whatever_the_character_looks_like():
    """ribera_fit_template_rig: the guesses come from the template rig (the actor's semantics, not its amplitude),
    so a character whose shapes move other regions in other directions (a sculpted one) does not decide how the ROM
    is read: the transfer ends near the actor's shapes, where ribera_fit from that character's shapes does not."""
    from rigbuild.retarget.run import make_training_set, prepare_model

    template, actor = _actor_and_character(1.5)
    V, faces = template.neutral, template.faces
    sculpted = Rig(V, np.roll(template.deltas, 1, axis=0)[..., [2, 0, 1]], list(template.shape_names), faces,
                   name="sculpted", marker_names=list(template.marker_names), marker_vertices=template.marker_vertices)
    R, t = Rotation.from_rotvec([0.1, 0.4, -0.2]).as_matrix(), np.array([5.0, 80.0, 900.0])
    names = list(template.marker_names)
    ts = make_training_set([_rom(actor, R, t)], [names], [0])
    mmap = vertex_marker_map(names, template.marker_vertices, faces)
    b0, D = sample_rig_at_markers(V, template.deltas, faces, mmap)
    tp = rb.TransferParams(guess="rbf", fit_lambda_cm=0.0, fit_mu=0.0)
    rp = rb.RetargetParams(bounds=(0.0, 1.0))
    truth = actor.deltas[:, actor.marker_vertices] @ R.T
    model = prepare_model(ts, sculpted, names, sculpted.marker_vertices, RIBERA_TEMPLATE_RIG_METHOD, tp, rp,
                          actor_rig=rb.RigAtMarkers(b0, D, names, list(template.shape_names)))
    np.testing.assert_allclose(model.transfer.dg, template.deltas[:, template.marker_vertices] @ R.T, atol=1e-8)
    assert model.transfer.info["rig_guess_shapes"] == 4
    err = np.abs(model.dp - truth).max()
    plain = prepare_model(ts, sculpted, names, sculpted.marker_vertices, "ribera_fit", tp, rp)
    err_plain = np.abs(plain.dp - truth).max()
    guess_err = np.abs(model.transfer.dg - truth).max()  # the template moves 5 mm where the actor moves 7.5
    assert err < 0.6 * guess_err and err_plain > 5 * err, (err, guess_err, err_plain)


class _Named(dict):
    """A stand-in for snakemake's Namedlist (attribute and .get access)."""

    __getattr__ = dict.__getitem__


def test_entry_point_reads_the_personalized_rig_and_the_marker_map(tmp_path):
    import runpy
    import types

    from rigbuild.io.curves import read_weight_curves_csv
    from rigbuild.io.markers import write_markers_npz
    from rigbuild.io.rigs import write_rig_npz

    character, actor = _actor_and_character(1.5)
    R, t = Rotation.from_rotvec([0.0, 0.3, 0.1]).as_matrix(), np.array([0.0, 50.0, 700.0])
    names = list(character.marker_names)
    write_markers_npz(tmp_path / "rom.npz", _rom(actor, R, t), names, 30.0)
    W = np.random.default_rng(0).uniform(0, 1, size=(10, 4))
    write_markers_npz(tmp_path / "perf.npz", actor.markers(actor.evaluate(W)) @ R.T + t, names, 30.0)
    write_rig_npz(tmp_path / "char.npz", character)
    write_rig_npz(tmp_path / "rig.npz", actor)
    mmap = vertex_marker_map(names, actor.marker_vertices, actor.faces)
    (tmp_path / "marker_map.json").write_text(json.dumps({"markers": mmap.to_json()}))
    out = {k: str(tmp_path / "out" / f) for k, f in (("weights", "weights.csv"), ("weights_json", "weights.json"),
                                                      ("gltf", "animation.gltf"), ("preview", "preview.png"),
                                                      ("metrics", "retarget_metrics.json"))}

    def job(**inputs):
        return types.SimpleNamespace(
            input=_Named(performance=str(tmp_path / "perf.npz"), training=[str(tmp_path / "rom.npz")],
                         rig=str(tmp_path / "char.npz"), **inputs),
            output=_Named(**out),
            params=_Named(ribera={"mu": 0.0, "lambda_cm": 0.0, "fit_lambda_cm": 0.0, "preview_frames": 2,
                                  "guess": "rbf", "fit_guess": "rbf"},
                          method=RIBERA_ACTOR_RIG_METHOD, character="grid", performance="perf00", neutral_frames=[0]),
            log=[str(tmp_path / "log.txt")], rule="retarget_ribera", threads=1)

    from rigbuild.retarget.stage import run_ribera

    def direct(**inputs):  # the stage function itself: its InputError, not the entry point's exit
        sm = job()
        return run_ribera(sm.input.performance, sm.input.training, sm.input.rig, RIBERA_ACTOR_RIG_METHOD, "grid",
                          "perf00", sm.params.ribera, [0], **out, **inputs)

    with pytest.raises(InputError, match="needs its rig and the take's marker map on it"):
        direct()
    sm = job(guess_rig=[str(tmp_path / "rig.npz")], marker_map=[str(tmp_path / "marker_map.json")])
    sm.params["guess_rig"] = str(tmp_path / "rig.npz")
    runpy.run_path("scripts/retarget.py", init_globals={"snakemake": sm})
    w, _, _ = read_weight_curves_csv(out["weights"])
    # the job is the library's ribera_fit_actor_rig with the rig at the map's markers (in the rig's frame)
    from rigbuild.retarget.params import ribera_from_config
    from rigbuild.retarget.run import make_training_set, retarget_performance

    p = ribera_from_config(job().params.ribera)
    ts = make_training_set([_rom(actor, R, t)], [names], [0])
    b0, D = sample_rig_at_markers(actor.neutral, actor.deltas, actor.faces, mmap)
    ref = retarget_performance(ts, actor.markers(actor.evaluate(W)) @ R.T + t, names, character, names,
                               character.marker_vertices, RIBERA_ACTOR_RIG_METHOD,
                               p.transfer_params(RIBERA_ACTOR_RIG_METHOD), p.retarget_params(RIBERA_ACTOR_RIG_METHOD),
                               actor_rig=rb.RigAtMarkers(b0, D, names, list(actor.shape_names)))
    np.testing.assert_allclose(w, ref.weights, atol=1e-5)
    for k in range(4):  # the actor's own shapes explain its performance (up to the ROM fit's E_Prior growth)
        assert np.corrcoef(w[:, k], W[:, k])[0, 1] > 0.99
    meta = json.loads(Path(out["weights_json"]).read_text())["meta"]
    assert meta["actor_rig"] == str(tmp_path / "rig.npz") and meta["marker_map"] == str(tmp_path / "marker_map.json")
    frag = json.loads(Path(out["metrics"]).read_text())["retarget"]
    assert list(frag) == [METHOD_KEYS[RIBERA_ACTOR_RIG_METHOD]] == ["ribera_fit_actor_rig"]
    assert frag["ribera_fit_actor_rig"]["grid"]["rig_guess_shapes"] == 4
    assert frag["ribera_fit_actor_rig"]["grid"]["rig_guess_markers"] == len(names)
    # a marker map on another mesh is refused by name
    bad = {n: {**v, "face": 10**6} for n, v in mmap.to_json().items()}
    (tmp_path / "bad.json").write_text(json.dumps({"markers": bad}))
    with pytest.raises(InputError, match="triangles outside"):
        direct(actor_rig=str(tmp_path / "rig.npz"), marker_map=str(tmp_path / "bad.json"))


# ------------------------------------------------------------------------------------------ the DAG
def test_touching_the_personalized_rig_replans_only_the_jobs_that_read_it(tmp_path):
    """Every file of the demo's DAG of the Ribera jobs (every method, two characters) made up to date at one
    time, then personalize/rig.npz touched: a dry run with ``--rerun-triggers mtime`` plans the marker map
    (actor_rig_weights) and the ribera_fit_actor_rig jobs, and no other Ribera method's job."""
    characters = ["template", "stylized"]
    targets = [f"results/demo/retarget/{m}/perf00/{c}/weights.csv" for m in RIBERA_METHODS for c in characters]
    jobs = jobs_after_touching_the_personalized_rig(tmp_path, targets)
    planned = sorted((w["method"], w["character"]) for r, w in jobs if r == "retarget_ribera")
    assert planned == sorted((RIBERA_ACTOR_RIG_METHOD, c) for c in characters)
    others = sorted({r for r, w in jobs if r != "retarget_ribera"})
    assert others == ["actor_rig_weights"], others
    assert [w["source"] for r, w in jobs if r == "actor_rig_weights"] == ["actor_rig"]