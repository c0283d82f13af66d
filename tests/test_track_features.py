"""Unit tests of tracking level helpers: dots, lifting, triangulation, guided matching, guided flow."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from rigbuild.camera import Camera, look_at
from rigbuild.errors import InputError
from rigbuild.track.features import (DotParams, assign_detections, depth_to_image_grid, detect_dots, lift,
                                     triangulate)
from rigbuild.track.flow import guided_flow
from rigbuild.track.matches import ViewFrame
from rigbuild.track.sparse import match_guided


def _cam(cid="c", center=(0, 0, -500), dist=(0, 0, 0, 0, 0), W=320, H=240):
    R, t = look_at(np.array(center, float), np.zeros(3), (0, 1, 0))
    return Camera(cid, W, H, [[400, 0, W / 2 - 0.5], [0, 400, H / 2 - 0.5], [0, 0, 1]], dist, R, t)


def test_detect_dots_finds_grey_discs_not_reddish_speckle():
    rng = np.random.default_rng(0)
    img = np.empty((120, 160, 3), np.float32)
    img[:] = (198, 148, 122)
    centres = np.array([[30.0, 40.0], [100.0, 60.0], [130.0, 95.0]])
    n_blobs = 0
    while n_blobs < 40:  # reddish dark speckle blobs (not dots), not touching the dots
        c = rng.integers(5, [155, 115])
        if np.min(np.linalg.norm(centres - c, axis=1)) > 10:
            cv2.circle(img, (int(c[0]), int(c[1])), 3, (70, 42, 34), -1)
            n_blobs += 1
    for x, y in centres:
        cv2.circle(img, (int(x), int(y)), 4, (25, 25, 25), -1)
    img += rng.normal(0, 1.5, img.shape)
    det, area = detect_dots(np.clip(img, 0, 255).astype(np.uint8), DotParams())
    assert det.shape[0] == 3
    a = assign_detections(centres, det, 2.0)
    assert np.all(a >= 0)
    np.testing.assert_allclose(det[a], centres, atol=0.3)


def test_detect_dots_on_the_mask_box_equals_the_whole_image():
    rng = np.random.default_rng(1)
    img = np.empty((200, 260, 3), np.float32)
    img[:] = (198, 148, 122)
    for x, y in rng.uniform([60, 50], [200, 150], (12, 2)):
        cv2.circle(img, (int(x), int(y)), 4, (25, 25, 25), -1)
    img = np.clip(img + rng.normal(0, 1.5, img.shape), 0, 255).astype(np.uint8)
    mask = np.zeros(img.shape[:2], bool)
    mask[55:150, 70:190] = True  # cuts some dots
    boxed = detect_dots(img, DotParams(), mask=mask)
    whole = mask.copy()
    whole[0, 0] = whole[-1, -1] = True  # the mask's box is the whole image: no crop (lone pixels are no dots)
    full = detect_dots(img, DotParams(), mask=whole)
    assert boxed[0].shape[0] >= 6
    np.testing.assert_allclose(boxed[0], full[0], rtol=0, atol=1e-9)  # centroids summed in crop coordinates
    np.testing.assert_array_equal(boxed[1], full[1])


#: the detector for realistic captures (the default ``threshold`` detector is for grey paint on a bright speckle)
CONTRAST = DotParams(detector="contrast")


def test_the_threshold_detector_misses_skin_hued_dots_that_the_contrast_detector_finds():
    rng = np.random.default_rng(6)
    img = _shaded_skin(rng, texture=0.03)
    centres = np.array([[x, y] for y in range(40, 220, 45) for x in range(40, 300, 45)], float)
    paint = np.zeros(img.shape[:2], np.float32)
    for x, y in centres:
        cv2.circle(paint, (int(x), int(y)), 3, 1.0, -1)
    img = img * (1 - 0.4 * paint)[..., None]  # 40 % darker than the skin around it, in the skin's hue
    img = np.clip(cv2.GaussianBlur(img, (0, 0), 0.8) + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
    found = [(assign_detections(centres, detect_dots(img, p)[0], 2.0) >= 0).mean() for p in (DotParams(), CONTRAST)]
    assert found[0] < 0.2 and found[1] > 0.9


def _shaded_skin(rng, H=240, W=320, texture=0.0):
    """Skin-hued image with a strong left-right shading ramp, a specular blob, smooth texture and noise."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    shade = 0.45 + 0.55 * xx / W
    spec = 60.0 * np.exp(-((xx - 250) ** 2 + (yy - 60) ** 2) / (2 * 15.0 ** 2))
    tex = 1.0 + texture * cv2.GaussianBlur(rng.normal(0, 1, (H, W)).astype(np.float32), (0, 0), 6.0)
    base = np.array([200.0, 150.0, 125.0], np.float32)
    return shade[..., None] * tex[..., None] * base + spec[..., None]


