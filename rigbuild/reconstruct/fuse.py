"""Oriented point cloud and surface from filtered depth maps (mm, world coordinates).

* :func:`depth_normals` - per-pixel world normals of a depth map, facing its camera.
* :func:`voxel_average` - merge the per-view fused points (mean position, normal and colour per voxel).
* :func:`tsdf_mesh` - open3d ``UniformTSDFVolume`` (open surface of what the cameras see).
* :func:`poisson_mesh` - open3d screened Poisson (closed surface).
* :func:`crop_mesh` - keep the mesh near the fused points (cropped to the head / object).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from rigbuild.camera import Camera
from rigbuild.reconstruct.filter import backproject_pixels


def pixel_normals(points: np.ndarray, camera: Camera, v: np.ndarray, u: np.ndarray,
                  max_step_px: float = 20.0) -> np.ndarray:
    """(N, 3) unit world normals at pixels ``(v, u)`` (N,) of a point map, facing ``camera``.

    points : (H, W, 3) float32 world points of a depth map (NaN = none, see ``filter.point_map``). The
    normal is the cross product of the central differences along u and v; pixels at the border, next to
    a missing pixel or across a discontinuity (a step over ``max_step_px`` pixel footprints) get 0.
    """
    import cv2

    H, W, _ = points.shape
    pm = np.ascontiguousarray(points, dtype=np.float32)
    kx = np.array([[-1.0, 0.0, 1.0]], np.float32)
    du = cv2.filter2D(pm, -1, kx, borderType=cv2.BORDER_CONSTANT)[v, u].astype(np.float64)
    dv = cv2.filter2D(pm, -1, kx.T, borderType=cv2.BORDER_CONSTANT)[v, u].astype(np.float64)
    Xc = pm[v, u].astype(np.float64)
    inner = (u >= 1) & (u <= W - 2) & (v >= 1) & (v <= H - 2)
    step = np.linalg.norm(Xc - camera.center, axis=1) / camera.K[0, 0]
    with np.errstate(invalid="ignore"):
        ok = inner & (np.linalg.norm(du, axis=1) < max_step_px * step) & \
            (np.linalg.norm(dv, axis=1) < max_step_px * step)
    c = normalize_rows(np.cross(np.nan_to_num(du), np.nan_to_num(dv)))
    flip = np.sum(c * (camera.center - Xc), axis=1) < 0
    c[flip] *= -1
    c[~ok] = 0
    return c


def depth_normals(depth: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W, 3) unit world normals from central differences of the back-projected depth map.

    Normals face the camera; pixels without depth or without both neighbours in u and v get (0, 0, 0).
    """
    H, W = depth.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    X = backproject_pixels(camera, u, v, depth.astype(np.float64))
    valid = depth > 0
    n = np.zeros((H, W, 3))
    du = X[1:-1, 2:] - X[1:-1, :-2]
    dv = X[2:, 1:-1] - X[:-2, 1:-1]
    ok = valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1] & valid[1:-1, 1:-1]
    c = np.cross(du, dv)
    # reject normals across discontinuities (steps much larger than a pixel footprint)
    z = depth[1:-1, 1:-1].astype(np.float64)
    step = z / camera.K[0, 0]
    ok &= (np.linalg.norm(du, axis=-1) < 20 * step) & (np.linalg.norm(dv, axis=-1) < 20 * step)
    norm = np.linalg.norm(c, axis=-1, keepdims=True)
    c = np.where(norm > 0, c / np.where(norm > 0, norm, 1), 0)
    to_cam = camera.center - X[1:-1, 1:-1]
    flip = np.sum(c * to_cam, axis=-1) < 0
    c[flip] *= -1
    n[1:-1, 1:-1] = np.where(ok[..., None], c, 0)
    return n


def voxel_average(points: np.ndarray, voxel_mm: float, *attrs: np.ndarray) -> tuple[np.ndarray, ...]:
    """Average ``points`` (N, 3) and per-point attributes (N, k) within cubic voxels of side ``voxel_mm``.

    Returns (M, 3) points followed by the (M, k) averaged attributes (voxel order is arbitrary but
    deterministic). ``voxel_mm <= 0`` returns the inputs unchanged.
    """
    if voxel_mm <= 0 or len(points) == 0:
        return (points, *attrs)
    key = np.floor(points / voxel_mm).astype(np.int64)
    key -= key.min(axis=0)
    dims = key.max(axis=0) + 1
    lin = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
    uniq, inv, cnt = np.unique(lin, return_inverse=True, return_counts=True)
    out = []
    for a in (points, *attrs):
        a2 = a.reshape(len(a), -1).astype(np.float64)
        s = np.zeros((len(uniq), a2.shape[1]))
        for k in range(a2.shape[1]):
            s[:, k] = np.bincount(inv, weights=a2[:, k], minlength=len(uniq))
        out.append(s / cnt[:, None])
    return tuple(out)


