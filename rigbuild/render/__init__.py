"""CPU rendering of textured meshes and calibration boards through OpenCV cameras with distortion.

``render_mesh(camera, mesh, ..., backend="auto")`` rasterizes with moderngl on a standalone EGL context
(:mod:`rigbuild.render.gl`) or ray casts with embreex (:mod:`rigbuild.render.embree`); ``"auto"`` uses GL
when an EGL context can be created and otherwise embree (with a one-line warning).
"""

from __future__ import annotations

import warnings

from rigbuild.camera import Camera
from rigbuild.render.common import RenderResult
from rigbuild.render.mesh import TexturedMesh, checker_texture, speckle_texture, vertex_normals

__all__ = [
    "RenderResult",
    "TexturedMesh",
    "checker_texture",
    "render_board",
    "render_mesh",
    "speckle_texture",
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

    Returns
    -------
    :class:`RenderResult` with colour (H, W, 3) uint8, depth (H, W) float32 camera z in mm (NaN background),
    tri_id (H, W) int32 (-1 background), bary (H, W, 3) float32.
    """
    kind = _pick_backend(backend)
    if kind == "gl":
        from rigbuild.render.gl import render_mesh as impl
    else:
        from rigbuild.render.embree import render_mesh as impl
    return impl(camera, mesh, light_dir=light_dir, ambient=ambient, background=background,
                noise_sigma=noise_sigma, seed=seed, msaa=msaa, with_color=with_color, with_geometry=with_geometry)


from rigbuild.render.board import render_board  # noqa: E402  (board.py uses render_mesh above)