def test_detect_dots_recall_on_shaded_noisy_skin_with_skin_hued_dots():
    rng = np.random.default_rng(3)
    img = _shaded_skin(rng, texture=0.05)
    centres = np.array([[x, y] for y in range(30, 220, 38) for x in range(30, 300, 38)], float)
    centres += rng.uniform(-3, 3, centres.shape)
    ratio = rng.uniform(0.4, 0.7, centres.shape[0])  # dot brightness / skin: darkness 0.3-0.6
    radius = rng.uniform(2.0, 3.8, centres.shape[0])
    hi = np.zeros(img.shape, np.float32)
    for (x, y), q, r in zip(centres, ratio, radius):  # sub-pixel discs (shift=3: 1/8 px), then blur (optics)
        cv2.circle(hi, (int(round(8 * x)), int(round(8 * y))), int(8 * r), (1 - q,) * 3, -1, shift=3)
    img = img * (1 - hi)  # the dot darkens the skin multiplicatively: it keeps the skin's hue
    img = cv2.GaussianBlur(img, (0, 0), 0.8) + rng.normal(0, 2.0, img.shape)
    det, _ = detect_dots(np.clip(img, 0, 255).astype(np.uint8), CONTRAST)
    a = assign_detections(centres, det, 2.0, ambiguity_ratio=1.0)
    assert (a >= 0).mean() >= 0.9
    assert det.shape[0] <= centres.shape[0] + 2  # no false positives to speak of (shading, highlight)
    err = np.linalg.norm(det[a[a >= 0]] - centres[a >= 0], axis=1)
    assert np.median(err) < 0.3


def test_detect_dots_finds_nothing_on_dot_free_textured_skin():
    rng = np.random.default_rng(4)
    img = _shaded_skin(rng, texture=0.08)
    img = cv2.GaussianBlur(img, (0, 0), 0.8) + rng.normal(0, 2.0, img.shape)
    det, _ = detect_dots(np.clip(img, 0, 255).astype(np.uint8), CONTRAST)
    assert det.shape[0] == 0


def test_detect_dots_ignores_lines_and_searches_mask_holes():
    rng = np.random.default_rng(5)
    img = np.clip(_shaded_skin(rng) + rng.normal(0, 1.5, (240, 320, 3)), 0, 255).astype(np.uint8)
    cv2.line(img, (40, 60), (140, 66), (60, 45, 40), 3)  # an eyebrow-like ridge
    cv2.circle(img, (200, 150), 3, (40, 30, 28), -1)
    mask = np.ones((240, 320), bool)
    mask[146:155, 196:205] = False  # the stereo hole on the dot
    det, _ = detect_dots(img, CONTRAST, mask=mask)
    assert det.shape[0] == 1
    np.testing.assert_allclose(det[0], [200, 150], atol=0.3)


def test_assign_detections_gates_and_rejects_ambiguous():
    pred = np.array([[0, 0], [10, 0], [50, 50], [np.nan, np.nan]], float)
    det = np.array([[0.5, 0], [10, 1], [80, 80], [52, 50], [53, 50]])
    a = assign_detections(pred, det, 5.0, ambiguity_ratio=1.5)
    assert a[0] == 0 and a[1] == 1 and a[3] == -1
    assert a[2] == -1  # two detections at 2 and 3 px: ambiguous


