"""Lights and surface reflectance for the mesh renderers (opt-in: ``render_mesh(..., lights=[...])``).

Shading model (the same in the GLSL shader of :mod:`rigbuild.render.gl` and the numpy code of
:mod:`rigbuild.render.embree`), in linear light, camera frame, per visible point with unit normal ``n``
(two-sided: flipped towards the camera), view direction ``v`` and, per light, direction ``l`` and
irradiance ``E`` (linear RGB, 1.0 = the irradiance that makes a white Lambertian surface at normal
incidence read 1.0)::

    L = rho * E_ambient + sum_i E_i * V_i * max(n.l_i, 0) * ((1 - F_i) * rho + pi * f_spec_i)

with ``rho`` the linear albedo (sRGB-decoded texture), ``V_i`` the shadow-map visibility (1 without
shadows) and ``f_spec`` the GGX (Trowbridge-Reitz) microfacet BRDF ``D * Vis * F``: normalized
``D = a^2 / (pi ((n.h)^2 (a^2 - 1) + 1)^2)`` with ``a = roughness^2``, the height-correlated Smith
visibility ``Vis = 0.5 / (n.l sqrt((n.v)^2 (1 - a^2) + a^2) + n.v sqrt((n.l)^2 (1 - a^2) + a^2))`` and
Schlick's Fresnel ``F = F0 + (1 - F0) (1 - v.h)^5``. The diffuse term is weighted by ``1 - F`` so the
two lobes do not add more energy than arrives.

Shadows: each light with ``shadows=True`` gets a shadow map (light-frame linear depth at the texel
centres of an orthographic (directional) or perspective (point) view covering the whole mesh); the
lookup is bilinear percentage-closer filtering, averaged over 16 taps on a Vogel disk of radius
``softness_mm`` (mm on the receiver, measured in the shadow map's plane) when ``softness_mm > 0``; the
depth bias is slope scaled (``texel_mm * (1 + (1.5 + r_texels) * tan(theta))``, tan capped at 10).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rigbuild.errors import InputError

#: Shadow map size (texels per side) for every shadowing light.
SHADOW_MAP_SIZE = 2048
#: Most lights one render takes (ambient lights included) and most shadow maps.
MAX_LIGHTS = 8
MAX_SHADOW_MAPS = 4
#: PCF taps on the Vogel disk for soft shadows.
PCF_TAPS = 16
_KINDS = ("ambient", "directional", "point")


@dataclass(frozen=True)
class Light:
    """One light.

    kind : ``"directional"`` (at infinity), ``"point"`` or ``"ambient"`` (uniform, unshadowed, diffuse only).
    direction : (3,) direction TOWARDS the light (directional), world frame, any length > 0.
    position : (3,) light position (point), world mm.
    color : (3,) linear RGB tint (multiplies ``intensity``).
    intensity : irradiance scale: a white Lambertian surface facing the light reads ``intensity``
        (point lights: at distance ``reference_mm``, inverse-square falloff around it).
    reference_mm : distance at which a point light delivers ``intensity``, mm.
    rig_mounted : True: ``direction``/``position`` are in the rendering camera's frame (OpenCV axes,
        x right, y down, z forward; mm), so the light moves with the camera (a ring or key light on a
        head-mounted camera). False: world frame.
    shadows : cast shadows with a shadow map.
    softness_mm : penumbra radius of the soft shadow (PCF radius on the receiver, mm); 0 = hard edge.
    """

    kind: str = "directional"
    direction: tuple | None = None
    position: tuple | None = None
    color: tuple = (1.0, 1.0, 1.0)
    intensity: float = 1.0
    reference_mm: float = 1000.0
    rig_mounted: bool = False
    shadows: bool = False
    softness_mm: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in _KINDS:
            raise InputError(f"Light: kind must be one of {_KINDS}, got {self.kind!r}")
        if self.kind == "directional":
            d = np.asarray(self.direction if self.direction is not None else (), dtype=np.float64)
            if d.shape != (3,) or not np.linalg.norm(d) > 0:
                raise InputError("Light: a directional light needs a non-zero direction (3,)")
        if self.kind == "point":
            p = np.asarray(self.position if self.position is not None else (), dtype=np.float64)
            if p.shape != (3,) or not np.all(np.isfinite(p)):
                raise InputError("Light: a point light needs a position (3,) in mm")
            if not self.reference_mm > 0:
                raise InputError("Light: reference_mm must be > 0")
        if np.asarray(self.color, dtype=np.float64).shape != (3,):
            raise InputError("Light: color must be an RGB triple")
        if not self.intensity >= 0:
            raise InputError("Light: intensity must be >= 0")
        if not self.softness_mm >= 0:
            raise InputError("Light: softness_mm must be >= 0")
        if self.kind == "ambient" and self.shadows:
            raise InputError("Light: an ambient light casts no shadows")

    @property
    def radiance(self) -> np.ndarray:
        """(3,) linear RGB irradiance scale ``intensity * color``."""
        return float(self.intensity) * np.asarray(self.color, dtype=np.float64)


@dataclass
class Material:
    """Specular reflectance of the surface (the diffuse albedo is the mesh texture).

    specular : F0, the normal-incidence Fresnel reflectance (skin about 0.028, index 1.4).
    roughness : GGX perceptual roughness in (0, 1] (``a = roughness^2``); skin 0.35-0.5.
    specular_map, roughness_map : (H, W) float arrays of F0 / roughness aligned with the albedo texture
        (same UVs; any size: resampled to the albedo's), or None = uniform / per-vertex. uint8 maps are
        read as value / 255.
    vertex_specular, vertex_roughness : (V,) per-vertex F0 / roughness (interpolated), or None. A quantity
        comes from its map if given, else from its vertex array, else the scalar.
    dot_specular, dot_roughness : F0 / roughness of the painted dots (matte paint), or None = the skin's.
    """

    specular: float = 0.028
    roughness: float = 0.45
    specular_map: np.ndarray | None = None
    roughness_map: np.ndarray | None = None
    vertex_specular: np.ndarray | None = None
    vertex_roughness: np.ndarray | None = None
    dot_specular: float | None = 0.02
    dot_roughness: float | None = 0.7
    _packed: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not 0.0 <= self.specular <= 1.0:
            raise InputError("Material: specular (F0) must be in [0, 1]")
        if not 0.0 < self.roughness <= 1.0:
            raise InputError("Material: roughness must be in (0, 1]")
        if self.specular_map is not None and self.vertex_specular is not None:
            raise InputError("Material: give specular_map or vertex_specular, not both")
        if self.roughness_map is not None and self.vertex_roughness is not None:
            raise InputError("Material: give roughness_map or vertex_roughness, not both")

    def vertex_values(self, n_vertices: int) -> np.ndarray:
        """(V, 2) float32 per-vertex (F0, roughness) (the scalars where no vertex array is given)."""
        out = np.empty((n_vertices, 2), dtype=np.float32)
        for k, (arr, val) in enumerate(((self.vertex_specular, self.specular), (self.vertex_roughness, self.roughness))):
            if arr is None:
                out[:, k] = val
            else:
                a = np.asarray(arr, dtype=np.float64).reshape(-1)
                if a.shape != (n_vertices,):
                    raise InputError(f"Material: per-vertex arrays must be ({n_vertices},), got {a.shape}")
                out[:, k] = a
        return out

    @property
    def has_maps(self) -> tuple[bool, bool]:
        """(specular from the map, roughness from the map)."""
        return self.specular_map is not None, self.roughness_map is not None

    def packed_map(self, shape: tuple[int, int]) -> np.ndarray | None:
        """(H, W, 3) float32 [F0, roughness, 0] at the albedo's size, or None without maps. Cached."""
        if self.specular_map is None and self.roughness_map is None:
            return None
        key = tuple(shape)
        hit = self._packed.get(key)
        if hit is not None:
            return hit
        import cv2

        H, W = shape
        out = np.zeros((H, W, 3), dtype=np.float32)
        out[..., 0] = self.specular
        out[..., 1] = self.roughness
        for k, m in ((0, self.specular_map), (1, self.roughness_map)):
            if m is None:
                continue
            a = np.asarray(m)
            a = a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)
            if a.ndim == 3:
                a = a[..., 0]
            if a.shape != (H, W):
                a = cv2.resize(a, (W, H), interpolation=cv2.INTER_LINEAR)
            out[..., k] = a
        out.setflags(write=False)
        self._packed.clear()
        self._packed[key] = out
        return out


