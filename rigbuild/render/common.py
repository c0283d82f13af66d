"""Pieces shared by the GL and embree renderers: the result type, per-pixel rays through distorted
OpenCV pixel centres (cached per camera), exact ray/triangle resolution, lighting and sensor noise.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigbuild.camera import Camera, distort_normalized

#: Default light direction (world, towards the light): frontal to an ICT-frame face (+z), from above.
DEFAULT_LIGHT_DIR = (0.0, 0.35, 1.0)


@dataclass
class RenderResult:
    """One rendered image and its exact per-pixel geometry (OpenCV pixel centres, distorted image).

    color : (H, W, 3) uint8 RGB.
    depth : (H, W) float32 camera-frame z of the visible surface, mm; NaN on background.
    tri_id : (H, W) int32 index of the visible triangle in ``mesh.faces``; -1 on background.
    bary : (H, W, 3) float32 barycentric coordinates of the visible point in that triangle (weights of
        ``faces[tri_id, 0..2]``); 0 on background.
    linear : (H, W, 3) float32 linear-light radiance before sensor noise and 8-bit conversion (only with
        ``output="linear"`` or ``"both"``; None otherwise). ``color`` is None with ``output="linear"``.
    motion_px : (H, W, 2) float32 image displacement (du, dv) of the visible surface point over the
        exposure, px (only with ``with_motion=True``); NaN on background.
    """

    color: np.ndarray | None
    depth: np.ndarray
    tri_id: np.ndarray
    bary: np.ndarray
    linear: np.ndarray | None = None
    motion_px: np.ndarray | None = None

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool, True where a triangle is visible."""
        return self.tri_id >= 0

    def points(self, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """(H, W, 3) world points reconstructed from ``tri_id``/``bary`` on a mesh (NaN on background)."""
        out = np.full(self.tri_id.shape + (3,), np.nan)
        m = self.mask
        tri = np.asarray(faces)[self.tri_id[m]]
        v = np.asarray(vertices, dtype=np.float64)
        b = self.bary[m].astype(np.float64)
        out[m] = np.einsum("nk,nkd->nd", b, v[tri])
        return out


# ------------------------------------------------------------------ rays through pixel centres
_UNDISTORT_CACHE: dict[tuple, np.ndarray] = {}
_UNDISTORT_CACHE_MAX = 32


def undistort_normalized(uv: np.ndarray, K: np.ndarray, dist: np.ndarray, iterations: int = 3) -> np.ndarray:
    """Distorted pixels (N, 2) -> normalized undistorted coordinates (N, 2), float64, polished by Newton.

    Starts from ``cv2.undistortPoints`` and takes ``iterations`` Gauss-Newton steps on the forward model
    :func:`rigbuild.camera.distort_normalized`, so that re-distorting is exact to about 1e-9 px.
    """
    import cv2

    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    K = np.asarray(K, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64)
    if not np.any(dist):
        y = (uv[:, 1] - K[1, 2]) / K[1, 1]
        x = (uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        return np.stack([x, y], 1)
    xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist,
                             criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-12)).reshape(-1, 2)
    # target distorted normalized coordinates
    yd = (uv[:, 1] - K[1, 2]) / K[1, 1]
    xd = (uv[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    x, y = xy[:, 0].copy(), xy[:, 1].copy()
    h = 1e-7
    for _ in range(iterations):
        fx, fy = distort_normalized(x, y, dist)
        rx, ry = fx - xd, fy - yd
        ax, ay = distort_normalized(x + h, y, dist)
        bx, by = distort_normalized(x, y + h, dist)
        j11, j21 = (ax - fx) / h, (ay - fy) / h
        j12, j22 = (bx - fx) / h, (by - fy) / h
        det = j11 * j22 - j12 * j21
        x -= (j22 * rx - j12 * ry) / det
        y -= (-j21 * rx + j11 * ry) / det
    return np.stack([x, y], 1)


def pixel_rays(camera: Camera) -> np.ndarray:
    """(H, W, 2) float64 normalized undistorted coordinates ``(x, y)`` of every pixel centre.

    The camera-frame ray of pixel ``(u, v)`` (column ``u``, row ``v``) is ``(x, y, 1)``: a point on it at
    camera depth ``z`` is ``z * (x, y, 1)``. Cached per intrinsics and size (read-only array).
    """
    key = (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes())
    xy = _UNDISTORT_CACHE.get(key)
    if xy is None:
        u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
        xy = undistort_normalized(np.stack([u.ravel(), v.ravel()], 1), camera.K, camera.dist)
        xy = xy.reshape(camera.height, camera.width, 2)
        xy.setflags(write=False)
        if len(_UNDISTORT_CACHE) >= _UNDISTORT_CACHE_MAX:
            _UNDISTORT_CACHE.pop(next(iter(_UNDISTORT_CACHE)))
        _UNDISTORT_CACHE[key] = xy
    return xy


# ------------------------------------------------------------------ exact ray/triangle resolution
def intersect_rays_triangles(xy: np.ndarray, tri_cam: np.ndarray, tri_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Intersect camera rays ``(x, y, 1)`` with triangles (Moller-Trumbore, float64).

    Parameters
    ----------
    xy : (N, 2) normalized ray coordinates.
    tri_cam : (F, 3, 3) camera-frame triangle corners, mm.
    tri_ids : (N,) triangle index per ray (>= 0).

    Returns
    -------
    z : (N,) camera depth of the hit on the triangle's plane (inf where parallel), mm.
    bary : (N, 3) barycentric coordinates (may be outside [0, 1] when the ray misses the triangle).
    """
    A = tri_cam[tri_ids, 0]
    e1 = tri_cam[tri_ids, 1] - A
    e2 = tri_cam[tri_ids, 2] - A
    d = np.empty_like(A)
    d[:, :2] = xy
    d[:, 2] = 1.0
    p = np.cross(d, e2)
    det = np.einsum("nd,nd->n", e1, p)
    s = -A
    q = np.cross(s, e1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        b1 = np.einsum("nd,nd->n", s, p) * inv
        b2 = np.einsum("nd,nd->n", d, q) * inv
        z = np.einsum("nd,nd->n", e2, q) * inv
    z = np.where(np.isfinite(z), z, np.inf)
    bary = np.stack([1.0 - b1 - b2, b1, b2], 1)
    bary[~np.isfinite(bary)] = -1.0
    return z, bary


_ADJ_CACHE: dict[int, tuple] = {}


def face_adjacency(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles sharing a vertex with each triangle, as CSR ``(ptr (F+1,), nbr)`` (includes itself).

    Cached per ``faces`` array object (treat it as immutable).
    """
    import weakref

    hit = _ADJ_CACHE.get(id(faces))
    if hit is not None and hit[0]() is faces:
        return hit[1], hit[2]
    f = np.asarray(faces, dtype=np.int64)
    F = f.shape[0]
    V = int(f.max()) + 1 if F else 0
    vert = f.reshape(-1)
    face_of = np.repeat(np.arange(F), 3)
    order = np.argsort(vert, kind="stable")
    vs, fs = vert[order], face_of[order]
    vptr = np.searchsorted(vs, np.arange(V + 1))
    deg = np.diff(vptr)
    # all (face, face') pairs meeting at a vertex
    rep = deg[vs]                                   # for every (vertex, face) entry, its vertex's degree
    a = np.repeat(fs, rep)
    start = np.repeat(vptr[vs], rep)
    offs = np.arange(rep.sum()) - np.repeat(np.cumsum(rep) - rep, rep)
    b = fs[start + offs]
    code = np.unique(a * F + b)
    a, b = code // F, code % F
    ptr = np.searchsorted(a, np.arange(F + 1))
    for k in [k for k, v in _ADJ_CACHE.items() if v[0]() is None]:
        del _ADJ_CACHE[k]
    try:
        _ADJ_CACHE[id(faces)] = (weakref.ref(faces), ptr, b)
    except TypeError:
        pass
    return ptr, b


def ring_search(
    pix: np.ndarray,
    cand: np.ndarray,
    rays: np.ndarray,
    tri_cam: np.ndarray,
    faces: np.ndarray,
    rings: int = 2,
    tol: float = 1e-7,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Find the visible triangle of pixels whose candidate triangles all miss their ray.

    Such a pixel lies next to rasterized surface but its ray hits a sliver no pinhole pixel centre hit
    (silhouettes, grazing angles): search the triangles sharing a vertex with the candidates, ring by
    ring, and keep the nearest hit.

    Parameters
    ----------
    pix : (n,) flat pixel indices; cand : (n, k) candidate triangle ids (-1 = none);
    rays : (H*W, 2) normalized ray coordinates; tri_cam : (F, 3, 3) camera-frame triangles, mm;
    faces : (F, 3) mesh triangles (for adjacency); rings : rings to search; tol : barycentric tolerance.

    Returns
    -------
    pix (m,), z (m,), tri (m,), bary (m, 3) for the pixels that were resolved.
    """
    out_p, out_z, out_t, out_b = [], [], [], []
    k = cand.shape[1]
    pix = np.repeat(np.asarray(pix, dtype=np.int64), k)
    tri = np.asarray(cand, dtype=np.int64).reshape(-1)
    keep = tri >= 0
    pix, tri = pix[keep], tri[keep]
    ptr, nbr = face_adjacency(faces)
    F = tri_cam.shape[0]
    for _ in range(rings):
        if not pix.size:
            break
        cnt = ptr[tri + 1] - ptr[tri]
        pix = np.repeat(pix, cnt)
        start = np.repeat(ptr[tri], cnt)
        offs = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        tri = nbr[start + offs]
        code = np.unique(pix * F + tri)
        pix, tri = code // F, code % F
        z, b = intersect_rays_triangles(rays[pix], tri_cam, tri)
        ok = (b.min(1) >= -tol) & (z > 0)
        if ok.any():
            zo, po, to, bo = z[ok], pix[ok], tri[ok], b[ok]
            order = np.lexsort((zo, po))
            first = order[np.r_[True, po[order][1:] != po[order][:-1]]]
            out_p.append(po[first]); out_z.append(zo[first]); out_t.append(to[first]); out_b.append(bo[first])
            done = np.isin(pix, po[first])
            pix, tri = pix[~done], tri[~done]
    if not out_p:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 3))
    return np.concatenate(out_p), np.concatenate(out_z), np.concatenate(out_t), np.concatenate(out_b)


def resolve_from_id_buffer(
    pin_ids: np.ndarray,
    map_x: np.ndarray,
    map_y: np.ndarray,
    xy: np.ndarray,
    tri_cam: np.ndarray,
    faces: np.ndarray | None = None,
    rings: int = 2,
    tol: float = 1e-7,
    disc_mm: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact depth/id/bary at distorted pixel centres from a rasterized pinhole id buffer.

    Each distorted pixel looks up the triangle ids at the 2x2 pinhole pixel centres around its pinhole
    position ``(map_x, map_y)``; where they agree the triangle is certain (a projected triangle is
    convex), elsewhere every candidate is intersected with the pixel's exact ray and the nearest valid
    hit wins. Where no candidate is hit, or the candidates' planes lie more than ``disc_mm`` apart along
    the ray (an occlusion boundary, where a nearer sub-pixel sliver may hide), the triangles around the
    candidates are searched too (:func:`ring_search`). No buffer value is ever interpolated.
    This is the numpy reference of the GLSL pass in :mod:`rigbuild.render.gl`.

    Parameters
    ----------
    pin_ids : (H', W') int32 pinhole triangle id + 1 (0 = background).
    map_x, map_y : (H, W) float pinhole pixel coordinates of each distorted pixel centre.
    xy : (H, W, 2) normalized ray coordinates of each distorted pixel centre.
    tri_cam : (F, 3, 3) camera-frame triangle corners, mm.
    faces : (F, 3) the mesh's triangles; enables the search of up to ``rings`` rings of neighbouring
        triangles (sharing a vertex) for pixels whose 2x2 candidates all miss (sub-pixel slivers).
    rings : neighbourhood rings searched for such pixels.
    tol : barycentric tolerance for accepting a hit on a triangle edge.
    disc_mm : candidate plane depths further apart than this (mm) mark an occlusion boundary.

    Returns
    -------
    depth (H, W) float32 (NaN background), tri_id (H, W) int32 (-1 background), bary (H, W, 3) float32.
    """
    H, W = map_x.shape
    Hp, Wp = pin_ids.shape
    i0 = np.clip(np.floor(map_x).astype(np.int64), 0, Wp - 2)
    j0 = np.clip(np.floor(map_y).astype(np.int64), 0, Hp - 2)
    ids4 = np.stack([pin_ids[j0, i0], pin_ids[j0, i0 + 1], pin_ids[j0 + 1, i0], pin_ids[j0 + 1, i0 + 1]], -1)
    ids4 = ids4.reshape(-1, 4).astype(np.int64) - 1
    rays = xy.reshape(-1, 2)
    n = H * W
    best_z = np.full(n, np.inf)
    best_id = np.full(n, -1, dtype=np.int64)
    best_b = np.zeros((n, 3))

    uniform = (ids4 == ids4[:, :1]).all(1)
    sure = np.flatnonzero(uniform & (ids4[:, 0] >= 0))
    if sure.size:
        z, b = intersect_rays_triangles(rays[sure], tri_cam, ids4[sure, 0])
        best_z[sure], best_id[sure], best_b[sure] = z, ids4[sure, 0], b
    mixed = np.flatnonzero(~uniform)
    plane_min = np.full(n, np.inf)
    plane_max = np.full(n, -np.inf)
    for k in range(4):
        sel = mixed[ids4[mixed, k] >= 0]
        if not sel.size:
            continue
        z, b = intersect_rays_triangles(rays[sel], tri_cam, ids4[sel, k])
        plane_min[sel] = np.minimum(plane_min[sel], z)
        plane_max[sel] = np.maximum(plane_max[sel], z)
        ok = (b.min(1) >= -tol) & (z > 0) & (z < best_z[sel])
        sel = sel[ok]
        best_z[sel], best_id[sel], best_b[sel] = z[ok], ids4[sel, k], b[ok]
    if faces is not None and rings > 0:
        # no valid candidate, or an occlusion boundary where a nearer sliver may hide
        todo = mixed[(best_id[mixed] < 0) | (plane_max[mixed] - plane_min[mixed] > disc_mm)]
        pix, z, tri, b = ring_search(todo, ids4[todo], rays, tri_cam, faces, rings, tol)
        better = (best_id[pix] < 0) | (z < best_z[pix])
        pix, z, tri, b = pix[better], z[better], tri[better], b[better]
        best_z[pix], best_id[pix], best_b[pix] = z, tri, b
    hit = best_id >= 0
    depth = np.where(hit, best_z, np.nan).astype(np.float32).reshape(H, W)
    return depth, best_id.astype(np.int32).reshape(H, W), best_b.astype(np.float32).reshape(H, W, 3)


# ------------------------------------------------------------------ shading helpers
#: Candidate dots kept per triangle by :func:`dot_candidates` (the GL shader's ivec4).
DOT_CANDIDATES = 4


def dot_candidates(tri: np.ndarray, centres: np.ndarray, radii: np.ndarray, margin_mm: float,
                   k: int = DOT_CANDIDATES) -> np.ndarray:
    """(F, k) int32: per triangle, every dot whose disc may reach within ``margin_mm`` of it, ascending.

    tri : (F, 3, 3) triangle corners, mm; centres : (M, 3) dot centres, mm (same frame); radii : (M,) mm.
    A dot is kept when ``|c - centroid| - R < r + margin_mm`` (``R`` the triangle's largest centroid-to-corner
    distance), a superset of the dots within ``r + margin_mm`` of the triangle. Unused slots are -1; a
    triangle with more than ``k`` candidates gets ``[-2, -1, ...]`` (try every dot).
    """
    from scipy.spatial import cKDTree

    tri = np.asarray(tri, dtype=np.float64)
    F = tri.shape[0]
    out = np.full((F, k), -1, dtype=np.int32)
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    if F == 0 or centres.shape[0] == 0:
        return out
    radii = np.broadcast_to(np.asarray(radii, dtype=np.float64), (centres.shape[0],))
    g = tri.mean(axis=1)
    R = np.linalg.norm(tri - g[:, None], axis=2).max(axis=1)
    reach = radii + margin_mm
    pairs = cKDTree(g).query_ball_point(centres, reach + R.max())  # per dot: faces possibly in reach
    dot = np.repeat(np.arange(centres.shape[0]), [len(q) for q in pairs])
    face = np.fromiter((f for q in pairs for f in q), dtype=np.int64, count=dot.size)
    keep = np.linalg.norm(centres[dot] - g[face], axis=1) - R[face] < reach[dot]
    dot, face = dot[keep], face[keep]
    order = np.lexsort((dot, face))
    dot, face = dot[order], face[order]
    start = np.searchsorted(face, np.arange(F))
    rank = np.arange(face.size) - start[face]
    fits = rank < k
    out[face[fits], rank[fits]] = dot[fits]
    counts = np.bincount(face, minlength=F)
    out[counts > k] = -1
    out[counts > k, 0] = -2
    return out


def light_in_camera(camera: Camera, light_dir) -> np.ndarray:
    """(3,) unit direction towards the light in the camera frame (``light_dir`` is world; None = default)."""
    l = np.asarray(DEFAULT_LIGHT_DIR if light_dir is None else light_dir, dtype=np.float64).reshape(3)
    n = np.linalg.norm(l)
    if not n > 0:
        raise ValueError("light_dir must be a non-zero 3-vector")
    return camera.R @ (l / n)


def background_rgb(background) -> np.ndarray:
    """(3,) float background colour from a scalar grey level or an RGB triple (0..255)."""
    return np.broadcast_to(np.asarray(background, dtype=np.float64), (3,)).astype(np.float64)


def noise_rng(camera: Camera, seed) -> np.random.Generator:
    """Generator for sensor noise: ``seed`` if given, else a fixed seed derived from the camera id."""
    if seed is None:
        seed = zlib.crc32(camera.id.encode("utf-8"))
    return np.random.default_rng(seed)


def finish_color(linear_rgb: np.ndarray, noise_sigma: float, camera: Camera, seed) -> np.ndarray:
    """Add Gaussian sensor noise (sigma in 8-bit levels) to a float (H, W, 3) 0..255 image; round to uint8."""
    img = np.asarray(linear_rgb, dtype=np.float32)
    if noise_sigma and noise_sigma > 0:
        rng = noise_rng(camera, seed)
        img = img + rng.standard_normal(img.shape, dtype=np.float32) * np.float32(noise_sigma)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------ linear light, lights, shadows
def srgb_to_linear(x):
    """sRGB-encoded values in [0, 1] -> linear light (IEC 61966-2-1); float32 in, float32 out."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.04045, x / np.float32(12.92),
                    ((x + np.float32(0.055)) / np.float32(1.055)) ** np.float32(2.4)).astype(np.float32)


def linear_to_srgb(x):
    """Linear light (clipped to [0, 1]) -> sRGB-encoded values in [0, 1], float32."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, x * np.float32(12.92),
                    np.float32(1.055) * x ** np.float32(1 / 2.4) - np.float32(0.055)).astype(np.float32)


def lights_in_camera(camera: Camera, lights) -> list[dict]:
    """Camera-frame description of each light.

    Returns a list of dicts: ``kind`` (0 ambient, 1 directional, 2 point), ``vec`` (3,) unit direction
    towards the light or position (mm), ``rad`` (3,) linear irradiance, ``ref2`` squared reference
    distance (mm^2, point lights), ``shadows``, ``softness`` (mm).
    """
    out = []
    for L in lights:
        if L.kind == "ambient":
            vec, kind = np.zeros(3), 0
        elif L.kind == "directional":
            d = np.asarray(L.direction, dtype=np.float64)
            d = d / np.linalg.norm(d)
            vec, kind = (d if L.rig_mounted else camera.R @ d), 1
        else:
            p = np.asarray(L.position, dtype=np.float64)
            vec, kind = (p if L.rig_mounted else camera.R @ p + camera.t), 2
        out.append(dict(kind=kind, vec=vec, rad=L.radiance, ref2=float(L.reference_mm) ** 2,
                        shadows=bool(L.shadows) and kind > 0, softness=float(L.softness_mm)))
    return out


@dataclass
class ShadowFrame:
    """Projection of a shadow map (camera frame -> texel coordinates, texel centres at integers).

    ``q = R @ p + t`` (light frame, z along the light's rays, mm); texel ``u = a * q_x / w + cu``,
    ``v = a * q_y / w + cv`` with ``w = q_z`` (perspective) or 1 (orthographic); the map stores ``q_z``.
    ``near``/``far``: the light-frame z range of the mesh (mm). ``size``: texels per side.
    """

    R: np.ndarray
    t: np.ndarray
    a: float
    cu: float
    cv: float
    perspective: bool
    near: float
    far: float
    size: int

    def texel_mm(self, qz):
        """Texel footprint on a receiver at light depth ``qz`` (mm)."""
        return qz / self.a if self.perspective else np.full_like(np.asarray(qz, dtype=np.float64), 1.0 / self.a)


def shadow_frame(light: dict, verts_cam: np.ndarray, size: int, margin: int = 4) -> ShadowFrame:
    """Shadow-map frame of one camera-frame light (from :func:`lights_in_camera`) covering ``verts_cam``."""
    if light["kind"] == 1:
        z = -light["vec"]
    else:
        centre = 0.5 * (verts_cam.min(0) + verts_cam.max(0))
        z = centre - light["vec"]
        z = z / np.linalg.norm(z)
    helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    half = (size - 1) / 2.0
    if light["kind"] == 1:
        t = np.zeros(3)
        q = verts_cam @ R.T
        lo, hi = q[:, :2].min(0), q[:, :2].max(0)
        ext = float(max(hi - lo)) * 0.5 + 1e-6
        a = (half - margin) / ext
        mid = 0.5 * (lo + hi)
        cu, cv = half - a * mid[0], half - a * mid[1]
        near, far = float(q[:, 2].min()), float(q[:, 2].max())
        return ShadowFrame(R, t, float(a), float(cu), float(cv), False, near, far, size)
    t = -R @ light["vec"]
    q = verts_cam @ R.T + t
    if q[:, 2].min() <= 1e-3:
        raise ValueError("point light inside or behind the mesh's extent: cannot build its shadow map")
    tan = float(np.abs(q[:, :2] / q[:, 2:3]).max()) + 1e-9
    a = (half - margin) / tan
    return ShadowFrame(R, t, float(a), half, half, True, float(q[:, 2].min()), float(q[:, 2].max()), size)


def vogel_taps(n: int = 16) -> np.ndarray:
    """(n, 2) float32 unit-disk sample offsets (Vogel spiral), area-uniform."""
    k = np.arange(n, dtype=np.float64)
    r = np.sqrt((k + 0.5) / n)
    ang = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(ang), r * np.sin(ang)], 1).astype(np.float32)


SHADOW_BIAS_CONST = 1.0
SHADOW_BIAS_SLOPE = 1.5


def shadow_visibility(smap: np.ndarray, frame: ShadowFrame, P: np.ndarray, n: np.ndarray, l: np.ndarray,
                      softness_mm: float, taps: int = 16) -> np.ndarray:
    """Visibility (N,) in [0, 1] of camera-frame points ``P`` (N, 3) with normals ``n`` towards unit
    light directions ``l`` (N, 3), by bilinear PCF on ``smap`` ((S, S) float32 light depth, inf empty).

    The numpy twin of the GLSL lookup in :mod:`rigbuild.render.gl`.
    """
    q = P @ frame.R.T + frame.t
    w = q[:, 2] if frame.perspective else 1.0
    u = frame.a * q[:, 0] / w + frame.cu
    v = frame.a * q[:, 1] / w + frame.cv
    tmm = frame.texel_mm(q[:, 2])
    cos = np.clip(np.einsum("nd,nd->n", n, l), 1e-4, 1.0)
    tan = np.minimum(np.sqrt(1.0 - cos ** 2) / cos, 10.0)
    r_tex = softness_mm / tmm
    bias = tmm * (SHADOW_BIAS_CONST + (SHADOW_BIAS_SLOPE + r_tex) * tan)
    ref = q[:, 2] - bias
    S = smap.shape[0]
    offs = vogel_taps(taps) if softness_mm > 0 else np.zeros((1, 2), np.float32)
    vis = np.zeros(P.shape[0])
    for o in offs:
        uu = u + o[0] * r_tex
        vv = v + o[1] * r_tex
        i0 = np.floor(uu)
        j0 = np.floor(vv)
        fx, fy = uu - i0, vv - j0
        i0 = i0.astype(np.int64)
        j0 = j0.astype(np.int64)
        acc = np.zeros(P.shape[0])
        for di, dj, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
            ii, jj = i0 + di, j0 + dj
            inside = (ii >= 0) & (ii < S) & (jj >= 0) & (jj < S)
            d = np.full(P.shape[0], np.inf)
            d[inside] = smap[jj[inside], ii[inside]]
            acc += wgt * (ref <= d)
        vis += acc
    return vis / len(offs)


def ggx_shade(albedo: np.ndarray, n: np.ndarray, P: np.ndarray, f0: np.ndarray, rough: np.ndarray,
              lights: list[dict], visibility: list) -> np.ndarray:
    """Linear radiance (N, 3) of camera-frame points (the model in :mod:`rigbuild.render.lights`).

    albedo : (N, 3) linear albedo; n : (N, 3) unit normals facing the camera; P : (N, 3) points, mm;
    f0, rough : (N,) F0 and perceptual roughness; lights : from :func:`lights_in_camera`;
    visibility : per light, (N,) shadow visibility or None (fully lit).
    """
    v = -P / np.maximum(np.linalg.norm(P, axis=1, keepdims=True), 1e-12)
    nv = np.clip(np.einsum("nd,nd->n", n, v), 1e-4, 1.0)
    a = np.maximum(rough, 0.02) ** 2
    a2 = a * a
    out = np.zeros_like(albedo, dtype=np.float64)
    for L, vis in zip(lights, visibility):
        if L["kind"] == 0:
            out += albedo * L["rad"]
            continue
        if L["kind"] == 1:
            l = np.broadcast_to(L["vec"], P.shape)
            E = np.broadcast_to(L["rad"], P.shape)
        else:
            d = L["vec"] - P
            dist2 = np.einsum("nd,nd->n", d, d)
            l = d / np.sqrt(dist2)[:, None]
            E = L["rad"][None, :] * (L["ref2"] / dist2)[:, None]
        nl = np.einsum("nd,nd->n", n, l)
        lit = nl > 0
        nl = np.maximum(nl, 0.0)
        h = l + v
        h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
        nh = np.clip(np.einsum("nd,nd->n", n, h), 0.0, 1.0)
        vh = np.clip(np.einsum("nd,nd->n", v, h), 0.0, 1.0)
        D = a2 / (np.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
        nlc = np.maximum(nl, 1e-4)
        Vis = 0.5 / (nlc * np.sqrt(nv * nv * (1.0 - a2) + a2) + nv * np.sqrt(nlc * nlc * (1.0 - a2) + a2))
        F = f0 + (1.0 - f0) * (1.0 - vh) ** 5
        spec = np.pi * D * Vis * F
        w = nl * (1.0 if vis is None else vis) * lit
        out += E * w[:, None] * ((1.0 - F)[:, None] * albedo + spec[:, None])
    return out.astype(np.float32)


def motion_image(camera: Camera, vertices: np.ndarray, faces: np.ndarray, motion: np.ndarray | None,
                 tri_id: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """(H, W, 2) float32 image displacement of the visible points over the exposure, px.

    ``project(X + dX) - project(X)`` with ``X`` the visible world point (from ``tri_id``/``bary``) and
    ``dX`` the barycentric interpolation of the per-vertex world motion ``motion`` (V, 3) mm (None: no
    motion, zeros on the surface). NaN on background.
    """
    H, W = tri_id.shape
    out = np.full((H, W, 2), np.nan, dtype=np.float32)
    m = tri_id >= 0
    if not m.any():
        return out
    tri = np.asarray(faces)[tri_id[m]]
    b = bary[m].astype(np.float64)
    if motion is None:
        out[m] = 0.0
        return out
    X = np.einsum("nk,nkd->nd", b, np.asarray(vertices, dtype=np.float64)[tri])
    dX = np.einsum("nk,nkd->nd", b, np.asarray(motion, dtype=np.float64)[tri])
    out[m] = (camera.project(X + dX) - camera.project(X)).astype(np.float32)
    return out


def finish_outputs(res: RenderResult, img: np.ndarray, lights, output: str, noise_sigma: float, camera: Camera,
                    seed, with_motion: bool, mesh) -> RenderResult:
    """Fill ``color`` / ``linear`` / ``motion_px`` of ``res`` from the float image ``img`` (8-bit levels
    on the legacy path, linear radiance with ``lights``)."""
    if output not in ("srgb8", "linear", "both"):
        raise ValueError(f"render output must be 'srgb8', 'linear' or 'both', got {output!r}")
    if lights is None:
        if output != "srgb8":
            res.linear = srgb_to_linear(np.clip(np.asarray(img, np.float32) / np.float32(255.0), 0.0, 1.0))
    else:
        lin = np.asarray(img, dtype=np.float32)
        if output != "linear":
            res.color = finish_color(linear_to_srgb(lin) * np.float32(255.0), noise_sigma, camera, seed)
        if output != "srgb8":
            res.linear = lin
    if output == "linear":
        res.color = None
    if with_motion:
        res.motion_px = motion_image(camera, mesh.vertices, mesh.faces, mesh.vertex_motion, res.tri_id, res.bary)
    return res


@dataclass(frozen=True)
class RenderOptions:
    """How :func:`rigbuild.render.render_mesh` shades and what it returns (one set of options for both
    backends; each field is documented there): light_dir (3,) or None, ambient, background, noise_sigma
    (8-bit levels), seed, msaa, with_color, with_geometry, lights, material, output, with_motion."""

    light_dir: Any = None
    ambient: float = 0.3
    background: Any = 128
    noise_sigma: float = 0.0
    seed: Any = None
    msaa: bool = True
    with_color: bool = True
    with_geometry: bool = True
    lights: Any = None
    material: Any = None
    output: str = "srgb8"
    with_motion: bool = False


def empty_result(camera: Camera, mesh, opt: RenderOptions) -> RenderResult:
    """What a render of a mesh without triangles returns: the background everywhere (colour through the same
    noise and output conversion as a real render), NaN depth, tri_id -1, zero barycentrics."""
    H, W = camera.height, camera.width
    img = np.broadcast_to(background_rgb(opt.background).astype(np.float32), (H, W, 3))
    res = RenderResult(finish_color(img, opt.noise_sigma, camera, opt.seed), np.full((H, W), np.nan, np.float32),
                       np.full((H, W), -1, np.int32), np.zeros((H, W, 3), np.float32))
    if opt.lights is not None:
        img = srgb_to_linear(img / np.float32(255.0))
    return finish_outputs(res, img, opt.lights, opt.output, opt.noise_sigma, camera, opt.seed, opt.with_motion, mesh)