def test_lift_and_triangulate_exact():
    cams = [_cam("a", (0, 0, -500)), _cam("b", (200, 30, -460)), _cam("c", (-150, -40, -480), dist=(0.05, 0, 0, 0, 0))]
    X = np.array([[0, 0, 0], [10, -5, 3], [-20, 15, -8.0]])
    uv = np.stack([c.project(X) for c in cams])
    Xt, rms, n = triangulate(cams, uv)
    np.testing.assert_allclose(Xt, X, atol=1e-6)
    assert np.all(n == 3) and np.all(rms < 1e-5)
    # lift with an exact depth map of a plane z = 0 seen by camera a (no distortion): world point recovered
    cam = cams[0]
    H, W = cam.height, cam.width
    depth = np.full((H, W), 500.0, np.float32)
    P = lift(cam, depth, cam.project(X[:1]))
    np.testing.assert_allclose(P, X[:1], atol=1e-3)
    # depth jump -> NaN
    depth[:, : W // 2] = 300.0
    assert np.isnan(lift(cam, depth, np.array([[W / 2 - 0.5, 10.0]]))).all()


def test_lift_fills_a_small_hole_from_the_surrounding_depth_only():
    cam = _cam("a", (0, 0, -500))
    depth = np.full((cam.height, cam.width), 500.0, np.float32)
    X = np.array([[10.0, -5.0, 0.0]])
    uv = cam.project(X)
    u, v = np.round(uv[0]).astype(int)
    depth[v - 3:v + 4, u - 3:u + 4] = np.nan  # stereo's hole on a dark dot
    assert np.isnan(lift(cam, depth, uv)).all()
    np.testing.assert_allclose(lift(cam, depth, uv, fill_radius_px=8), X, atol=1e-3)
    assert np.isnan(lift(cam, depth, uv, fill_radius_px=3)).all()  # the window sees no depth
    depth[:, : u] = 300.0  # an edge across the window: no depth is guessed
    depth[v - 3:v + 4, u - 3:u + 4] = np.nan
    assert np.isnan(lift(cam, depth, uv, fill_radius_px=8)).all()


def test_depth_to_image_grid_undistorts():
    cam = _cam("d", dist=(-0.2, 0.05, 0, 0, 0))
    H, W = cam.height, cam.width
    ys, xs = np.mgrid[0:H, 0:W]
    d_pin = (500 + 0.1 * xs).astype(np.float32)  # depth varies along the pinhole x axis
    d_img = depth_to_image_grid(d_pin, cam)
    uv = np.array([[20.0, 30.0], [300.0, 200.0]])
    pin = cam.undistort_points(uv) * 400 + [W / 2 - 0.5, H / 2 - 0.5]
    np.testing.assert_allclose(d_img[uv[:, 1].astype(int), uv[:, 0].astype(int)], 500 + 0.1 * pin[:, 0], atol=1e-3)


def test_depth_to_image_grid_with_precomputed_cells_is_identical_and_a_step_stays_out():
    from rigbuild.track.features import depth_discontinuity, image_to_pinhole_cells

    cam = _cam("d", dist=(-0.2, 0.05, 0.001, -0.002, 0.01))
    H, W = cam.height, cam.width
    ys, xs = np.mgrid[0:H, 0:W]
    d_pin = np.where(xs < W // 2, 500 + 0.1 * xs, 560.0).astype(np.float32)  # a 30+ mm step at the middle
    d_pin[100:110, 50:60] = 0  # a hole
    once = depth_to_image_grid(d_pin, cam)
    cells = image_to_pinhole_cells(cam, cam.K, d_pin.shape)
    assert np.array_equal(depth_to_image_grid(d_pin, cam, cells=cells), once, equal_nan=True)
    cols = np.isnan(once).mean(axis=0)
    assert cols[W // 2 - 3:W // 2 + 3].max() > 0.9 and np.isnan(once).mean() < 0.1  # the step is cut, not smeared
    # the 2x2 spread: max - min of the four neighbours, NaN when any is NaN (as a reduction over them)
    d = np.array([[1.0, 2.0, np.nan], [4.0, 8.0, 3.0]], np.float32)
    np.testing.assert_array_equal(depth_discontinuity(d, np.array([[0.5, 0.5], [1.5, 0.5], [-1, 0]])),
                                  [7.0, np.nan, np.nan])
    # and equal to the stacked reduction on a random float32 map with holes
    rng = np.random.default_rng(3)
    big = rng.uniform(400, 600, (60, 80)).astype(np.float32)
    big[rng.random(big.shape) < 0.1] = np.nan
    uv = rng.uniform(-2, 82, (5000, 2))
    ok = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= 79) & (uv[:, 1] <= 59)
    u0, v0 = np.minimum(np.floor(uv[ok, 0]).astype(int), 78), np.minimum(np.floor(uv[ok, 1]).astype(int), 58)
    n = np.stack([big[v0, u0], big[v0, u0 + 1], big[v0 + 1, u0], big[v0 + 1, u0 + 1]], axis=1).astype(np.float64)
    want = np.full(len(uv), np.nan)
    want[ok] = n.max(1) - n.min(1)
    np.testing.assert_array_equal(depth_discontinuity(big, uv), want)


def test_viewframe_requires_depth():
    with pytest.raises(InputError, match="no depth map"):
        ViewFrame(_cam(), np.zeros((240, 320, 3), np.uint8), None)


def test_match_guided_respects_search_region_and_threshold():
    rng = np.random.default_rng(1)
    D = rng.normal(size=(5, 128)).astype(np.float32) * 50
    src = np.array([[10, 10], [50, 50], [90, 90], [130, 130], [170, 170.0]])
    tgt = src + [3, -2]
    pred = src.copy()
    pred[4] += 40  # prediction far off -> outside the radius
    s, t, d = match_guided(src, D, pred, tgt, D + 1.0, radius_px=8, threshold=100, ratio=0.9)
    assert sorted(s.tolist()) == [0, 1, 2, 3] and np.all(s == t)
    s2, _, _ = match_guided(src, D, pred, tgt, D + 30.0, radius_px=8, threshold=100, ratio=0.9)
    assert s2.size == 0  # descriptor distance 30 * sqrt(128) > threshold


def test_guided_flow_recovers_shift_with_guide():
    rng = np.random.default_rng(2)
    base = cv2.GaussianBlur(rng.uniform(0, 255, (200, 260)).astype(np.float32), (0, 0), 2.0)
    base = cv2.normalize(base, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    shift = np.array([17.3, -9.6])  # too big for a 1-level DIS without a guide
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    tgt = cv2.warpAffine(base, M, (260, 200), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    guide = np.zeros((200, 260, 2), np.float32) + (shift + [1.2, -0.8]).astype(np.float32)  # approximate guide
    flow, fb = guided_flow(base, tgt, guide, "medium")
    inner = (slice(40, 160), slice(40, 220))
    err = np.linalg.norm(flow[inner] - shift, axis=2)
    assert np.median(err) < 0.1
    assert np.median(fb[inner]) < 0.2


def test_stage_reads_reconstruct_depth_files(tmp_path):
    """The tracking stage reads the reconstruct stage's depth npz (pinhole grids) onto the distorted image grid,
    and a missing file is an InputError naming the file."""
    from rigbuild.io.depth import write_depth
    from rigbuild.track import plots
    from rigbuild.track import stage as mod

    cams = [_cam("b", dist=(-0.1, 0, 0, 0, 0)), _cam("a")]
    pin = [Camera(c.id, c.width, c.height, c.K, np.zeros(5), c.R, c.t) for c in cams]
    depth = np.stack([np.full((240, 320), 480.0, np.float32), np.full((240, 320), 510.0, np.float32)])
    write_depth(tmp_path / "000003.npz", pin[::-1], depth[::-1], np.ones_like(depth))  # file order a, b
    maps = mod.read_depth_maps(tmp_path / "000003.npz", cams)
    assert np.nanmedian(maps[0]) == pytest.approx(480.0, abs=0.01)  # camera b found by id
    assert np.nanmedian(maps[1]) == pytest.approx(510.0, abs=0.01)
    with pytest.raises(InputError, match="depth"):
        mod.read_depth_maps(tmp_path / "000004.npz", cams)
    # report figures of the stage
    rows = [{"frame": f, "dots": 40, "sparse": 900, "flow": 5000, "anchor_matches": 2000, "residual_median_mm": 0.05,
             "residual_p90_mm": 0.2, "lost": f == 2, "reason": ""} for f in range(4)]
    plots.residual_plot(tmp_path / "residuals.png", rows, "test")
    import cv2

    img = cv2.imread(str(tmp_path / "residuals.png"))
    assert img is not None and img.shape[0] > 100 and img.shape[1] > 300


def test_surface_neighbours_follow_the_mesh_not_the_gap():
    from rigbuild.track.features import surface_neighbours

    # a unit square (two triangles, diagonal 0-2) and a second square 0.1 above it, not connected to it
    sq = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    V = np.concatenate([sq, sq + [0, 0, 0.1]])
    F = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    nb, d = surface_neighbours(V, F, np.array([0, 1, 2, 4]), k=2, limit_mm=10.0)
    np.testing.assert_array_equal(nb[0], [1, 2])  # vertex 0: vertex 1 (one edge), vertex 2 (the diagonal)
    np.testing.assert_allclose(d[0], [1.0, np.sqrt(2.0)])
    np.testing.assert_allclose(d[1], [1.0, 1.0])  # vertex 1: vertices 0 and 2, one edge each
    # vertex 4 is 0.1 from vertex 0 in space but on another surface: no neighbour along the mesh
    np.testing.assert_array_equal(nb[3], [-1, -1])
    assert np.all(np.isinf(d[3]))


def test_consistent_displacements_drops_the_odd_one_out():
    from rigbuild.track.features import consistent_displacements

    d = np.array([[1.0, 0, 0], [1.2, 0, 0], [0.9, 0, 0], [9.0, 0, 0], [5.0, 5.0, 0]])
    present = np.array([True, True, True, True, False])
    nbrs = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2], [0, 1, 2]])
    ok = consistent_displacements(d, present, nbrs, tolerance_mm=2.0)
    np.testing.assert_array_equal(ok, [True, True, True, False, False])
    lonely = consistent_displacements(d, present, np.full((5, 3), -1), tolerance_mm=2.0)
    np.testing.assert_array_equal(lonely, present)  # no present neighbour: kept


def test_points_flow_recovers_a_large_shift():
    from rigbuild.track.flow import points_flow

    rng = np.random.default_rng(3)
    # texture with structure at every scale (as a face has), so the coarse pyramid levels see it
    tex = sum(cv2.resize(cv2.GaussianBlur(rng.random((480 // k, 640 // k)), (0, 0), 1.0), (640, 480))
              for k in (1, 4, 16))
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    shifted = np.roll(tex, (30, 45), axis=(0, 1))  # 45 px right, 30 px down
    pts = np.array([[300.0, 200.0], [350.5, 260.25], [np.nan, np.nan]])
    f = points_flow(tex, shifted, pts, scale=0.5)
    np.testing.assert_allclose(f[:2], [[45.0, 30.0], [45.0, 30.0]], atol=0.3)
    assert np.isnan(f[2]).all()


def test_overlay_sheet_shows_every_camera(tmp_path):
    """Issue 24: a frame's tracking overlay tiles every camera's view (rows of at most 4, evenly filled), each
    with the tracked vertices (green), the markers (red) and its camera id."""
    from rigbuild.track.plots import draw_overlay

    V = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    for n, (rows, cols) in ((6, (2, 3)), (8, (2, 4)), (5, (2, 3)), (3, (1, 3))):
        views = [ViewFrame(_cam(f"c{k}", center=(20.0 * k, 0, -500)), np.full((240, 320, 3), 60, np.uint8),
                           np.full((240, 320), 500.0, np.float32)) for k in range(n)]
        draw_overlay(tmp_path / "f.jpg", views, V, np.array([[0.0, 20.0, 0.0]]), np.array([0, 1]))
        sheet = cv2.imread(str(tmp_path / "f.jpg"))
        assert sheet.shape == (rows * 240, cols * 320, 3), n
        for k in range(n):  # each tile: the camera id at top left, the vertex 0 drawn where that camera sees it
            r, c = divmod(k, cols)
            tile = sheet[r * 240:(r + 1) * 240, c * 320:(c + 1) * 320].astype(int)
            u, v = np.round(views[k].camera.project(V[:1])[0]).astype(int)
            assert tile[v, u, 1] > 150 and tile[v, u, 1] > tile[v, u, 2] + 60
            assert tile[8:28, 8:40].max() > 200
        if n == 5:
            assert sheet[240:, 2 * 320:].max() < 20  # the empty cell stays black
