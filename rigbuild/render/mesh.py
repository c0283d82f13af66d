"""Renderable meshes: a textured triangle mesh with optional painted marker dots, and a speckle albedo.

Texture coordinates follow the OBJ convention: ``(u, v)`` in texture units, ``v`` up, so ``v = 0`` is the
bottom row of the ``texture`` image and ``v = 1`` its top row; coordinates outside ``[0, 1]`` wrap
(UDIM-style tiles such as ICT's ``u`` in ``[0, 7]`` reuse the same image).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from rigbuild.errors import InputError
from rigbuild.geometry.mesh import vertex_normals  # noqa: F401 (re-exported)


@dataclass
class TexturedMesh:
    """A triangle mesh with an albedo texture, ready to render.

    Attributes
    ----------
    vertices : (V, 3) float64 world positions, mm.
    faces : (F, 3) int64 vertex indices per triangle.
    uvs : (T, 2) float64 texture coordinates (OBJ convention, wrap outside [0, 1]).
    face_uvs : (F, 3) int64 indices into ``uvs`` per triangle corner.
    texture : (H, W, 3) uint8 albedo (RGB). Treated as immutable by the renderers (GL caches the upload
        per array object): make a new array instead of editing one in place.
    dot_centers : (M, 3) float64 world centres of painted marker dots, mm, or None. A surface point
        within ``dot_radius_mm`` (3-D distance) of a centre is painted ``dot_albedo``, so a dot is a disc
        of that radius on the skin that moves with the centre (pass deformed marker vertices per frame).
    dot_radius_mm : scalar or (M,) dot radius, mm.
    dot_albedo : (3,) RGB paint colour of the dots (0..255), or (M, 3) one colour per dot.
    vertex_normals : (V, 3) float64 unit normals for shading, or None (area-weighted from the faces).
    vertex_motion : (V, 3) float64 world displacement of each vertex over the exposure, mm, or None;
        ``render_mesh(..., with_motion=True)`` projects it to per-pixel image motion.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    face_uvs: np.ndarray
    texture: np.ndarray
    dot_centers: np.ndarray | None = None
    dot_radius_mm: float | np.ndarray = 1.5
    dot_albedo: tuple[int, int, int] = (25, 25, 25)
    vertex_normals: np.ndarray | None = None
    vertex_motion: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64)
        self.faces = np.asarray(self.faces, dtype=np.int64)
        self.uvs = np.asarray(self.uvs, dtype=np.float64)
        self.face_uvs = np.asarray(self.face_uvs, dtype=np.int64)
        if self.dot_centers is not None:
            self.dot_centers = np.asarray(self.dot_centers, dtype=np.float64).reshape(-1, 3)
        if self.vertex_normals is not None:
            self.vertex_normals = np.asarray(self.vertex_normals, dtype=np.float64)
        if self.vertex_motion is not None:
            self.vertex_motion = np.asarray(self.vertex_motion, dtype=np.float64)
        self.validate()

    def validate(self) -> None:
        """Raise :class:`InputError` on inconsistent shapes or indices."""
        V, F = self.vertices.shape[0], self.faces.shape[0]
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise InputError(f"TexturedMesh: vertices must be (V, 3), got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise InputError(f"TexturedMesh: faces must be (F, 3) triangles, got {self.faces.shape}")
        if self.face_uvs.shape != (F, 3):
            raise InputError(f"TexturedMesh: face_uvs must be ({F}, 3), got {self.face_uvs.shape}")
        if self.uvs.ndim != 2 or self.uvs.shape[1] != 2:
            raise InputError(f"TexturedMesh: uvs must be (T, 2), got {self.uvs.shape}")
        if F and (self.faces.min() < 0 or self.faces.max() >= V):
            raise InputError("TexturedMesh: face index out of range")
        if F and (self.face_uvs.min() < 0 or self.face_uvs.max() >= self.uvs.shape[0]):
            raise InputError("TexturedMesh: face_uvs index out of range")
        t = self.texture
        if not (isinstance(t, np.ndarray) and t.dtype == np.uint8 and t.ndim == 3 and t.shape[2] == 3):
            raise InputError("TexturedMesh: texture must be an (H, W, 3) uint8 array")
        if self.vertex_normals is not None and self.vertex_normals.shape != (V, 3):
            raise InputError(f"TexturedMesh: vertex_normals must be ({V}, 3)")
        if self.dot_centers is not None:
            r = np.broadcast_to(np.asarray(self.dot_radius_mm, dtype=np.float64), (self.dot_centers.shape[0],))
            if np.any(r <= 0):
                raise InputError("TexturedMesh: dot_radius_mm must be positive")
        a = np.asarray(self.dot_albedo, dtype=np.float64)
        M = 0 if self.dot_centers is None else self.dot_centers.shape[0]
        if not (a.shape == (3,) or a.shape == (M, 3)):
            raise InputError(f"TexturedMesh: dot_albedo must be (3,) or ({M}, 3), got {a.shape}")
        if self.vertex_motion is not None and self.vertex_motion.shape != (V, 3):
            raise InputError(f"TexturedMesh: vertex_motion must be ({V}, 3)")

    @property
    def per_dot_albedo(self) -> bool:
        """True when ``dot_albedo`` gives one colour per dot."""
        return np.ndim(self.dot_albedo) == 2

    def dot_colors(self) -> np.ndarray:
        """(M, 3) float32 dot paint colours, 0..255 (empty without dots)."""
        M = 0 if self.dot_centers is None else self.dot_centers.shape[0]
        a = np.asarray(self.dot_albedo, dtype=np.float32)
        return np.ascontiguousarray(np.broadcast_to(a, (M, 3)) if a.ndim == 1 else a)

    @property
    def dot_radii(self) -> np.ndarray:
        """(M,) dot radii in mm (empty when there are no dots)."""
        if self.dot_centers is None:
            return np.zeros(0)
        return np.broadcast_to(np.asarray(self.dot_radius_mm, dtype=np.float64), (self.dot_centers.shape[0],)).copy()

    def normals(self) -> np.ndarray:
        """(V, 3) unit vertex normals (``vertex_normals`` or area-weighted face normals)."""
        if self.vertex_normals is not None:
            return self.vertex_normals
        return vertex_normals(self.vertices, self.faces)

    def with_vertices(self, vertices: np.ndarray, dot_centers: np.ndarray | None = None,
                      vertex_motion: np.ndarray | None = None) -> "TexturedMesh":
        """The same mesh (topology, UVs, texture, dots style) with new vertex positions (and dot centres,
        and per-vertex exposure motion)."""
        return TexturedMesh(vertices, self.faces, self.uvs, self.face_uvs, self.texture,
                            self.dot_centers if dot_centers is None else dot_centers,
                            self.dot_radius_mm, self.dot_albedo, None, vertex_motion)


# --------------------------------------------------------------------------- speckle
SKIN_RGB = (198.0, 148.0, 122.0)
SPECKLE_RGB = (70.0, 42.0, 34.0)


def _band_noise(rng: np.random.Generator, size: int, scale_px: float) -> np.ndarray:
    """Periodic (tileable) Gaussian-filtered white noise with blob size about ``scale_px``; unit std."""
    from scipy import fft

    white = rng.standard_normal((size, size), dtype=np.float32)
    fy = np.fft.fftfreq(size).astype(np.float32)
    fx = np.fft.rfftfreq(size).astype(np.float32)
    sigma = scale_px / 2.0  # Gaussian blur sigma in texels; its transfer function is exp(-2 pi^2 s^2 f^2)
    H = np.exp(np.float32(-2.0 * np.pi ** 2 * sigma ** 2) * (fy[:, None] ** 2 + fx[None, :] ** 2))
    out = fft.irfft2(fft.rfft2(white) * H, s=(size, size))
    return out / (out.std() + 1e-12)


@lru_cache(maxsize=4)
def _speckle_cached(size: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    scales = [s for s in (3.0, 6.0, 12.0, 24.0) if s < size / 4] or [max(1.0, size / 8)]
    weights = np.array([1.0, 0.8, 0.6, 0.4])[: len(scales)]
    field = sum(w * _band_noise(rng, size, s) for w, s in zip(weights, scales))
    field /= field.std() + 1e-12
    # Soft threshold -> blobs of paint/pigment covering about 35 % of the skin.
    blobs = 1.0 / (1.0 + np.exp(-(field - 0.4) / 0.18))
    # Slow tone variation (blotches) and fine pore-scale grain.
    tone = 1.0 + 0.08 * _band_noise(rng, size, max(2.0, size / 16))
    grain = 0.04 * rng.standard_normal((size, size))
    skin = np.asarray(SKIN_RGB)[None, None, :] * (tone + grain)[..., None]
    dark = np.asarray(SPECKLE_RGB)[None, None, :]
    img = skin * (1.0 - blobs[..., None]) + dark * blobs[..., None]
    out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    out.setflags(write=False)
    return out


def speckle_texture(size: int = 2048, seed: int = 0) -> np.ndarray:
    """A skin-toned albedo with dark multi-scale speckle, good for stereo matching and optical flow.

    Band-limited random blobs at about 3, 6, 12 and 24 texels over a skin tone with slow blotches and
    fine grain. The texture tiles seamlessly (built by FFT filtering), so wrapped UV tiles show no
    seam. Deterministic per ``(size, seed)``.

    Returns
    -------
    (size, size, 3) uint8 RGB, read-only; the same array object for the same arguments (so the GL
    renderer uploads it once). ``.copy()`` it to edit.
    """
    size = int(size)
    if size < 8:
        raise ValueError("speckle_texture: size must be >= 8")
    return _speckle_cached(size, int(seed))


def checker_texture(size: int = 256, squares: int = 8, colors=((230, 230, 230), (40, 40, 40))) -> np.ndarray:
    """A (size, size, 3) uint8 checkerboard with ``squares`` squares per side (tests, debugging)."""
    idx = (np.arange(size) * squares // size)
    parity = (idx[:, None] + idx[None, :]) % 2
    c = np.asarray(colors, dtype=np.uint8)
    return c[parity]
