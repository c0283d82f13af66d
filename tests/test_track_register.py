"""Neutral registration: dot labeling, closest-point / ray terms, non-rigid registration of a template to a
synthetic actor's neutral scan (procedural head, no external data)."""

from __future__ import annotations

import numpy as np
import pytest

from rigbuild.errors import InputError
from rigbuild.geometry.rigid import apply_rigid
from rigbuild.track.laplacian import vertex_normals
from rigbuild.track.mesh import build_tracking_mesh
from rigbuild.track.params import RegistrationParams
from rigbuild.track.register import label_dots, ray_targets, register_neutral, relabel_dots, require_markers


@pytest.fixture(scope="module")
def head():
    from rigbuild.io.rigs import load_rig

    return load_rig("procedural")


def _rot(deg, axis=(0.3, 1.0, 0.2)):
    import cv2

    a = np.asarray(axis, float)
    return cv2.Rodrigues(a / np.linalg.norm(a) * np.radians(deg))[0]


def test_label_dots_recovers_permutation_and_similarity(head):
    tm = head.markers()
    rng = np.random.default_rng(0)
    perm = rng.permutation(tm.shape[0])
    R, t, s = _rot(12), np.array([10.0, -30.0, 420.0]), 1.07
    dots = apply_rigid(tm, R, t, s)[perm] + rng.normal(0, 0.1, tm.shape)
    labels, (s2, R2, t2), rms = label_dots(tm, dots[:-3])  # three dots not detected
    inv = np.argsort(perm)
    expect = np.where(inv < tm.shape[0] - 3, inv, -1)
    np.testing.assert_array_equal(labels, expect)
    assert s2 == pytest.approx(s, rel=2e-3)
    np.testing.assert_allclose(R2, R, atol=3e-3)
    assert rms < 0.25


