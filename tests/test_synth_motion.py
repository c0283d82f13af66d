"""Synthetic actors, motion and marker I/O: exact properties on small cases."""

from __future__ import annotations

import numpy as np
import pytest

from rigbuild.errors import InputError
from rigbuild.io.markers import read_markers, write_markers_c3d, write_markers_npz
from rigbuild.rig import Rig
from rigbuild.synth.actor import make_actor_rig
from rigbuild.synth.motion import (antagonist_overlap, apply_base_shapes, is_lower_face, make_head_motion,
                                   make_performance_weights, make_rom_weights,
                                   markers_from_rig)

NAMES = ["jawOpen", "eyeBlink_L", "eyeBlink_R", "mouthSmile_L", "mouthSmile_R", "browInnerUp_L",
         "browInnerUp_R", "cheekSquint_L", "cheekSquint_R", "mouthPucker", "mouthFunnel", "noseSneer_L"]


def _grid_rig(K=len(NAMES)):
    g = np.stack(np.meshgrid(np.linspace(-80, 80, 9), np.linspace(-100, 100, 11)), -1).reshape(-1, 2)
    neutral = np.hstack([g, np.zeros((g.shape[0], 1))])
    faces = []
    for j in range(10):
        for i in range(8):
            a = j * 9 + i
            faces += [[a, a + 1, a + 10], [a, a + 10, a + 9]]
    rng = np.random.default_rng(0)
    deltas = np.zeros((K, neutral.shape[0], 3))
    for k in range(K):
        c = rng.uniform(-60, 60, 2)
        d = np.exp(-((g - c) ** 2).sum(1) / (2 * 30.0**2))
        deltas[k, :, rng.integers(3)] = 5 * d
    return Rig(neutral, deltas, NAMES[:K], np.array(faces), marker_names=["a", "b", "c"], marker_vertices=[0, 40, 98])


def test_rom_weights_cover_every_shape_and_start_end_neutral():
    seqs = make_rom_weights(NAMES, 4, 11, seed=3, coverage=2)
    assert len(seqs) == 4 and all(s.shape == (11, len(NAMES)) for s in seqs)
    assert all(np.all(s[0] == 0) and np.all(s[-1] == 0) for s in seqs)
    peaks = np.stack(seqs).max(axis=(0, 1))
    assert np.all(peaks == 1.0)  # performed at full intensity: every shape reaches weight 1
    partial = np.stack(make_rom_weights(NAMES, 4, 11, seed=3, coverage=2, peak_range=(0.6, 0.9))).max(axis=(0, 1))
    assert partial.min() >= 0.6 - 1e-12 and partial.max() <= 0.9 + 1e-12 and partial.std() > 0
    # every shape peaks in exactly `coverage` sequences, with partners (sparse combinations)
    active = np.stack([(s.max(0) > 0) for s in seqs])
    assert np.all(active.sum(0) >= 2) and np.all(active.sum(1) >= 2)
    # shapes sharing a sequence are not collinear in time (identifiable)
    for s in seqs:
        cols = s[:, s.max(0) > 0]
        assert np.linalg.matrix_rank(cols, tol=1e-3) == cols.shape[1] or cols.shape[1] > cols.shape[0]


def test_mouth_close_is_performed_on_an_open_jaw():
    names = NAMES + ["mouthClose"]
    W = np.array([[0.0, 0.3], [0.5, 0.2], [0.1, 0.0]])  # columns jawOpen, mouthClose
    out = apply_base_shapes(W, ["jawOpen", "mouthClose"])
    np.testing.assert_array_equal(out, [[0.3, 0.3], [0.5, 0.2], [0.1, 0.0]])
    np.testing.assert_array_equal(apply_base_shapes(W, ["jawLeft", "mouthClose"]), W)  # no base in the rig
    j, c = names.index("jawOpen"), names.index("mouthClose")
    for seqs in (make_rom_weights(names, 4, 11, seed=3, coverage=2), [make_performance_weights(names, 600, 60.0, seed=2)]):
        for s in seqs:
            assert np.all(s[:, j] >= s[:, c])
    assert max(s[:, c].max() for s in make_rom_weights(names, 4, 11, seed=3)) == 1.0