def normalize_rows(n: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length (zero rows stay zero)."""
    L = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(L > 0, n / np.where(L > 0, L, 1), 0)


def robust_bbox(points: np.ndarray, quantile: float = 0.001, margin_mm: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """(min (3,), max (3,)) of the points between the ``quantile`` and ``1 - quantile`` per axis, plus margin."""
    sub = points[:: max(1, len(points) // 200000)]
    lo = np.quantile(sub, quantile, axis=0) - margin_mm
    hi = np.quantile(sub, 1 - quantile, axis=0) + margin_mm
    return lo, hi


def tsdf_mesh(depths: Sequence[np.ndarray], cameras: Sequence[Camera], bbox: tuple[np.ndarray, np.ndarray],
              voxel_mm: float = 1.0, trunc_voxels: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """Integrate depth maps into a uniform TSDF over the cube enclosing ``bbox``; marching cubes.

    depths : per view (H, W) float32 mm on the pinhole grid of ``cameras`` (0 = none).
    Returns vertices (V, 3) mm and triangles (F, 3).
    """
    import open3d as o3d

    lo, hi = np.asarray(bbox[0], float), np.asarray(bbox[1], float)
    length = float(np.max(hi - lo))
    res = int(np.ceil(length / voxel_mm))
    length = res * voxel_mm
    origin = (lo + hi) / 2 - length / 2
    vol = o3d.pipelines.integration.UniformTSDFVolume(
        length=length, resolution=res, sdf_trunc=trunc_voxels * voxel_mm,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.NoColor, origin=origin.reshape(3, 1))
    for depth, cam in zip(depths, cameras):
        if not np.any(depth > 0):
            continue
        H, W = depth.shape
        color = o3d.geometry.Image(np.zeros((H, W, 3), np.uint8))
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            color, o3d.geometry.Image(np.ascontiguousarray(depth, dtype=np.float32)), depth_scale=1.0,
            depth_trunc=float(depth.max()) + 1.0, convert_rgb_to_intensity=False)
        intr = o3d.camera.PinholeCameraIntrinsic(W, H, cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2])
        ext = np.eye(4)
        ext[:3, :3], ext[:3, 3] = cam.R, cam.t
        vol.integrate(rgbd, intr, ext)
    mesh = vol.extract_triangle_mesh()
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)


def poisson_mesh(points: np.ndarray, normals: np.ndarray, depth: int = 9, density_quantile: float = 0.0,
                 scale: float = 1.1) -> tuple[np.ndarray, np.ndarray]:
    """Screened Poisson surface of an oriented cloud (open3d). Closed unless trimmed.

    ``density_quantile > 0`` removes vertices whose Poisson density is below that quantile (opens the
    surface where there was no data). Returns vertices (V, 3) and triangles (F, 3). Runs on one thread:
    open3d's default (every hardware thread) gives different vertices on every call (:mod:`rigbuild.determinism`).
    """
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pc, depth=depth, scale=scale,
                                                                            linear_fit=False, n_threads=1)
    if density_quantile > 0:
        dens = np.asarray(dens)
        mesh.remove_vertices_by_mask(dens < np.quantile(dens, density_quantile))
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)


def crop_mesh(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, max_dist_mm: float,
              min_component_fraction: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Drop triangles with a vertex farther than ``max_dist_mm`` from every point, then connected
    components with fewer than ``min_component_fraction`` of the remaining triangles; reindex."""
    from scipy.spatial import cKDTree

    if len(faces) == 0:
        return vertices, faces
    d, _ = cKDTree(points).query(vertices, k=1, distance_upper_bound=max_dist_mm)
    near = np.isfinite(d)
    faces = faces[near[faces].all(axis=1)]
    if len(faces) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return keep_components(vertices, faces, min_component_fraction)


def keep_components(vertices: np.ndarray, faces: np.ndarray, min_fraction: float = 0.0,
                    largest_only: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Keep the connected components (shared vertices) with at least ``min_fraction`` of the triangles,
    or only the largest one; unused vertices are dropped and faces reindexed."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if len(faces) == 0:
        return vertices, faces
    nv = len(vertices)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(nv, nv))
    _, lab = connected_components(g, directed=False)
    flab = lab[faces[:, 0]]
    cnt = np.bincount(flab)
    keep = flab == np.argmax(cnt) if largest_only else cnt[flab] >= min_fraction * len(faces)
    faces = faces[keep]
    used = np.unique(faces)
    remap = -np.ones(nv, np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[faces]


def boundary_edge_count(faces: np.ndarray) -> tuple[int, int]:
    """(edges used by one triangle, edges used by more than two) of a triangle mesh; (0, 0) = closed
    2-manifold surface (every edge shared by exactly two triangles)."""
    if len(faces) == 0:
        return 0, 0
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, c = np.unique(e, axis=0, return_counts=True)
    return int(np.sum(c == 1)), int(np.sum(c > 2))
