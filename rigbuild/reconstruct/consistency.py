"""Cross-view stereo consistency: a stage-side quality number that needs no ground truth.

Each view's depth points are projected into a neighbouring view and compared with that view's own depth
there: ``|z_j(X) - d_j(pi_j(X))|``, the disagreement of two independent depth estimates of one surface point
along view ``j``'s optical axis (mm). Only pixels where both views have depth count (a depth map holds depth
only where the stereo's NCC and texture tests passed); ``d_j`` is sampled bilinearly and never across a depth
edge (:func:`rigbuild.reconstruct.filter.sample_depth_bilinear`). The median over every view and its
neighbours, both directions, is robust to the occlusions a neighbour sees (a minority of pixels on a face).

Depth maps are (H, W) float32 camera ``z`` in mm on the pinhole grid of their camera (0 = none).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from rigbuild.camera import Camera
from rigbuild.reconstruct.filter import backproject_pixels, sample_depth_bilinear


#: depth pixels sampled per view: the median is settled long before (the cost stays flat with the resolution)
MAX_PIXELS_PER_VIEW = 20000


def view_points(depth: np.ndarray, camera: Camera, max_pixels: int | None = MAX_PIXELS_PER_VIEW) -> np.ndarray:
    """(N, 3) world points mm of a depth map's pixels with depth; at most ``max_pixels`` of them, evenly
    spaced in raster order (None: all)."""
    v, u = np.nonzero(depth > 0)
    if max_pixels is not None and len(v) > max_pixels:
        sel = np.linspace(0, len(v) - 1, int(max_pixels)).astype(np.int64)
        v, u = v[sel], u[sel]
    return backproject_pixels(camera, u.astype(np.float64), v.astype(np.float64), depth[v, u].astype(np.float64))


def depth_differences(X: np.ndarray, depth_j: np.ndarray, cam_j: Camera) -> np.ndarray:
    """(M,) mm ``|z_j(X) - d_j|`` for the points ``X`` (N, 3) that lie in front of view ``j`` and project
    onto its depth (bilinear, not across a depth edge); the others are left out."""
    Xc = X @ cam_j.R.T + cam_j.t
    zj = Xc[:, 2]
    front = zj > 1e-6
    Xc, zj = Xc[front], zj[front]
    K = cam_j.K
    x, y = Xc[:, 0] / zj, Xc[:, 1] / zj
    dj = sample_depth_bilinear(depth_j, K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2])
    ok = np.isfinite(dj)
    return np.abs(zj[ok] - dj[ok])


def stereo_consistency(depths: Sequence[np.ndarray], cameras: Sequence[Camera], pairs: Sequence[Sequence[int]],
                       max_pixels: int | None = MAX_PIXELS_PER_VIEW) -> dict[str, float | int]:
    """Median cross-view depth disagreement of one frame.

    Parameters
    ----------
    depths : per view (H, W) float32 mm (0 = none) on the pinhole grid of ``cameras``.
    cameras : pinhole cameras (no distortion) of those grids.
    pairs : per view ``i`` the views ``j`` it is compared with (e.g. the consistency filter's check views).
    max_pixels : depth pixels of each view tested (:func:`view_points`; None: all).

    Returns
    -------
    ``median_mm`` (NaN when no pixel pair was compared), ``p90_mm`` and ``n_pixels`` (pixel pairs compared).
    """
    diffs = []
    for i, js in enumerate(pairs):
        js = [j for j in js if j != i]
        if js:
            X = view_points(depths[i], cameras[i], max_pixels)
            diffs += [depth_differences(X, depths[j], cameras[j]) for j in js]
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    if not len(d):
        return {"median_mm": float("nan"), "p90_mm": float("nan"), "n_pixels": 0}
    med, p90 = np.percentile(d, [50, 90])
    return {"median_mm": float(med), "p90_mm": float(p90), "n_pixels": int(len(d))}
