"""Synthetic multi-view scenes for the reconstruction tests and benchmark (embreex ray casting).

An independent, exact renderer: one ray per sub-pixel sample through OpenCV pixel centres (with the
camera's distortion), speckle texture looked up through the mesh UVs, Lambertian shading with a head
light. Used as ground truth for :mod:`rigbuild.reconstruct`; it does not depend on ``rigbuild.render``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from rigbuild.camera import Camera, look_at


@dataclass
class Scene:
    """vertices (V, 3) mm; faces (F, 3); uvs (T, 2); face_uvs (F, 3); texture (S, S) float32 in [0, 1]."""

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    face_uvs: np.ndarray
    texture: np.ndarray


def speckle_texture(size: int = 2048, seed: int = 0, blob_px: float = 1.6) -> np.ndarray:
    """(size, size) float32 speckle in [0.1, 0.9]: blurred white noise, contrast-stretched."""
    rng = np.random.default_rng(seed)
    noise = rng.random((size, size)).astype(np.float32)
    tex = cv2.GaussianBlur(noise, (0, 0), blob_px)
    tex = (tex - tex.mean()) / (tex.std() + 1e-9)
    return np.clip(0.5 + 0.16 * tex, 0.05, 0.95).astype(np.float32)


def uv_sphere(radius: float = 60.0, center=(0.0, 0.0, 0.0), n_lat: int = 96, n_lon: int = 192):
    """Triangulated UV sphere -> vertices (V, 3), faces (F, 3), uvs (V, 2) (face_uvs = faces)."""
    lat = np.linspace(0, np.pi, n_lat + 1)
    lon = np.linspace(0, 2 * np.pi, n_lon + 1)
    LA, LO = np.meshgrid(lat, lon, indexing="ij")
    v = np.stack([np.sin(LA) * np.cos(LO), np.cos(LA), np.sin(LA) * np.sin(LO)], -1).reshape(-1, 3)
    v = v * radius + np.asarray(center, dtype=np.float64)
    uv = np.stack([LO / (2 * np.pi), LA / np.pi], -1).reshape(-1, 2)
    idx = np.arange((n_lat + 1) * (n_lon + 1)).reshape(n_lat + 1, n_lon + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return v, f, uv


def camera_arc(n_cameras: int, width: int, height: int, focal_px: float, distance_mm: float,
               target=(0.0, 0.0, 0.0), yaw_span_deg: float = 120.0, rows: int = 1, pitch_deg=(-10.0, 10.0),
               dist=(0.0, 0.0, 0.0, 0.0, 0.0), facing=(0.0, 0.0, 1.0)) -> list[Camera]:
    """Cameras on a yaw arc of ``yaw_span_deg`` (first and last camera at its ends; with ``rows=2`` the
    second row at ``pitch_deg[1]`` is offset by half a step) at ``distance_mm`` looking at ``target``.

    ``facing`` is the world direction the subject faces (cameras sit on that side); world up is +y.
    """
    target = np.asarray(target, dtype=np.float64)
    per_row = int(np.ceil(n_cameras / rows))
    cams = []
    fwd = np.asarray(facing, float) / np.linalg.norm(facing)
    up = np.array([0.0, 1.0, 0.0])
    side = np.cross(up, fwd)
    for i in range(n_cameras):
        r, k = divmod(i, per_row)
        n_row = min(per_row, n_cameras - r * per_row)
        frac = (k + 0.5 * (r % 2)) / max(n_row - 1 + 0.5 * (rows - 1), 1)
        yaw = np.deg2rad(-yaw_span_deg / 2 + yaw_span_deg * frac)
        pitch = np.deg2rad(pitch_deg[r] if rows == 2 else 0.0)
        d = np.cos(pitch) * (np.cos(yaw) * fwd + np.sin(yaw) * side) + np.sin(pitch) * up
        R, t = look_at(target + distance_mm * d, target, up)
        K = np.array([[focal_px, 0, (width - 1) / 2 + 3.0], [0, focal_px, (height - 1) / 2 - 2.0], [0, 0, 1]])
        cams.append(Camera(f"cam{i:02d}", width, height, K, dist, R, t))
    return cams


def pixel_rays(camera: Camera, supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """World ray origins (N, 3) and unit directions (N, 3) for ``supersample``² samples per pixel.

    Sample order: row-major over the (H*s, W*s) sub-pixel grid, samples centred in each pixel.
    """
    s = supersample
    off = (np.arange(s) + 0.5) / s - 0.5
    u = (np.arange(camera.width)[:, None] + off[None, :]).reshape(-1)
    v = (np.arange(camera.height)[:, None] + off[None, :]).reshape(-1)
    U, V = np.meshgrid(u, v)
    uv = np.stack([U.ravel(), V.ravel()], 1)
    d = camera.rays(uv)
    o = np.broadcast_to(camera.center, d.shape)
    return o, d


def bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a 2-D array at float pixel coordinates (clamped to the border)."""
    H, W = img.shape
    x = np.clip(x, 0, W - 1.000001)
    y = np.clip(y, 0, H - 1.000001)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    return ((1 - fx) * (1 - fy) * img[y0, x0] + fx * (1 - fy) * img[y0, x0 + 1]
            + (1 - fx) * fy * img[y0 + 1, x0] + fx * fy * img[y0 + 1, x0 + 1])


