"""Camera and sensor model: post-processing of a rendered linear-light image into a camera's 8-bit RGB.

Everything here works on numpy arrays and is independent of the renderer. Conventions:

- ``linear`` images are float (H, W, 3) RGB in linear light, scaled so that 1.0 is the sensor's white
  level at ``exposure = 1`` and ``gain = 1`` (a renderer's 0..255 output divided by 255).
- Pixel centres at integer coordinates (OpenCV); ``camera`` is a :class:`rigbuild.camera.Camera`.
- Depths are camera-frame z in mm (NaN on background); lengths on the sensor in mm; blur sizes in pixels.

:func:`apply_sensor` runs the whole chain in the order light meets it: scene radiance -> motion blur over
the exposure -> lens defocus -> lens vignetting -> exposure -> colour filter array (RGGB Bayer mosaic) ->
photo-electrons with shot noise, well saturation and read noise -> ADC quantization -> white balance gains
(digital, on the raw channels) -> demosaicing (OpenCV) -> sRGB 8-bit -> optional JPEG.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Mapping, Optional

import numpy as np

from rigbuild.errors import InputError

#: config block the parameters come from (error messages name keys under it)
WHERE = "synthetic.camera"

#: ``demosaic_method`` values (OpenCV's VNG is 8-bit only, so it is not offered for 12-bit raw)
DEMOSAIC_METHODS = ("bilinear", "ea")


def _demosaic_code(method: str) -> int:
    """OpenCV code demosaicing an RGGB sensor (R at row 0, column 0) to RGB.

    OpenCV names Bayer patterns after the second row's second and third pixels, so RGGB is its
    ``BayerBG`` (``COLOR_BayerRGGB2RGB`` is the same code in OpenCV >= 4.8); the round-trip tests in
    tests/test_render_sensor.py check it.
    """
    import cv2

    return {"bilinear": cv2.COLOR_BayerBG2RGB, "ea": cv2.COLOR_BayerBG2RGB_EA}[method]


# ------------------------------------------------------------------ parameters
@dataclass
class SensorParams:
    """A machine-vision colour camera (defaults: a 1.2 MP global-shutter CCD/CMOS at 3.75 um pitch).

    Attributes
    ----------
    exposure : multiplier on the linear radiance (exposure time x aperture area, relative).
    white_balance : (3,) digital gains on the raw R, G, B channels (1, 1, 1 = neutral).
    full_well_e : electrons that reach the white level at ``gain = 1`` (well capacity).
    read_noise_e : read noise standard deviation, electrons.
    gain : ISO-like analogue gain: the white level is reached at ``full_well_e / gain`` electrons, so a
        higher gain makes each electron count more (brighter, noisier).
    bayer : RGGB colour filter array demosaiced by OpenCV (False: a sensor that measures all three
        channels at every pixel).
    demosaic_method : "ea" (OpenCV edge-aware) or "bilinear".
    adc_bits : bits of the analogue-to-digital converter (raw values are quantized to 2**bits - 1).
    jpeg_quality : JPEG quality 1..100 of the delivered image, or None (lossless).
    vignetting : fractional light fall-off at the image corner farthest from the principal point
        (0 = none; 0.25 = the corner gets 75 % of the centre's light), cos^4-like radial profile.
    f_number : lens f-number N for depth of field (None = pinhole, no defocus).
    focus_distance_mm : camera depth in focus, mm (None = the median depth of the visible surface).
    pixel_pitch_mm : sensor pixel pitch, mm (focal length in mm = fx * pitch).
    motion_blur_samples : sub-frame samples integrating the motion over the exposure (1 = no blur).
    exposure_sd : per-camera exposure offset of a rig whose cameras are not matched: camera ``c`` exposes
        ``exposure * exp(N(0, exposure_sd^2))`` (log-normal, drawn once per camera; 0 = matched cameras).
    white_balance_sd : per-camera white-balance offset: the red and blue gains of camera ``c`` are multiplied
        by ``exp(N(0, white_balance_sd^2))`` each (green fixed; 0 = matched cameras). See :func:`camera_sensor`.
    """

    exposure: float = 1.0
    white_balance: tuple = (1.0, 1.0, 1.0)
    full_well_e: float = 10000.0
    read_noise_e: float = 6.0
    gain: float = 1.0
    bayer: bool = True
    demosaic_method: str = "ea"
    adc_bits: int = 12
    jpeg_quality: Optional[int] = None
    vignetting: float = 0.25
    f_number: Optional[float] = 8.0
    focus_distance_mm: Optional[float] = None
    pixel_pitch_mm: float = 0.00375
    motion_blur_samples: int = 5
    exposure_sd: float = 0.0
    white_balance_sd: float = 0.0

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "SensorParams":
        """Build and check from the ``synthetic.camera`` mapping; missing keys keep their defaults.

        Raises :class:`~rigbuild.errors.InputError` naming ``synthetic.camera.<key>`` and the fix for an
        unknown key (with "did you mean"), a negative noise, a non-positive f-number, gain, exposure,
        full well, pitch or focus distance, a JPEG quality outside 1..100 and other malformed values.
        """
        from rigbuild.params import check_keys

        d = dict(d or {})
        check_keys(d, [f.name for f in dataclasses.fields(cls)], WHERE)
        if "white_balance" in d and isinstance(d["white_balance"], list):
            d["white_balance"] = tuple(d["white_balance"])
        p = cls(**d)
        p.check()
        return p

    def check(self) -> None:
        """Raise InputError naming the first bad field (see :meth:`from_dict`)."""

        def bad(key: str, value: Any, need: str, fix: str) -> InputError:
            return InputError(f"'{WHERE}.{key}' must be {need}, got {value!r}", path="config", fix=fix)

        def number(key: str) -> float:
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise bad(key, v, "a finite number", f"set {WHERE}.{key} to a number")
            return float(v)

        for key, fix in (("exposure", "1.0 is the nominal exposure"),
                         ("full_well_e", "a typical well holds 5000-30000 electrons"),
                         ("gain", "1.0 is unity gain; 2.0 doubles the brightness and the noise"),
                         ("pixel_pitch_mm", "machine-vision pixels are 0.002-0.006 mm")):
            if not number(key) > 0:
                raise bad(key, getattr(self, key), "> 0", f"set {WHERE}.{key} to a positive value ({fix})")
        for key in ("exposure_sd", "white_balance_sd"):
            if number(key) < 0:
                raise bad(key, getattr(self, key), ">= 0 (a standard deviation of the log gain)",
                          f"set {WHERE}.{key} to 0 (matched cameras) or a typical 0.05-0.2")
        if number("read_noise_e") < 0:
            raise bad("read_noise_e", self.read_noise_e, ">= 0 (a standard deviation)",
                      f"set {WHERE}.read_noise_e to 0 (no read noise) or a typical 2-10 electrons")
        v = number("vignetting")
        if not 0 <= v < 1:
            raise bad("vignetting", v, "in [0, 1) (fractional fall-off at the corner)",
                      f"set {WHERE}.vignetting to 0 (none) or a typical 0.1-0.4")
        wb = self.white_balance
        try:
            wb_ok = len(wb) == 3 and all(not isinstance(g, bool) and float(g) > 0 and math.isfinite(float(g))
                                         for g in wb)
        except (TypeError, ValueError):
            wb_ok = False
        if not wb_ok:
            raise bad("white_balance", wb, "three positive gains [r, g, b]",
                      f"set {WHERE}.white_balance to e.g. [1.0, 1.0, 1.0]")
        if not isinstance(self.bayer, bool):
            raise bad("bayer", self.bayer, "true or false", f"set {WHERE}.bayer to true (RGGB) or false")
        if self.demosaic_method not in DEMOSAIC_METHODS:
            raise bad("demosaic_method", self.demosaic_method, f"one of {', '.join(DEMOSAIC_METHODS)}",
                      f"set {WHERE}.demosaic_method to 'ea' (edge-aware) or 'bilinear'")
        b = self.adc_bits
        if isinstance(b, bool) or not isinstance(b, int) or not 8 <= b <= 16:
            raise bad("adc_bits", b, "an integer in 8..16", f"set {WHERE}.adc_bits to 12 (typical) or 8..16")
        q = self.jpeg_quality
        if q is not None and (isinstance(q, bool) or not isinstance(q, int) or not 1 <= q <= 100):
            raise bad("jpeg_quality", q, "null or an integer in 1..100",
                      f"set {WHERE}.jpeg_quality to null (no compression) or e.g. 90")
        if self.f_number is not None and not number("f_number") > 0:
            raise bad("f_number", self.f_number, "> 0 or null",
                      f"set {WHERE}.f_number to null (pinhole, no defocus) or a lens f-number such as 8")
        if self.focus_distance_mm is not None and not number("focus_distance_mm") > 0:
            raise bad("focus_distance_mm", self.focus_distance_mm, "> 0 mm or null",
                      f"set {WHERE}.focus_distance_mm to null (focus at the median depth) or the camera "
                      "distance to the face in mm")
        n = self.motion_blur_samples
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise bad("motion_blur_samples", n, "an integer >= 1",
                      f"set {WHERE}.motion_blur_samples to 1 (no blur) or e.g. 5")


def camera_sensor(params: SensorParams, camera_id: str, seed: int) -> SensorParams:
    """The sensor of one camera of a rig: ``params`` with its exposure and white balance offset by a
    log-normal draw (``params.exposure_sd``, ``params.white_balance_sd``) from a generator seeded by ``seed``
    and ``camera_id`` (the same camera gets the same offsets in every image of a session). Returns ``params``
    itself when both standard deviations are 0."""
    if not params.exposure_sd and not params.white_balance_sd:
        return params
    import zlib

    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(camera_id.encode("utf-8")), 71])
    z = rng.standard_normal(3)
    exposure = float(params.exposure) * math.exp(float(params.exposure_sd) * z[0])
    r, g, b = (float(x) for x in params.white_balance)
    wb = (r * math.exp(float(params.white_balance_sd) * z[1]), g, b * math.exp(float(params.white_balance_sd) * z[2]))
    return dataclasses.replace(params, exposure=exposure, white_balance=wb)


# ------------------------------------------------------------------ optics
def vignetting_map(camera, strength: float) -> np.ndarray:
    """(H, W) float32 relative illumination of each pixel, 1 at the principal point.

    A cos^4 law ``(1 + (r / r0)^2)^-2`` in normalized image coordinates ``r = |((u - cx)/fx, (v - cy)/fy)|``,
    with ``r0`` chosen so that the image corner farthest from the principal point gets ``1 - strength``.
    """
    H, W = camera.height, camera.width
    if not strength:
        return np.ones((H, W), np.float32)
    if not 0 <= strength < 1:
        raise ValueError("vignetting strength must be in [0, 1)")
    K = camera.K
    x = ((np.arange(W, dtype=np.float64) - K[0, 2]) / K[0, 0]) ** 2
    y = ((np.arange(H, dtype=np.float64) - K[1, 2]) / K[1, 1]) ** 2
    r2_corner = max(x[0], x[-1]) + max(y[0], y[-1])
    # cos^4(theta) = 1 - strength at the corner: tan^2(theta) = (1 - strength)^-1/2 - 1
    tan2 = (1.0 - strength) ** -0.5 - 1.0
    s = tan2 / r2_corner
    return ((1.0 + s * (y[:, None] + x[None, :])) ** -2).astype(np.float32)


def vignette(linear: np.ndarray, camera, strength: float) -> np.ndarray:
    """Lens vignetting: ``linear`` (H, W, 3) times :func:`vignetting_map` (corner fall-off ``strength``)."""
    if not strength:
        return np.asarray(linear, dtype=np.float32)
    return np.asarray(linear, dtype=np.float32) * vignetting_map(camera, strength)[..., None]


def circle_of_confusion_px(depth_mm, focus_mm: float, f_number: float, focal_mm: float,
                           pitch_mm: float) -> np.ndarray:
    """Thin-lens blur circle diameter in pixels for points at camera depth ``depth_mm`` (any shape, mm).

    ``c = (f / N) * |d - s| / d * f / (s - f) / pitch`` for focal length ``f`` mm, f-number ``N``, focus
    distance ``s`` mm and object depth ``d`` mm (``d = inf`` gives the limit ``(f / N) f / (s - f)``).
    Zero at ``d = s``; NaN where ``depth_mm`` is NaN. ``s`` must exceed ``f``.
    """
    d = np.asarray(depth_mm, dtype=np.float64)
    f, s = float(focal_mm), float(focus_mm)
    if not s > f:
        raise ValueError(f"focus distance {s} mm must exceed the focal length {f} mm")
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.where(np.isinf(d), 1.0, np.abs(d - s) / d)
    return (f / f_number) * rel * f / (s - f) / pitch_mm


#: CoC diameters (px) of the blur layers :func:`defocus_blur` interpolates between
_COC_LEVELS = np.array([0.0, 1.0, 2.0, 3.0, 4.0, 5.5, 8.0, 11.0, 16.0, 22.0, 32.0, 45.0, 64.0])


def defocus_blur(linear: np.ndarray, coc_px: np.ndarray, max_coc_px: float = 32.0) -> np.ndarray:
    """Spatially varying defocus of ``linear`` (H, W, C) by a per-pixel blur circle ``coc_px`` (H, W), px.

    The image is blurred into a few layers of fixed circle diameter (Gaussians with the disc's second
    moment: sigma = diameter / 4) and each pixel interpolates linearly between the two layers that bracket
    its diameter (clipped to ``[0, max_coc_px]``; NaN = sharp). Mirror borders, so a uniform blur keeps
    the image mean. Returns float32 (H, W, C).
    """
    import cv2

    img = np.asarray(linear, dtype=np.float32)
    c = np.nan_to_num(np.asarray(coc_px, dtype=np.float32), nan=0.0)
    c = np.clip(c, 0.0, float(max_coc_px))
    if not c.size or float(c.max()) <= 0.0:
        return img.copy()
    levels = _COC_LEVELS[_COC_LEVELS < max_coc_px]
    levels = np.append(levels, max_coc_px).astype(np.float32)
    top = int(np.searchsorted(levels, float(c.max()), side="left"))   # highest layer with weight
    out = np.zeros_like(img)
    for j in range(top + 1):
        # piecewise-linear "hat" weight of layer j at each pixel's diameter (weights sum to 1)
        up = (c - levels[j - 1]) / (levels[j] - levels[j - 1]) if j > 0 else np.ones_like(c)
        down = (levels[j + 1] - c) / (levels[j + 1] - levels[j]) if j + 1 < len(levels) else np.ones_like(c)
        w = np.clip(np.minimum(up, down), 0.0, 1.0)
        if not w.any():
            continue
        sigma = float(levels[j]) / 4.0
        layer = img if sigma <= 0 else cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        out += layer * (w[..., None] if img.ndim == 3 else w)
    return out


def motion_blur(linear: np.ndarray, motion_px: np.ndarray, samples: int) -> np.ndarray:
    """Integrate ``linear`` (H, W, C) over the exposure along per-pixel screen motion ``motion_px`` (H, W, 2).

    ``motion_px[v, u] = (du, dv)`` is the displacement, in pixels, of the surface seen at pixel (u, v)
    during the exposure (NaN = static). The output averages the image sampled (bilinear, ``cv2.remap``) at
    ``(u, v) + t * motion`` for ``samples`` midpoints ``t`` of equal sub-intervals of [-0.5, 0.5]: a
    point moving ``v`` px becomes a streak of length ``v`` centred on its mid-exposure position.
    Returns float32 (H, W, C).
    """
    import cv2

    img = np.asarray(linear, dtype=np.float32)
    if samples <= 1 or motion_px is None:
        return img.copy()
    m = np.nan_to_num(np.asarray(motion_px, dtype=np.float32), nan=0.0)
    if not np.any(m):
        return img.copy()
    H, W = img.shape[:2]
    gx = np.broadcast_to(np.arange(W, dtype=np.float32)[None, :], (H, W))
    gy = np.broadcast_to(np.arange(H, dtype=np.float32)[:, None], (H, W))
    mx, my = m[..., 0], m[..., 1]
    out = np.zeros_like(img)
    for i in range(int(samples)):
        t = np.float32((i + 0.5) / samples - 0.5)
        out += cv2.remap(img, gx + t * mx, gy + t * my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    out *= np.float32(1.0 / samples)
    return out


# ------------------------------------------------------------------ sensor
def apply_exposure_white_balance(linear: np.ndarray, exposure: float, wb) -> np.ndarray:
    """``linear`` (..., 3) times ``exposure`` times the per-channel gains ``wb`` (3,). float32."""
    g = np.float32(exposure) * np.asarray(wb, dtype=np.float32).reshape(3)
    return np.asarray(linear, dtype=np.float32) * g


def electrons_per_unit(full_well_e: float, gain: float) -> float:
    """Electrons that make linear value 1.0 (the white level) at ``gain``: ``full_well_e / gain``."""
    return float(full_well_e) / float(gain)


def shot_and_read_noise(linear: np.ndarray, full_well_e: float, read_noise_e: float, gain: float,
                        rng: np.random.Generator) -> np.ndarray:
    """Photon shot noise, well saturation and read noise on a linear image (any shape). float32.

    With ``e = full_well_e / gain`` electrons per linear unit, a pixel of value ``L >= 0`` collects
    ``Poisson(L * e)`` electrons, clipped at ``full_well_e``, plus ``N(0, read_noise_e^2)``; the result is
    divided by ``e``. Below saturation, mean ``L`` and variance ``L / e + (read_noise_e / e)^2``.
    Values can be negative (read noise) or above 1; the ADC (:func:`quantize_adc`) clips.
    """
    e = electrons_per_unit(full_well_e, gain)
    lam = np.clip(np.nan_to_num(np.asarray(linear, dtype=np.float64), nan=0.0), 0.0, None) * e
    el = np.minimum(rng.poisson(lam), full_well_e).astype(np.float32)
    if read_noise_e > 0:
        el += rng.standard_normal(el.shape, dtype=np.float32) * np.float32(read_noise_e)
    el *= np.float32(1.0 / e)
    return el


def quantize_adc(x: np.ndarray, bits: int) -> np.ndarray:
    """Linear values (any shape, white = 1) -> raw digital numbers uint16 in ``0 .. 2**bits - 1`` (clipped)."""
    white = float(2 ** int(bits) - 1)
    return np.rint(np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0) * np.float32(white)).astype(np.uint16)


def bayer_mosaic(rgb: np.ndarray) -> np.ndarray:
    """RGGB colour filter array: (H, W, 3) -> (H, W), R at (even row, even column), B at (odd, odd)."""
    rgb = np.asarray(rgb)
    raw = np.empty(rgb.shape[:2], dtype=rgb.dtype)
    raw[0::2, 0::2] = rgb[0::2, 0::2, 0]
    raw[0::2, 1::2] = rgb[0::2, 1::2, 1]
    raw[1::2, 0::2] = rgb[1::2, 0::2, 1]
    raw[1::2, 1::2] = rgb[1::2, 1::2, 2]
    return raw


def bayer_channel_gains(shape: tuple, gains) -> np.ndarray:
    """(H, W) float32 map of per-channel gains ``gains`` (3,) laid out on the RGGB mosaic."""
    g = np.asarray(gains, dtype=np.float32).reshape(3)
    H, W = shape[:2]
    out = np.empty((H, W), np.float32)
    out[0::2, 0::2] = g[0]
    out[0::2, 1::2] = g[1]
    out[1::2, 0::2] = g[1]
    out[1::2, 1::2] = g[2]
    return out


def demosaic(raw: np.ndarray, method: str = "ea", white_level: float | None = None) -> np.ndarray:
    """RGGB mosaic (H, W) -> linear RGB (H, W, 3) float32 in units of ``white_level`` (OpenCV demosaicing).

    ``raw`` is uint8/uint16 digital numbers (``white_level`` default: the dtype's maximum) or float in
    0..1 (quantized to 16 bits first; ``white_level`` ignored). ``method``: "ea" (edge-aware) or "bilinear".
    """
    import cv2

    raw = np.asarray(raw)
    if np.issubdtype(raw.dtype, np.floating):
        raw, white_level = quantize_adc(raw, 16), 65535.0
    elif raw.dtype not in (np.uint8, np.uint16):
        raw = raw.astype(np.uint16)
    if white_level is None:
        white_level = float(np.iinfo(raw.dtype).max)
    rgb = cv2.demosaicing(np.ascontiguousarray(raw), _demosaic_code(method))
    return rgb.astype(np.float32) * np.float32(1.0 / white_level)


# ------------------------------------------------------------------ output encoding
def _srgb_encode(x: np.ndarray) -> np.ndarray:
    """sRGB transfer function (IEC 61966-2-1) of linear ``x`` in 0..1, float64."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


_SRGB_LUTS: dict[int, np.ndarray] = {}


def srgb8_lut(white: int) -> np.ndarray:
    """(white + 1,) uint8: the sRGB 8-bit code of each raw digital number ``0..white`` (white = linear 1)."""
    lut = _SRGB_LUTS.get(int(white))
    if lut is None:
        lut = np.rint(_srgb_encode(np.arange(int(white) + 1) / float(white)) * 255.0).astype(np.uint8)
        lut.setflags(write=False)
        _SRGB_LUTS[int(white)] = lut
    return lut


def to_srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear light (any shape, white = 1) -> sRGB-encoded uint8 (IEC 61966-2-1 transfer, clipped, rounded).

    Evaluated through a 16-bit table: the linear value is rounded to 1/65535 first (exact to the formula
    except within 1e-5 of a rounding boundary).
    """
    x = np.nan_to_num(np.asarray(linear, dtype=np.float32), nan=0.0)
    return srgb8_lut(65535)[quantize_adc(x, 16)]


def from_srgb8(rgb8: np.ndarray) -> np.ndarray:
    """Inverse of :func:`to_srgb8`: uint8 sRGB (any shape) -> linear float32 in 0..1."""
    from rigbuild.render.common import srgb_to_linear

    return srgb_to_linear(np.asarray(rgb8, dtype=np.float32) / np.float32(255.0))


def jpeg_round_trip(rgb8: np.ndarray, quality: int | None) -> np.ndarray:
    """Encode (H, W, 3) uint8 RGB as JPEG at ``quality`` (1..100) and decode it (OpenCV, 4:2:0 chroma).

    ``quality`` None returns the image unchanged.
    """
    import cv2

    if quality is None:
        return rgb8
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb8[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("cv2.imencode failed to write a JPEG")
    return np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1])


# ------------------------------------------------------------------ the whole chain
def focal_length_mm(camera, pitch_mm: float) -> float:
    """Lens focal length in mm: the mean of ``fx`` and ``fy`` (pixels) times the pixel pitch (mm)."""
    return 0.5 * (camera.K[0, 0] + camera.K[1, 1]) * float(pitch_mm)


def apply_sensor(linear: np.ndarray, camera, params: SensorParams, rng: np.random.Generator,
                 depth_mm: np.ndarray | None = None, motion_px: np.ndarray | None = None) -> np.ndarray:
    """A rendered linear-light image (H, W, 3), white = 1, as the camera delivers it: uint8 RGB (H, W, 3).

    Order: motion blur (``motion_px`` (H, W, 2) px over the exposure, ``params.motion_blur_samples``) ->
    defocus (``depth_mm`` (H, W) camera z, NaN background; needs ``params.f_number``; focus at
    ``params.focus_distance_mm`` or the median visible depth; the background takes the blur of the
    farthest visible depth, so that the face does not bleed over it) -> vignetting -> exposure -> RGGB
    mosaic (``params.bayer``) -> shot/read noise in electrons -> ADC -> white balance -> demosaic ->
    sRGB 8-bit -> JPEG (``params.jpeg_quality``). ``rng`` draws the noise.
    """
    img = np.asarray(linear, dtype=np.float32)
    if motion_px is not None and params.motion_blur_samples > 1:
        img = motion_blur(img, motion_px, params.motion_blur_samples)
    if params.f_number is not None and depth_mm is not None:
        d = np.asarray(depth_mm, dtype=np.float64)
        fin = np.isfinite(d) & (d > 0)
        if fin.any():
            focal = focal_length_mm(camera, params.pixel_pitch_mm)
            focus = params.focus_distance_mm if params.focus_distance_mm is not None else float(np.median(d[fin]))
            d = np.where(fin, d, d[fin].max())
            img = defocus_blur(img, circle_of_confusion_px(d, focus, params.f_number, focal, params.pixel_pitch_mm))
    img = vignette(img, camera, params.vignetting)
    img = img * np.float32(params.exposure)
    if params.bayer:
        img = bayer_mosaic(img)
    img = shot_and_read_noise(img, params.full_well_e, params.read_noise_e, params.gain, rng)
    white = 2 ** params.adc_bits - 1
    dn = quantize_adc(img, params.adc_bits)
    if any(g != 1 for g in params.white_balance):
        wb = bayer_channel_gains(dn.shape, params.white_balance) if params.bayer else \
            np.asarray(params.white_balance, dtype=np.float32)
        dn = np.rint(np.minimum(dn * wb, np.float32(white))).astype(np.uint16)
    if params.bayer:
        import cv2

        dn = cv2.demosaicing(np.ascontiguousarray(dn), _demosaic_code(params.demosaic_method))
    return jpeg_round_trip(srgb8_lut(white)[dn], params.jpeg_quality)
