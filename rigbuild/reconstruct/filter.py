"""Multi-view consistency filtering of per-view depth maps and per-pixel fusion of consistent points.

Depth maps are (H, W) float32 camera ``z`` in mm on the pinhole grid of their camera (0 = none).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from rigbuild.camera import Camera
from rigbuild.progress import progress


def backproject_pixels(camera: Camera, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
    """World points (N, 3) mm of pinhole pixels ``(u, v)`` (N,) with camera depth ``z`` (N,) mm."""
    K = camera.K
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    Xc = np.stack([x * z, y * z, z], axis=-1)
    return (Xc - camera.t) @ camera.R


def depth_to_points(depth: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Valid pixels of a depth map -> world points (N, 3) mm and their pixel coordinates ``v, u`` (N,)."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    return backproject_pixels(camera, u.astype(np.float64), v.astype(np.float64), z), v, u


def sample_depth_bilinear(depth: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear depth at float pixels (N,); NaN where outside or where any of the 4 taps has no depth."""
    H, W = depth.shape
    out = np.full(u.shape, np.nan)
    inside = (u >= 0) & (v >= 0) & (u < W - 1) & (v < H - 1)
    ui, vi = u[inside], v[inside]
    x0, y0 = np.floor(ui).astype(np.int64), np.floor(vi).astype(np.int64)
    fx, fy = ui - x0, vi - y0
    d00, d01 = depth[y0, x0], depth[y0, x0 + 1]
    d10, d11 = depth[y0 + 1, x0], depth[y0 + 1, x0 + 1]
    val = (1 - fx) * (1 - fy) * d00 + fx * (1 - fy) * d01 + (1 - fx) * fy * d10 + fx * fy * d11
    ok = (d00 > 0) & (d01 > 0) & (d10 > 0) & (d11 > 0)
    # a tap set spanning a depth discontinuity is not a surface sample
    dmax = np.maximum(np.maximum(d00, d01), np.maximum(d10, d11))
    dmin = np.minimum(np.minimum(d00, d01), np.minimum(d10, d11))
    ok &= (dmax - dmin) < 0.02 * dmax
    val[~ok] = np.nan
    out[inside] = val
    return out


def views_within_angle(cameras: Sequence[Camera], max_angle_deg: float, max_views: int | None = None) -> list[list[int]]:
    """For each camera the other cameras whose optical axes are within ``max_angle_deg``, nearest first,
    at most ``max_views`` of them."""
    D = np.stack([c.R[2] for c in cameras])
    ang = np.degrees(np.arccos(np.clip(D @ D.T, -1, 1)))
    out = []
    for i in range(len(cameras)):
        js = [int(j) for j in np.argsort(ang[i], kind="stable") if j != i and ang[i, j] <= max_angle_deg]
        out.append(js[:max_views] if max_views is not None else js)
    return out


