"""Hand-painted dots and performance markers (rigbuild.synth.dots, rigbuild.synth.markers): offsets against
sigma, missing fraction, sizes, centres on the moving skin; marker gaps from the cameras' view and noise."""

from __future__ import annotations

import numpy as np
import pytest

from rigbuild.camera import Camera, look_at
from rigbuild.rig import Rig
from rigbuild.synth.dots import dot_centres, edge_neighbours, no_dots, place_painted_dots
from rigbuild.synth.markers import marker_visibility, performance_markers


@pytest.fixture(scope="module")
def head():
    from rigbuild.io.rigs import load_rig

    return load_rig("procedural")


def _plane(n=61, half=30.0, z=0.0, start=0):
    g = np.stack(np.meshgrid(np.linspace(-half, half, n), np.linspace(-half, half, n)), -1).reshape(-1, 2)
    P = np.hstack([g, np.full((g.shape[0], 1), z)])
    faces = []
    for j in range(n - 1):
        for i in range(n - 1):
            a = j * n + i
            faces += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]  # normals +z
    return P, np.asarray(faces) + start


def test_offsets_on_a_plane_are_the_drawn_gaussian():
    P, faces = _plane()
    rig = Rig(P, np.zeros((0, P.shape[0], 3)), [], faces)
    centre = np.flatnonzero((np.abs(P[:, :2]) <= 8).all(1))
    sites = np.resize(centre, 1500)
    pd = place_painted_dots(rig, sites, sigma_mm=2.0, missing_fraction=0.0, seed=1)
    d = dot_centres(pd, P) - P[sites[pd.site]]
    assert np.abs(d[:, 2]).max() == 0.0  # on the plane
    # a walk on a plane is the straight tangent offset: same length as drawn, exactly
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), np.hypot(*pd.offset_mm.T), atol=1e-9)
    # per-axis standard deviation against sigma (1500 dots: standard error 1.8 %)
    assert d[:, 0].std() == pytest.approx(2.0, rel=0.07) and d[:, 1].std() == pytest.approx(2.0, rel=0.07)
    assert np.abs(d[:, :2].mean(0)).max() < 0.2


def test_dots_walk_along_the_curved_skin(head):
    from rigbuild.dots import painted_dot_vertices

    sites = painted_dot_vertices(head, 14.0)
    big = np.concatenate([sites] * 10)
    pd = place_painted_dots(head, big, sigma_mm=2.0, missing_fraction=0.0, seed=3)
    L = np.hypot(*pd.offset_mm.T)
    full = np.isclose(pd.walked_mm, L, rtol=1e-9)  # the whole offset walked along the skin ...
    assert full.mean() >= 0.99 and np.all(pd.walked_mm <= L + 1e-9)  # ... unless the walk met a border (lids, lips)
    chord = np.linalg.norm(dot_centres(pd, head.neutral) - head.neutral[big[pd.site]], axis=1)
    assert np.all(chord <= L + 1e-9) and np.median(chord / np.maximum(L, 1e-12)) > 0.995  # geodesic ~ chord at 2 mm
    rms = np.sqrt((pd.walked_mm[full] ** 2).mean() / 2)  # per-axis sd of the geodesic offsets
    assert rms == pytest.approx(2.0, rel=0.06)  # 1080 dots: standard error 2.2 %
    # centres lie on their triangles (barycentric, non-negative) and follow the skin in a deformed frame
    assert np.all(pd.bary >= 0) and np.allclose(pd.bary.sum(1), 1)
    moved = head.neutral + head.deltas[head.shape_index("jawOpen")]
    c = dot_centres(pd, moved)
    expect = np.einsum("dkc,dk->dc", moved[head.faces[pd.triangles]], pd.bary)
    np.testing.assert_allclose(c, expect, atol=1e-12)
    stacked = dot_centres(pd, np.stack([head.neutral, moved]))
    assert stacked.shape == (2, len(pd), 3) and np.allclose(stacked[1], c)


def test_missing_sizes_darkness_and_exact_sites(head):
    sites = np.arange(0, head.n_vertices, 7)[:400]
    M = 69
    pd = place_painted_dots(head, sites, 2.0, missing_fraction=0.05, seed=0, keep_first=M)
    assert pd.missing_sites.size == round(0.05 * (400 - M)) and len(pd) == 400 - pd.missing_sites.size
    assert pd.missing_sites.min() >= M  # the first sites (markers) are always painted
    assert np.array_equal(np.sort(np.concatenate([pd.site, pd.missing_sites])), np.arange(400))
    d = 2 * pd.radius_mm
    assert d.min() >= 2.0 and d.max() <= 4.0 and d.mean() == pytest.approx(3.0, abs=0.12)
    assert pd.albedo.dtype == np.uint8 and pd.albedo.min() >= round(255 * 0.05) and pd.albedo.max() <= round(255 * 0.25)
    assert np.unique(pd.albedo[:, 0]).size > 10 and np.all(pd.albedo[:, 0] == pd.albedo[:, 2])
    exact = place_painted_dots(head, sites, 0.0, missing_fraction=0.0)
    assert np.array_equal(dot_centres(exact, head.neutral), head.neutral[sites])  # sigma 0: bit-exact at the sites
    assert len(no_dots()) == 0 and len(place_painted_dots(head, [], 2.0)) == 0
    with pytest.raises(ValueError, match="sigma"):
        place_painted_dots(head, sites, -1.0)