def test_head_motion_starts_at_identity_and_respects_bounds():
    R, t = make_head_motion(50, seed=1, max_rotation_deg=3.0, max_translation_mm=5.0)
    assert np.allclose(R[0], np.eye(3)) and np.allclose(t[0], 0)
    assert np.allclose(np.einsum("fij,fkj->fik", R, R), np.eye(3), atol=1e-12)
    angles = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert angles.max() <= 3.0 * np.sqrt(3) + 1e-9 and np.abs(t).max() <= 5.0 + 1e-9


def test_performance_weights_smooth_and_bounded():
    W = make_performance_weights(NAMES, 600, 60.0, seed=2)
    assert W.shape == (600, len(NAMES)) and W.min() >= 0 and W.max() <= 1
    assert (W.max(0) > 0.1).sum() >= 6
    assert np.abs(np.diff(W, 2, axis=0)).max() < 0.5  # no jumps
    blinks = W[:, [1, 2]]
    assert np.allclose(blinks[:, 0], blinks[:, 1])  # both eyes blink together
    assert np.array_equal(W, make_performance_weights(NAMES, 600, 60.0, seed=2))


def test_markers_from_rig_exact_and_gaps():
    rig = _grid_rig()
    W = np.zeros((3, rig.n_shapes))
    W[1, 0] = 1.0
    m = markers_from_rig(rig, W)
    assert np.array_equal(m[0], rig.neutral[[0, 40, 98]])
    assert np.allclose(m[1], (rig.neutral + rig.deltas[0])[[0, 40, 98]])
    R = np.repeat(np.eye(3)[None], 3, 0)
    t = np.array([[0, 0, 0], [1, 2, 3], [0, 0, 0]], float)
    assert np.allclose(markers_from_rig(rig, W, R, t)[1], m[1] + [1, 2, 3])
    gapped = markers_from_rig(rig, np.zeros((200, rig.n_shapes)), gap_fraction=0.1, seed=1)
    frac = np.isnan(gapped[..., 0]).mean()
    assert 0.1 <= frac < 0.2


def test_actor_rig_perturbations_are_as_documented():
    rig = _grid_rig()
    actor, info = make_actor_rig(rig, seed=5, crosstalk=0.08, warp=0.0, asymmetry=0.0, max_tilt_deg=0.0)
    assert actor.shape_names == rig.shape_names and actor.n_vertices == rig.n_vertices
    k = rig.shape_index("noseSneer_L")  # no crosstalk source listed for it -> pure intensity scaling
    assert np.allclose(actor.deltas[k], info["intensity"][k] * rig.deltas[k])
    j, b = rig.shape_index("jawOpen"), rig.shape_index("browInnerUp_L")
    expected = info["intensity"][j] * rig.deltas[j] + 0.08 * (rig.deltas[b] + rig.deltas[rig.shape_index("browInnerUp_R")])
    assert np.allclose(actor.deltas[j], expected)
    assert np.all((0.6 <= info["intensity"]) & (info["intensity"] <= 1.5))
    assert not np.allclose(actor.neutral, rig.neutral)
    a2, _ = make_actor_rig(rig, seed=5, crosstalk=0.08, warp=0.0, asymmetry=0.0, max_tilt_deg=0.0)
    assert np.array_equal(a2.deltas, actor.deltas) and np.array_equal(a2.neutral, actor.neutral)