def render(scene: Scene, camera: Camera, supersample: int = 2, ambient: float = 0.25,
           background: float = 0.02, noise_sigma: float = 0.0, seed: int = 0) -> dict:
    """Ray-cast one view. Returns dict: ``image`` (H, W) uint8, ``depth`` (H, W) float32 z-depth mm at
    pixel centres (0 = background, no supersampling), ``tri`` (H, W) int64 (-1 = background)."""
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    es = rtcs.EmbreeScene()
    TriangleMesh(es, scene.vertices[scene.faces].astype(np.float32))
    H, W, s = camera.height, camera.width, supersample
    o, d = pixel_rays(camera, s)
    res = es.run(o.astype(np.float32), d.astype(np.float32), output=1)
    prim = res["primID"].astype(np.int64)
    hit = prim >= 0
    b1, b2 = res["u"].astype(np.float64), res["v"].astype(np.float64)
    shade = np.full(prim.shape, background, dtype=np.float64)
    if hit.any():
        p = prim[hit]
        fu = scene.face_uvs[p]
        uv = (1 - b1[hit] - b2[hit])[:, None] * scene.uvs[fu[:, 0]] + b1[hit, None] * scene.uvs[fu[:, 1]] \
            + b2[hit, None] * scene.uvs[fu[:, 2]]
        S = scene.texture.shape[0]
        tex = bilinear(scene.texture, uv[:, 0] * (S - 1), (1 - uv[:, 1]) * (S - 1))
        tri = scene.vertices[scene.faces[p]]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
        lam = np.abs(np.sum(n * d[hit], axis=1))
        shade[hit] = tex * (ambient + (1 - ambient) * lam)
    img = shade.reshape(H, s, W, s).mean(axis=(1, 3))
    if noise_sigma > 0:
        img = img + np.random.default_rng(seed).normal(0, noise_sigma, img.shape)
    image = np.clip(np.round(img * 255), 0, 255).astype(np.uint8)
    # centre-sample depth / triangle ids
    o1, d1 = pixel_rays(camera, 1)
    r1 = es.run(o1.astype(np.float32), d1.astype(np.float32), output=1)
    p1 = r1["primID"].astype(np.int64)
    dcam = d1 @ camera.R.T
    depth = np.where(p1 >= 0, r1["tfar"] * dcam[:, 2], 0.0).astype(np.float32).reshape(H, W)
    return {"image": image, "depth": depth, "tri": p1.reshape(H, W)}


def ict_scene(ict_rig, weights=None, texture_size: int = 2048, seed: int = 0) -> Scene:
    """The ICT head (mm), optionally posed by blendshape ``weights``, with a speckle texture."""
    v = ict_rig.neutral if weights is None else ict_rig.evaluate(weights)
    return Scene(v, ict_rig.faces, ict_rig.uvs, ict_rig.face_uvs, speckle_texture(texture_size, seed))


def sphere_scene(radius: float = 60.0, center=(0.0, 0.0, 0.0), texture_size: int = 1024, seed: int = 0) -> Scene:
    v, f, uv = uv_sphere(radius, center)
    return Scene(v, f, uv, f, speckle_texture(texture_size, seed, blob_px=1.2))
