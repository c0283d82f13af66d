"""Ray-casting renderer with embreex: one primary ray per distorted OpenCV pixel centre.

The independent oracle for the GL renderer in tests and the fallback where EGL is absent. Rays are the
camera's (:meth:`rigbuild.camera.Camera.rays` model: undistorted pixel centres), cast in the camera frame
from the origin with direction ``(x, y, 1)`` so that the hit distance is the camera depth ``z``. Colour:
the same Lambert model as the GL shader; texture lookups are trilinear over a mip pyramid with the level
chosen from the pixel's texel footprint (isotropic, no anisotropy and no anti-aliasing, 1 sample/pixel).
"""

from __future__ import annotations

import numpy as np

from rigbuild.camera import Camera
from rigbuild.render.common import (
    RenderResult,
    background_rgb,
    finish_color,
    light_in_camera,
    pixel_rays,
)
from rigbuild.render.mesh import TexturedMesh


def cast_rays(vertices_cam: np.ndarray, faces: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast camera-frame rays ``(x, y, 1)`` from the origin against a triangle mesh with embree.

    Parameters
    ----------
    vertices_cam : (V, 3) camera-frame vertices, mm; faces : (F, 3) triangles (shared vertices, so edges
        are watertight).
    xy : (N, 2) normalized ray coordinates.

    Returns
    -------
    z : (N,) float64 depth (NaN on miss); tri : (N,) int64 triangle (-1 on miss); bary : (N, 3) float64.
    """
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(vertices_cam, dtype=np.float32),
                 np.ascontiguousarray(faces, dtype=np.int32))
    n = xy.shape[0]
    org = np.zeros((n, 3), dtype=np.float32)
    d = np.ones((n, 3), dtype=np.float32)
    d[:, :2] = xy
    res = scene.run(org, d, output=1)
    tri = np.asarray(res["primID"]).astype(np.int64)
    hit = (np.asarray(res["geomID"]) >= 0) & (tri >= 0)
    tri[~hit] = -1
    u = np.asarray(res["u"], dtype=np.float64)
    v = np.asarray(res["v"], dtype=np.float64)
    bary = np.stack([1.0 - u - v, u, v], 1)
    bary[~hit] = 0.0
    z = np.where(hit, np.asarray(res["tfar"], dtype=np.float64), np.nan)
    return z, tri, bary


def _mip_pyramid(texture: np.ndarray) -> list[np.ndarray]:
    import cv2

    levels = [texture.astype(np.float32)]
    while min(levels[-1].shape[:2]) > 1:
        h, w = levels[-1].shape[:2]
        levels.append(cv2.resize(levels[-1], (max(1, w // 2), max(1, h // 2)), interpolation=cv2.INTER_AREA))
    return levels


def sample_texture(texture: np.ndarray, uv: np.ndarray, lod: np.ndarray | None = None) -> np.ndarray:
    """Trilinear texture lookup with wrap-around.

    texture : (H, W, 3) uint8; uv : (N, 2) OBJ-convention coordinates (v up); lod : (N,) mip level
    (0 = full resolution; None = bilinear at level 0). Returns (N, 3) float32 in 0..255.
    """
    import cv2

    levels = _mip_pyramid(texture) if lod is not None else [texture.astype(np.float32)]
    n = uv.shape[0]
    out = np.zeros((n, 3), dtype=np.float32)
    if lod is None:
        lod = np.zeros(n)
    lod = np.clip(np.nan_to_num(lod, nan=0.0), 0.0, len(levels) - 1)
    lo = np.floor(lod).astype(np.int64)
    frac = (lod - lo).astype(np.float32)

    def lookup(level: int, idx: np.ndarray) -> np.ndarray:
        img = levels[level]
        h, w = img.shape[:2]
        u = np.mod(uv[idx, 0], 1.0) * w - 0.5
        v = (1.0 - np.mod(uv[idx, 1], 1.0)) * h - 0.5
        m = u.size
        cols = 1024
        rows = -(-m // cols)
        mx = np.zeros(rows * cols, dtype=np.float32)
        my = np.zeros(rows * cols, dtype=np.float32)
        mx[:m], my[:m] = u, v
        s = cv2.remap(img, mx.reshape(rows, cols), my.reshape(rows, cols),
                      interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        return s.reshape(-1, 3)[:m]

    for level in np.unique(lo):
        idx = np.flatnonzero(lo == level)
        a = lookup(int(level), idx)
        if level + 1 < len(levels):
            b = lookup(int(level) + 1, idx)
            f = frac[idx, None]
            a = a * (1 - f) + b * f
        out[idx] = a
    return out


def render_mesh(
    camera: Camera,
    mesh: TexturedMesh,
    light_dir=None,
    ambient: float = 0.3,
    background=128,
    noise_sigma: float = 0.0,
    seed: int | None = None,
    msaa: bool = True,
    with_color: bool = True,
    with_geometry: bool = True,
) -> RenderResult:
    """Render ``mesh`` seen by ``camera`` by ray casting (same signature and model as the GL renderer).

    ``msaa`` is accepted for signature compatibility and ignored (1 sample per pixel); ``with_color=False``
    skips shading (``color`` is the plain background).
    """
    del msaa
    xy = pixel_rays(camera)
    H, W = camera.height, camera.width
    if mesh.faces.shape[0] == 0:
        img = np.broadcast_to(background_rgb(background).astype(np.float32), (H, W, 3))
        return RenderResult(finish_color(img, noise_sigma, camera, seed), np.full((H, W), np.nan, np.float32),
                            np.full((H, W), -1, np.int32), np.zeros((H, W, 3), np.float32))
    V = camera.world_to_camera(mesh.vertices)
    z, tri, bary = cast_rays(V, mesh.faces, xy.reshape(-1, 2))
    hit = np.flatnonzero(tri >= 0)
    bg = background_rgb(background)
    color = np.empty((H * W, 3), dtype=np.float32)
    color[:] = bg.astype(np.float32)
    if hit.size and with_color:
        t = tri[hit]
        b = bary[hit]
        P = z[hit, None] * np.concatenate([xy.reshape(-1, 2)[hit], np.ones((hit.size, 1))], 1)
        N = mesh.normals() @ camera.R.T
        n = np.einsum("nk,nkd->nd", b, N[mesh.faces[t]])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        flip = np.einsum("nd,nd->n", n, P) > 0
        n[flip] *= -1
        uv = np.einsum("nk,nkd->nd", b, mesh.uvs[mesh.face_uvs[t]])
        # mip level from the texel footprint: texels per mm on this triangle x mm per pixel at depth z
        Vw = mesh.vertices
        f3 = mesh.faces
        area3 = 0.5 * np.linalg.norm(np.cross(Vw[f3[:, 1]] - Vw[f3[:, 0]], Vw[f3[:, 2]] - Vw[f3[:, 0]]), axis=1)
        tuv = mesh.uvs[mesh.face_uvs] * np.array([mesh.texture.shape[1], mesh.texture.shape[0]])
        e1, e2 = tuv[:, 1] - tuv[:, 0], tuv[:, 2] - tuv[:, 0]
        area_uv = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
        texels_per_mm = np.sqrt(area_uv / np.maximum(area3, 1e-12))
        mm_per_px = z[hit] / np.sqrt(camera.K[0, 0] * camera.K[1, 1])
        lod = np.log2(np.maximum(texels_per_mm[t] * mm_per_px, 1e-6))
        albedo = sample_texture(mesh.texture, uv, lod)
        if mesh.dot_centers is not None and mesh.dot_centers.shape[0]:
            C = camera.world_to_camera(mesh.dot_centers)
            r = mesh.dot_radii
            cover = np.zeros(hit.size)
            for c, rad in zip(C, r):
                dist = np.linalg.norm(P - c, axis=1)
                cover = np.maximum(cover, np.clip((rad - dist) / mm_per_px + 0.5, 0.0, 1.0))
            dot = np.asarray(np.broadcast_to(mesh.dot_albedo, (3,)), dtype=np.float32)
            albedo = albedo * (1 - cover[:, None]).astype(np.float32) + dot * cover[:, None].astype(np.float32)
        L = light_in_camera(camera, light_dir)
        shade = ambient + (1.0 - ambient) * np.maximum(n @ L, 0.0)
        color[hit] = albedo * shade[:, None].astype(np.float32)
    depth = z.astype(np.float32).reshape(H, W)
    return RenderResult(
        finish_color(color.reshape(H, W, 3), noise_sigma, camera, seed),
        depth,
        tri.astype(np.int32).reshape(H, W),
        bary.astype(np.float32).reshape(H, W, 3),
    )
