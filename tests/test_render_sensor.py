"""Camera / sensor model (rigbuild.render.sensor): each stage against an exact or statistical answer."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigbuild.camera import Camera
from rigbuild.errors import InputError
from rigbuild.render import sensor as S


def _camera(W=160, H=120, f=200.0, cx=None, cy=None) -> Camera:
    cx = (W - 1) / 2 if cx is None else cx
    cy = (H - 1) / 2 if cy is None else cy
    return Camera("c0", W, H, [[f, 0, cx], [0, f, cy], [0, 0, 1]], np.zeros(5), np.eye(3), np.zeros(3))


def _texture(H=96, W=128, seed=0) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random((H, W, 3), dtype=np.float32), (0, 0), 1.0) * 0.8 + 0.1


# ------------------------------------------------------------------ noise
@pytest.mark.parametrize("level", [0.02, 0.2, 0.6])
def test_noise_variance_matches_the_model(level):
    fw, read, gain = 10000.0, 6.0, 2.0
    e = fw / gain                                      # electrons per linear unit
    x = np.full((400, 500), level, np.float32)
    y = S.shot_and_read_noise(x, fw, read, gain, np.random.default_rng(1))
    var_model = level / e + (read / e) ** 2
    assert y.dtype == np.float32 and y.shape == x.shape
    assert abs(y.mean() - level) < 4 * math.sqrt(var_model / x.size)
    assert y.var() == pytest.approx(var_model, rel=0.03)     # estimator sd ~0.3 % at 2e5 samples


def test_noise_gain_and_saturation():
    x = np.full((200, 200), 0.3, np.float32)
    v1 = S.shot_and_read_noise(x, 8000.0, 0.0, 1.0, np.random.default_rng(2)).var()
    v4 = S.shot_and_read_noise(x, 8000.0, 0.0, 4.0, np.random.default_rng(2)).var()
    assert v4 / v1 == pytest.approx(4.0, rel=0.05)           # shot variance scales with the gain
    # the well saturates at full_well_e electrons: at gain 1 that is linear 1.0
    sat = S.shot_and_read_noise(np.full((50, 50), 3.0, np.float32), 8000.0, 0.0, 1.0, np.random.default_rng(3))
    assert np.all(sat == 1.0)
    # no light, no read noise: exactly zero; read noise only: sigma = read / e
    z = S.shot_and_read_noise(np.zeros((300, 300), np.float32), 8000.0, 5.0, 1.0, np.random.default_rng(4))
    assert z.std() == pytest.approx(5.0 / 8000.0, rel=0.03)


# ------------------------------------------------------------------ Bayer
def test_bayer_layout_is_rggb():
    rgb = np.zeros((4, 4, 3), np.float32)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 1.0, 2.0, 3.0
    raw = S.bayer_mosaic(rgb)
    assert raw.shape == (4, 4)
    np.testing.assert_array_equal(raw[:2, :2], [[1.0, 2.0], [2.0, 3.0]])


@pytest.mark.parametrize("method", ["ea", "bilinear"])
@pytest.mark.parametrize("colour", [(0.8, 0.5, 0.2), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.1, 0.7, 0.3)])
def test_bayer_round_trip_flat_field(method, colour):
    c = np.asarray(colour, np.float32)
    rgb = np.broadcast_to(c, (30, 41, 3)).copy()
    out = S.demosaic(S.bayer_mosaic(rgb), method)
    assert out.shape == rgb.shape and out.dtype == np.float32
    assert np.abs(out - c).max() < 2e-5                     # 16-bit quantization only, borders included


@pytest.mark.parametrize("method", ["ea", "bilinear"])
@pytest.mark.parametrize("axis", [0, 1])
def test_bayer_round_trip_edge_error_bounded(method, axis):
    a, b = np.array([0.8, 0.5, 0.2], np.float32), np.array([0.1, 0.3, 0.6], np.float32)
    H, W, e = 40, 60, 27                                    # step between index e-1 and e (odd: both phases)
    coord = np.arange(W if axis == 1 else H)
    side = (coord < e)
    rgb = np.where(side[None, :, None] if axis == 1 else side[:H, None, None], a, b) * np.ones((H, W, 1), np.float32)
    err = np.abs(S.demosaic(S.bayer_mosaic(rgb), method) - rgb)
    dist = np.abs(coord - (e - 0.5))                       # distance of each row/column to the edge
    far = dist > 1.5
    err_far = err[:, far] if axis == 1 else err[far]
    near = err[:, ~far] if axis == 1 else err[~far]
    assert err_far.max() < 2e-5                             # exact away from the edge
    assert np.all(near.max(axis=(0, 1) if axis == 1 else (0, 1)) <= 0.5 * np.abs(a - b) + 1e-4)


# ------------------------------------------------------------------ vignetting
@pytest.mark.parametrize("strength", [0.1, 0.3, 0.6])
def test_vignetting_corner_ratio_equals_parameter(strength):
    cam = _camera()
    img = np.ones((cam.height, cam.width, 3), np.float32)
    v = S.vignette(img, cam, strength)
    centre = v[59:61, 79:81].max()
    for r, c in [(0, 0), (0, -1), (-1, 0), (-1, -1)]:
        assert v[r, c, 0] / centre == pytest.approx(1 - strength, rel=1e-4)
    # cos^4 profile: monotone along the diagonal, 1 at the principal point
    m = S.vignetting_map(cam, strength)
    d = np.diagonal(m[:, 20:140][:, ::1])[:60]
    assert np.all(np.diff(d) > 0)
    assert S.vignetting_map(cam, 0.0).min() == 1.0


def test_vignetting_off_centre_principal_point():
    cam = _camera(cx=50.0, cy=40.0)
    m = S.vignetting_map(cam, 0.25)
    assert m[40, 50] == pytest.approx(1.0)
    assert m[-1, -1] == pytest.approx(0.75, rel=1e-5)       # the farthest corner
    assert min(m[0, 0], m[0, -1], m[-1, 0]) > 0.75


# ------------------------------------------------------------------ defocus
def test_circle_of_confusion_thin_lens():
    f, N, s, pitch = 50.0, 2.0, 1000.0, 0.005
    # c = (f/N) |d - s| / d * f / (s - f): d = 2000 -> 25 * 0.5 * 50/950 = 0.657895 mm
    c = S.circle_of_confusion_px(np.array([2000.0, 1000.0, 500.0, np.inf, np.nan]), s, N, f, pitch)
    assert c[0] == pytest.approx(25 * 0.5 * 50 / 950 / pitch, rel=1e-12)
    assert c[1] == 0.0
    assert c[2] == pytest.approx(25 * 1.0 * 50 / 950 / pitch, rel=1e-12)
    assert c[3] == pytest.approx(25 * 50 / 950 / pitch, rel=1e-12)
    assert np.isnan(c[4])
    with pytest.raises(ValueError):
        S.circle_of_confusion_px(100.0, 40.0, 2.0, 50.0, pitch)


def test_defocus_preserves_mean_and_blurs_more_with_larger_coc():
    img = _texture()
    H, W = img.shape[:2]
    stds = []
    for coc in [0.0, 1.5, 3.0, 6.0, 12.0]:
        out = S.defocus_blur(img, np.full((H, W), coc))
        assert out.shape == img.shape and out.dtype == np.float32
        np.testing.assert_allclose(out.mean((0, 1)), img.mean((0, 1)), rtol=1e-5)
        stds.append(float(out.std()))
    assert all(b < a for a, b in zip(stds, stds[1:]))
    np.testing.assert_array_equal(S.defocus_blur(img, np.zeros((H, W))), img)


def test_defocus_point_spread_second_moment():
    # a point under a uniform circle d spreads with the disc's second moment: sigma^2 = (d / 4)^2 per axis
    for d in [4.0, 8.0, 11.0, 9.0]:
        img = np.zeros((81, 81, 3), np.float32)
        img[40, 40] = 1.0
        out = S.defocus_blur(img, np.full((81, 81), d))[..., 0]
        x = np.arange(81) - 40.0
        var = float((out.sum(0) * x**2).sum() / out.sum())
        lv = S._COC_LEVELS
        if d in lv:
            assert var == pytest.approx((d / 4) ** 2, rel=0.02)
        else:  # between two layers: the interpolated spread lies between theirs
            j = np.searchsorted(lv, d) - 1
            assert (lv[j] / 4) ** 2 < var < (lv[j + 1] / 4) ** 2


def test_defocus_spatially_varying_keeps_sharp_pixels_sharp():
    img = _texture()
    H, W = img.shape[:2]
    coc = np.zeros((H, W))
    coc[:, W // 2:] = 8.0
    out = S.defocus_blur(img, coc)
    np.testing.assert_array_equal(out[:, : W // 2], img[:, : W // 2])
    assert out[:, W // 2 + 10:].std() < 0.6 * img[:, W // 2 + 10:].std()


# ------------------------------------------------------------------ motion blur
@pytest.mark.parametrize("motion", [(20.0, 0.0), (0.0, 13.0), (12.0, 9.0), (7.3, -4.1)])
def test_motion_blur_streak_matches_motion(motion):
    H, W, n = 80, 100, 41
    img = np.zeros((H, W, 3), np.float32)
    y0, x0 = 40, 50
    img[y0, x0] = 1.0
    m = np.broadcast_to(np.asarray(motion, np.float32), (H, W, 2))
    out = S.motion_blur(img, m, n)[..., 0]
    assert out.sum() == pytest.approx(1.0, rel=1e-5)                    # energy kept
    yy, xx = np.mgrid[0:H, 0:W]
    cx, cy = (out * xx).sum(), (out * yy).sum()
    assert (cx, cy) == (pytest.approx(x0, abs=1e-4), pytest.approx(y0, abs=1e-4))   # centred at mid-exposure
    # second moment along the motion, exactly: mean over samples of (t v)^2 + f (1 - f) (bilinear spread)
    t = (np.arange(n) + 0.5) / n - 0.5
    for k, (c0, g) in enumerate([(x0, xx), (y0, yy)]):
        off = t * motion[k]
        frac = off - np.floor(off)
        expect = np.mean(off**2 + frac * (1 - frac))
        assert ((out * (g - c0) ** 2).sum()) == pytest.approx(expect, rel=1e-4, abs=1e-5)
    # streak length: the lit pixels span the motion's length along its direction
    v = math.hypot(*motion)
    u = np.asarray(motion) / v
    proj = ((xx - x0) * u[0] + (yy - y0) * u[1])[out > 1e-6]
    assert v - 1.0 <= proj.max() - proj.min() <= v + 2.0


def test_motion_blur_no_motion_is_identity():
    img = _texture(40, 50)
    np.testing.assert_array_equal(S.motion_blur(img, np.zeros((40, 50, 2)), 5), img)
    np.testing.assert_array_equal(S.motion_blur(img, np.ones((40, 50, 2)), 1), img)
    np.testing.assert_array_equal(S.motion_blur(img, np.full((40, 50, 2), np.nan), 5), img)


# ------------------------------------------------------------------ encoding
def test_srgb_transfer():
    x = np.linspace(0, 1, 10001, dtype=np.float32)
    ref = np.rint(S._srgb_encode(x) * 255)
    assert np.abs(S.to_srgb8(x).astype(int) - ref).max() <= 1
    np.testing.assert_array_equal(S.to_srgb8(np.array([0.0, 1.0, 0.5, -1.0, 7.0, np.nan])), [0, 255, 188, 0, 255, 0])
    y = np.arange(256, dtype=np.uint8)
    np.testing.assert_array_equal(S.to_srgb8(S.from_srgb8(y)), y)


def test_jpeg_quality_ordering():
    rgb8 = S.to_srgb8(_texture(96, 128, seed=5))
    assert S.jpeg_round_trip(rgb8, None) is rgb8
    err = {q: float(np.mean((S.jpeg_round_trip(rgb8, q).astype(float) - rgb8) ** 2)) for q in (30, 95)}
    out = S.jpeg_round_trip(rgb8, 95)
    assert out.shape == rgb8.shape and out.dtype == np.uint8
    assert 0 < err[95] < 0.5 * err[30]


def test_exposure_white_balance():
    x = np.full((2, 2, 3), 0.25, np.float32)
    np.testing.assert_allclose(S.apply_exposure_white_balance(x, 2.0, (1.0, 0.5, 1.5))[0, 0], [0.5, 0.25, 0.75])


# ------------------------------------------------------------------ the chain
def _quiet(**kw) -> S.SensorParams:
    base = dict(full_well_e=1e9, read_noise_e=0.0, vignetting=0.0, f_number=None, adc_bits=16, jpeg_quality=None)
    base.update(kw)
    return S.SensorParams(**base)


def test_apply_sensor_noise_free_chain_is_srgb_of_the_input():
    cam = _camera(128, 96)
    img = _texture(96, 128)
    out = S.apply_sensor(img, cam, _quiet(bayer=False), np.random.default_rng(0))
    assert out.shape == (96, 128, 3) and out.dtype == np.uint8
    assert np.abs(out.astype(int) - S.to_srgb8(img)).max() <= 1
    flat = np.full((96, 128, 3), (0.6, 0.3, 0.1), np.float32)
    out = S.apply_sensor(flat, cam, _quiet(), np.random.default_rng(0))     # Bayer + demosaic
    assert np.abs(out.astype(int) - S.to_srgb8(flat)).max() <= 1


def test_apply_sensor_white_balance_exposure_and_determinism():
    cam = _camera(64, 48)
    grey = np.full((48, 64, 3), 0.2, np.float32)
    for bayer in (True, False):
        out = S.apply_sensor(grey, cam, _quiet(bayer=bayer, exposure=1.5, white_balance=(2.0, 1.0, 0.5)),
                             np.random.default_rng(0))
        np.testing.assert_allclose(out[10, 10].astype(int), S.to_srgb8(np.array([0.6, 0.3, 0.15])), atol=1)
    p = S.SensorParams(jpeg_quality=90)
    img = _texture(48, 64)
    depth = np.full((48, 64), 400.0)
    depth[:5] = np.nan
    motion = np.full((48, 64, 2), 3.0)
    a = S.apply_sensor(img, cam, p, np.random.default_rng(7), depth, motion)
    b = S.apply_sensor(img, cam, p, np.random.default_rng(7), depth, motion)
    np.testing.assert_array_equal(a, b)
    # default sensor noise at mid grey: the 8-bit noise is visible but small
    noisy = S.apply_sensor(np.full((96, 128, 3), 0.2, np.float32), _camera(128, 96), S.SensorParams(vignetting=0.0),
                           np.random.default_rng(1))
    assert 0.3 < noisy[10:-10, 10:-10].std() < 5.0


# ------------------------------------------------------------------ parameters
def test_params_from_dict_defaults_and_values():
    assert S.SensorParams.from_dict(None) == S.SensorParams()
    p = S.SensorParams.from_dict({"white_balance": [1.1, 1.0, 0.9], "f_number": 5.6, "jpeg_quality": 90,
                                  "focus_distance_mm": 450})
    assert p.white_balance == (1.1, 1.0, 0.9) and p.f_number == 5.6 and p.jpeg_quality == 90


@pytest.mark.parametrize("key,value", [
    ("read_noise_e", -1.0), ("f_number", 0.0), ("f_number", -2.8), ("jpeg_quality", 0), ("jpeg_quality", 101),
    ("jpeg_quality", 90.5), ("gain", 0.0), ("exposure", -1.0), ("full_well_e", 0), ("vignetting", 1.0),
    ("vignetting", -0.1), ("white_balance", [1.0, 0.0, 1.0]), ("white_balance", [1.0, 1.0]),
    ("motion_blur_samples", 0), ("pixel_pitch_mm", 0.0), ("focus_distance_mm", -5.0), ("adc_bits", 20),
    ("demosaic_method", "vng"), ("bayer", "yes"), ("exposure", "bright"),
])
def test_params_from_dict_rejects_bad_values(key, value):
    with pytest.raises(InputError) as e:
        S.SensorParams.from_dict({key: value})
    msg = str(e.value)
    assert f"synthetic.camera.{key}" in msg and "fix:" in msg


def test_params_from_dict_unknown_key_did_you_mean():
    with pytest.raises(InputError) as e:
        S.SensorParams.from_dict({"f_numbr": 8})
    msg = str(e.value)
    assert "synthetic.camera.f_numbr" in msg and "did you mean 'f_number'" in msg


# ------------------------------------------------------------------ per-camera offsets
def test_camera_sensor_offsets_are_log_normal_per_camera():
    p = S.SensorParams(exposure=2.0, white_balance=(1.5, 1.0, 1.2), exposure_sd=0.1, white_balance_sd=0.05)
    ids = [f"cam{i:03d}" for i in range(4000)]
    per_cam = [S.camera_sensor(p, c, seed=7) for c in ids]
    log_e = np.log([q.exposure / 2.0 for q in per_cam])
    log_r = np.log([q.white_balance[0] / 1.5 for q in per_cam])
    log_b = np.log([q.white_balance[2] / 1.2 for q in per_cam])
    n = len(ids)
    for logs, sd in ((log_e, 0.1), (log_r, 0.05), (log_b, 0.05)):
        assert abs(logs.mean()) < 4 * sd / math.sqrt(n)
        assert logs.std() == pytest.approx(sd, rel=4 / math.sqrt(2 * n))  # 4 sigma of the sample sd
    assert all(q.white_balance[1] == 1.0 for q in per_cam)  # green is the reference channel
    again = S.camera_sensor(p, "cam003", seed=7)
    assert (again.exposure, again.white_balance) == (per_cam[3].exposure, per_cam[3].white_balance)
    assert S.camera_sensor(p, "cam003", seed=8).exposure != per_cam[3].exposure
    matched = S.SensorParams()
    assert S.camera_sensor(matched, "cam003", seed=7) is matched


@pytest.mark.parametrize("key", ["exposure_sd", "white_balance_sd"])
def test_camera_offsets_reject_negative_sd(key):
    with pytest.raises(InputError) as e:
        S.SensorParams.from_dict({key: -0.1})
    assert f"synthetic.camera.{key}" in str(e.value)
