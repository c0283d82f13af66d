"""A realistic skin appearance for the synthetic heads: albedo, roughness and specular maps in a UV atlas.

:func:`skin_albedo` paints a rig (the ICT head or the procedural head, or any rig in the ICT frame with 68
landmarks) into one square atlas: skin with low-frequency tone and redness, multi-scale pores and fine
texture at 0.2-2 mm, freckles and moles, lips, eyebrow hair strokes, stubble shadow, a hairline and a hair
cap of low texture; on ICT also sclera / iris / pupil, teeth, gums and a dark mouth interior.

The rig's own UVs are UDIM-like tiles that overlap once wrapped (ICT's face, eyeballs and eye overlays all
use tile 0), so the atlas is a re-packing of the rig's UV charts (one chart per tile and region group, each
kept as the rig laid it out, scaled to a common texel density in mm): :class:`SkinAppearance` carries the
new ``uvs`` / ``face_uvs`` to render with.

The painting is in texture space: the atlas is rasterized once (triangle id and barycentrics of every texel,
vectorized), so every texel knows its point on the neutral surface (mm); regions come from the rig's
structure (ICT submesh vertex ranges) and its 68 landmarks; fine texture is FFT-filtered noise at sizes in
mm. Roughness is the GGX / Trowbridge-Reitz perceptual roughness (alpha = roughness^2), specular is the
normal-incidence Fresnel reflectance F0 (dimensionless).

:func:`skin_contrast` is the measure of real skin the synthetic skin is matched to: the luminance's local
std / mean in square windows of 1, 2 and 3 mm on the cheeks and the forehead, after dividing by a
Gaussian low-pass of :data:`SHADING_SIGMA_MM`; :data:`JAMES_CONTRAST` holds its value on the real scan.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from rigbuild.errors import InputError

#: window sizes (mm) of the local contrast measure
CONTRAST_WINDOWS_MM = (1.0, 2.0, 3.0)
#: sigma (mm) of the Gaussian low-pass that removes shading before the contrast is measured
SHADING_SIGMA_MM = 8.0
#: skin_contrast of the real head scan menpo3d-james-head: {window mm: median local std / mean}
JAMES_CONTRAST = {1.0: 0.0732, 2.0: 0.0942, 3.0: 0.1079}

# ICT-FaceKit submesh vertex ranges (README of ICT-FaceKit): label per range
ICT_N_VERTICES = 26719
REGION_CODES = {
    "background": 0, "skin": 1, "head": 2, "mouth_socket": 3, "eye_socket": 4, "gums": 5, "teeth": 6,
    "sclera": 7, "iris": 8, "lacrimal": 9, "eye_blend": 10, "eye_occlusion": 11, "eyelashes": 12,
}
_ICT_RANGES = [  # (first, end) vertex ids, region name
    (0, 9409, "skin"), (9409, 11248, "head"), (11248, 13294, "mouth_socket"), (13294, 14062, "eye_socket"),
    (14062, 17039, "gums"), (17039, 21451, "teeth"), (21451, 22221, "sclera"), (22221, 23021, "iris"),
    (23021, 23791, "sclera"), (23791, 24591, "iris"), (24591, 24999, "lacrimal"), (24999, 25047, "eye_blend"),
    (25047, 25351, "eye_occlusion"), (25351, 26719, "eyelashes"),
]
_ICT_LEFT_EYE = (21451, 23021)  # left eyeball (sclera + iris); the right one is 23021-24591
#: regions that are transparent overlays in ICT's intended shading (render them hidden)
OVERLAY_REGIONS = ("eye_blend", "eye_occlusion")


# ============================================================================ rasterization in UV space
def rasterize_uv(uvs: np.ndarray, face_uvs: np.ndarray, shape: tuple[int, int],
                 chunk: int = 1 << 22) -> tuple[np.ndarray, np.ndarray]:
    """Rasterize triangles in texture space: the triangle covering each texel centre and its barycentrics.

    uvs (T, 2) OBJ convention (v up; row 0 of the image is v = 1), face_uvs (F, 3); shape (H, W) texels.
    Texel (r, c) has its centre at u = (c + 0.5) / W, v = 1 - (r + 0.5) / H. Coordinates are not wrapped.
    Vectorized: triangles are grouped by bounding-box size (powers of two) and tested in batches.

    Returns tri (H, W) int32 (-1 where no triangle covers the centre; a later triangle wins where two
    overlap) and bary (H, W, 3) float32.
    """
    H, W = int(shape[0]), int(shape[1])
    P = np.asarray(uvs, dtype=np.float64)[np.asarray(face_uvs)]
    x = P[..., 0] * W - 0.5
    y = (1.0 - P[..., 1]) * H - 0.5
    x0 = np.clip(np.ceil(x.min(1)), 0, W - 1).astype(np.int64)
    x1 = np.clip(np.floor(x.max(1)), 0, W - 1).astype(np.int64)
    y0 = np.clip(np.ceil(y.min(1)), 0, H - 1).astype(np.int64)
    y1 = np.clip(np.floor(y.max(1)), 0, H - 1).astype(np.int64)
    den = (y[:, 1] - y[:, 2]) * (x[:, 0] - x[:, 2]) + (x[:, 2] - x[:, 1]) * (y[:, 0] - y[:, 2])
    ok = (x1 >= x0) & (y1 >= y0) & (np.abs(den) > 1e-12) & (x.max(1) >= 0) & (y.max(1) >= 0) \
        & (x.min(1) <= W - 1) & (y.min(1) <= H - 1)
    tri = np.full((H, W), -1, dtype=np.int32)
    bary = np.zeros((H, W, 3), dtype=np.float32)
    bw = 1 << np.ceil(np.log2(np.maximum(x1 - x0 + 1, 1))).astype(np.int64)
    bh = 1 << np.ceil(np.log2(np.maximum(y1 - y0 + 1, 1))).astype(np.int64)
    key = bw * 100003 + bh
    eps = -1e-6
    for k in np.unique(key[ok]):
        ids = np.flatnonzero(ok & (key == k))
        kw, kh = int(bw[ids[0]]), int(bh[ids[0]])
        step = max(1, chunk // (kw * kh))
        ox = np.arange(kw)[None, None, :]
        oy = np.arange(kh)[None, :, None]
        for s in range(0, ids.size, step):
            t = ids[s : s + step]
            gx = x0[t][:, None, None] + ox
            gy = y0[t][:, None, None] + oy
            xa, ya = x[t][:, :, None, None], y[t][:, :, None, None]
            d = den[t][:, None, None]
            l0 = ((ya[:, 1] - ya[:, 2]) * (gx - xa[:, 2]) + (xa[:, 2] - xa[:, 1]) * (gy - ya[:, 2])) / d
            l1 = ((ya[:, 2] - ya[:, 0]) * (gx - xa[:, 2]) + (xa[:, 0] - xa[:, 2]) * (gy - ya[:, 2])) / d
            l2 = 1.0 - l0 - l1
            inside = (l0 >= eps) & (l1 >= eps) & (l2 >= eps) & (gx <= x1[t][:, None, None]) \
                & (gy <= y1[t][:, None, None])
            n, r, c = np.nonzero(inside)
            gxs, gys = gx[n, 0, c], gy[n, r, 0]
            tri[gys, gxs] = t[n]
            bary[gys, gxs] = np.stack([l0[n, r, c], l1[n, r, c], l2[n, r, c]], -1)
    return tri, bary


def texel_points(tri: np.ndarray, bary: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                 where: np.ndarray | None = None) -> np.ndarray:
    """Surface points (N, 3) of the texels ``where`` (default: all covered texels, tri >= 0)."""
    where = tri >= 0 if where is None else where
    t = tri[where]
    b = bary[where]
    f = np.asarray(faces)[t]
    V = np.asarray(vertices, dtype=np.float32)
    return b[:, 0:1] * V[f[:, 0]] + b[:, 1:2] * V[f[:, 1]] + b[:, 2:3] * V[f[:, 2]]


def texel_density(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, face_uvs: np.ndarray,
                  shape: tuple[int, int], face_mask: np.ndarray | None = None) -> float:
    """Texels per mm: sqrt(texel area / surface area) of the triangles in ``face_mask``, area-weighted
    (i.e. sqrt(sum texel area / sum mm^2)). vertices in mm; shape (H, W) of the texture."""
    f = np.asarray(faces) if face_mask is None else np.asarray(faces)[face_mask]
    fu = np.asarray(face_uvs) if face_mask is None else np.asarray(face_uvs)[face_mask]
    Vt = np.asarray(vertices, dtype=np.float64)[f]
    a3 = 0.5 * np.linalg.norm(np.cross(Vt[:, 1] - Vt[:, 0], Vt[:, 2] - Vt[:, 0]), axis=1)
    T = np.asarray(uvs, dtype=np.float64)[fu] * np.array([shape[1], shape[0]], dtype=np.float64)
    e1, e2 = T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]
    a2 = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    return float(np.sqrt(a2.sum() / max(a3.sum(), 1e-12)))


# ============================================================================ the contrast measure
def skin_patches(landmarks_xyz: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Measurement patches (centre (3,) mm, radius mm) from the 68 Multi-PIE landmarks (68, 3): both
    cheeks and both sides of the forehead (away from the midline, where photo-textures have their seam).

    Cheek centre: the mean of a jaw point at cheek level, the nose wing and the lower lid (landmarks
    2, 31, 41 and 14, 35, 46), radius 10 mm; forehead: 25 mm above the middle of each brow (19, 24)
    along the chin-to-brow direction, radius 10 mm. Centres are snapped to the surface by
    :func:`patch_mask`.
    """
    L = np.asarray(landmarks_xyz, dtype=np.float64)
    up = 0.5 * (L[19] + L[24]) - L[8]
    up /= np.linalg.norm(up)
    return [
        (L[[2, 31, 41]].mean(0), 10.0),
        (L[[14, 35, 46]].mean(0), 10.0),
        (L[19] + 25.0 * up, 10.0),
        (L[24] + 25.0 * up, 10.0),
    ]


