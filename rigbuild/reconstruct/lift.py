"""Lift 2-D image points to 3-D through a reconstructed depth map (for tracking).

Depth maps (``rigbuild.io.depth``) hold camera ``z`` in mm on the *pinhole* grid of the calibrated camera
(same ``K``, ``R``, ``t``, distortion removed); image points usually live in the original, distorted
images, so :func:`depth_at` undistorts them first.
"""

from __future__ import annotations

import numpy as np

from rigbuild.camera import Camera


def sample_depth(depth: np.ndarray, x: np.ndarray, y: np.ndarray, max_rel_step: float = 0.02) -> np.ndarray:
    """Bilinear depth at float grid pixels ``(x, y)`` (N,); NaN outside the map, where a tap has no depth,
    or where the 4 taps span a step larger than ``max_rel_step`` of the depth (a silhouette)."""
    H, W = depth.shape
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    out = np.full(x.shape, np.nan)
    inside = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (y >= 0) & (x <= W - 1) & (y <= H - 1)
    xi, yi = x[inside], y[inside]
    x0 = np.minimum(np.floor(xi).astype(np.int64), W - 2)
    y0 = np.minimum(np.floor(yi).astype(np.int64), H - 2)
    fx, fy = xi - x0, yi - y0
    d = np.nan_to_num(np.asarray(depth, np.float64), nan=0.0)
    taps = np.stack([d[y0, x0], d[y0, x0 + 1], d[y0 + 1, x0], d[y0 + 1, x0 + 1]])
    w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
    val = np.sum(taps * w, axis=0)
    ok = np.all(taps > 0, axis=0) & ((taps.max(0) - taps.min(0)) <= max_rel_step * taps.max(0))
    val[~ok] = np.nan
    out[inside] = val
    return out


def depth_at(depth: np.ndarray, camera: Camera, uv: np.ndarray, distorted: bool = True) -> np.ndarray:
    """World points (N, 3) mm where the rays through pixels ``uv`` (N, 2) meet the depth map's surface.

    Parameters
    ----------
    depth : (H, W) camera z in mm on the pinhole grid of ``camera`` (0/NaN = none).
    camera : the calibrated camera (its ``K``, ``R``, ``t``; ``dist`` is used to undistort ``uv``).
    uv : pixel coordinates in the original image (``distorted=True``) or on the pinhole grid.

    Returns
    -------
    (N, 3) world points; rows are NaN where there is no depth (outside, hole, silhouette).
    """
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    K = camera.K
    if distorted and np.any(camera.dist):
        xy = camera.undistort_points(uv)
    else:
        y = (uv[:, 1] - K[1, 2]) / K[1, 1]
        xy = np.stack([(uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0], y], 1)
    gx = K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2]
    gy = K[1, 1] * xy[:, 1] + K[1, 2]
    z = sample_depth(depth, gx, gy)
    Xc = np.stack([xy[:, 0] * z, xy[:, 1] * z, z], 1)
    return (Xc - camera.t) @ camera.R
