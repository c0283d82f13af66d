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


def pair_depth_differences(depth_i: np.ndarray, cam_i: Camera, depth_j: np.ndarray, cam_j: Camera,
                           stride: int = 1) -> np.ndarray:
    """(N,) mm ``|z_j(X) - d_j|`` for the depth pixels of view ``i`` (every ``stride``-th row and column)
    whose point ``X`` lies in front of view ``j`` and projects onto depth of view ``j``."""
    s = max(1, int(stride))
    sub = depth_i[::s, ::s]
    v, u = np.nonzero(sub > 0)
    z = sub[v, u].astype(np.float64)
    X = backproject_pixels(cam_i, u.astype(np.float64) * s, v.astype(np.float64) * s, z)
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
                       stride: int = 2) -> dict[str, float | int]:
    """Median cross-view depth disagreement of one frame.

    Parameters
    ----------
    depths : per view (H, W) float32 mm (0 = none) on the pinhole grid of ``cameras``.
    cameras : pinhole cameras (no distortion) of those grids.
    pairs : per view ``i`` the views ``j`` it is compared with (e.g. the consistency filter's check views).
    stride : every ``stride``-th pixel row and column of each view is tested (the median needs no more).

    Returns
    -------
    ``median_mm`` (NaN when no pixel pair was compared), ``p90_mm`` and ``n_pixels`` (pixel pairs compared).
    """
    diffs = [pair_depth_differences(depths[i], cameras[i], depths[j], cameras[j], stride)
             for i in range(len(depths)) for j in pairs[i] if j != i]
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    if not len(d):
        return {"median_mm": float("nan"), "p90_mm": float("nan"), "n_pixels": 0}
    med, p90 = np.percentile(d, [50, 90])
    return {"median_mm": float(med), "p90_mm": float(p90), "n_pixels": int(len(d))}
