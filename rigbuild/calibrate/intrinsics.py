"""Per-camera intrinsics (focal, principal point, Brown distortion) and per-view board poses.

Zhang's method as implemented by ``cv2.calibrateCamera`` (homography initialization + Levenberg-Marquardt
over K, ``[k1, k2, p1, p2, k3]`` and the board poses). Its board poses seed the pose graph
(:mod:`rigbuild.calibrate.posegraph`) and its intrinsics seed the global bundle adjustment.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from rigbuild.errors import InputError

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass
class Intrinsics:
    """Single-camera calibration.

    K : (3, 3) pixels; dist : (5,) ``[k1, k2, p1, p2, k3]``;
    R_views : (V, 3, 3), t_views : (V, 3) board-to-camera pose of each view (board units, mm);
    rms_px : RMS reprojection error over all corners (OpenCV's definition: sqrt(mean |du|^2));
    view_rms_px : (V,) per-view RMS.
    """

    K: np.ndarray
    dist: np.ndarray
    R_views: np.ndarray
    t_views: np.ndarray
    rms_px: float
    view_rms_px: np.ndarray


def calibration_flags(fix_k3: bool = False, zero_tangent: bool = False, fix_aspect: bool = False) -> int:
    """OpenCV ``calibrateCamera`` flags for the distortion model choices."""
    flags = 0
    if fix_k3:
        flags |= cv2.CALIB_FIX_K3
    if zero_tangent:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    if fix_aspect:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    return flags


def calibrate_intrinsics(
    object_points: Sequence[np.ndarray],
    image_points: Sequence[np.ndarray],
    image_size: tuple[int, int],
    flags: int = 0,
    criteria: tuple | None = None,
    camera: str = "",
) -> Intrinsics:
    """Calibrate one camera from V views of a planar board.

    object_points : V arrays (N_v, 3) board-frame corners, mm (z = 0).
    image_points : V arrays (N_v, 2) detected pixels.
    image_size : (width, height).
    flags : OpenCV calibration flags (:func:`calibration_flags`); 0 = OpenCV's default model.
    criteria : OpenCV termination criteria; default 100 iterations / 1e-12.
    """
    if len(object_points) < 2:
        raise InputError(f"camera '{camera}': {len(object_points)} usable board views, at least 2 are needed",
                         fix="re-shoot the calibration images of this camera with the whole board visible")
    obj = [np.ascontiguousarray(o, dtype=np.float32).reshape(-1, 1, 3) for o in object_points]
    img = [np.ascontiguousarray(p, dtype=np.float32).reshape(-1, 1, 2) for p in image_points]
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, tuple(int(s) for s in image_size), None, None,
                                                    flags=flags, criteria=criteria or _CRITERIA)
    R = np.stack([cv2.Rodrigues(r)[0] for r in rvecs])
    t = np.stack([np.asarray(tv, dtype=np.float64).reshape(3) for tv in tvecs])
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)[:5]
    view_rms = np.empty(len(obj))
    for i, (o, p, r, tv) in enumerate(zip(obj, img, rvecs, tvecs)):
        proj = cv2.projectPoints(o, r, tv, K, dist)[0].reshape(-1, 2)
        view_rms[i] = np.sqrt(np.mean(np.sum((proj - p.reshape(-1, 2)) ** 2, axis=1)))
    return Intrinsics(np.asarray(K, dtype=np.float64), np.pad(dist, (0, 5 - dist.size)), R, t, float(rms), view_rms)