def patch_mask(points: np.ndarray, surface: np.ndarray, patches: list[tuple[np.ndarray, float]]) -> np.ndarray:
    """(N,) bool: texel points (N, 3) within a patch's radius of the surface point nearest its centre.

    surface (M, 3): points to snap the centres to (e.g. the mesh vertices of the skin)."""
    out = np.zeros(points.shape[0], dtype=bool)
    for c, r in patches:
        c0 = surface[np.argmin(((surface - c) ** 2).sum(1))]
        out |= ((points - c0) ** 2).sum(1) < r * r
    return out


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear light."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def luminance(image: np.ndarray) -> np.ndarray:
    """(H, W) linear-light luminance (Rec. 709 weights) of an (H, W, 3) uint8 sRGB image."""
    lin = srgb_to_linear(np.asarray(image, dtype=np.float32) / 255.0)
    return lin @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


def local_contrast(lum: np.ndarray, covered: np.ndarray, patch: np.ndarray, px_per_mm: float,
                   windows_mm=CONTRAST_WINDOWS_MM, shading_sigma_mm: float = SHADING_SIGMA_MM) -> dict[float, float]:
    """Median local contrast std / mean of ``lum`` in square windows, after dividing out shading.

    lum (H, W) float luminance; covered (H, W) bool texels on the surface; patch (H, W) bool window
    centres to measure; px_per_mm texels per mm. The low-pass is a normalized Gaussian convolution
    (sigma ``shading_sigma_mm``) over the covered texels; a window counts only when every texel in it is
    covered. Returns {window_mm: median contrast}.
    """
    import cv2

    m = covered.astype(np.float32)
    L = np.where(covered, lum, 0.0).astype(np.float32)
    s = shading_sigma_mm * px_per_mm
    k = int(2 * np.ceil(3 * s) + 1)
    low = cv2.GaussianBlur(L, (k, k), s, borderType=cv2.BORDER_CONSTANT) / np.maximum(
        cv2.GaussianBlur(m, (k, k), s, borderType=cv2.BORDER_CONSTANT), 1e-6)
    N = np.where(covered, L / np.maximum(low, 1e-6), 0.0).astype(np.float32)
    out = {}
    for w in windows_mm:
        n = max(2, int(round(w * px_per_mm)))
        box = lambda a: cv2.boxFilter(a, -1, (n, n), normalize=True, borderType=cv2.BORDER_CONSTANT)  # noqa: E731
        cov = box(m)
        mu = box(N)
        var = np.maximum(box(N * N) - mu * mu, 0.0)
        sel = patch & (cov > 0.9999)
        out[float(w)] = float(np.median(np.sqrt(var[sel]) / np.maximum(mu[sel], 1e-6))) if sel.any() else float("nan")
    return out


def skin_contrast(texture: np.ndarray, vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray,
                  face_uvs: np.ndarray, landmarks_xyz: np.ndarray, skin_faces: np.ndarray | None = None,
                  windows_mm=CONTRAST_WINDOWS_MM) -> dict[float, float]:
    """Local luminance contrast of a textured mesh's skin on the cheeks and forehead (see the module doc).

    texture (H, W, 3) uint8 sRGB; vertices (V, 3) mm; faces, face_uvs (F, 3); uvs (T, 2) in [0, 1]
    (OBJ convention); landmarks_xyz (68, 3) mm; skin_faces (F,) bool triangles that count as skin
    (default all). Texels per mm from the patch triangles' UV and surface areas.
    Returns {window_mm: median std/mean}.
    """
    H, W = texture.shape[:2]
    tri, bary = rasterize_uv(uvs, face_uvs, (H, W))
    skin_faces = np.ones(len(faces), bool) if skin_faces is None else np.asarray(skin_faces, bool)
    covered = (tri >= 0) & skin_faces[np.maximum(tri, 0)]
    pts = texel_points(tri, bary, vertices, faces, covered)
    sv = np.unique(np.asarray(faces)[skin_faces])
    patches = skin_patches(landmarks_xyz)
    inside = patch_mask(pts, np.asarray(vertices)[sv], patches)
    patch = np.zeros((H, W), bool)
    patch[covered] = inside
    # texel density of the triangles under the patches
    pf = np.zeros(len(faces), bool)
    pf[np.unique(tri[patch])] = True
    ppm = texel_density(vertices, faces, uvs, face_uvs, (H, W), pf)
    return local_contrast(luminance(texture), covered, patch, ppm, windows_mm)