def test_marker_c3d_roundtrip(tmp_path):
    rng = np.random.default_rng(0)
    m = 100.0 + np.cumsum(rng.normal(scale=2.0, size=(40, 5, 3)), axis=0)  # a random walk, 120 mm/s at 60 fps
    m[3:9, 2] = np.nan
    names = ["browInner_L", "browInner_R", "lipUpper_C", "jaw_C", "nose_C"]
    write_markers_c3d(tmp_path / "p.c3d", m, names, 60.0)
    take = read_markers(tmp_path / "p.c3d")
    assert take.names == names and take.fps == 60.0
    assert np.array_equal(np.isnan(take.markers), np.isnan(m))
    assert np.nanmax(np.abs(take.markers - m)) < 1e-4  # float32 storage
    write_markers_npz(tmp_path / "p.npz", m, names, 60.0)
    assert np.allclose(read_markers(tmp_path / "p.npz").markers, m, equal_nan=True)
    assert take.subset(["jaw_C", "nose_C"]).markers.shape == (40, 2, 3)
    with pytest.raises(InputError, match="not in the take"):
        take.subset(["chin_X"])
    allnan = np.full((4, 2, 3), np.nan)
    write_markers_npz(tmp_path / "bad.npz", allnan, ["a", "b"], 30.0)
    with pytest.raises(InputError, match="all frames are gaps"):
        read_markers(tmp_path / "bad.npz")
    (tmp_path / "trunc.c3d").write_bytes((tmp_path / "p.c3d").read_bytes()[:300])
    with pytest.raises(InputError, match="trunc.c3d"):
        read_markers(tmp_path / "trunc.c3d")


ARKIT = ["browDown_L", "browDown_R", "browInnerUp_L", "browInnerUp_R", "eyeBlink_L", "eyeBlink_R", "eyeWide_L",
         "eyeWide_R", "jawOpen", "jawLeft", "jawRight", "mouthClose", "mouthFunnel", "mouthPress_L", "mouthPress_R",
         "mouthLeft", "mouthRight", "mouthSmile_L", "mouthSmile_R", "mouthFrown_L", "mouthFrown_R", "mouthPucker",
         "mouthStretch_L", "mouthStretch_R", "mouthRollLower", "mouthRollUpper", "cheekPuff_L", "noseSneer_L"]


def test_antagonist_overlap_is_the_largest_joint_weight():
    names = ["mouthLeft", "mouthRight", "jawOpen"]
    W = np.array([[0.0, 0.0, 1.0], [0.7, 0.2, 1.0], [0.3, 0.4, 0.0]])
    assert antagonist_overlap(W, names) == pytest.approx(0.3)
    assert antagonist_overlap(W[:, [0, 2]], ["mouthLeft", "jawOpen"]) == 0.0
    assert is_lower_face("jawOpen") and is_lower_face("cheekPuff_L") and not is_lower_face("eyeBlink_L")


def test_rom_performs_lower_face_shapes_in_turn_without_antagonists():
    lower = [i for i, n in enumerate(ARKIT) if is_lower_face(n)]
    base = {ARKIT.index("jawOpen")}
    for seed in range(4):
        seqs = make_rom_weights(ARKIT, 6, 15, seed=seed, coverage=2, lower_face_lanes=2)
        W = np.stack(seqs)
        assert np.all(W.max(axis=(0, 1)) == 1.0)  # still every shape at full intensity
        for s in seqs:
            assert antagonist_overlap(s, ARKIT) <= 0.25  # (best of the redraws: lanes cross-fade)
            # at most two lanes near their extremes at once (jawOpen may also carry mouthClose)
            near = s[:, lower] > 0.5
            near_wo_base = near[:, [j for j, i in enumerate(lower) if i not in base]]
            assert near_wo_base.sum(1).max() <= 2
        one = make_rom_weights(ARKIT, 6, 15, seed=seed, lower_face_lanes=1)
        for s in one:
            lower_wo = [i for i in lower if i not in base]
            assert (s[:, lower_wo] > 0.5).sum(1).max() <= 1
    with pytest.raises(ValueError, match="lower_face_lanes"):
        make_rom_weights(ARKIT, 2, 15, lower_face_lanes=0)


