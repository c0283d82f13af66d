"""Occlusion gaps, head motion and bad input in both retargeting methods (issue 23): frames with too few
markers bridged, a take that cannot be used named in a clear error, a take whose marker names match none of
the character's map and a character sharing no shape name with the actor's rig."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rigbuild.errors import InputError
from rigbuild.retarget.common import bridge_rigid_motion, check_marker_overlap, map_markers_to_vertices
from rigbuild.retarget.seol import bridge_sparse_frames, remove_head_motion, retarget_seol


def _rigid_take(F=60, M=12, seed=0):
    """Markers of a rigid head under smooth motion: (F, M, 3), the neutral (M, 3), true R (F, 3, 3), t (F, 3)."""
    rng = np.random.default_rng(seed)
    Y = rng.normal(scale=40.0, size=(M, 3))
    s = np.linspace(0, 1, F)
    R = Rotation.from_rotvec(np.column_stack([0.2 * np.sin(3 * s), 0.1 * s, -0.15 * s])).as_matrix()
    t = np.column_stack([5 * s, -3 * s, 2 * np.sin(2 * s)])
    X = np.einsum("fij,mj->fmi", R, Y) + t[:, None]
    return X, Y, R, t


def test_head_motion_bridged_over_frames_with_too_few_markers():
    X, Y, R_true, t_true = _rigid_take()
    X = X.copy()
    X[10:15] = np.nan  # tracking lost on every marker
    X[20, 2:] = np.nan  # two markers left
    w = np.ones(12)
    w[:8] = 0.0  # the weighted head-motion markers are 8..11
    X[30, 8:] = np.nan  # none of them visible: fitted on the other visible markers
    stab, R, t = remove_head_motion(X, Y, w, path="take.c3d")
    err = np.degrees(np.linalg.norm(Rotation.from_matrix(np.einsum("fji,fjk->fik", R_true, R)).as_rotvec(), axis=1))
    assert err[30] < 1e-6  # fitted exactly on its other markers
    assert err[[10, 12, 14, 20]].max() < 0.5  # bridged: smooth motion, interpolated
    assert np.abs(t - t_true)[[10, 12, 14, 20]].max() < 0.5
    fine = np.setdiff1d(np.arange(60), [10, 11, 12, 13, 14, 20])
    np.testing.assert_allclose(stab[fine][np.isfinite(stab[fine])],
                               np.broadcast_to(Y, stab[fine].shape)[np.isfinite(stab[fine])], atol=1e-6)


def test_head_motion_of_a_take_without_any_usable_frame_names_the_file():
    X, Y, _, _ = _rigid_take(F=5)
    X = X.copy()
    X[:, 2:] = np.nan
    with pytest.raises(InputError, match=r"take\.c3d: no frame of the take has 3 visible markers"):
        remove_head_motion(X, Y, path="take.c3d")


def test_bridge_rigid_motion_slerps_between_fitted_frames():
    R = Rotation.from_rotvec([[0, 0, 0], [0, 0, 0], [0, 0, 0.4]]).as_matrix()
    t = np.array([[0.0, 0, 0], [9, 9, 9], [2.0, 0, 0]])
    Rb, tb = bridge_rigid_motion(R, t, np.array([True, False, True]))
    np.testing.assert_allclose(Rotation.from_matrix(Rb[1]).as_rotvec(), [0, 0, 0.2], atol=1e-12)
    np.testing.assert_allclose(tb[1], [1.0, 0, 0])


def test_sparse_frames_filled_in_time_and_observed_markers_kept():
    F, M = 10, 5
    stab = np.tile(np.arange(F, dtype=float)[:, None, None], (1, M, 3))
    stab[4, 1:] = np.nan  # one marker left: filled from frames 3 and 5 (keeps its own)
    stab[4, 0] = 100.0
    out = bridge_sparse_frames(stab, "take.npz")
    assert out[4, 0, 0] == 100.0 and np.allclose(out[4, 1:], 4.0)
    with pytest.raises(InputError, match=r"take\.npz: no frame of the take has 3 visible markers"):
        bridge_sparse_frames(np.full((4, M, 3), np.nan), "take.npz")


def test_seol_retargets_a_take_with_occluded_frames_and_head_motion():
    from rigbuild.assets.head import procedural_head_rig
    from rigbuild.synth.retarget_scenes import synthetic_performance

    head = procedural_head_rig()
    case = synthetic_performance(head, n_frames=200, fps=60, seed=3, noise_mm=0.05, gap_fraction=0.01)
    X = np.array(case["markers"], dtype=float, copy=True)
    X[50:54] = np.nan  # the whole face lost for 4 frames
    X[120, 3:] = np.nan  # 3 markers left in one frame
    res = retarget_seol(X, head, alpha=1e-6, baselines=False, source_path="perf.npz")
    full = retarget_seol(case["markers"], head, alpha=1e-6, baselines=False).weights
    assert np.all(np.isfinite(res.weights)) and np.all(np.isfinite(res.head_rotation))
    # across the lost frames the weights of the shapes the markers observe follow the solve of the complete
    # take (no dip to the prior's neutral)
    from rigbuild.eval.seol import evaluated_shapes

    seen = evaluated_shapes(case["actor"], case["weights"])
    W, full = res.weights[:, seen], full[:, seen]
    span = np.ptp(full, axis=0).max()
    assert np.abs(W[48:56] - full[48:56]).max() < 0.1 * span
    assert np.abs(W[118:123] - full[118:123]).max() < 0.1 * span


def test_a_take_whose_marker_names_match_none_of_the_map_names_the_file_and_the_fix():
    with pytest.raises(InputError, match=r"perf\.c3d: none of the performance's 3 marker names \(A, B, C\) is "
                                         r"in the marker map of 'ict'") as e:
        check_marker_overlap(["A", "B", "C"], ["ForeHead_M", "Chin"], "the performance", "perf.c3d", "ict")
    assert "animface_ict.json" in str(e.value) and "fix:" in str(e.value)
    check_marker_overlap(["A", "Chin"], ["ForeHead_M", "Chin"])  # one in common: the per-marker check follows
    with pytest.raises(InputError, match=r"map\.json: none of the actor's marker set's 2 marker names"):
        map_markers_to_vertices(["A", "B"], ["ForeHead_M", "Chin"], [1, 2], "ict", "map.json")
    with pytest.raises(InputError, match="has no vertex for 1 of 2 markers: A"):
        map_markers_to_vertices(["A", "Chin"], ["ForeHead_M", "Chin"], [1, 2], "ict", "map.json")


def test_stage_jobs_reject_a_take_with_foreign_marker_names(tmp_path):
    from rigbuild.assets.head import procedural_head_rig
    from rigbuild.io.markers import write_markers_npz
    from rigbuild.io.rigs import write_rig_npz
    from rigbuild.retarget.stage import run_ribera, run_seol

    rig = procedural_head_rig()
    write_rig_npz(tmp_path / "char.npz", rig)
    markers = rig.markers()[None].repeat(4, 0)
    foreign = [f"marker{i}" for i in range(markers.shape[1])]
    write_markers_npz(tmp_path / "perf.npz", markers, foreign, 60.0)
    write_markers_npz(tmp_path / "rom.npz", markers, foreign, 60.0)
    outs = {k: str(tmp_path / k) for k in ("weights", "weights_json", "gltf", "metrics")}
    with pytest.raises(InputError, match=r"perf\.npz: none of the performance's .* marker names \(marker0, "):
        run_seol(str(tmp_path / "perf.npz"), str(tmp_path / "char.npz"), None, None, "c", "p", {},
                 plot=str(tmp_path / "plot.png"), system=str(tmp_path / "s.npz"), **outs)
    with pytest.raises(InputError, match=r"perf\.npz: none of the performance's"):
        run_ribera(str(tmp_path / "perf.npz"), [str(tmp_path / "rom.npz")], str(tmp_path / "char.npz"), "rbf", "c",
                   "p", {}, [0], preview=str(tmp_path / "preview.png"), **outs)
    assert not any((tmp_path / k).exists() for k in outs)  # no half-written output


def test_a_character_sharing_no_shape_name_with_the_actor_rig_names_the_files():
    from rigbuild.eval.retarget import retarget_metrics

    W = np.zeros((5, 2))
    with pytest.raises(InputError, match=r"weights\.csv: the character's 2 shapes \(smile, frown, \.\.\.\) share no "
                                         r"name with the actor's rig's 2 \(mouthSmile_L, mouthFrown_L, \.\.\.\) in "
                                         r"truth\.npz") as e:
        retarget_metrics(W, ["smile", "frown"], W, ["mouthSmile_L", "mouthFrown_L"], np.ones((2, 3, 3)),
                         "weights.csv", "truth.npz")
    assert "fix: name the character's blendshapes as the actor's rig does" in str(e.value)
