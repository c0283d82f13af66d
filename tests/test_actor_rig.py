"""The personalized rig feeding retargeting (rigbuild/retarget/actor_rig.py) and its building blocks: batched
Kabsch, batched box QPs, points on a mesh's skin; exact answers on tiny analytic cases, error bounds on a
synthetic take of the procedural rig with hand-placed markers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rigbuild.errors import InputError
from rigbuild.geometry.box_qp import solve_box_qp_batched
from rigbuild.geometry.mesh import closest_surface_points, points_on_surface
from rigbuild.geometry.rigid import fit_rigid_motion, fit_rigid_motion_batched
from rigbuild.personalize.weights import solve_box_qp_active_set
from rigbuild.retarget.actor_rig import (MarkerMap, fit_marker_map, marker_map_for_take, refine_rig_at_markers,
                                         sample_rig_at_markers, semantic_transfer, solve_actor_weights,
                                         solve_actor_weights_refined, solve_frames_point_to_plane,
                                         vertex_marker_map)
from rigbuild.retarget.params import actor_rig_from_config


def test_batched_kabsch_recovers_each_rigid_motion_exactly():
    rng = np.random.default_rng(0)
    B, N = 7, 12
    src = rng.normal(size=(B, N, 3)) * 50
    R = Rotation.random(B, random_state=1).as_matrix()
    t = rng.normal(size=(B, 3)) * 100
    dst = np.einsum("bij,bnj->bni", R, src) + t[:, None]
    w = rng.random((B, N))
    w[0, :5] = 0.0
    dst[0, :5] = np.nan  # a missing point is ignored where its weight is 0
    Rb, tb = fit_rigid_motion_batched(src, dst, w)
    assert np.abs(Rb - R).max() < 1e-10 and np.abs(tb - t).max() < 1e-8
    R1, t1 = fit_rigid_motion(src[3], dst[3], w[3])
    assert np.allclose(Rb[3], R1) and np.allclose(tb[3], t1)


def test_batched_kabsch_gives_identity_without_points():
    R, t = fit_rigid_motion_batched(np.ones((1, 3, 3)), np.full((1, 3, 3), np.nan), np.zeros((1, 3)))
    assert np.array_equal(R[0], np.eye(3)) and np.array_equal(t[0], np.zeros(3))


def test_batched_box_qp_matches_the_serial_active_set_solver():
    rng = np.random.default_rng(2)
    B, K = 60, 9
    A = rng.normal(size=(B, 15, K))
    H = np.einsum("bmk,bml->bkl", A, A) + 1e-3 * np.eye(K)
    f = rng.normal(size=(B, K)) * 4
    x, ok = solve_box_qp_batched(H, f, 0.0, 1.0)
    assert ok.all()
    for b in range(B):
        assert np.abs(x[b] - solve_box_qp_active_set(H[b], f[b])).max() < 1e-10
    # warm start from another guess reaches the same optimum
    x2, ok2 = solve_box_qp_batched(H, f, 0.0, 1.0, x0=np.full((B, K), 0.5))
    assert ok2.all() and np.abs(x2 - x).max() < 1e-10


def test_batched_box_qp_one_dimensional_closed_form():
    # min 1/2 h x^2 + f x on [0, 1]: x = clip(-f / h, 0, 1)
    h = np.array([2.0, 2.0, 2.0])
    f = np.array([-1.0, 3.0, -5.0])
    x, ok = solve_box_qp_batched(h[:, None, None], f[:, None])
    assert ok.all() and np.allclose(x[:, 0], [0.5, 0.0, 1.0])


def _square():
    V = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0]], dtype=float)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    return V, F


def test_closest_surface_points_and_points_on_surface_round_trip():
    V, F = _square()
    P = np.array([[2.0, 1.0, 3.0], [1.0, 8.0, -2.0]])
    fid, bary, dist = closest_surface_points(V, F, P)
    assert list(fid) == [0, 1]
    assert np.allclose(dist, [3.0, -2.0])  # signed along the normal (+z)
    assert np.allclose(points_on_surface(V, F, fid, bary), [[2, 1, 0], [1, 8, 0]])
    assert np.allclose(points_on_surface(V, F, fid, bary, dist), P)
    # a batch of poses of one topology
    poses = np.stack([V, V + [0, 0, 5]])
    assert np.allclose(points_on_surface(poses, F, fid, bary)[1], [[2, 1, 5], [1, 8, 5]])


def test_vertex_marker_map_puts_markers_on_their_vertices():
    V, F = _square()
    m = vertex_marker_map(["a", "b", "c"], np.array([3, 1, 2]), F)
    assert np.allclose(m.points(V, F), V[[3, 1, 2]])
    with pytest.raises(InputError):
        vertex_marker_map(["x"], np.array([7]), np.vstack([F, [[0, 1, 7]]])[:2])


def _toy_rig(rng, M=30, K=6):
    """A marker-space rig: neutral (M, 3) mm and K shapes with random local displacement patterns."""
    b0 = rng.normal(size=(M, 3)) * np.array([60.0, 80.0, 30.0])
    D = rng.normal(size=(K, M, 3)) * 4.0 * (rng.random((K, M, 1)) < 0.5)
    return b0, D


def test_actor_weights_are_exact_on_noise_free_markers():
    rng = np.random.default_rng(3)
    b0, D = _toy_rig(rng)
    F = 40
    W = rng.uniform(0.05, 0.95, size=(F, D.shape[0]))
    W[::5, 2] = 0.0  # some at the bound
    R = Rotation.from_rotvec(rng.normal(size=(F, 3)) * 0.08).as_matrix()
    t = rng.normal(size=(F, 3)) * 20 + [0, -300, 900]
    P = np.einsum("fij,fmj->fmi", R, b0 + np.einsum("fk,kmc->fmc", W, D)) + t[:, None]
    P[7, :4] = np.nan  # gaps
    sol = solve_actor_weights(b0, D, P, lambda_l1=0.0, tol=1e-9, sweeps=50)
    assert sol.converged
    assert np.abs(sol.weights - W).max() < 1e-6
    assert np.abs(sol.rotations - R).max() < 1e-7 and np.abs(sol.translations - t).max() < 1e-5
    assert np.nanmax(sol.residual_mm) < 1e-5


def test_actor_weights_hold_the_pose_of_a_frame_without_markers():
    rng = np.random.default_rng(4)
    b0, D = _toy_rig(rng)
    W = np.full((5, D.shape[0]), 0.3)
    P = np.repeat((b0 + np.einsum("k,kmc->mc", W[0], D))[None], 5, 0)
    P[2] = np.nan
    sol = solve_actor_weights(b0, D, P, lambda_t=1.0, tol=1e-10, sweeps=400)
    assert np.isnan(sol.residual_mm[2]) and np.allclose(sol.rotations[2], sol.rotations[1])
    assert np.abs(sol.weights[2] - 0.3).max() < 1e-4  # from its neighbours through the temporal term
    with pytest.raises(InputError, match="3 visible markers"):
        solve_actor_weights(b0, D, np.full_like(P, np.nan))


def test_l1_sparsity_shrinks_weights_and_bounds_hold():
    rng = np.random.default_rng(5)
    b0, D = _toy_rig(rng)
    W = rng.uniform(0, 1, size=(20, D.shape[0]))
    P = b0 + np.einsum("fk,kmc->fmc", W, D) + rng.normal(scale=0.3, size=(20,) + b0.shape)
    plain = solve_actor_weights(b0, D, P, lambda_l1=0.0)
    sparse = solve_actor_weights(b0, D, P, lambda_l1=200.0)
    assert sparse.weights.sum() < plain.weights.sum()
    assert plain.weights.min() >= 0 and plain.weights.max() <= 1


def test_point_to_plane_fit_ignores_sliding_along_the_skin():
    """Markers moved along the plane of their normals fit as well as the true ones: the pose stays exact."""
    rng = np.random.default_rng(6)
    b0, D = _toy_rig(rng, M=40, K=3)
    n = rng.normal(size=(40, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    slide = np.cross(n, rng.normal(size=(40, 3)))  # perpendicular to n
    R = Rotation.from_rotvec([[0.02, -0.05, 0.03]]).as_matrix()
    t = np.array([[5.0, -2.0, 700.0]])
    W = np.array([[0.2, 0.6, 0.0]])
    true = b0 + np.einsum("k,kmc->mc", W[0], D)
    P = (true[None] @ R[0].T) + t[:, None]
    sol = solve_frames_point_to_plane(b0 + slide, D, n, P, iterations=30)
    assert np.abs(sol.rotations - R).max() < 1e-6 and np.abs(sol.weights - W).max() < 1e-6


def test_semantic_transfer_matches_shapes_by_name():
    W = np.array([[0.1, 0.2, 0.3]])
    out, shared = semantic_transfer(W, ["jawOpen", "eyeBlinkLeft", "mouthSmileLeft"],
                                    ["mouthSmileLeft", "browInnerUp", "jawOpen"])
    assert shared == ["mouthSmileLeft", "jawOpen"] and np.allclose(out, [[0.3, 0.0, 0.1]])
    with pytest.raises(InputError, match="no shape name"):
        semantic_transfer(W, ["a", "b", "c"], ["x"])


def _posed_take(rng, b0, D, F=60):
    """Markers (F, M, 3) mm of a marker-space rig under random weights and head motion; (P, W, R, t)."""
    W = rng.uniform(0.0, 1.0, size=(F, D.shape[0])) * (rng.random((F, D.shape[0])) < 0.5)
    R = Rotation.from_rotvec(rng.normal(size=(F, 3)) * 0.05).as_matrix()
    t = rng.normal(size=(F, 3)) * 10 + [0, -300, 900]
    P = np.einsum("fij,fmj->fmi", R, b0 + np.einsum("fk,kmc->fmc", W, D)) + t[:, None]
    return P, W, R, t


def test_warm_started_solve_reaches_the_cold_solution():
    rng = np.random.default_rng(7)
    b0, D = _toy_rig(rng)
    P, W, _, _ = _posed_take(rng, b0, D, F=30)
    cold = solve_actor_weights(b0, D, P, tol=1e-10, sweeps=200)
    warm = solve_actor_weights(b0, D, P, tol=1e-10, sweeps=200, initial=cold)
    assert warm.sweeps <= 2 and np.abs(warm.weights - cold.weights).max() < 1e-8
    assert np.abs(warm.weights - W).max() < 1e-6


def test_rig_refinement_shape_step_closed_forms():
    """Given the true weights and poses: no prior recovers the true rig at the markers exactly (the take alone),
    an overwhelming prior returns the prior, and a prior of p frames is the weighted mean of the two for a
    marker seen at weight 1 in every one of F frames (its normal equations are (F + p) x = F x_true + p x_prior)."""
    from rigbuild.retarget.actor_rig import ActorWeights

    rng = np.random.default_rng(8)
    b0, D = _toy_rig(rng, M=12, K=4)
    P, W, R, t = _posed_take(rng, b0, D, F=50)
    solved = ActorWeights(W, R, t, np.zeros(len(W)), np.ones(D.shape[0], bool), 1, True)
    b_prior, D_prior = b0 + rng.normal(size=b0.shape), D + rng.normal(size=D.shape)
    b, d = refine_rig_at_markers(b_prior, D_prior, P, solved, prior=0.0)
    assert np.abs(b - b0).max() < 1e-6 and np.abs(d - D).max() < 1e-6
    b, d = refine_rig_at_markers(b_prior, D_prior, P, solved, prior=1e12)
    assert np.abs(b - b_prior).max() < 1e-6 and np.abs(d - D_prior).max() < 1e-6
    one = ActorWeights(np.zeros((50, 4)), R, t, np.zeros(50), np.ones(4, bool), 1, True)  # neutral frames only
    Pn = np.einsum("fij,mj->fmi", R, b0) + t[:, None]
    b, _ = refine_rig_at_markers(b_prior, D_prior, Pn, one, prior=25.0)
    assert np.allclose(b, (50 * b0 + 25 * b_prior) / 75, atol=1e-9)


def test_rig_refinement_corrects_a_wrong_shape_from_the_take():
    """A personalized rig with one shape wrong at the markers (noise of 60 % of its RMS on every coordinate):
    solving the take from it mixes the weights up; refining the rig on the take brings that shape and the weights
    back towards the truth (measured: weight error 0.0166 -> 0.0110, the shape's error 11.4 -> 4.1 mm), and 0
    iterations is the plain solve."""
    rng = np.random.default_rng(9)
    b0, D = _toy_rig(rng, M=30, K=6)
    P, W, _, _ = _posed_take(rng, b0, D, F=400)
    P = P + rng.normal(scale=0.1, size=P.shape)
    D_wrong = D.copy()
    D_wrong[2] = D[2] + 0.6 * np.linalg.norm(D[2]) / np.sqrt(D[2].size) * rng.normal(size=D[2].shape)
    plain = solve_actor_weights(b0, D_wrong, P)
    same, first, b, d = solve_actor_weights_refined(b0, D_wrong, P, 0, 10.0)
    assert np.array_equal(same.weights, plain.weights) and np.array_equal(b, b0) and np.array_equal(d, D_wrong)
    refined, first, _, d = solve_actor_weights_refined(b0, D_wrong, P, 10, 10.0)
    assert np.array_equal(first.weights, plain.weights)
    err_plain, err_refined = np.abs(plain.weights - W).mean(), np.abs(refined.weights - W).mean()
    assert err_refined < 0.8 * err_plain
    assert np.linalg.norm(d[2] - D[2]) < 0.5 * np.linalg.norm(D_wrong[2] - D[2])
    assert np.nanmean(refined.residual_mm) < np.nanmean(plain.residual_mm)


def test_temporal_term_joins_the_unrefined_and_the_final_solve():
    """A smooth take (weights varying over about a second at 30 fps) with 0.5 mm marker noise: the temporal term
    lowers the weight error (measured 0.0172 -> 0.0122 at lambda_t 200 mm^2); it enters the solve from the
    unrefined rig (iterations 0: that solve is returned twice, the temporal solve warm-started from the plain one,
    at the cold temporal solve's minimum) and the final solve after the refinement rounds, which run without it."""
    rng = np.random.default_rng(10)
    b0, D = _toy_rig(rng, M=30, K=6)
    F = 150
    time_s = np.arange(F) / 30.0
    W = 0.5 + 0.45 * np.sin(2 * np.pi * 0.7 * time_s[:, None] * (1 + np.arange(6)) / 3 + np.arange(6))
    P = b0 + np.einsum("fk,kmc->fmc", W, D) + rng.normal(scale=0.5, size=(F,) + b0.shape)
    kw = dict(tol=1e-8, sweeps=400)
    plain, _, _, _ = solve_actor_weights_refined(b0, D, P, 0, 10.0, **kw)
    smooth, first, b, d = solve_actor_weights_refined(b0, D, P, 0, 10.0, lambda_t=200.0, **kw)
    assert smooth is first and np.array_equal(b, b0) and np.array_equal(d, D)
    cold = solve_actor_weights(b0, D, P, lambda_t=200.0, **kw)
    assert np.abs(smooth.weights - cold.weights).max() < 1e-5
    err_plain, err_smooth = np.abs(plain.weights - W).mean(), np.abs(smooth.weights - W).mean()
    assert err_smooth < 0.8 * err_plain, (err_plain, err_smooth)
    refined, first2, b2, d2 = solve_actor_weights_refined(b0, D, P, 2, 10.0, lambda_t=200.0, **kw)
    assert np.array_equal(first2.weights, smooth.weights)
    rounds, _, b3, d3 = solve_actor_weights_refined(b0, D, P, 2, 10.0, **kw)
    assert np.array_equal(b2, b3) and np.array_equal(d2, d3)  # the rounds ran without the temporal term
    assert np.abs(refined.weights - solve_actor_weights(b3, d3, P, lambda_t=200.0, **kw).weights).max() < 1e-5


def test_temporal_solve_converges_in_a_few_sweeps_on_shapes_that_share_their_motion():
    """Two shapes that nearly share their marker motion (an eyeBlink / eyeLookDown pair) at 60 fps: with the
    temporal term the weights of every frame are one box QP per Gauss-Newton sweep (block tridiagonal), so the
    solve settles in as few sweeps as the per-frame one (measured 3; red-black block sweeps took 17 at lambda_t 36
    and 60 at 200)."""
    rng = np.random.default_rng(11)
    b0, D = _toy_rig(rng, M=30, K=6)
    D[1] = 0.95 * D[0] + 0.3 * D[1]
    F = 200
    time_s = np.arange(F) / 60.0
    W = np.clip(0.5 + 0.6 * np.sin(2 * np.pi * 0.5 * time_s[:, None] * (1 + np.arange(6)) / 3 + np.arange(6)), 0, 1)
    P = b0 + np.einsum("fk,kmc->fmc", W, D) + rng.normal(scale=0.3, size=(F,) + b0.shape)
    plain = solve_actor_weights(b0, D, P, tol=1e-6, sweeps=400)
    for lambda_t in (36.0, 200.0):
        sol = solve_actor_weights(b0, D, P, lambda_t=lambda_t, tol=1e-6, sweeps=400, initial=plain)
        assert sol.converged and sol.sweeps <= 5, (lambda_t, sol.sweeps)
        assert np.abs(sol.weights - W).mean() < np.abs(plain.weights - W).mean()


def test_actor_rig_params_are_checked():
    assert actor_rig_from_config({}).lambda_l1 >= 0
    assert actor_rig_from_config({}).refine_iterations == 0  # the plain solve unless a config turns it on
    p = actor_rig_from_config({"lambda_t": 1.0, "lambda_velocity": 0.01})
    assert p.temporal_weight(60.0) == pytest.approx(1.0 + 0.01 * 3600)
    assert p.temporal_weight(30.0) == pytest.approx(10.0)
    for bad in ({"bounds": [1, 0]}, {"lambda_l1": -1}, {"sweeps": 0}, {"lamda_t": 1.0}, {"refine_iterations": -1},
                {"refine_iterations": 1.5}, {"refine_prior": -2.0}, {"lambda_velocity": -0.01}):
        with pytest.raises(InputError):
            actor_rig_from_config(bad)


@pytest.fixture(scope="module")
def procedural_take():
    """A 10 s take of the procedural rig at 30 fps: speech-like weights, head motion, 69 markers placed by hand
    (uniform inside the triangle beside each marker vertex, about 2.8 mm off it), 0.3 mm noise, 2 % gaps."""
    from rigbuild.io.rigs import load_rig
    from rigbuild.synth.motion import make_head_motion, make_performance_weights

    rig = load_rig("procedural")
    rng = np.random.default_rng(1)
    F = 300
    W = make_performance_weights(rig.shape_names, F, 30.0, seed=3)
    R, t = make_head_motion(F, seed=4, max_rotation_deg=4.0, max_translation_mm=6.0)
    t = t + np.array([10.0, -400.0, 600.0])
    start = marker_map_for_take(rig, rig.marker_names)
    true = MarkerMap(start.names, start.face_ids.copy(), rng.dirichlet([1, 1, 1], size=len(start.names)),
                     np.zeros(len(start.names)))
    posed = rig.neutral[None] + np.einsum("fk,kvc->fvc", W, rig.deltas)
    P = np.einsum("fmc,fdc->fmd", true.points(posed, rig.faces), R) + t[:, None]
    P += rng.normal(scale=0.3, size=P.shape)
    P[rng.random(P.shape[:2]) < 0.02] = np.nan
    return rig, W, true, start, P


def test_marker_map_finds_hand_placed_markers_on_the_skin(procedural_take):
    rig, _, true, start, P = procedural_take
    err0 = np.linalg.norm(start.points(rig.neutral, rig.faces) - true.points(rig.neutral, rig.faces), axis=1)
    m = fit_marker_map(rig.neutral, rig.deltas, rig.faces, P, start.names, start, lambda_l1=0.5)
    err = np.linalg.norm(m.points(rig.neutral, rig.faces) - true.points(rig.neutral, rig.faces), axis=1)
    assert err0.mean() > 2.0  # the template's vertices are far from where the markers were placed
    assert err.mean() < 0.5, err.mean()  # measured 0.20 mm
    assert m.surface_rms_mm < 0.6  # the 0.3 mm noise
    round_trip = MarkerMap.from_json(m.to_json())
    assert np.allclose(round_trip.points(rig.neutral, rig.faces), m.points(rig.neutral, rig.faces))


def test_actor_weights_from_the_true_rig_follow_the_performance(procedural_take):
    from rigbuild.eval.retarget import active_shapes, mean_correlation, weight_mae
    from rigbuild.retarget.common import lowpass_markers

    rig, W, true, start, P = procedural_take
    p = actor_rig_from_config({})
    m = fit_marker_map(rig.neutral, rig.deltas, rig.faces, P, start.names, start, lambda_l1=p.lambda_l1)
    b0, D = sample_rig_at_markers(rig.neutral, rig.deltas, rig.faces, m)
    sol = solve_actor_weights(b0, D, lowpass_markers(P, 30.0, p.marker_lowpass_hz), lambda_l1=p.lambda_l1)
    assert sol.converged
    corr = mean_correlation(sol.weights, W, active_shapes(W))
    assert corr > 0.85, corr  # measured 0.90 (0.30 mm noise; some shapes barely move the 69 markers)
    assert weight_mae(sol.weights, W) < 0.05  # measured 0.039
    # the vertex map (markers assumed on the template's vertices) is measurably worse
    b0v, Dv = sample_rig_at_markers(rig.neutral, rig.deltas, rig.faces, start)
    vsol = solve_actor_weights(b0v, Dv, lowpass_markers(P, 30.0, p.marker_lowpass_hz), lambda_l1=p.lambda_l1)
    assert mean_correlation(vsol.weights, W, active_shapes(W)) < corr - 0.05


def test_tracked_markers_on_map_sample_each_frame_at_the_skin_points():
    from rigbuild.retarget.actor_rig import tracked_markers_on_map

    V, F = _square()
    frames = np.stack([V, V + [1.0, 2.0, 3.0], V * 2.0])
    m = MarkerMap(["a", "b"], np.array([0, 1]), np.array([[1.0, 0, 0], [0, 0.5, 0.5]]), np.array([0.0, 1.0]))
    out = tracked_markers_on_map(frames, F, m, lost=np.array([False, False, True]))
    assert np.allclose(out[0], [[0, 0, 0], [5, 10, 1]])  # b: the middle of an edge, 1 mm along +z
    assert np.allclose(out[1], out[0] + [1, 2, 3])
    assert np.isnan(out[2]).all()
    with pytest.raises(InputError, match="topology"):
        tracked_markers_on_map(frames, F[:1], m)


def test_markers_placed_on_the_neutral_from_the_takes_most_neutral_frames(procedural_take):
    """No rig, only the actor's neutral mesh: the take's frames at the neutral expression (a tenth of it here,
    held at rest as a take starts and ends) place the hand-placed markers on the skin; the expressive frames,
    which a rigid fit to the neutral leaves with large residuals, are not used."""
    from rigbuild.retarget.actor_rig import place_markers_on_neutral

    rig, W, true, start, P = procedural_take
    at_rest = np.zeros(W.shape[0], dtype=bool)
    at_rest[:15] = at_rest[-15:] = True  # 1 s of rest at each end: those frames show the neutral
    moving = np.abs(W).sum(1) > 0.5
    assert moving[~at_rest].mean() > 0.8  # the rest of the take is expressive
    Q = P.copy()
    rest = true.points(rig.neutral, rig.faces)
    rng = np.random.default_rng(5)
    Rr = Rotation.random(at_rest.sum(), random_state=6).as_matrix()
    Q[at_rest] = np.einsum("fij,mj->fmi", Rr, rest) + rng.normal(scale=50.0, size=(at_rest.sum(), 1, 3))
    Q[at_rest] += rng.normal(scale=0.3, size=Q[at_rest].shape)
    err0 = np.linalg.norm(start.points(rig.neutral, rig.faces) - rest, axis=1)
    m = place_markers_on_neutral(rig.neutral, rig.faces, Q, start, neutral_fraction=0.1)
    err = np.linalg.norm(m.points(rig.neutral, rig.faces) - rest, axis=1)
    assert err0.mean() > 2.0
    assert err.mean() < 0.25, err.mean()  # measured 0.16 mm: 30 frames of 0.3 mm noise
    assert m.surface_rms_mm < 0.6 and m.placed.all()
    # every frame, expressions included, pulls the markers off their skin points: measured 0.84 mm (0.16 above)
    worse = place_markers_on_neutral(rig.neutral, rig.faces, Q, start, neutral_fraction=1.0)
    assert np.linalg.norm(worse.points(rig.neutral, rig.faces) - rest, axis=1).mean() > 3 * err.mean()


def test_markers_placed_on_the_neutral_exactly_without_noise():
    """Noise-free points of a curved sheet moved rigidly, mixed with frames of another shape: each marker lands
    on its own surface point (exact up to the rounds' convergence)."""
    from rigbuild.retarget.actor_rig import place_markers_on_neutral

    n = 12
    x, y = np.meshgrid(np.linspace(-30, 30, n), np.linspace(-30, 30, n))
    V = np.stack([x.ravel(), y.ravel(), 0.02 * (x**2 + 2 * y**2).ravel()], 1)
    quads = [(i * n + j, i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j)
             for i in range(n - 1) for j in range(n - 1)]
    F = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    rng = np.random.default_rng(2)
    M = 9
    fids = rng.choice(len(F), M, replace=False)
    true = MarkerMap([f"m{i}" for i in range(M)], fids, rng.dirichlet([2, 2, 2], size=M), np.zeros(M))
    start = vertex_marker_map(true.names, F[fids, 0], F)
    rest = true.points(V, F)
    Rr = Rotation.random(40, random_state=3).as_matrix()
    take = np.einsum("fij,mj->fmi", Rr, rest) + rng.normal(scale=20.0, size=(40, 1, 3))
    take[10:] += rng.normal(scale=4.0, size=(30, M, 3))  # 30 frames of other expressions
    take[3, 4] = np.nan  # a gap
    m = place_markers_on_neutral(V, F, take, start, neutral_fraction=0.25, min_frames=5, iterations=4)
    assert np.abs(m.points(V, F) - rest).max() < 1e-6
    with pytest.raises(InputError, match="6 or more"):
        place_markers_on_neutral(V, F, take[:, :5], MarkerMap(start.names[:5], start.face_ids[:5],
                                                               start.barycentric[:5], start.normal_offset[:5]))


def test_take_marker_params_are_checked():
    from rigbuild.retarget.params import from_config, take_markers_from_config

    assert take_markers_from_config({}).rom == "take"
    assert from_config({"take_markers": {"rom": "marker_set"}}).take_markers.rom == "marker_set"
    for bad in ({"rom": "vertices"}, {"neutral_fraction": 0.0}, {"neutral_fraction": 1.5}, {"min_frames": 0},
                {"iterations": 0}, {"trim": 1.0}, {"neutral_fractoin": 0.1}):
        with pytest.raises(InputError):
            take_markers_from_config(bad)


def test_eval_of_the_take_markers_is_exact_on_a_known_placement(tmp_path, procedural_take):
    """The take-marker map's ground-truth evaluation: a map at the markers' true skin points scores 0 mm, and
    the marker set's vertices score their exact distance to those points."""
    import json

    from rigbuild.eval.retarget import run_eval_take_markers
    from rigbuild.io.rigs import write_rig_npz

    rig, W, true, start, P = procedural_take
    write_rig_npz(tmp_path / "actor.npz", rig)
    rest = true.points(rig.neutral, rig.faces)
    R = Rotation.from_euler("y", 20, degrees=True).as_matrix()
    truth = {"shape_names": np.asarray(rig.shape_names), "weights": np.zeros((1, len(rig.shape_names))),
             "markers": (rest @ R.T + [5.0, -3.0, 400.0])[None], "rotation": R[None],
             "translation": np.array([[5.0, -3.0, 400.0]]), "marker_names": np.asarray(true.names)}
    np.savez(tmp_path / "truth.npz", **truth)
    (tmp_path / "map.json").write_text(json.dumps({"markers": true.to_json()}))
    m = run_eval_take_markers(tmp_path / "map.json", tmp_path / "truth.npz", tmp_path / "actor.npz",
                              tmp_path / "metrics.json")
    assert m["marker_map_skin_error_mm"] == pytest.approx(0.0, abs=1e-4)  # the rig file stores float32
    expected = np.linalg.norm(start.points(rig.neutral, rig.faces) - rest, axis=1).mean()
    assert m["marker_set_skin_error_mm"] == pytest.approx(expected, rel=1e-4)
    assert json.loads((tmp_path / "metrics.json").read_text())["retarget"]["take_markers"] == m


def test_rig_at_markers_takes_the_refined_rig_from_the_actor_rig_solve(tmp_path):
    """Ribera's and Seol's actor-rig methods read the rig at the markers from the take's actor-rig solve when it
    holds a refined one (rule actor_rig_weights with refine_iterations), the personalized rig's otherwise; a solve
    of other markers is refused by name."""
    import json

    from rigbuild.io.rigs import load_rig, write_rig_npz
    from rigbuild.retarget.stage import load_rig_at_markers

    rig = load_rig("procedural")
    write_rig_npz(tmp_path / "rig.npz", rig)
    mmap = vertex_marker_map(rig.marker_names, rig.marker_vertices, rig.faces)
    (tmp_path / "marker_map.json").write_text(json.dumps({"markers": mmap.to_json()}))
    b0, D = sample_rig_at_markers(rig.neutral, rig.deltas, rig.faces, mmap)
    np.savez(tmp_path / "plain.npz", weights=np.zeros((2, len(D))), marker_names=np.asarray(mmap.names))
    np.savez(tmp_path / "refined.npz", marker_names=np.asarray(mmap.names), rig_neutral_at_markers=b0 + 1.0,
             rig_deltas_at_markers=2.0 * D)
    np.savez(tmp_path / "other.npz", marker_names=np.asarray(mmap.names[::-1]), rig_neutral_at_markers=b0,
             rig_deltas_at_markers=D)
    for solve, (want_b0, want_D) in ((None, (b0, D)), ("plain.npz", (b0, D)), ("refined.npz", (b0 + 1.0, 2.0 * D))):
        got = load_rig_at_markers(tmp_path / "rig.npz", tmp_path / "marker_map.json",
                                  None if solve is None else tmp_path / solve)
        np.testing.assert_allclose(got.neutral, want_b0, atol=1e-9)
        np.testing.assert_allclose(got.deltas, want_D, atol=1e-9)
    with pytest.raises(InputError, match="other markers or shapes"):
        load_rig_at_markers(tmp_path / "rig.npz", tmp_path / "marker_map.json", tmp_path / "other.npz")
