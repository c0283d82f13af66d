"""Seol's movement matching from the actor's personalized rig (method ``seol_actor_rig``, issue 26): the source
neutral and expression space are the rig at the markers rotated into the take's frame (exact on an analytic rig),
so the scale map is shape by shape: identity when the actor rig is the character, and the driving weights come
back when the actor's shapes move more than the character's (which the neutral-guessed map cannot see); the stage
reads the rig and the marker map, and only this method's jobs depend on the personalized rig in the DAG."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dry_run import jobs_after_touching_the_personalized_rig
from grid_mesh import grid_mesh
from rigbuild.errors import InputError
from rigbuild.retarget.actor_rig import sample_rig_at_markers, vertex_marker_map
from rigbuild.retarget.methods import METHOD_KEYS, SEOL_ACTOR_RIG_METHOD, SEOL_METHOD, SEOL_METHODS
from rigbuild.retarget.ribera import RigAtMarkers
from rigbuild.retarget.seol import retarget_seol
from rigbuild.retarget.seol.actor_space import actor_expression_space, actor_space_blendshapes
from rigbuild.rig import Rig


class _Named(dict):
    """A stand-in for snakemake's Namedlist (attribute and .get access)."""

    __getattr__ = dict.__getitem__




def _dome(n: int = 9, spacing: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid (mm, :func:`grid_mesh.grid_mesh`) bent into a dome ``z = -0.004 (r^2)`` (markers not
    coplanar)."""
    V, faces = grid_mesh(n, spacing * (n - 1))
    c = (n - 1) * spacing / 2
    V[:, 2] = -0.004 * ((V[:, 0] - c) ** 2 + (V[:, 1] - c) ** 2)
    return V, faces


def _character_and_actor(scale: float = 1.5) -> tuple[Rig, Rig]:
    """A dome character with four bump shapes (each along its own axis) and the actor: the same face whose
    shapes move ``scale`` x as much (its personalized rig); markers on every other vertex."""
    V, faces = _dome()
    deltas = np.zeros((4, V.shape[0], 3))
    for k, (cx, cy) in enumerate([(20, 20), (60, 20), (20, 60), (60, 60)]):
        inside = (V[:, 0] - cx) ** 2 + (V[:, 1] - cy) ** 2 <= 15.0**2
        deltas[k, inside, k % 3] = 5.0
    mk = np.array([i * 9 + j for i in range(0, 9, 2) for j in range(0, 9, 2)])
    names = [f"m{i}" for i in range(mk.size)]
    shapes = [f"s{k}" for k in range(4)]
    character = Rig(V, deltas, shapes, faces, name="dome", marker_names=names, marker_vertices=mk)
    actor = Rig(V, scale * deltas, shapes, faces, name="actor", marker_names=names, marker_vertices=mk)
    return character, actor


def _rig_at_markers(actor: Rig) -> RigAtMarkers:
    names = list(actor.marker_names)
    mmap = vertex_marker_map(names, actor.marker_vertices, actor.faces)
    b0, D = sample_rig_at_markers(actor.neutral, actor.deltas, actor.faces, mmap)
    return RigAtMarkers(b0, D, names, list(actor.shape_names))


def _driving_weights(n_frames: int = 60) -> np.ndarray:
    """Smooth weights in [0, 1] starting and ending at neutral (F, 4)."""
    t = np.linspace(0.0, 1.0, n_frames)
    W = np.stack([np.sin(np.pi * t) ** 2 * (0.4 + 0.5 * np.sin(2 * np.pi * (k + 1) * t / 3) ** 2)
                  for k in range(4)], axis=1)
    return W


def test_actor_space_is_the_rig_at_the_markers_in_the_take_frame():
    character, actor = _character_and_actor(1.5)
    rig = _rig_at_markers(actor)
    R, t = Rotation.from_rotvec([0.2, -0.5, 0.3]).as_matrix(), np.array([10.0, -30.0, 800.0])
    order = [5, 0, 3] + [i for i in range(len(rig.marker_names)) if i not in (5, 0, 3)]
    names = [rig.marker_names[i] for i in order]
    Y = rig.neutral[order] @ R.T + t
    shape_names = ["s2", "other", "s0", "s3", "s1"]
    space = actor_expression_space(rig, Y, names, shape_names)
    np.testing.assert_allclose(space.rotation, R, atol=1e-10)
    np.testing.assert_allclose(space.translation, t, atol=1e-8)
    np.testing.assert_allclose(space.neutral, Y, atol=1e-8)
    assert space.alignment_rms_mm < 1e-9
    for j, name in enumerate(shape_names):
        if name == "other":
            assert not space.shapes[j] and np.all(space.deltas[j] == 0)
        else:
            np.testing.assert_allclose(space.deltas[j], rig.deltas[int(name[1])][order] @ R.T, atol=1e-10)
    # a character shape the rig lacks keeps the neutral-guessed map; without one that is refused
    guessed = np.full(space.deltas.shape, 7.0)
    dstar = actor_space_blendshapes(space, guessed)
    assert np.all(dstar[1] == 7.0)
    np.testing.assert_allclose(dstar[[0, 2, 3, 4]], space.deltas[[0, 2, 3, 4]])
    with pytest.raises(InputError, match="lacks some of the character's shapes"):
        actor_space_blendshapes(space, None)
    # a marker the map lacks: measured neutral there, the rig fitted on the others
    Y2 = np.vstack([Y, [[1.0, 2.0, 3.0]]])
    s2 = actor_expression_space(rig, Y2, names + ["extra"], ["s0"])
    assert s2.markers.tolist() == [True] * len(names) + [False]
    np.testing.assert_allclose(s2.neutral, Y2, atol=1e-8)


def _take(actor: Rig, W: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return actor.markers(actor.evaluate(W)) @ R.T + t


KW = dict(alpha=1e-9, boundary_values="perframe", head_refine_iterations=0, baselines=False)


def test_identity_map_when_the_actor_rig_is_the_character():
    """Actor rig == character: the shape-by-shape map is the identity (b* = the character's marker shapes in the
    take's frame) and the weights are the driving weights."""
    character, _ = _character_and_actor()
    R, t = Rotation.from_rotvec([0.1, 0.4, -0.2]).as_matrix(), np.array([5.0, 80.0, 900.0])
    W = _driving_weights()
    X = _take(character, W, R, t)
    Y = character.neutral[character.marker_vertices] @ R.T + t
    res = retarget_seol(X, character, source_neutral=Y, actor_rig=_rig_at_markers(character), **KW)
    np.testing.assert_allclose(res.system.B.T.reshape(4, -1, 3),
                               character.deltas[:, character.marker_vertices] @ R.T, atol=1e-9)
    assert res.actor_space.shapes.all() and res.actor_space.alignment_rms_mm < 1e-9
    # the same solve as the paper's calibration, whose neutral-fitted RBF is the identity here too
    np.testing.assert_allclose(res.weights, retarget_seol(X, character, source_neutral=Y, **KW).weights, atol=1e-8)
    np.testing.assert_allclose(res.weights, W, atol=1e-3)  # up to the spacetime system's Tikhonov ridge (1e-6)


def test_actor_rig_recovers_the_weights_the_neutral_guess_cannot():
    """The actor's shapes move 1.5 x the character's over the same neutral: the neutral-guessed map is the
    identity, so plain Seol returns ~1.5 x the weights; seol_actor_rig matches shape by shape and returns them."""
    character, actor = _character_and_actor(1.5)
    R, t = Rotation.from_rotvec([-0.3, 0.2, 0.1]).as_matrix(), np.array([0.0, 50.0, 700.0])
    W = _driving_weights()
    X = _take(actor, W, R, t)
    Y = actor.neutral[actor.marker_vertices] @ R.T + t
    ar = retarget_seol(X, character, source_neutral=Y, actor_rig=_rig_at_markers(actor), **KW)
    np.testing.assert_allclose(ar.weights, W, atol=1e-3)
    plain = retarget_seol(X, character, source_neutral=Y, **KW)
    assert plain.actor_space is None
    np.testing.assert_allclose(plain.weights, 1.5 * W, atol=2e-3)  # the guessed map is wrong by the actor's scale


def test_stage_reads_the_personalized_rig_and_the_marker_map(tmp_path):
    import runpy
    import types

    from rigbuild.io.curves import read_weight_curves_csv
    from rigbuild.io.markers import write_markers_npz
    from rigbuild.io.rigs import write_rig_npz
    from rigbuild.retarget.stage import run_seol

    character, actor = _character_and_actor(1.5)
    R, t = Rotation.from_rotvec([0.0, 0.3, 0.1]).as_matrix(), np.array([0.0, 50.0, 700.0])
    names = list(character.marker_names)
    W = _driving_weights()
    write_markers_npz(tmp_path / "rom.npz", _take(actor, np.zeros((3, 4)), R, t), names, 30.0)
    write_markers_npz(tmp_path / "perf.npz", _take(actor, W, R, t), names, 30.0)
    write_rig_npz(tmp_path / "char.npz", character)
    write_rig_npz(tmp_path / "rig.npz", actor)
    mmap = vertex_marker_map(names, actor.marker_vertices, actor.faces)
    (tmp_path / "marker_map.json").write_text(json.dumps({"markers": mmap.to_json()}))
    seol = {"alpha": 1e-9, "boundary_values": "perframe", "head_refine_iterations": 0,
            "actor_rig": {"sobolev_corner_hz": 2.0}}  # what seol_actor_rig runs with instead

    def outputs(method):
        return {k: str(tmp_path / method / f) for k, f in
                (("weights", "weights.csv"), ("weights_json", "weights.json"), ("gltf", "animation.gltf"),
                 ("plot", "velocity_error.png"), ("metrics", "retarget_metrics.json"), ("system", "system.npz"))}

    def job(method, **inputs):
        return types.SimpleNamespace(
            input=_Named(performance=str(tmp_path / "perf.npz"), rig=str(tmp_path / "char.npz"),
                         neutral=[str(tmp_path / "rom.npz")], **inputs),
            output=_Named(**outputs(method)),
            params=_Named(seol=seol, method=method, character="dome", performance="perf00", neutral_frames=[0]),
            log=[str(tmp_path / f"{method}.log")], rule="retarget_seol", threads=1)

    with pytest.raises(InputError, match="needs its rig and the take.s marker map on it"):
        run_seol(str(tmp_path / "perf.npz"), str(tmp_path / "char.npz"), [str(tmp_path / "rom.npz")], [0], "dome",
                 "perf00", seol, method=SEOL_ACTOR_RIG_METHOD, **outputs("x"))
    runpy.run_path("scripts/retarget_seol.py", init_globals={"snakemake": job(
        SEOL_ACTOR_RIG_METHOD, actor_rig=[str(tmp_path / "rig.npz")], marker_map=[str(tmp_path / "marker_map.json")])})
    runpy.run_path("scripts/retarget_seol.py", init_globals={"snakemake": job(SEOL_METHOD, actor_rig=[], marker_map=[])})
    w_ar, _, _ = read_weight_curves_csv(outputs(SEOL_ACTOR_RIG_METHOD)["weights"])
    w_plain, _, _ = read_weight_curves_csv(outputs(SEOL_METHOD)["weights"])
    assert np.abs(w_ar - W).max() < 1e-3 < np.abs(w_plain - W).max()
    meta = json.loads(Path(outputs(SEOL_ACTOR_RIG_METHOD)["weights_json"]).read_text())["meta"]
    assert meta["actor_rig"] == str(tmp_path / "rig.npz") and meta["method"] == "seol2012_actor_rig"
    assert meta["params"]["sobolev_corner_hz"] == 2.0 and meta["params"]["actor_rig"] == {}
    plain_meta = json.loads(Path(outputs(SEOL_METHOD)["weights_json"]).read_text())["meta"]
    assert plain_meta["params"]["sobolev_corner_hz"] is None and plain_meta["params"]["actor_rig"]
    frag = json.loads(Path(outputs(SEOL_ACTOR_RIG_METHOD)["metrics"]).read_text())["retarget"]
    assert METHOD_KEYS[SEOL_ACTOR_RIG_METHOD] == "seol_actor_rig"
    assert sorted(frag) == ["noconst_actor_rig", "perframe_prior_actor_rig", "perframe_range_actor_rig",
                            "seol_actor_rig"]
    v = frag["seol_actor_rig"]["dome"]
    assert v["rig_space_shapes"] == 4 and v["rig_space_markers"] == len(names) and v["rig_alignment_rms_mm"] < 1e-3  # float32 marker files
    plain = json.loads(Path(outputs(SEOL_METHOD)["metrics"]).read_text())["retarget"]
    assert sorted(plain) == ["noconst", "perframe_prior", "perframe_range", "seol"]
    assert "rig_space_shapes" not in plain["seol"]["dome"]


def test_seol_actor_rig_fields_are_checked_and_replace_the_blocks():
    from rigbuild.retarget.params import seol_from_config

    p = seol_from_config({"weight_bounds": [0, 1.5],
                          "actor_rig": {"sobolev_corner_hz": 10.0, "weight_bounds": [0, 1]}})
    assert p.for_method(SEOL_METHOD) is p and p.weight_bounds == (0, 1.5)
    q = p.for_method(SEOL_ACTOR_RIG_METHOD)
    assert q.weight_bounds == (0, 1) and q.sobolev_corner_hz == 10.0 and q.actor_rig == {} and q.alpha == p.alpha
    with pytest.raises(InputError, match="did you mean 'sobolev_corner_hz'"):
        seol_from_config({"actor_rig": {"sobolev_cornerhz": 1.0}})
    with pytest.raises(InputError, match="actor_rig.gaps"):
        seol_from_config({"actor_rig": {"gaps": "fill"}})
    with pytest.raises(InputError, match="another actor_rig block"):
        seol_from_config({"actor_rig": {"actor_rig": {"alpha": 1.0}}})


# ------------------------------------------------------------------------------------------ the DAG
def test_touching_the_personalized_rig_replans_only_the_seol_actor_rig_jobs(tmp_path):
    """Every file of the demo's DAG of both Seol methods' jobs (two characters) made up to date at one time, then
    personalize/rig.npz touched: a dry run with ``--rerun-triggers mtime`` plans the marker map
    (actor_rig_weights) and the seol_actor_rig jobs, and no seol job."""
    characters = ["template", "stylized"]
    targets = [f"results/demo/retarget/{m}/perf00/{c}/weights.csv" for m in SEOL_METHODS for c in characters]
    jobs = jobs_after_touching_the_personalized_rig(tmp_path, targets)
    planned = sorted((w["method"], w["character"]) for r, w in jobs if r == "retarget_seol")
    assert planned == sorted((SEOL_ACTOR_RIG_METHOD, c) for c in characters)
    others = sorted({r for r, w in jobs if r != "retarget_seol"})
    assert others == ["actor_rig_weights"], others
    assert [w["source"] for r, w in jobs if r == "actor_rig_weights"] == ["actor_rig"]