def james_skin_contrast(folder: str | Path | None = None) -> dict[float, float]:
    """:func:`skin_contrast` of the real head scan ``menpo3d-james-head`` (james.obj, .jpg, .ljson).

    folder: default ``$RIGBUILD_DATA/menpo3d-james-head``. The scan is in mm; every triangle counts as skin
    (the patches avoid brows, eyes and the photo seam).
    """
    import json

    import cv2

    from rigbuild.io.obj import read_obj

    if folder is None:
        from rigbuild.paths import data_dir

        folder = data_dir() / "menpo3d-james-head"
    folder = Path(folder)
    mesh = read_obj(folder / "james.obj")
    img = cv2.imread(str(folder / "james.jpg"), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError("cannot read james.jpg", path=folder)
    lj = json.loads((folder / "james.ljson").read_text())
    lm = np.asarray(lj["groups"]["LJSON"]["landmarks"]["points"], dtype=np.float64)
    return skin_contrast(img[..., ::-1], mesh.vertices, mesh.faces, mesh.uvs, mesh.face_uvs, lm)


# ============================================================================ the atlas
@dataclass(frozen=True)
class SkinParams:
    """Appearance parameters (colours sRGB 0-255; lengths mm; strengths scale factors, 1 = default look)."""

    tone: tuple = (200.0, 152.0, 128.0)  # base skin albedo
    redness: float = 1.0  # cheeks, nose, chin
    lip: tuple = (168.0, 86.0, 86.0)
    hair: tuple = (52.0, 36.0, 26.0)  # hair cap and brows
    iris: tuple = (92.0, 108.0, 112.0)
    texture: float = 1.0  # scale of the fine (pore) texture amplitude; 1 matches JAMES_CONTRAST
    freckles: float = 1.0  # freckle density scale
    moles: int = 6
    stubble: float = 0.6  # 0 = clean shaven
    brow_hairs: int = 420  # hair strokes per brow
    hairline_mm: float = 62.0  # forehead height: hairline above the mid-brow

    def __post_init__(self) -> None:
        for f in ("redness", "texture", "freckles", "stubble"):
            if getattr(self, f) < 0:
                raise InputError(f"skin: {f} must be >= 0, got {getattr(self, f)}", fix=f"set skin.{f} >= 0")
        if self.moles < 0 or self.brow_hairs < 0:
            raise InputError("skin: moles and brow_hairs must be >= 0")


@dataclass(frozen=True)
class SkinAppearance:
    """A painted atlas and the UVs to render it with.

    texture : (S, S, 3) uint8 sRGB albedo, read-only.
    roughness : (S, S) float32 GGX perceptual roughness in [0, 1] (alpha = roughness^2).
    specular : (S, S) float32 normal-incidence reflectance F0.
    uvs : (3F, 2) float64 atlas texture coordinates in [0, 1] (OBJ convention, one per triangle corner).
    face_uvs : (F, 3) int64 indices into ``uvs`` (= arange(3F).reshape(F, 3)).
    regions : (S, S) uint8 region code per texel (:data:`REGION_CODES`; 0 = gutter).
    face_regions : (F,) uint8 region code per triangle.
    visible_faces : (F,) bool, False for ICT's transparent eye overlays (:data:`OVERLAY_REGIONS`), which an
        opaque renderer should drop (they cover the cornea).
    px_per_mm : texels per mm of the skin charts (every chart is scaled to px_per_mm x its density).
    """

    texture: np.ndarray
    roughness: np.ndarray
    specular: np.ndarray
    uvs: np.ndarray
    face_uvs: np.ndarray
    regions: np.ndarray
    face_regions: np.ndarray
    visible_faces: np.ndarray
    px_per_mm: float


#: texel density of each region relative to the skin (small, hidden or flat regions get fewer texels)
_DENSITY = {"skin": 1.0, "head": 0.6, "mouth_socket": 0.35, "eye_socket": 0.5, "gums": 0.3, "teeth": 0.35,
            "sclera": 1.2, "iris": 1.2, "lacrimal": 0.5, "eye_blend": 0.2, "eye_occlusion": 0.2, "eyelashes": 0.25}
_CLASS = {"sclera": 1, "iris": 1, "eye_blend": 2, "eye_occlusion": 2}  # charts that overlap the skin's tile


def vertex_regions(rig) -> np.ndarray:
    """(V,) uint8 region code per vertex: ICT submesh ranges for the ICT topology, else all skin."""
    lab = np.full(rig.n_vertices, REGION_CODES["skin"], dtype=np.uint8)
    if rig.n_vertices == ICT_N_VERTICES:
        for a, b, name in _ICT_RANGES:
            lab[a:b] = REGION_CODES[name]
    return lab


def atlas_layout(vertices, faces, uvs, face_uvs, face_regions, size: int, pad_px: int = 4):
    """Re-pack a rig's UV charts into one square atlas at a common texel density.

    A chart is the set of triangles of one UV tile (floor of the centroid's u, v) and one chart class
    (eyes and eye overlays apart from the rest, since ICT stacks them on the face's tile); each keeps the
    rig's layout, scaled to (texels per mm) x (its regions' density, :data:`_DENSITY`), shelf-packed with
    ``pad_px`` texels between charts. Returns (uvs (3F, 2), face_uvs (F, 3), px_per_mm).
    """
    names = {v: k for k, v in REGION_CODES.items()}
    F = len(faces)
    T = np.asarray(uvs, dtype=np.float64)[np.asarray(face_uvs)]  # (F, 3, 2)
    Vt = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    a3 = 0.5 * np.linalg.norm(np.cross(Vt[:, 1] - Vt[:, 0], Vt[:, 2] - Vt[:, 0]), axis=1)
    e1, e2 = T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]
    a2 = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    tile = np.floor(T.mean(1)).astype(np.int64)
    cls = np.array([_CLASS.get(names[int(r)], 0) for r in range(len(REGION_CODES))])[face_regions]
    dens_of = np.array([_DENSITY.get(names[int(r)], 1.0) for r in range(len(REGION_CODES))])[face_regions]
    key = (tile[:, 0] * 1000 + tile[:, 1]) * 10 + cls
    charts = []
    for k in np.unique(key):
        m = key == k
        P = T[m] - tile[m][:, None, :]
        lo, hi = P.reshape(-1, 2).min(0), P.reshape(-1, 2).max(0)
        mm_per_uv = np.sqrt(a3[m].sum() / max(a2[m].sum(), 1e-12))
        dm = float((dens_of[m] * a3[m]).sum() / max(a3[m].sum(), 1e-12))
        charts.append((m, lo, (hi - lo) * mm_per_uv * dm, mm_per_uv * dm))

    def pack(ppm):
        order = sorted(range(len(charts)), key=lambda i: -charts[i][2][1])
        x = y = shelf = 0.0
        pos = {}
        for i in order:
            w, h = charts[i][2] * ppm
            if x + w + pad_px > size and x > 0:
                x, y, shelf = 0.0, y + shelf + pad_px, 0.0
            pos[i] = (x + pad_px, y + pad_px)
            x += w + pad_px
            shelf = max(shelf, h)
        return pos, y + shelf + 2 * pad_px, max(c[2][0] * ppm + 2 * pad_px for c in charts)

    lo_p, hi_p = 1e-3, 1e3
    for _ in range(50):
        mid = np.sqrt(lo_p * hi_p)
        _, h, w = pack(mid)
        lo_p, hi_p = (mid, hi_p) if (h <= size and w <= size) else (lo_p, mid)
    ppm = lo_p
    pos, _, _ = pack(ppm)
    out = np.zeros((F, 3, 2))
    for i, (m, lo, _, s) in enumerate(charts):
        P = T[m] - tile[m][:, None, :]
        out[m] = (np.asarray(pos[i]) + (P - lo) * s * ppm) / size
    return out.reshape(-1, 2), np.arange(3 * F, dtype=np.int64).reshape(F, 3), float(ppm)