def point_map(depth: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W, 3) float32 world points of every pixel of a depth map (NaN where there is no depth)."""
    H, W = depth.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    z = np.where(depth > 0, depth, np.nan).astype(np.float32)
    K = camera.K
    y = (v - np.float32(K[1, 2])) * np.float32(1.0 / K[1, 1])
    x = (u - np.float32(K[0, 2]) - np.float32(K[0, 1]) * y) * np.float32(1.0 / K[0, 0])
    Xc = np.stack([x * z, y * z, z], axis=-1)
    return ((Xc - camera.t.astype(np.float32)) @ camera.R.astype(np.float32)).astype(np.float32)


def _map_views(fn, n: int, threads: int, desc: str | None = None) -> list:
    """``[fn(0), ..., fn(n - 1)]``, on a thread pool when ``threads > 1``; ``desc``: label of a progress bar
    (shown only on a terminal)."""
    bar = (lambda it: progress(it, desc, total=n, unit="view")) if desc else (lambda it: it)
    if threads <= 1 or n <= 1:
        return [fn(k) for k in bar(range(n))]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=threads) as ex:
        return list(bar(ex.map(fn, range(n))))


@dataclass
class ConsistencyResult:
    """Per view: ``depth`` filtered (H, W) float32 (0 = rejected), ``n_views`` (H, W) uint8 number of
    views agreeing (the reference included); ``points`` (N, 3) fused world points of the kept pixels
    (mean of the reference point and the agreeing views' points), ``pixels`` (N, 2) int (v, u) of those
    points; ``point_maps`` per view (H, W, 3) float32 world points of the unfiltered depth (NaN = none)."""

    depth: list[np.ndarray]
    n_views: list[np.ndarray]
    points: list[np.ndarray]
    pixels: list[np.ndarray]
    point_maps: list[np.ndarray]


def consistency_filter(depths: Sequence[np.ndarray], cameras: Sequence[Camera], check_views: Sequence[Sequence[int]],
                       abs_tol_mm: float = 0.5, rel_tol: float = 0.002, min_views: int = 2,
                       threads: int = 1) -> ConsistencyResult:
    """Keep depth pixels that ``min_views - 1`` other views agree with, and fuse them.

    A pixel of view ``i`` with world point ``X`` agrees with view ``j`` when ``X`` projects inside ``j``
    onto a pixel (nearest) with depth ``d_j`` and ``|z_j(X) - d_j| <= abs_tol_mm + rel_tol * z_j(X)``.
    The fused point is the mean of ``X`` and the agreeing views' surface points at those pixels (points
    on the surface, at most half a pixel apart along it, so their mean stays on the surface and its noise
    across the surface drops with the number of views).

    Parameters
    ----------
    depths : per view (H, W) float32 mm on the pinhole grid of ``cameras`` (0 = none).
    cameras : pinhole cameras (no distortion) of those grids.
    check_views : per view, the views to test against (e.g. :func:`views_within_angle`).
    threads : views processed in parallel (numpy releases the GIL on large arrays).
    """
    maps = _map_views(lambda k: point_map(depths[k], cameras[k]), len(depths), threads)

    def one_view(i: int):
        depth = depths[i]
        v, u = np.nonzero(depth > 0)
        X = maps[i][v, u]
        acc = X.astype(np.float64)
        count = np.ones(len(X), np.int64)
        for j in check_views[i]:
            cj = cameras[j]
            Hj, Wj = depths[j].shape
            Xc = X @ cj.R.T.astype(np.float32) + cj.t.astype(np.float32)
            z = Xc[:, 2]
            inv = np.float32(1.0) / np.where(z > 1e-6, z, np.float32(np.inf))
            uj = np.rint(cj.K[0, 0] * Xc[:, 0] * inv + cj.K[0, 1] * Xc[:, 1] * inv + cj.K[0, 2])
            vj = np.rint(cj.K[1, 1] * Xc[:, 1] * inv + cj.K[1, 2])
            inside = (z > 1e-6) & (uj >= 0) & (uj <= Wj - 1) & (vj >= 0) & (vj <= Hj - 1)
            idx = np.nonzero(inside)[0]
            ui, vi = uj[idx].astype(np.int64), vj[idx].astype(np.int64)
            dj = depths[j][vi, ui]
            ok = (dj > 0) & (np.abs(z[idx] - dj) <= abs_tol_mm + rel_tol * z[idx])
            idx, ui, vi = idx[ok], ui[ok], vi[ok]
            acc[idx] += maps[j][vi, ui]
            count[idx] += 1
        keep = count >= min_views
        d = np.zeros_like(depth)
        d[v[keep], u[keep]] = depth[v[keep], u[keep]]
        n = np.zeros(depth.shape, np.uint8)
        n[v[keep], u[keep]] = np.minimum(count[keep], 255)
        return d, n, acc[keep] / count[keep, None], np.stack([v[keep], u[keep]], 1)

    res = _map_views(one_view, len(depths), threads)
    out_d, out_n, out_p, out_px = (list(x) for x in zip(*res)) if res else ([], [], [], [])
    return ConsistencyResult(out_d, out_n, out_p, out_px, maps)