def test_edge_neighbours_of_a_quad():
    nb = edge_neighbours(np.array([[0, 1, 2], [0, 2, 3]]))
    assert nb.tolist() == [[-1, -1, 1], [0, -1, -1]]


def _camera(cid, centre, target=(0, 0, 0), size=(640, 480), f=800.0):
    R, t = look_at(np.asarray(centre, float), np.asarray(target, float))
    K = np.array([[f, 0, size[0] / 2], [0, f, size[1] / 2], [0, 0, 1]])
    return Camera(cid, size[0], size[1], K, np.zeros(5), R, t)


def test_occluded_and_back_facing_markers_are_gaps():
    """A skin plane (normals +z) with an occluding plate in front of its left half, two cameras in front."""
    P, faces = _plane(21, 40.0)
    Q, qf = _plane(5, 10.0, z=50.0, start=P.shape[0])
    Q[:, 0] -= 22.0  # plate over x in [-32, -12]
    V = np.vstack([P, Q])
    F = np.vstack([faces, qf])
    rig = Rig(V, np.zeros((1, V.shape[0], 3)), ["none"], F)
    left = int(np.argmin(np.linalg.norm(P - [-20, 0, 0], axis=1)))
    right = int(np.argmin(np.linalg.norm(P - [20, 0, 0], axis=1)))
    pl = place_painted_dots(rig, [left, right], 0.0, 0.0)
    cams = [_camera("a", [-20, 0, 400]), _camera("b", [20, 0, 400])]
    seen = marker_visibility(V, F, pl, cams, sign=1.0)
    assert seen.tolist() == [[False, True], [False, True]]
    m = performance_markers(rig, np.zeros((3, 1)), None, None, pl, cams, noise_mm=0.0, normal_sign=1.0)
    assert np.isnan(m[:, 0]).all() and np.array_equal(m[:, 1], np.repeat(P[[right]], 3, 0))
    # seen from behind the skin: faces away from both cameras -> gaps
    back = [_camera("c", [-20, 0, -400]), _camera("d", [20, 0, -400])]
    assert not marker_visibility(V, F, pl, back, sign=1.0).any()
    # out of the image
    assert not marker_visibility(V, F, pl, [_camera("e", [0, 0, 400], target=(300, 0, 0))], sign=1.0).any()


def test_marker_behind_the_head_is_a_gap_and_noise_std(head):
    from rigbuild.synth.motion import make_head_motion, make_performance_weights
    from rigbuild.synth.rig_layout import make_camera_rig

    fc = head.neutral[head.face_vertices].mean(0)
    cams = make_camera_rig(4, 640, 480, 450.0, (-45, 45), 1, target=fc)
    back = int(np.argmin(head.neutral[:, 2]))  # the back of the skull
    nose = int(np.argmax(head.neutral[:, 2]))
    pl = place_painted_dots(head, [back, nose], 0.0, 0.0)
    W = make_performance_weights(head.shape_names, 6, 30.0, seed=1)
    R, t = make_head_motion(6, seed=2, max_rotation_deg=8.0, max_translation_mm=10.0, bound="total")
    m, seen = performance_markers(head, W, R, t, pl, cams, noise_mm=0.3, seed=0, return_seen=True)
    assert np.isnan(m[:, 0]).all() and np.all(seen[:, 0] == 0)
    assert np.isfinite(m[:, 1]).all() and np.all(seen[:, 1] >= 2)
    # noise against the model: per-axis sd 0.3 mm (clean positions from the posed mesh)
    M = place_painted_dots(head, head.marker_vertices, 2.0, 0.0, seed=5)
    Wn = make_performance_weights(head.shape_names, 40, 30.0, seed=2)
    R2, t2 = make_head_motion(40, seed=3)
    noisy = performance_markers(head, Wn, R2, t2, M, None, noise_mm=0.3, seed=7)
    clean = performance_markers(head, Wn, R2, t2, M, None, noise_mm=0.0)
    posed = np.einsum("fij,fvj->fvi", R2, head.evaluate(Wn)) + t2[:, None]
    np.testing.assert_allclose(clean, dot_centres(M, posed), atol=1e-9)
    r = (noisy - clean).reshape(-1)
    assert r.std() == pytest.approx(0.3, rel=0.03) and abs(r.mean()) < 0.01  # 8280 samples: s.e. of sd 0.8 %