# ============================================================================ painting helpers
def _smooth(e0, e1, x):
    """Smoothstep of x from edge e0 (0) to e1 (1), elementwise; e1 < e0 gives a falling step."""
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _lin(rgb) -> np.ndarray:
    """(..., 3) sRGB 0-255 -> float32 linear light."""
    return srgb_to_linear(np.asarray(rgb, dtype=np.float32) / 255.0)


def _noise_fields(rng, size: int, sigmas_px, weights) -> np.ndarray:
    """Sum of Gaussian-filtered white noise fields (each of unit variance) x weights, one FFT pair; (S, S)."""
    from scipy import fft

    white = rng.standard_normal((size, size), dtype=np.float32)
    fy = np.fft.fftfreq(size).astype(np.float32)
    fx = np.fft.rfftfreq(size).astype(np.float32)
    f2 = fy[:, None] ** 2 + fx[None, :] ** 2
    ffull = np.fft.fftfreq(size)
    H = np.zeros_like(f2)
    for s, w in zip(sigmas_px, weights):
        g1 = np.exp(-2.0 * np.pi ** 2 * s * s * ffull ** 2)
        norm = np.sqrt(np.mean(g1 ** 2) ** 2)  # variance of the filtered unit white noise
        H += np.float32(w / norm) * np.exp(np.float32(-2.0 * np.pi ** 2 * s * s) * f2)
    return fft.irfft2(fft.rfft2(white, workers=1) * H, s=(size, size), workers=1).astype(np.float32)


