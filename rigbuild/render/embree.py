"""Ray-casting renderer with embreex: one primary ray per distorted OpenCV pixel centre.

The independent oracle for the GL renderer in tests and the fallback where EGL is absent. Rays are the
camera's (:meth:`rigbuild.camera.Camera.rays` model: undistorted pixel centres), cast in the camera frame
from the origin with direction ``(x, y, 1)`` so that the hit distance is the camera depth ``z``. Colour:
the same Lambert model as the GL shader (with ``lights``: the same linear GGX + Lambert model and shadow
maps, here built by ray casting from each light; see :mod:`rigbuild.render.lights`); texture lookups are trilinear over a mip pyramid with the level
chosen from the pixel's texel footprint (isotropic, no anisotropy and no anti-aliasing, 1 sample/pixel).
"""

from __future__ import annotations

import numpy as np

from rigbuild.camera import Camera
from rigbuild.render.common import (
    RenderOptions,
    RenderResult,
    background_rgb,
    empty_result,
    finish_color,
    finish_outputs,
    ggx_shade,
    light_in_camera,
    lights_in_camera,
    pixel_rays,
    shadow_frame,
    shadow_visibility,
    srgb_to_linear,
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


def render_mesh(camera: Camera, mesh: TexturedMesh, opt: RenderOptions) -> RenderResult:
    """Render ``mesh`` seen by ``camera`` by ray casting (same options and model as the GL renderer).

    ``opt.msaa`` is ignored (1 sample per pixel); ``opt.with_color=False`` skips shading (``color`` is the plain
    background). Shadows come from shadow maps built by ray casting from each shadowing light (the same maps
    and lookup as the GL shader).
    """
    if mesh.faces.shape[0] == 0:
        return empty_result(camera, mesh, opt)
    light_dir, ambient, background = opt.light_dir, opt.ambient, opt.background
    noise_sigma, seed = opt.noise_sigma, opt.seed
    with_color, with_geometry, lights, material = opt.with_color, opt.with_geometry, opt.lights, opt.material
    output, with_motion = opt.output, opt.with_motion
    xy = pixel_rays(camera)
    H, W = camera.height, camera.width
    V = camera.world_to_camera(mesh.vertices)
    z, tri, bary = cast_rays(V, mesh.faces, xy.reshape(-1, 2))
    hit = np.flatnonzero(tri >= 0)
    bg = background_rgb(background)
    color = np.empty((H * W, 3), dtype=np.float32)
    color[:] = bg.astype(np.float32)
    if lights is not None:
        color[:] = srgb_to_linear(bg / 255.0)
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
        cover = None
        if mesh.dot_centers is not None and mesh.dot_centers.shape[0]:
            C = camera.world_to_camera(mesh.dot_centers)
            r = mesh.dot_radii
            cover = np.zeros(hit.size)
            which = np.zeros(hit.size, dtype=np.int64)
            for i, (c, rad) in enumerate(zip(C, r)):
                dist = np.linalg.norm(P - c, axis=1)
                ci = np.clip((rad - dist) / mm_per_px + 0.5, 0.0, 1.0)
                which[ci > cover] = i
                cover = np.maximum(cover, ci)
            if mesh.per_dot_albedo:
                dot = mesh.dot_colors()[which]
            else:
                dot = np.asarray(np.broadcast_to(mesh.dot_albedo, (3,)), dtype=np.float32)
            albedo = albedo * (1 - cover[:, None]).astype(np.float32) + dot * cover[:, None].astype(np.float32)
        if lights is None:
            L = light_in_camera(camera, light_dir)
            shade = ambient + (1.0 - ambient) * np.maximum(n @ L, 0.0)
            color[hit] = albedo * shade[:, None].astype(np.float32)
        else:
            color[hit] = _shade_lit(camera, mesh, V, lights, material, albedo, n, P, t, b, uv, lod, cover)
    depth = z.astype(np.float32).reshape(H, W)
    res = RenderResult(
        None if lights is not None else finish_color(color.reshape(H, W, 3), noise_sigma, camera, seed),
        depth,
        tri.astype(np.int32).reshape(H, W),
        bary.astype(np.float32).reshape(H, W, 3),
    )
    return finish_outputs(res, color.reshape(H, W, 3), lights, output, noise_sigma, camera, seed, with_motion, mesh)


def shadow_map_rays(frame, verts_cam: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(S, S) float32 light-frame depth at the texel centres of ``frame`` by ray casting (inf = empty)."""
    S = frame.size
    j, i = np.mgrid[0:S, 0:S].astype(np.float64)
    x = ((i - frame.cu) / frame.a).reshape(-1)
    y = ((j - frame.cv) / frame.a).reshape(-1)
    R = frame.R                     # light = R @ camera + t; rows: camera = light @ R (t = 0 for ortho)
    if frame.perspective:
        d_l = np.stack([x, y, np.ones_like(x)], 1)
        org = np.broadcast_to(-R.T @ frame.t, d_l.shape)
    else:
        z0 = frame.near - 10.0
        d_l = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (x.size, 3))
        org = np.stack([x, y, np.full_like(x, z0)], 1) @ R
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(verts_cam, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.int32))
    res = scene.run(np.ascontiguousarray(org, dtype=np.float32), np.ascontiguousarray(d_l @ R, dtype=np.float32),
                    output=1)
    hit = np.asarray(res["geomID"]) >= 0
    t = np.asarray(res["tfar"], dtype=np.float64)
    depth = np.where(hit, t if frame.perspective else t + z0, np.inf)
    return depth.astype(np.float32).reshape(S, S)


def _shade_lit(camera, mesh, V, lights, material, albedo8, n, P, t, b, uv, lod, cover) -> np.ndarray:
    """Linear radiance (N, 3) of the hit points with the GGX + shadow-map model of :mod:`rigbuild.render.lights`."""
    from rigbuild.render.lights import SHADOW_MAP_SIZE, Material

    mat = material if material is not None else Material()
    rho = srgb_to_linear(np.clip(albedo8 / np.float32(255.0), 0.0, 1.0))
    fr = np.einsum("nk,nkd->nd", b, mat.vertex_values(mesh.vertices.shape[0])[mesh.faces[t]].astype(np.float64))
    packed = mat.packed_map(mesh.texture.shape[:2])
    if packed is not None:
        s = sample_texture(packed, uv, lod)
        use_s, use_r = mat.has_maps
        if use_s:
            fr[:, 0] = s[:, 0]
        if use_r:
            fr[:, 1] = s[:, 1]
    if cover is not None:
        if mat.dot_specular is not None:
            fr[:, 0] = fr[:, 0] * (1 - cover) + mat.dot_specular * cover
        if mat.dot_roughness is not None:
            fr[:, 1] = fr[:, 1] * (1 - cover) + mat.dot_roughness * cover
    Ls = lights_in_camera(camera, lights)
    vis = []
    for L in Ls:
        if not L["shadows"]:
            vis.append(None)
            continue
        frame = shadow_frame(L, V, SHADOW_MAP_SIZE)
        smap = shadow_map_rays(frame, V, mesh.faces)
        if L["kind"] == 1:
            l = np.broadcast_to(L["vec"], P.shape)
        else:
            d = L["vec"] - P
            l = d / np.linalg.norm(d, axis=1, keepdims=True)
        vis.append(shadow_visibility(smap, frame, P, n, l, L["softness"]))
    return ggx_shade(rho.astype(np.float64), n, P, fr[:, 0], fr[:, 1], Ls, vis)