#: Skin, cornea and wet-lip reflectance (F0, roughness) for building maps.
SKIN_SPECULAR = (0.028, 0.45)
CORNEA_SPECULAR = (0.025, 0.08)
WET_LIP_SPECULAR = (0.035, 0.22)


def default_studio_lights(face_centre, cameras, distance_mm: float | None = None) -> list[Light]:
    """A capture-studio light set: a key light on the rig, a fill, a rim light and a little ambient.

    The key light sits beside the rig's central camera (the one looking most directly at the face
    from the mean viewing direction), 25 % of its distance above and 15 % to the side, so it is fixed
    to the rig; every camera renders the same world lighting (use ``Light(rig_mounted=True)`` for a
    light that moves with each camera). Fill: opposite side, lower, weaker; both cast soft shadows
    (2 shadow maps). Rim: a directional light from behind and above, no shadow map. Ambient 0.05.

    Parameters
    ----------
    face_centre : (3,) world point the lights aim at, mm.
    cameras : the rig's :class:`rigbuild.camera.Camera` list (at least one).
    distance_mm : key and fill distance from the face (None: the central camera's distance).

    Returns
    -------
    list of 4 :class:`Light` (key, fill, rim, ambient); the key delivers irradiance 0.75 at the face.
    """
    c = np.asarray(face_centre, dtype=np.float64).reshape(3)
    cams = list(cameras)
    if not cams:
        raise InputError("default_studio_lights: needs at least one camera")
    dirs = np.array([cam.center - c for cam in cams])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    mean = dirs.mean(0)
    mean /= np.linalg.norm(mean)
    cam = cams[int(np.argmax(dirs @ mean))]
    fwd = cam.center - c
    dist = float(np.linalg.norm(fwd)) if distance_mm is None else float(distance_mm)
    fwd /= np.linalg.norm(fwd)
    up = -cam.R[1]                       # camera y points down in the image
    up -= fwd * (up @ fwd)
    up /= np.linalg.norm(up)
    side = np.cross(up, fwd)
    key = c + dist * (fwd + 0.25 * up + 0.15 * side)
    fill = c + dist * (fwd * 0.8 - 0.1 * up - 0.9 * side)
    rim = -fwd + 0.8 * up + 0.3 * side
    return [
        Light("point", position=tuple(key), intensity=0.75, color=(1.0, 0.98, 0.95),
              reference_mm=float(np.linalg.norm(key - c)), shadows=True, softness_mm=2.0),
        Light("point", position=tuple(fill), intensity=0.3, color=(0.95, 0.97, 1.0),
              reference_mm=float(np.linalg.norm(fill - c)), shadows=True, softness_mm=6.0),
        Light("directional", direction=tuple(rim), intensity=0.35),
        Light("ambient", intensity=0.05),
    ]