def test_label_dots_ignores_dark_spots_far_from_the_face(head):
    tm = head.markers()
    rng = np.random.default_rng(1)
    perm = rng.permutation(tm.shape[0])
    R, t, s = _rot(-20), np.array([-5.0, 20.0, 450.0]), 0.95
    dots = apply_rigid(tm, R, t, s)[perm] + rng.normal(0, 0.1, tm.shape)
    centre, size = dots.mean(0), np.linalg.norm(dots - dots.mean(0), axis=1).max()
    far = centre + rng.choice([-1, 1], (tm.shape[0] // 3, 3)) * 1.5 * size  # hair, background
    labels, (s2, R2, _), _ = label_dots(tm, np.concatenate([dots, far]))
    np.testing.assert_array_equal(labels, np.argsort(perm))
    assert s2 == pytest.approx(s, rel=2e-3)
    np.testing.assert_allclose(R2, R, atol=3e-3)


def test_relabel_dots_is_one_to_one_and_gated():
    markers = np.array([[0.0, 0, 0], [10, 0, 0], [20, 0, 0], [np.nan, np.nan, np.nan]])
    dots = np.array([[10.5, 0, 0], [0.4, 0, 0], [14.0, 0, 0], [1.0, 0, 0]])
    # marker 0 takes dot 1 (0.4 mm), marker 1 dot 0 (0.5 mm); marker 2 has nothing within 3 mm; NaN marker unassigned
    np.testing.assert_array_equal(relabel_dots(markers, dots, 3.0), [1, 0, -1, -1])
    np.testing.assert_array_equal(relabel_dots(markers, dots, 10.0), [1, 0, 2, -1])


def test_ray_targets_exact():
    o = np.array([[0, 0, 0.0], [1, 1, 1]])
    d = np.array([[0, 0, 1.0], [1, 0, 0]])
    p = np.array([[3, 4, 5.0], [0, 7, 1]])
    np.testing.assert_allclose(ray_targets(p, o, d), [[0, 0, 5], [0, 1, 1]])


def test_require_markers_names_the_fix(head):
    bare = head.with_markers([], [])
    with pytest.raises(InputError, match="marker"):
        require_markers(bare)


def test_tracking_mesh_and_attachment(head):
    tm = build_tracking_mesh(head.neutral, head.faces, head.face_region)
    assert tm.n + tm.untracked.size == head.n_vertices
    moved = tm.local(head.neutral) + [1.0, 2.0, 3.0]
    full = tm.to_full(moved, head.neutral)
    np.testing.assert_allclose(full - head.neutral, np.broadcast_to([1.0, 2.0, 3.0], full.shape), atol=1e-12)
    tri, bary = tm.vertex_points(np.arange(tm.n))
    np.testing.assert_allclose(np.einsum("nk,nkd->nd", bary, moved[tm.faces[tri]]), moved)


def _warped_actor_scan(head, seed=4):
    """A warped actor (``seed``) of ``head`` moved rigidly 400 mm in front of the camera, and a dense scan of its
    face region: (truth (V, 3), face vertex ids, scan points (40000, 3), unit normals (40000, 3), the rng)."""
    from rigbuild.synth.actor import make_actor_rig

    actor, _ = make_actor_rig(head, seed=seed)
    R, t = _rot(5), np.array([3.0, -8.0, 400.0])
    truth = apply_rigid(actor.neutral, R, t)
    face = head.face_vertices
    F = head.faces[np.isin(head.faces, face).all(1)]
    rng = np.random.default_rng(1)
    tri = rng.integers(0, len(F), 40000)
    b = rng.dirichlet([1, 1, 1], tri.size)
    N = vertex_normals(truth, head.faces)
    pts = np.einsum("nk,nkd->nd", b, truth[F[tri]])
    nrm = np.einsum("nk,nkd->nd", b, N[F[tri]])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return truth, face, pts, nrm, rng


def test_stencil_matched_dots_keep_the_painted_dots_only():
    """Dots near a stencil site are kept one per site; a detection far from every site (a brow hair, an iris) and
    the second of two detections near one site are not; sites off the mesh (-1) take none; gate 0 keeps all."""
    from rigbuild.track.register import stencil_matched_dots

    p = np.array([[0.0, 0, 0], [20, 0, 0], [0, 20, 0], [20, 20, 0]])
    mk_local = np.array([0, 1, 2, -1])
    dots = np.array([[1.0, 0, 0], [20, 2, 0], [10, 10, 0], [0, 21.5, 0], [0, 23, 0], [20, 20, 0]])
    keep = stencil_matched_dots(p, mk_local, dots, 4.0)
    assert keep.tolist() == [True, True, False, True, False, False]
    assert stencil_matched_dots(p, mk_local, dots, 1.2).tolist() == [True, False, False, False, False, False]
    assert stencil_matched_dots(p, mk_local, dots, 0.0) is None


def test_register_neutral_to_warped_actor_scan(head):
    truth, face, pts, nrm, rng = _warped_actor_scan(head)
    dots = truth[head.marker_vertices][rng.permutation(head.marker_vertices.size)]
    reg = register_neutral(head, pts, nrm, dots, params=RegistrationParams(iterations=10))
    err = np.linalg.norm(reg.vertices[face] - truth[face], axis=1)
    s, Rs, ts = reg.similarity
    err_sim = np.linalg.norm(apply_rigid(head.neutral[face], Rs, ts, s) - truth[face], axis=1)
    assert np.all(reg.dot_labels >= 0)
    assert reg.dot_rms_mm < 0.1
    assert reg.scan_rms_mm < 0.3
    assert err.mean() < 0.3 * err_sim.mean()
    print("registration error mean", err.mean(), "similarity only", err_sim.mean())
    assert err.mean() < 0.6


def test_point_cloud_normals_exact_on_a_plane_and_oriented():
    """Points on the plane z = 0.3 x - 0.2 y: every PCA normal is the plane's normal, exactly, signed like the
    orientation hint (half the hints point the other way)."""
    from rigbuild.geometry.mesh import point_cloud_normals

    rng = np.random.default_rng(0)
    xy = rng.uniform(-10, 10, size=(500, 2))
    P = np.column_stack([xy, 0.3 * xy[:, 0] - 0.2 * xy[:, 1]])
    n_true = np.array([-0.3, 0.2, 1.0]) / np.linalg.norm([-0.3, 0.2, 1.0])
    hint = np.where((np.arange(500) % 2 == 0)[:, None], n_true + [0.5, 0, 0], -n_true)
    n = point_cloud_normals(P, hint, k=12)
    expected = np.where((np.arange(500) % 2 == 0)[:, None], n_true, -n_true)
    np.testing.assert_allclose(n, expected, atol=1e-9)
    assert point_cloud_normals(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0, 3)


def test_register_neutral_with_stencil_dots_beats_markers_alone(head):
    """The same warped actor and scan as above: painting the stencil dots between the markers (and telling the
    registration where they are on the template) lowers the face-region error; the markers output stays the
    marker vertices."""
    from rigbuild.dots import painted_dot_vertices

    truth, face, pts, nrm, rng = _warped_actor_scan(head)
    errors = {}
    for spacing in (None, 16.0):
        dv = painted_dot_vertices(head, spacing)
        dots = truth[dv][rng.permutation(dv.size)]
        reg = register_neutral(head, pts, nrm, dots, params=RegistrationParams(iterations=10), dot_vertices=dv)
        assert reg.dot_labels.shape == (dv.size,)
        assert np.mean(reg.dot_labels >= 0) > 0.95
        assert reg.markers.shape == (head.marker_vertices.size, 3)
        np.testing.assert_allclose(reg.markers, reg.vertices[head.marker_vertices])
        errors[spacing] = float(np.linalg.norm(reg.vertices[face] - truth[face], axis=1).mean())
    print("registration error: markers only", errors[None], "with the 16 mm stencil", errors[16.0])
    assert painted_dot_vertices(head, 16.0).size > head.marker_vertices.size + 20
    assert errors[16.0] < 0.8 * errors[None]


def test_closest_point_targets_gate_distance_and_normal_angle():
    from scipy.spatial import cKDTree

    from rigbuild.track.register import closest_point_targets

    scan = np.array([[0.0, 0.0, 1.0], [10.0, 0.0, 0.5], [20.0, 0.0, 5.0]])
    a = np.radians(45.0)
    scan_n = np.array([[0, 0, 1.0], [np.sin(a), 0, np.cos(a)], [0, 0, 1.0]])
    pts = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [20.0, 0.0, 0.0]])
    nrm = np.tile([0, 0, 1.0], (3, 1))
    tgt, w, d = closest_point_targets(pts, nrm, cKDTree(scan), scan, scan_n, gate_mm=2.0, max_angle_deg=60.0)
    np.testing.assert_allclose(tgt[0], [0, 0, 1.0])  # on the tangent plane of the scan point
    np.testing.assert_allclose(d, [1.0, 0.5, 5.0])
    np.testing.assert_allclose(w, [1.0, np.cos(a), 0.0])  # third: beyond the distance gate
    _, w30, _ = closest_point_targets(pts, nrm, cKDTree(scan), scan, scan_n, gate_mm=2.0, max_angle_deg=30.0)
    np.testing.assert_allclose(w30, [1.0, 0.0, 0.0])  # the 45-degree normal is rejected at 30 degrees