def test_rom_and_head_motion_defaults_unchanged():
    """The opt-in options off reproduce the code before them (values from that code, rtol 1e-9)."""
    from rigbuild.synth.motion import make_head_motion, make_rom_weights

    s = np.stack(make_rom_weights(ARKIT, 4, 15, seed=1, peak_range=(0.5, 1.0)))
    assert float(s.sum()) == pytest.approx(124.8173350602998, rel=1e-9)
    assert float((s ** 2).sum()) == pytest.approx(72.5001698072607, rel=1e-9)
    R, t = make_head_motion(40, seed=2, max_rotation_deg=2.0, max_translation_mm=3.0)
    assert float(R.sum()) == pytest.approx(119.97106782761949, rel=1e-9)
    assert float(t.sum()) == pytest.approx(19.831602134828923, rel=1e-9)


def test_rom_holds_peaks_with_ease():
    from rigbuild.synth.motion import hold_lengths, rom_frames_needed

    names = [n for n in ARKIT if n != "mouthClose"]  # (jawOpen would inherit mouthClose's hold as its base)
    F = 60
    lengths = []
    for seed in range(3):
        seqs = make_rom_weights(names, 6, F, seed=seed, coverage=2, peak_range=(0.5, 1.0), hold_frames=(3, 8))
        W = np.stack(seqs)
        peaks = W.max(axis=(0, 1))
        assert peaks.min() >= 0.5 and peaks.max() <= 1.0 and peaks.std() > 0.05
        for s in seqs:
            assert np.all(s[0] == 0) and np.all(s[-1] == 0)
            for k in np.flatnonzero(s.max(0) > 0):
                runs = hold_lengths(s[:, k])
                assert len(runs) == 1 and 3 <= runs[0] <= 8
                lengths += runs
                h0 = int(np.flatnonzero(np.abs(s[:, k] - s[:, k].max()) <= 1e-12)[0])
                h1 = h0 + runs[0] - 1
                peak = s[h0, k]
                # eased in and out over at least two captured frames each, monotone
                assert np.all((s[h0 - 2:h0, k] > 0) & (s[h0 - 2:h0, k] < peak))
                assert np.all((s[h1 + 1:h1 + 3, k] > 0) & (s[h1 + 1:h1 + 3, k] < peak))
                assert np.all(np.diff(s[:h0 + 1, k]) >= -1e-12) and np.all(np.diff(s[h1:, k]) <= 1e-12)
    assert set(lengths) == set(range(3, 9))  # every hold length occurs
    with pytest.raises(ValueError, match="too short for hold_frames"):
        make_rom_weights(names, 2, 15, hold_frames=(3, 8))
    assert rom_frames_needed((3, 8), 3, 2) == int(np.ceil((3 + 3.5) / (0.5 + 1 / 3 - 0.15) * 3.5)) + 1


def test_head_motion_total_bounds_and_neutral_pose():
    from scipy.spatial.transform import Rotation

    def angle(R):
        return np.degrees(np.linalg.norm(Rotation.from_matrix(R).as_rotvec(), axis=-1))

    R, t = make_head_motion(60, seed=4, max_rotation_deg=8.0, max_translation_mm=10.0, bound="total")
    assert np.allclose(R[0], np.eye(3)) and np.allclose(t[0], 0)
    assert angle(R).max() == pytest.approx(8.0, abs=1e-9) and np.linalg.norm(t, axis=1).max() == pytest.approx(10.0)
    R2, t2 = make_head_motion(60, seed=4, max_rotation_deg=8.0, max_translation_mm=10.0, bound="total",
                              neutral_pose_deg=5.0, neutral_pose_mm=7.0)
    assert angle(R2[0]) == pytest.approx(5.0) and np.linalg.norm(t2[0]) == pytest.approx(7.0)  # not the identity
    rel = np.einsum("fij,kj->fik", R2, R2[0])  # R_f R_0^T: the motion inside the sequence
    assert angle(rel).max() == pytest.approx(8.0, abs=1e-9)
    assert np.linalg.norm(t2 - t2[0], axis=1).max() == pytest.approx(10.0)
    assert np.allclose(rel, R) and np.allclose(t2 - t2[0], t)
    with pytest.raises(ValueError, match="bound"):
        make_head_motion(10, bound="sphere")
