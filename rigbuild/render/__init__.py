"""CPU rendering of textured meshes and calibration boards through OpenCV cameras with distortion.

``render_mesh(camera, mesh, ..., backend="auto")`` rasterizes with moderngl on a standalone EGL context
(:mod:`rigbuild.render.gl`) or ray casts with embreex (:mod:`rigbuild.render.embree`); ``"auto"`` uses GL
when an EGL context can be created and otherwise embree (with a one-line warning).

Opt-in realism (defaults reproduce the 8-bit single-light Lambert images bit for bit): ``lights=[Light, ...]``
with a :class:`Material` shades in linear light with GGX specular and shadow maps
(:mod:`rigbuild.render.lights`); ``output="linear"`` returns the float radiance for a sensor model;
``with_motion=True`` returns the per-pixel image motion of ``TexturedMesh.vertex_motion``.
"""

from __future__ import annotations

import warnings

from rigbuild.camera import Camera
from rigbuild.render.common import RenderResult, linear_to_srgb, srgb_to_linear
from rigbuild.render.lights import Light, Material, default_studio_lights
from rigbuild.render.mesh import TexturedMesh, checker_texture, speckle_texture, vertex_normals

__all__ = [
    "Light",
    "Material",
    "RenderResult",
    "TexturedMesh",
    "checker_texture",
    "default_studio_lights",
    "linear_to_srgb",
    "render_board",
    "render_mesh",
    "speckle_texture",
    "srgb_to_linear",
    "vertex_normals",
]

_WARNED = []


def _pick_backend(backend: str) -> str:
    if backend in ("gl", "embree"):
        return backend
    if backend != "auto":
        raise ValueError(f"render backend must be 'auto', 'gl' or 'embree', got {backend!r}")
    from rigbuild.render.gl import egl_available

    if egl_available():
        return "gl"
    if not _WARNED:
        from rigbuild.render.gl import _STATE

        warnings.warn(f"rigbuild.render: no EGL context ({_STATE.get('error')}); using the embree ray caster",
                      RuntimeWarning, stacklevel=3)
        _WARNED.append(True)
    return "embree"


def render_mesh(
    camera: Camera,
    mesh: TexturedMesh,
    light_dir=None,
    ambient: float = 0.3,
    background=128,
    noise_sigma: float = 0.0,
    seed: int | None = None,
    msaa: bool = True,
    backend: str = "auto",
    with_color: bool = True,
    with_geometry: bool = True,
    lights=None,
    material=None,
    output: str = "srgb8",
    with_motion: bool = False,
) -> RenderResult:
    """Render a textured mesh through a distorted OpenCV camera.

    Parameters
    ----------
    camera : :class:`rigbuild.camera.Camera` (world in mm).
    mesh : :class:`TexturedMesh` in world mm.
    light_dir : (3,) world direction towards a distant light (None: frontal-from-above default).
    ambient : ambient fraction of the Lambert shading.
    background : grey level or RGB triple for pixels without surface.
    noise_sigma : Gaussian sensor noise std in 8-bit levels.
    seed : noise seed (None: derived from the camera id; same seed -> identical image).
    msaa : anti-alias the colour (GL only).
    backend : ``"auto"``, ``"gl"`` or ``"embree"``.
    with_color : False skips shading (``color`` is then the plain background): geometry buffers only.
    with_geometry : False skips the exact depth/id/barycentric resolve (GL; they come back as NaN / -1 / 0):
        colour only, about twice as fast (used for the synthetic session's images).
    lights : None (the single Lambert light above, 8-bit model, unchanged) or a list of
        :class:`rigbuild.render.lights.Light` (up to 8, up to 4 with shadows): linear-light GGX + Lambert
        shading with shadow maps; ``light_dir`` and ``ambient`` are then unused (add an ``"ambient"`` Light).
    material : :class:`rigbuild.render.lights.Material` (None: uniform skin, F0 0.028, roughness 0.45).
    output : ``"srgb8"`` (``color`` uint8: with ``lights``, sRGB-encoded radiance plus noise),
        ``"linear"`` (``linear`` (H, W, 3) float32 radiance before noise and 8-bit conversion; ``color``
        None) or ``"both"``. Without ``lights``, ``linear`` is the sRGB decoding of the noiseless 8-bit
        levels.
    with_motion : also return ``motion_px`` (H, W, 2) float32, the projected displacement of
        ``mesh.vertex_motion`` at each pixel (NaN on background; zeros when the mesh has no motion);
        forces the geometry pass.

    Returns
    -------
    :class:`RenderResult` with colour (H, W, 3) uint8, depth (H, W) float32 camera z in mm (NaN background),
    tri_id (H, W) int32 (-1 background), bary (H, W, 3) float32, and ``linear`` / ``motion_px`` when asked.
    """
    kind = _pick_backend(backend)
    if kind == "gl":
        from rigbuild.render.gl import render_mesh as impl
    else:
        from rigbuild.render.embree import render_mesh as impl
    from rigbuild.render.common import RenderOptions

    return impl(camera, mesh, RenderOptions(light_dir, ambient, background, noise_sigma, seed, msaa, with_color,
                                            with_geometry, lights, material, output, with_motion))


from rigbuild.render.board import render_board  # noqa: E402  (board.py uses render_mesh above)