def _warped_scan(head, seed=4):
    """:func:`_warped_actor_scan` as (truth, the face-region triangles, scan points, unit normals)."""
    truth, face, pts, nrm, _ = _warped_actor_scan(head, seed)
    return truth, head.faces[np.isin(head.faces, face).all(1)], pts, nrm


@pytest.mark.parametrize("n_landmarks, bound_mm", [(60, 2.5), (150, 2.5)])
def test_register_neutral_landmark_level_with_unlabeled_dots(head, n_landmarks, bound_mm):
    """coarse: landmarks on the warped actor: surface landmarks as a detector gives them (a shared bias: the set
    shifted by 3 mm and scaled by 2 %, plus 0.5 mm noise; a tenth unreliable and 6 mm off) place and pull the
    template (a similarity and ICP on the scan below AFFINE_MIN_LANDMARKS reliable ones, else affine); dots
    painted off the template's vertices (random points of the face) are unlabeled features; each gets its own
    surface location. The face error is a fraction of the landmark placement's (the template placed by the
    biased landmarks alone)."""
    from rigbuild.track.register import AFFINE_MIN_LANDMARKS, LandmarkObservations

    truth, F, pts, nrm = _warped_scan(head)
    rng = np.random.default_rng(2)
    n = n_landmarks
    lt = rng.choice(len(F), n, replace=False)
    lb = rng.dirichlet([2, 2, 2], n)
    X = np.einsum("nk,nkd->nd", lb, truth[F[lt]])
    X = (X - X.mean(0)) * 1.02 + X.mean(0) + [2.0, -2.0, 1.0] + rng.normal(0, 0.5, (n, 3))
    rel = np.ones(n)
    X[: n // 10] += rng.normal(0, 6.0, (n // 10, 3))
    rel[: n // 10] = 0.05  # sliding contour points: unreliable
    lm = LandmarkObservations(X, F[lt], lb, rel)
    # hand-painted dots: near each marker, a random point of a triangle around it, not the vertex
    near = [np.flatnonzero((F == v).any(1)) for v in head.marker_vertices]
    dt = np.array([rng.choice(k) for k in near])
    db = rng.dirichlet([1, 1, 1], dt.size)
    dots = np.einsum("nk,nkd->nd", db, truth[F[dt]])[rng.permutation(dt.size)]
    face = head.face_vertices
    reg = register_neutral(head, pts, nrm, dots, params=RegistrationParams(iterations=10, coarse="landmarks"),
                           landmarks=lm)
    err = np.linalg.norm(reg.vertices[face] - truth[face], axis=1).mean()
    base = register_neutral(head, pts, nrm, dots, params=RegistrationParams(iterations=10))
    err_dots = np.linalg.norm(base.vertices[face] - truth[face], axis=1).mean()
    print(f"{n} landmarks ({'affine' if n - n // 10 >= AFFINE_MIN_LANDMARKS else 'similarity'}): landmark level "
          f"{err:.3f} mm, dot labeling on off-vertex dots {err_dots:.3f} mm")
    s, R, t = reg.similarity
    from rigbuild.geometry.rigid import fit_similarity

    s0, R0, t0 = fit_similarity(np.einsum("nk,nkd->nd", lb, head.neutral[F[lt]])[n // 10:], X[n // 10:])
    err_placed = np.linalg.norm(apply_rigid(head.neutral[face], R0, t0, s0) - truth[face], axis=1).mean()
    print(f"  placed by the landmarks alone: {err_placed:.3f} mm")
    assert err < bound_mm and err < 0.7 * err_placed
    v, b, k = reg.dot_surface
    at = np.einsum("nk,nkd->nd", b, reg.vertices[v])
    assert k.size >= 0.9 * dots.shape[0]  # nearly every dot is on the registered skin ...
    assert np.linalg.norm(at - dots[k], axis=1).mean() < 0.3  # ... where its own surface point is
    assert reg.dot_labels.shape == (head.marker_vertices.size,)
    with pytest.raises(InputError, match="no face landmarks"):
        register_neutral(head, pts, nrm, dots, params=RegistrationParams(coarse="landmarks"))


def test_register_neutral_landmark_level_unpainted(head):
    """coarse: landmarks with no dots at all (an unpainted face): the landmarks and the scan alone register the
    template, as well as with the dots (within 0.3 mm), and no dot gets a label or a surface point."""
    from rigbuild.track.register import LandmarkObservations

    truth, F, pts, nrm = _warped_scan(head)
    rng = np.random.default_rng(2)
    n = 150
    lt = rng.choice(len(F), n, replace=False)
    lb = rng.dirichlet([2, 2, 2], n)
    X = np.einsum("nk,nkd->nd", lb, truth[F[lt]]) + rng.normal(0, 0.5, (n, 3))
    lm = LandmarkObservations(X, F[lt], lb, np.ones(n))
    face = head.face_vertices
    params = RegistrationParams(iterations=10, coarse="landmarks")
    reg = register_neutral(head, pts, nrm, np.zeros((0, 3)), params=params, landmarks=lm)
    err = np.linalg.norm(reg.vertices[face] - truth[face], axis=1).mean()
    painted = register_neutral(head, pts, nrm, truth[head.marker_vertices], params=params, landmarks=lm)
    err_painted = np.linalg.norm(painted.vertices[face] - truth[face], axis=1).mean()
    print(f"unpainted {err:.3f} mm, with the markers painted {err_painted:.3f} mm")
    assert err < err_painted + 0.3
    assert (reg.dot_labels < 0).all() and reg.dot_labels.shape == (head.marker_vertices.size,)
    assert reg.dot_surface is None or reg.dot_surface[0].shape[0] == 0


def test_local_surface_points_round_trip(head):
    """Surface points as full-topology triangle corners (any corner order) map to the tracking mesh's triangles
    and corner order, giving the same 3-D points."""
    from rigbuild.track.stage import local_surface_points

    tm = build_tracking_mesh(head.neutral, head.faces, head.face_region)
    rng = np.random.default_rng(0)
    t = rng.integers(0, tm.faces.shape[0], 50)
    b = rng.dirichlet([1, 1, 1], 50)
    full = tm.vertex_ids[tm.faces[t]]
    perm = rng.permutation(3)
    tri, bary = local_surface_points(tm, full[:, perm], b[:, perm])
    local = tm.local(head.neutral)
    np.testing.assert_allclose(np.einsum("nk,nkd->nd", bary, local[tm.faces[tri]]),
                               np.einsum("nk,nkd->nd", b, local[tm.faces[t]]), atol=1e-9)
    with pytest.raises(InputError, match="not on the tracked face mesh"):
        local_surface_points(tm, np.array([[0, 0, 0]]), np.array([[1.0, 0, 0]]))


def test_soft_hand_placed_dots_register_better_than_pinned_dots_and_keep_their_own_skin_points(head):
    """Dots painted 2 mm (sd) off their stencil sites on the warped actor: pinning each site vertex to its dot
    (dot_weight 10) carries the placement error into the registration; soft dots (0.3) let the scan and the
    Laplacian prior average it out, and with ``dot_surface_points`` each labeled dot keeps its own point on the
    registered skin (within the last gate of its dot)."""
    from rigbuild.dots import painted_dot_vertices
    from rigbuild.synth.actor import make_actor_rig
    from rigbuild.synth.dots import dot_centres, place_painted_dots

    truth, face, pts, nrm, rng = _warped_actor_scan(head)
    actor, _ = make_actor_rig(head, seed=4)
    sites = painted_dot_vertices(head, 16.0)
    pd = place_painted_dots(actor, sites, sigma_mm=2.0, seed=4, missing_fraction=0.0,
                            keep_first=head.marker_vertices.size)
    R, t = _rot(5), np.array([3.0, -8.0, 400.0])
    dots = apply_rigid(dot_centres(pd, actor.neutral), R, t)
    errors = {}
    for label, kw in (("pinned", {}), ("soft", {"dot_weight": 0.3, "lam_schedule": (0.02, 0.5),
                                                 "dot_surface_points": True})):
        reg = register_neutral(head, pts, nrm, dots, params=RegistrationParams(iterations=10, **kw), dot_vertices=sites)
        errors[label] = float(np.linalg.norm(reg.vertices[face] - truth[face], axis=1).mean())
        assert (reg.dot_surface is None) == (label == "pinned")
    vids, bary, ids = reg.dot_surface
    at = np.einsum("nk,nkd->nd", bary, reg.vertices[vids])
    assert ids.size > 0.8 * sites.size and np.allclose(bary.sum(1), 1.0) and np.all(bary >= -1e-9)
    assert np.linalg.norm(at - dots[ids], axis=1).max() <= RegistrationParams().gate_schedule_mm[1] + 1e-6
    print("registration error with 2 mm hand-placed dots:", errors)
    assert errors["soft"] < 0.8 * errors["pinned"]


def test_smooth_stencil_offsets_keeps_the_slow_part_and_drops_a_wrong_match():
    """Offsets of matched dots from their sites: a constant (the mesh's slow error) plus zero-sum placement noise
    and one dot given to the wrong site (20 mm off). With a window wider than the grid the smooth part is the
    constant, exactly: the noise sums to zero and the wrong match is left out."""
    from rigbuild.track.register import smooth_stencil_offsets

    g = np.arange(5) * 16.0
    sites = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    sites = np.column_stack([sites, np.zeros(len(sites))])
    rng = np.random.default_rng(4)
    noise = rng.normal(0, 2.0, (len(sites) - 1, 3))
    noise -= noise.mean(0)
    const = np.array([1.0, -0.5, 0.2])
    offsets = np.vstack([const + noise, const + [20.0, 0.0, 0.0]])
    out = smooth_stencil_offsets(sites, offsets, sigma_mm=1e6)
    np.testing.assert_allclose(out, np.tile(const, (len(sites), 1)), atol=1e-9)
    # a narrow window follows each dot: the placement noise is not averaged away
    assert np.abs(smooth_stencil_offsets(sites, offsets, sigma_mm=1.0)[:-1] - offsets[:-1]).max() < 1e-6


def test_stencil_warp_slides_the_mesh_by_the_dots_tangential_offset():
    """A flat grid whose painted dots all sit 1 mm / -0.5 mm along the surface and 0.5 mm above their stencil
    sites: the stencil warp moves every vertex by the tangential part (1, -0.5, 0) and leaves the normal part to
    the scan."""
    from types import SimpleNamespace

    from grid_mesh import grid_mesh
    from rigbuild.track.register import _stencil_warp

    V, F = grid_mesh(n=21, size=100.0)
    sites = np.flatnonzero((np.round(V[:, 0]) % 25 == 0) & (np.round(V[:, 1]) % 25 == 0))
    dots = V[sites] + [1.0, -0.5, 0.5]
    params = RegistrationParams(stencil_warp=1.0, stencil_smoothing_mm=30.0)
    p = _stencil_warp(V, SimpleNamespace(faces=F), sites, dots[::-1], params)
    np.testing.assert_allclose(p - V, np.tile([1.0, -0.5, 0.0], (len(V), 1)), atol=1e-9)
    # half the step with stencil_warp 0.5; nothing moves with too few matched dots
    half = _stencil_warp(V, SimpleNamespace(faces=F), sites, dots, RegistrationParams(stencil_warp=0.5,
                                                                                      stencil_smoothing_mm=30.0))
    np.testing.assert_allclose(half - V, np.tile([0.5, -0.25, 0.0], (len(V), 1)), atol=1e-9)
    np.testing.assert_array_equal(_stencil_warp(V, SimpleNamespace(faces=F), sites, dots[:3], params), V)


def test_stencil_warp_corrects_a_landmark_level_registration_with_hand_placed_dots(head):
    """coarse: landmarks on the warped actor with a detector's landmarks (shared 3 mm shift, 2 % scale, 0.5 mm noise,
    a tenth unreliable and 6 mm off) and stencil dots painted by hand (2 mm sd off their sites, 5 % missing,
    unlabeled): the dots only pull closest points, so the landmarks' shared bias stays in the tangential
    placement; the stencil warp's local means of the dots' offsets from their sites take most of it out."""
    from rigbuild.dots import painted_dot_vertices
    from rigbuild.synth.actor import make_actor_rig
    from rigbuild.synth.dots import dot_centres, place_painted_dots
    from rigbuild.track.register import LandmarkObservations

    truth, F, pts, nrm = _warped_scan(head)
    face = head.face_vertices
    actor, _ = make_actor_rig(head, seed=4)
    sites = painted_dot_vertices(head, 16.0)
    pd = place_painted_dots(actor, sites, sigma_mm=2.0, seed=4, missing_fraction=0.05,
                            keep_first=head.marker_vertices.size)
    dots = apply_rigid(dot_centres(pd, actor.neutral), _rot(5), np.array([3.0, -8.0, 400.0]))
    rng = np.random.default_rng(4)
    n = 150
    lt, lb = rng.choice(len(F), n, replace=False), rng.dirichlet([2, 2, 2], n)
    X = np.einsum("nk,nkd->nd", lb, truth[F[lt]])
    X = (X - X.mean(0)) * 1.02 + X.mean(0) + [2.0, -2.0, 1.0] + rng.normal(0, 0.5, (n, 3))
    rel = np.ones(n)
    X[: n // 10] += rng.normal(0, 6.0, (n // 10, 3))
    rel[: n // 10] = 0.05
    lm = LandmarkObservations(X, F[lt], lb, rel)
    err = {}
    for w in (0.0, 1.0):
        reg = register_neutral(head, pts, nrm, dots, landmarks=lm, dot_vertices=sites,
                               params=RegistrationParams(iterations=10, coarse="landmarks", stencil_warp=w))
        err[w] = float(np.linalg.norm(reg.vertices[face] - truth[face], axis=1).mean())
    print("landmark level with hand-placed stencil dots, face error without / with the stencil warp:", err)
    assert err[1.0] < 0.7 * err[0.0]