def _seg_dist(P: np.ndarray, A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (N, K) from points P (N, D) to segments A-B (K, D) and the segment parameter t (N, K)."""
    AB = B - A
    t = np.clip(((P[:, None, :] - A[None]) * AB[None]).sum(-1) / np.maximum((AB * AB).sum(-1), 1e-12), 0, 1)
    d = np.linalg.norm(P[:, None, :] - (A[None] + t[..., None] * AB[None]), axis=-1)
    return d, t


def _polygon_sdf(P2: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Signed distance (N,) of 2-D points to a closed polygon (K, 2): negative inside."""
    A, B = poly, np.roll(poly, -1, axis=0)
    d, _ = _seg_dist(P2, A, B)
    x, y = P2[:, 0:1], P2[:, 1:2]
    cond = (A[None, :, 1] > y) != (B[None, :, 1] > y)
    xint = A[None, :, 0] + (y - A[None, :, 1]) * (B[None, :, 0] - A[None, :, 0]) / (B[None, :, 1] - A[None, :, 1] + 1e-12)
    inside = (cond & (x < xint)).sum(1) % 2 == 1
    dm = d.min(1)
    return np.where(inside, -dm, dm)


def _sphere_fit(X: np.ndarray) -> np.ndarray:
    """Centre (3,) of the least-squares sphere through points X (N, 3)."""
    A = np.column_stack([2 * X, np.ones(len(X))])
    sol = np.linalg.lstsq(A, (X * X).sum(1), rcond=None)[0]
    return sol[:3]


#: Gaussian sigmas (mm) of the fine-texture octaves
FINE_SIGMAS_MM = (0.1, 0.2, 0.4, 0.8, 1.6)
#: amplitude (log-albedo std) of each fine-texture octave
FINE_WEIGHTS = (0.034, 0.034, 0.034, 0.034, 0.034)

_CACHE: dict = {}


def _rig_key(rig) -> str:
    """Cache key (hex digest) of the rig's neutral, faces, UVs and landmarks."""
    h = hashlib.blake2b(digest_size=16)
    for a in (rig.neutral, rig.faces, rig.uvs, rig.face_uvs, rig.landmarks):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def skin_albedo(rig, size: int = 2048, seed: int = 0, params: SkinParams | None = None) -> SkinAppearance:
    """Paint a realistic skin appearance for ``rig`` into a square atlas (see the module doc).

    rig : a :class:`rigbuild.rig.Rig` in mm in the ICT frame (+x the actor's left, +y up, +z out of the
        face) with UVs and all 68 landmarks (the ICT rig, the procedural head, or an actor made from them).
    size : atlas side S in texels (>= 256). seed : randomness of the pattern. params : :class:`SkinParams`.

    Returns a :class:`SkinAppearance` (texture (S, S, 3) uint8 sRGB, roughness and specular (S, S) float32,
    the atlas UVs). Deterministic per (rig, size, seed, params); cached (the same object is returned).
    """
    params = SkinParams() if params is None else params
    size = int(size)
    if size < 256:
        raise InputError(f"skin_albedo: size must be >= 256, got {size}")
    if rig.uvs is None or rig.face_uvs is None:
        raise InputError(f"rig '{rig.name}' has no UVs", fix="use a rig with texture coordinates")
    if rig.landmarks is None or np.any(np.asarray(rig.landmarks) < 0):
        raise InputError(f"rig '{rig.name}' needs all 68 landmarks to place the skin regions")
    if rig.units != "mm":
        rig = rig.to_units("mm")
    key = (_rig_key(rig), size, int(seed), params)
    if key not in _CACHE:
        if len(_CACHE) >= 4:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = _paint(rig, size, int(seed), params)
    return _CACHE[key]


# ============================================================================ painting
@dataclass(frozen=True, eq=False)
class _Canvas:
    """The rasterized atlas: the N covered texels (in row-major order) and where they lie on the head.

    S : atlas side (texels). ppm : texels per mm. cov : (S, S) bool covered texels.
    rr, cc : (N,) int64 row and column of each covered texel. t : (N,) int32 triangle id.
    lab : (N,) uint8 region code. pos : (N, 3) neutral surface point (mm). isk : (N,) bool skin or head.
    q : (N, 3) float32 point in the face frame (mm; x the actor's left, y up, z out of the face, origin at
        landmark 27). Lq : (68, 3) the landmarks in the face frame (mm).
    """

    S: int
    ppm: float
    cov: np.ndarray
    rr: np.ndarray
    cc: np.ndarray
    t: np.ndarray
    lab: np.ndarray
    pos: np.ndarray
    isk: np.ndarray
    q: np.ndarray
    Lq: np.ndarray

    def gauss(self, c, s) -> np.ndarray:
        """(N,) isotropic Gaussian exp(-|q - c|^2 / 2 s^2) around c (3,) mm in the face frame, sigma s mm."""
        d = self.q - np.asarray(c, np.float32)
        return np.exp(np.einsum("ij,ij->i", d, d) / np.float32(-2 * s * s))


@dataclass(frozen=True, eq=False)
class _Noise:
    """Texture-space noise. fine_img : (S, S) float32 fine texture (log-albedo, octaves
    :data:`FINE_SIGMAS_MM`); fine : (N,) float32 fine_img on the covered texels x SkinParams.texture;
    low : (N,) float32 blotches at 6 and 15 mm; low2 : (N,) float32 unit-variance noise at 3 mm."""

    fine_img: np.ndarray
    fine: np.ndarray
    low: np.ndarray
    low2: np.ndarray


@dataclass(frozen=True, eq=False)
class _Fields:
    """Per-texel weights (N,) in [0, 1] (redness up to 1.2) of the skin features, from the landmarks.

    lips, brow, beard (stubble), hair (hair cap), fuzz (the band below the hairline), red (redness),
    tzone (the oily forehead and nose); brow_axis : the two brow polylines (5, 3) mm in the face frame,
    outer -> inner; zc : z (mm, face frame) of the head's vertical axis, 15 mm behind landmarks 0 and 16.
    """

    lips: np.ndarray
    brow: np.ndarray
    brow_axis: list
    beard: np.ndarray
    hair: np.ndarray
    fuzz: np.ndarray
    zc: float
    red: np.ndarray
    tzone: np.ndarray


def _face_frame(L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Face frame of the 68 landmarks L (68, 3) mm: rotation (3, 3) (rows x: eye corner 36 -> 45, y: chin
    -> mid-brow made orthogonal, z = x cross y) and origin (3,) at landmark 27 (nose bridge)."""
    ex = L[45] - L[36]
    ex /= np.linalg.norm(ex)
    up = 0.5 * (L[19] + L[24]) - L[8]
    ey = up - (up @ ex) * ex
    ey /= np.linalg.norm(ey)
    return np.stack([ex, ey, np.cross(ex, ey)]), L[27]


def _canvas(rig, S: int, flab: np.ndarray) -> tuple[_Canvas, np.ndarray, np.ndarray]:
    """Lay out and rasterize the atlas of ``rig`` (mm) at S x S texels; flab (F,) region per triangle.

    Returns the :class:`_Canvas`, the atlas uvs (3F, 2) and face_uvs (F, 3)."""
    X = rig.neutral
    uvs, face_uvs, ppm = atlas_layout(X, rig.faces, rig.uvs, rig.face_uvs, flab, S)
    tri, bary = rasterize_uv(uvs, face_uvs, (S, S))
    cov = tri >= 0
    t = tri[cov]
    lab = flab[t]
    pos = texel_points(tri, bary, X, rig.faces, cov)
    isk = (lab == REGION_CODES["skin"]) | (lab == REGION_CODES["head"])
    L = X[rig.landmarks]
    Rf, o = _face_frame(L)
    q = ((pos - o) @ Rf.T).astype(np.float32)
    Lq = (L - o) @ Rf.T
    rr, cc = np.nonzero(cov)
    return _Canvas(S, ppm, cov, rr, cc, t, lab, pos, isk, q, Lq), uvs, face_uvs


def _noise(rng, cv: _Canvas, texture: float) -> _Noise:
    """Draw the texture-space noise (sizes in mm, via cv.ppm): three FFT-filtered fields, in this order."""
    import cv2

    S, ppm, cov = cv.S, cv.ppm, cv.cov
    fine_img = _noise_fields(rng, S, [s * ppm for s in FINE_SIGMAS_MM], FINE_WEIGHTS)
    small = max(32, S // 8)
    low_img = _noise_fields(rng, small, [6.0 * ppm * small / S, 15.0 * ppm * small / S], [0.6, 0.8])
    low_img = cv2.resize(low_img, (S, S), interpolation=cv2.INTER_CUBIC)
    fine = fine_img[cov] * np.float32(texture)
    low = low_img[cov]
    low2 = cv2.resize(_noise_fields(rng, small, [3.0 * ppm * small / S], [1.0]), (S, S),
                      interpolation=cv2.INTER_CUBIC)[cov]
    return _Noise(fine_img, fine, low, low2)


# ---------------------------------------------------------------------------- skin fields
def _lip_mask(cv: _Canvas) -> np.ndarray:
    """(N,) float32 lip weight: inside the outer lip contour (landmarks 48-59), a 0.8 mm soft edge."""
    q, Lq = cv.q, cv.Lq
    mouth_y, lip_z = Lq[48:68, 1].mean(), Lq[48:60, 2].mean()
    lips = np.zeros(len(q), np.float32)
    near_mouth = cv.isk & (q[:, 2] > lip_z - 14.0) & (np.abs(q[:, 1] - mouth_y) < 30)
    if near_mouth.any():
        sd = _polygon_sdf(q[near_mouth, :2], Lq[48:60, :2])
        lips[near_mouth] = _smooth(0.8, -0.8, sd)
    return lips


def _brow_mask(cv: _Canvas) -> tuple[np.ndarray, list]:
    """(N,) float32 brow weight (a band 2.5 mm below the brow landmarks, half-width 2 mm at the outer end
    to 5 mm at the inner end) and the two brow polylines (5, 3) mm, outer -> inner."""
    q, Lq = cv.q, cv.Lq
    brow = np.zeros(len(q), np.float32)
    brow_axis = []
    for ids in ((17, 18, 19, 20, 21), (26, 25, 24, 23, 22)):  # outer -> inner
        pts = Lq[list(ids)] - np.array([0.0, 2.5, 0.0])
        sel = cv.isk & (np.abs(q[:, 1] - pts[:, 1].mean()) < 20) & (q[:, 2] > Lq[ids[0], 2] - 20)
        d, tt = _seg_dist(q[sel], pts[:-1], pts[1:])
        k = np.argmin(d, 1)
        s_along = (k + tt[np.arange(len(k)), k]) / (len(ids) - 1)  # 0 outer .. 1 inner
        half = 2.0 + 3.0 * s_along
        brow[sel] = np.maximum(brow[sel], _smooth(half + 1.2, half - 1.2, d[np.arange(len(k)), k]))
        brow_axis.append(pts)
    return brow, brow_axis


def _beard_mask(cv: _Canvas, lips: np.ndarray, stubble: float) -> np.ndarray:
    """(N,) stubble weight x min(stubble, 1): under the nose, over the chin and jaw, the sideburns and the
    front of the neck; not on the lips."""
    q, Lq = cv.q, cv.Lq
    eye_y, mouth_y, nose_y, chin_y = Lq[36:48, 1].mean(), Lq[48:68, 1].mean(), Lq[33, 1], Lq[8, 1]
    jaw_x = 0.5 * (abs(Lq[2, 0]) + abs(Lq[14, 0]))
    ax = np.abs(q[:, 0])
    top = np.interp(ax, [0, 0.45 * jaw_x, 0.7 * jaw_x, 0.95 * jaw_x, 1.05 * jaw_x],
                    [nose_y - 4, nose_y - 8, mouth_y + 4, mouth_y + 12, eye_y - 20])
    beard = _smooth(top + 3, top - 3, q[:, 1]) * _smooth(chin_y - 45, chin_y - 25, q[:, 1]) * cv.isk
    beard *= 1.0 - lips * 0.95
    beard *= _smooth(-60, -30, q[:, 2] - Lq[8, 2]) + (q[:, 2] > Lq[2, 2] - 25)  # front of the neck and the jaw
    return np.clip(beard, 0, 1) * np.float32(min(stubble, 1.0))


def _hair_masks(cv: _Canvas, low2: np.ndarray, hairline_mm: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Hair cap weight (N,), hairline fuzz weight (N,) (8 mm below the line) and zc (mm, see :class:`_Fields`).

    The hairline is a height by azimuth around the head's vertical axis, ``hairline_mm`` above the mid-brow
    at the front, jittered by 2.5 mm x low2."""
    q, Lq = cv.q, cv.Lq
    brow_y, eye_y, mouth_y = Lq[17:27, 1].mean(), Lq[36:48, 1].mean(), Lq[48:68, 1].mean()
    zc = 0.5 * (Lq[0, 2] + Lq[16, 2]) - 15.0
    az = np.degrees(np.abs(np.arctan2(q[:, 0], q[:, 2] - zc)))
    yf = brow_y + hairline_mm
    line = np.interp(az, [0, 30, 55, 75, 84, 96, 118, 180],
                     [yf, yf + 2, yf - 8, eye_y + 22, eye_y - 22, eye_y + 18, eye_y - 10, mouth_y - 5])
    line = line + 2.5 * low2
    hair = _smooth(line - 1.5, line + 2.5, q[:, 1]) * cv.isk
    fuzz = _smooth(line - 8, line, q[:, 1]) * (1 - hair) * cv.isk
    return hair, fuzz, zc


def _redness(cv: _Canvas, low: np.ndarray, redness: float) -> tuple[np.ndarray, np.ndarray]:
    """Redness (N,) float32 in [0, 1.2] (cheeks, nose tip, chin, forehead, x ``redness``, plus blotches) and
    the T-zone weight (N,) in [0, 1] (nose and forehead)."""
    Lq, gauss = cv.Lq, cv.gauss
    red = redness * (0.9 * gauss(Lq[[2, 31, 41]].mean(0), 14.0) + 0.9 * gauss(Lq[[14, 35, 46]].mean(0), 14.0)
                     + 0.8 * gauss(Lq[30], 9.0) + 0.35 * gauss(Lq[8] + [0, 8, 0], 12.0)
                     + 0.25 * gauss(0.5 * (Lq[19] + Lq[24]) + [0, 30, 0], 25.0)).astype(np.float32)
    red = np.clip(red + 0.15 * low, 0, 1.2)
    tzone = (gauss(Lq[30] + [0, 15, 0], 16.0) + gauss(0.5 * (Lq[19] + Lq[24]) + [0, 25, 0], 22.0)).clip(0, 1)
    return red, tzone


def _skin_fields(cv: _Canvas, nz: _Noise, p: SkinParams) -> _Fields:
    """All the per-texel feature weights of the skin (no random draws)."""
    lips = _lip_mask(cv)
    brow, brow_axis = _brow_mask(cv)
    beard = _beard_mask(cv, lips, p.stubble)
    hair, fuzz, zc = _hair_masks(cv, nz.low2, p.hairline_mm)
    red, tzone = _redness(cv, nz.low, p.redness)
    return _Fields(lips, brow, brow_axis, beard, hair, fuzz, zc, red, tzone)


# ---------------------------------------------------------------------------- skin colour (linear light)
def _base_tone(cv: _Canvas, nz: _Noise, fl: _Fields, p: SkinParams) -> np.ndarray:
    """(N, 3) linear-light albedo: the tone, reddened by fl.red, blotched by the low noise, times the fine
    texture exp(fine) (damped on the lips and the hair cap)."""
    N = len(cv.q)
    low, low2 = nz.low, nz.low2
    base = _lin(p.tone)[None, :] * np.ones((N, 1), np.float32)
    red_tint = _lin(p.tone) * np.array([1.0, 0.72, 0.78], np.float32)
    base = base + (red_tint - base) * (0.45 * fl.red)[:, None]
    base *= np.exp(0.06 * low)[:, None] * np.array([1.0, 1.0, 1.0], np.float32)
    base *= (1.0 + 0.02 * low2[:, None] * np.array([1.0, -0.5, -1.0], np.float32))
    amp = np.float32(1.0) - 0.5 * fl.lips - 0.6 * fl.hair
    return base * np.exp(nz.fine * amp)[:, None]


def _pores(rng, cv: _Canvas, col: np.ndarray, skin_idx: np.ndarray, area_mm2: float,
           lips: np.ndarray) -> np.ndarray:
    """Darken col (N, 3) by sparse pits ~0.1-0.2 mm (1.2 per mm^2 of the texels ``skin_idx``, area_mm2)."""
    import cv2

    pits = np.zeros((cv.S, cv.S), np.float32)
    n_pits = int(1.2 * area_mm2)
    if n_pits and skin_idx.size:
        k = rng.choice(skin_idx, n_pits)
        np.add.at(pits, (cv.rr[k], cv.cc[k]), rng.uniform(0.5, 1.0, n_pits).astype(np.float32))
        pits = cv2.GaussianBlur(pits, (0, 0), max(0.5, 0.07 * cv.ppm))
        pits /= max(float(pits.max()), 1e-6) * 0.5
    col *= (1.0 - 0.10 * np.clip(pits[cv.cov], 0, 1) * (1 - lips))[:, None]
    return col


def _freckles(rng, cv: _Canvas, fl: _Fields, skin_idx: np.ndarray, area_mm2: float,
              density: float) -> np.ndarray:
    """(S, S) float32 freckle image: discs 0.25-0.9 mm, density x 0.004 per mm^2, more where red and on
    the nose, none on the lips."""
    import cv2

    spots = np.zeros((cv.S, cv.S), np.float32)
    if skin_idx.size:
        wf = (0.15 + fl.red[skin_idx] + 1.5 * cv.gauss(cv.Lq[30] + [0, 12, 0], 18.0)[skin_idx]) \
            * (1 - fl.lips[skin_idx])
        nf = int(density * 0.004 * area_mm2)
        for i in rng.choice(skin_idx, nf, p=wf / wf.sum()) if nf else []:
            r_px = max(1, int(round(rng.uniform(0.25, 0.9) * cv.ppm)))
            cv2.circle(spots, (int(cv.cc[i]), int(cv.rr[i])), r_px, float(rng.uniform(0.3, 1.0)), -1, cv2.LINE_AA)
        spots = cv2.GaussianBlur(spots, (0, 0), max(0.5, 0.15 * cv.ppm))
    return spots


def _moles(rng, cv: _Canvas, fl: _Fields, skin_idx: np.ndarray, count: int) -> np.ndarray:
    """(S, S) float32 mole image: ``count`` discs 0.6-1.6 mm on the front of the face, off hair and lips."""
    import cv2

    moles = np.zeros((cv.S, cv.S), np.float32)
    if skin_idx.size:
        face_idx = skin_idx[(cv.q[skin_idx, 2] > fl.zc) & (fl.hair[skin_idx] < 0.1) & (fl.lips[skin_idx] < 0.1)]
        for i in rng.choice(face_idx, count) if (count and face_idx.size) else []:
            r_px = max(1, int(round(rng.uniform(0.6, 1.6) * cv.ppm)))
            cv2.circle(moles, (int(cv.cc[i]), int(cv.rr[i])), r_px, 1.0, -1, cv2.LINE_AA)
        moles = cv2.GaussianBlur(moles, (0, 0), max(0.5, 0.12 * cv.ppm))
    return moles


def _paint_lips(col: np.ndarray, nz: _Noise, lips: np.ndarray, lip_rgb) -> np.ndarray:
    """Blend col (N, 3) to the lip colour (sRGB 0-255, with the fine and low texture) by the lip weight."""
    lipc = _lin(lip_rgb) * np.exp(0.5 * nz.fine)[:, None] * (1.0 + 0.08 * nz.low)[:, None]
    return col * (1 - lips[:, None]) + lipc * lips[:, None]


def _stubble(rng, cv: _Canvas, col: np.ndarray, beard: np.ndarray) -> np.ndarray:
    """Darken col (N, 3) by the stubble: a blue-grey shadow and dark follicle dots (0.8 per mm^2)."""
    import cv2

    dots = np.zeros((cv.S, cv.S), np.float32)
    bidx = np.flatnonzero(beard > 0.05)
    if bidx.size:
        nd = int(0.8 * bidx.size / cv.ppm ** 2)
        k = rng.choice(bidx, nd)
        np.add.at(dots, (cv.rr[k], cv.cc[k]), 1.0)
        dots = np.clip(cv2.GaussianBlur(dots, (0, 0), max(0.5, 0.09 * cv.ppm)) * 6.0, 0, 1)
    shadow = beard[:, None] * (0.28 * np.array([1.0, 0.95, 0.85], np.float32) + 0.35 * dots[cv.cov][:, None])
    col *= 1.0 - shadow
    return col


def _brow_strokes(rng, cv: _Canvas, brow: np.ndarray, brow_axis: list, n_hairs: int) -> np.ndarray:
    """(N,) float32 eyebrow hair strokes: per brow ``n_hairs`` 3-D segments 4-8 mm long rooted on the brow
    texels, pointing outwards and up, drawn in the atlas as polylines of brow texels (1 texel wide)."""
    import cv2
    from scipy.spatial import cKDTree

    q, cc, rr = cv.q, cv.cc, cv.rr
    bsel = np.flatnonzero(brow > 0.02)
    strokes = np.zeros(len(q), np.float32)
    if bsel.size and n_hairs:
        tree = cKDTree(q[bsel])
        stroke_img = np.zeros((cv.S, cv.S), np.float32)
        for pts in brow_axis:
            root_k = rng.integers(0, bsel.size, 4 * n_hairs)
            near = np.linalg.norm(q[bsel[root_k]][:, None, :] - pts[None], axis=-1).min(1) < 6.0
            roots = q[bsel[root_k[near][: n_hairs]]]
            d, tt = _seg_dist(roots, pts[:-1], pts[1:])
            kk = np.argmin(d, 1)
            tang = (pts[1:] - pts[:-1])[kk]
            tang = -tang / np.linalg.norm(tang, axis=1, keepdims=True)  # towards the outer end
            s_in = (kk + tt[np.arange(len(kk)), kk]) / (len(pts) - 1)
            dirv = tang * (1 - 0.7 * s_in[:, None]) + np.array([0, 1.0, 0]) * (0.25 + 0.9 * s_in[:, None])
            dirv += rng.normal(0, 0.15, dirv.shape)
            dirv /= np.linalg.norm(dirv, axis=1, keepdims=True)
            length = rng.uniform(4.0, 8.0, len(roots))[:, None]
            # the stroke as a polyline of brow texels (nearest texel to points along it), drawn in the atlas
            chain = np.stack([tree.query(roots + f * length * dirv)[1] for f in (0.0, 0.25, 0.5, 0.75, 1.0)], 1)
            ids = bsel[chain]
            poly = np.stack([cc[ids], rr[ids]], -1).astype(np.int32)
            cv2.polylines(stroke_img, list(poly), False, 1.0, 1, cv2.LINE_AA)
        strokes = stroke_img[cv.cov]
    return strokes


def _paint_hair(col: np.ndarray, cv: _Canvas, nz: _Noise, fl: _Fields, hair_lin: np.ndarray) -> np.ndarray:
    """Darken col (N, 3) by the hairline fuzz and blend to the hair cap (hair_lin (3,) linear, low texture)."""
    col *= (1.0 - 0.18 * fl.fuzz)[:, None]
    hairc = hair_lin * np.exp(0.25 * nz.fine_img[cv.cov] * 0.3 + 0.08 * nz.low)[:, None]
    return col * (1 - fl.hair[:, None]) + hairc * fl.hair[:, None]


def _paint_skin(rng, cv: _Canvas, nz: _Noise, fl: _Fields, p: SkinParams) -> tuple[np.ndarray, np.ndarray]:
    """The skin's albedo col (N, 3) linear light and the brow-hair weight bh (N, 1).

    The random draws happen in this order: pores, freckles, moles, stubble dots, brow strokes."""
    col = _base_tone(cv, nz, fl, p)
    skin_idx = np.flatnonzero(cv.isk & (fl.hair < 0.5))
    area_mm2 = skin_idx.size / cv.ppm ** 2
    col = _pores(rng, cv, col, skin_idx, area_mm2, fl.lips)
    fr = _freckles(rng, cv, fl, skin_idx, area_mm2, p.freckles)[cv.cov][:, None]
    mo = _moles(rng, cv, fl, skin_idx, p.moles)[cv.cov][:, None]
    col *= 1.0 - 0.25 * fr * (1.0 - np.array([0.0, 0.15, 0.25], np.float32))
    col = col * (1 - mo) + _lin((92, 60, 48)) * mo
    col = _paint_lips(col, nz, fl.lips, p.lip)
    col = _stubble(rng, cv, col, fl.beard)
    hair_lin = _lin(p.hair)
    strokes = _brow_strokes(rng, cv, fl.brow, fl.brow_axis, p.brow_hairs)
    bh = (np.clip(strokes * 1.2, 0, 1) * fl.brow + 0.25 * fl.brow)[:, None] * np.clip(p.brow_hairs / 200.0, 0, 1)
    col = col * (1 - bh) + hair_lin * bh
    col = _paint_hair(col, cv, nz, fl, hair_lin)
    return col, bh


def _skin_material(nz: _Noise, fl: _Fields, bh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GGX perceptual roughness (N,) and F0 (N,) float32 of the skin: 0.45 / 0.028, shinier on the T-zone
    and the lips (0.22), rougher with stubble, hair and brows 0.55 / 0.045."""
    fine = nz.fine
    rough = np.full(len(fine), 0.45, np.float32)
    spec = np.full(len(fine), 0.028, np.float32)
    rough += 0.03 * np.clip(fine / 0.1, -1, 1) - 0.08 * fl.tzone + 0.06 * fl.beard
    rough = rough * (1 - fl.lips) + (0.22 + 0.02 * np.clip(fine / 0.1, -1, 1)) * fl.lips
    spec += 0.008 * fl.lips + 0.006 * fl.tzone
    hb = np.maximum(fl.hair, bh[:, 0])
    rough = rough * (1 - hb) + 0.55 * hb
    spec = spec * (1 - hb) + 0.045 * hb
    return rough, spec


# ---------------------------------------------------------------------------- the ICT inner parts
def _paint_ict_mouth(cv: _Canvas, nz: _Noise, col, rough, spec, lip_rgb) -> None:
    """Paint ICT's mouth socket, gums, teeth, eye sockets, lacrimal parts, eyelashes and eye overlays into
    col (N, 3) linear light, rough (N,) and spec (N,), in place; the mouth parts darken with depth
    behind the lips (0 at the lips' front, 1 at 40 mm)."""
    R, q, lab, fine = REGION_CODES, cv.q, cv.lab, nz.fine
    zf = cv.Lq[48:68, 2].max()

    def sub(name):
        m = np.flatnonzero(lab == R[name])
        return m, np.clip((zf - q[m, 2]) / 40.0, 0, 1)[:, None]  # depth: 0 at the lips' front, 1 40 mm behind

    m, depth = sub("mouth_socket")
    lipm = _smooth(8.0, 2.0, zf - q[m, 2])[:, None]
    c_m = _lin((120, 48, 48)) * (1 - 0.85 * _smooth(0.1, 0.6, depth))
    col[m] = c_m * (1 - lipm) + _lin(lip_rgb) * lipm
    rough[m], spec[m] = 0.2, 0.03
    m, depth = sub("gums")
    col[m] = _lin((165, 78, 80)) * np.exp(0.3 * fine[m])[:, None] * (1 - 0.7 * depth)
    rough[m], spec[m] = 0.18, 0.03
    m, depth = sub("teeth")
    col[m] = _lin((226, 216, 192)) * np.exp(0.2 * fine[m])[:, None] * (1 - 0.6 * depth)
    rough[m], spec[m] = 0.25, 0.04
    m = lab == R["eye_socket"]
    col[m] = _lin((175, 95, 92)) * 0.6
    rough[m], spec[m] = 0.15, 0.03
    m = lab == R["lacrimal"]
    col[m] = _lin((205, 160, 150))
    rough[m], spec[m] = 0.08, 0.03
    m = lab == R["eyelashes"]
    col[m] = _lin((28, 22, 20))
    rough[m], spec[m] = 0.5, 0.04
    m = (lab == R["eye_blend"]) | (lab == R["eye_occlusion"])
    col[m] = _lin((215, 205, 195))


def _eye_axis_coords(rig, cv: _Canvas, vlab: np.ndarray, eye: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For the eyeball texels ``eye`` (N,) bool: distance r (N,) float32 mm from their eye's optical axis
    (sphere centre of the sclera -> iris centroid) and the signed distance (N,) float32 mm along it
    from the centre; 0 elsewhere."""
    R, X, N = REGION_CODES, rig.neutral, len(cv.q)
    left = (rig.faces[cv.t, 0] >= _ICT_LEFT_EYE[0]) & (rig.faces[cv.t, 0] < _ICT_LEFT_EYE[1])
    r_ax = np.zeros(N, np.float32)
    front = np.zeros(N, np.float32)
    for side, (a, b) in ((True, (21451, 23021)), (False, (23021, 24591))):
        c = _sphere_fit(X[a:b][vlab[a:b] == R["sclera"]])
        ic = X[a:b][vlab[a:b] == R["iris"]].mean(0)
        axis = (ic - c) / np.linalg.norm(ic - c)
        sel = eye & (left == side)
        rel = cv.pos[sel] - c
        front[sel] = rel @ axis
        r_ax[sel] = np.linalg.norm(rel - np.outer(rel @ axis, axis), axis=1)
    return r_ax, front


def _paint_ict_eyes(rig, cv: _Canvas, nz: _Noise, vlab: np.ndarray, col, rough, spec, iris_rgb) -> None:
    """Paint ICT's eyeballs into col, rough, spec (in place) by the distance r from the optical axis:
    pupil r < 1.8 mm, iris (streaked, sRGB ``iris_rgb``) r < 6 mm, sclera; a smooth cornea r < 6.4 mm."""
    lab = cv.lab
    eye = (lab == REGION_CODES["sclera"]) | (lab == REGION_CODES["iris"])
    if not eye.any():
        return
    r_ax, front = _eye_axis_coords(rig, cv, vlab, eye)
    low2 = nz.low2
    fr_ = front > 0
    ang = np.arctan2(cv.q[:, 1], cv.q[:, 0])
    streak = np.cos(ang * 37 + 3 * low2) * 0.15 + 0.3 * nz.fine
    iris_c = _lin(iris_rgb) * np.exp(streak)[:, None] * (0.75 + 0.25 * _smooth(5.8, 3.0, r_ax))[:, None]
    sclera_c = _lin((228, 218, 208)) * (1 - 0.12 * _smooth(8.0, 12.0, r_ax))[:, None]
    sclera_c *= 1 - 0.05 * np.clip(low2, -1, 1)[:, None] * np.array([0, 1, 1], np.float32)
    w_iris = (_smooth(6.3, 5.7, r_ax) * fr_)[:, None]
    w_pup = (_smooth(1.95, 1.65, r_ax) * fr_)[:, None]
    c_e = sclera_c * (1 - w_iris) + iris_c * w_iris
    c_e = c_e * (1 - w_pup) + _lin((10, 9, 9)) * w_pup
    col[eye] = c_e[eye]
    corn = (_smooth(6.8, 6.0, r_ax) * fr_).astype(np.float32)
    rough[eye] = (0.15 * (1 - corn) + 0.04 * corn)[eye]
    spec[eye] = (0.03 * (1 - corn) + 0.025 * corn)[eye]


# ---------------------------------------------------------------------------- to images
def _to_images(cv: _Canvas, col, rough, spec) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The (S, S) maps from the per-texel values: texture (S, S, 3) uint8 sRGB from col (N, 3) linear,
    roughness (S, S) float32 clipped to [0.02, 1], specular (S, S) float32 in [0, 1], each with its gutters
    filled by the nearest covered texel, and regions (S, S) uint8 (0 in the gutters). All read-only."""
    from scipy import ndimage

    S, cov = cv.S, cv.cov
    lv = np.linspace(0.0, 1.0, 8192)
    lut = np.clip(np.rint(255.0 * np.where(lv <= 0.0031308, 12.92 * lv, 1.055 * lv ** (1 / 2.4) - 0.055)), 0, 255)
    tex = np.zeros((S, S, 3), np.uint8)
    tex[cov] = lut.astype(np.uint8)[np.clip(col * 8191.0 + 0.5, 0, 8191).astype(np.int32)]
    rmap = np.zeros((S, S), np.float32)
    rmap[cov] = np.clip(rough, 0.02, 1.0)
    smap = np.zeros((S, S), np.float32)
    smap[cov] = np.clip(spec, 0.0, 1.0)
    reg = np.zeros((S, S), np.uint8)
    reg[cov] = cv.lab
    _, (iy, ix) = ndimage.distance_transform_edt(~cov, return_distances=True, return_indices=True)
    tex, rmap, smap = tex[iy, ix], rmap[iy, ix], smap[iy, ix]
    for a in (tex, rmap, smap, reg):
        a.setflags(write=False)
    return tex, rmap, smap, reg


def _paint(rig, S: int, seed: int, p: SkinParams) -> SkinAppearance:
    """Paint ``rig`` (mm, ICT frame, 68 landmarks) into an S x S atlas with the random stream of ``seed``."""
    rng = np.random.default_rng(seed)
    vlab = vertex_regions(rig)
    flab = vlab[rig.faces[:, 0]]
    cv, uvs, face_uvs = _canvas(rig, S, flab)
    nz = _noise(rng, cv, p.texture)
    fl = _skin_fields(cv, nz, p)
    col, bh = _paint_skin(rng, cv, nz, fl, p)
    rough, spec = _skin_material(nz, fl, bh)
    if rig.n_vertices == ICT_N_VERTICES:
        _paint_ict_mouth(cv, nz, col, rough, spec, p.lip)
        _paint_ict_eyes(rig, cv, nz, vlab, col, rough, spec, p.iris)
    tex, rmap, smap, reg = _to_images(cv, col, rough, spec)
    vis = ~np.isin(flab, [REGION_CODES[n] for n in OVERLAY_REGIONS])
    return SkinAppearance(tex, rmap, smap, uvs, face_uvs, reg, flab, vis, cv.ppm)
