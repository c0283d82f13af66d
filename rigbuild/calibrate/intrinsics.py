"""Per-camera intrinsics (focal, principal point, Brown distortion) and per-view board poses.

Zhang's method as implemented by ``cv2.calibrateCamera`` (homography initialization + Levenberg-Marquardt
over K, ``[k1, k2, p1, p2, k3]`` and the board poses). Its board poses seed the pose graph
(:mod:`rigbuild.calibrate.posegraph`) and its intrinsics seed the global bundle adjustment.

Known intrinsics (session.yaml ``intrinsics:``, :func:`given_intrinsics`) skip Zhang's method: the board
poses come from ``cv2.solvePnP`` with the given K and distortion (:func:`board_poses`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import os
from pathlib import Path

import cv2
import numpy as np

from rigbuild.determinism import opencv_threads
from rigbuild.errors import InputError

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass
class Intrinsics:
    """Single-camera calibration.

    K : (3, 3) pixels; dist : (5,) ``[k1, k2, p1, p2, k3]``;
    R_views : (V, 3, 3), t_views : (V, 3) board-to-camera pose of each view (board units, mm);
    rms_px : RMS reprojection error over all corners (OpenCV's definition: sqrt(mean |du|^2));
    view_rms_px : (V,) per-view RMS.
    sd : (4,) standard deviations of fx, fy, cx, cy, px (``cv2.calibrateCameraExtended``; NaN = held by a flag
        or not estimated here).
    """

    K: np.ndarray
    dist: np.ndarray
    R_views: np.ndarray
    t_views: np.ndarray
    rms_px: float
    view_rms_px: np.ndarray
    sd: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))


def calibration_flags(fix_k3: bool = False, zero_tangent: bool = False, fix_aspect: bool = False,
                      fix_principal_point: bool = False) -> int:
    """OpenCV ``calibrateCamera`` flags for the distortion model choices (the principal point is held at
    the image centre ((w - 1) / 2, (h - 1) / 2), the aspect ratio at fx = fy)."""
    flags = 0
    if fix_k3:
        flags |= cv2.CALIB_FIX_K3
    if zero_tangent:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    if fix_aspect:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    if fix_principal_point:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
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
    OpenCV runs it on one thread: on more its result varies from call to call (:mod:`rigbuild.determinism`).
    """
    if len(object_points) < 2:
        raise InputError(f"camera '{camera}': {len(object_points)} usable board views, at least 2 are needed",
                         fix="re-shoot the calibration images of this camera with the whole board visible")
    obj = [np.ascontiguousarray(o, dtype=np.float32).reshape(-1, 1, 3) for o in object_points]
    img = [np.ascontiguousarray(p, dtype=np.float32).reshape(-1, 1, 2) for p in image_points]
    w, h = (int(s) for s in image_size)
    K0 = np.array([[1.0, 0, (w - 1) / 2], [0, 1.0, (h - 1) / 2], [0, 0, 1]])  # ratio 1, centre (fixed-flag starts)
    with opencv_threads(1):  # more threads: a different K on every call (rigbuild.determinism)
        rms, K, dist, rvecs, tvecs, sd_intr, _, _ = cv2.calibrateCameraExtended(
            obj, img, (w, h), K0, None, flags=flags, criteria=criteria or _CRITERIA)
    R = np.stack([cv2.Rodrigues(r)[0] for r in rvecs])
    t = np.stack([np.asarray(tv, dtype=np.float64).reshape(3) for tv in tvecs])
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)[:5]
    view_rms = np.empty(len(obj))
    for i, (o, p, r, tv) in enumerate(zip(obj, img, rvecs, tvecs)):
        proj = cv2.projectPoints(o, r, tv, K, dist)[0].reshape(-1, 2)
        view_rms[i] = np.sqrt(np.mean(np.sum((proj - p.reshape(-1, 2)) ** 2, axis=1)))
    return Intrinsics(np.asarray(K, dtype=np.float64), np.pad(dist, (0, 5 - dist.size)), R, t, float(rms), view_rms,
                      _held_as_nan(np.asarray(sd_intr, dtype=np.float64).reshape(-1)[:4]))


def _held_as_nan(sd: np.ndarray) -> np.ndarray:
    """OpenCV reports 0 for an unknown a flag holds (fixed principal point, fx of a fixed aspect ratio)."""
    return np.where(sd > 0, sd, np.nan)


def board_poses(object_points: Sequence[np.ndarray], image_points: Sequence[np.ndarray], K: np.ndarray,
                dist: np.ndarray) -> Intrinsics:
    """Board-to-camera pose of each view for a camera of known ``K`` (3, 3) and ``dist`` (5,):
    ``cv2.solvePnP`` (IPPE for the planar board, then Levenberg-Marquardt). Returns an :class:`Intrinsics`
    holding the given K and dist, the poses and the reprojection RMS."""
    K = np.asarray(K, dtype=np.float64)
    dist = np.pad(np.asarray(dist, dtype=np.float64).reshape(-1)[:5], (0, 5 - min(5, np.size(dist))))
    R, t, e2, view_rms = [], [], [], []
    for o, p in zip(object_points, image_points):
        o = np.ascontiguousarray(o, dtype=np.float64).reshape(-1, 3)
        p = np.ascontiguousarray(p, dtype=np.float64).reshape(-1, 2)
        ok, rvec, tvec = cv2.solvePnP(o, p, K, dist, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            ok, rvec, tvec = cv2.solvePnP(o, p, K, dist)
        rvec, tvec = cv2.solvePnPRefineLM(o, p, K, dist, rvec, tvec)
        proj = cv2.projectPoints(o, rvec, tvec, K, dist)[0].reshape(-1, 2)
        d2 = np.sum((proj - p) ** 2, axis=1)
        R.append(cv2.Rodrigues(rvec)[0])
        t.append(np.asarray(tvec, dtype=np.float64).reshape(3))
        e2.append(d2)
        view_rms.append(np.sqrt(d2.mean()))
    return Intrinsics(K, dist, np.stack(R), np.stack(t), float(np.sqrt(np.concatenate(e2).mean())),
                      np.asarray(view_rms))


def given_intrinsics(raw: object, root: str | os.PathLike, cameras: Sequence[str]
                     ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """session.yaml ``intrinsics:`` -> camera id -> (K (3, 3) px, dist (5,)).

    raw : the inline mapping (camera id -> ``{K: 3x3, dist: [k1, k2, p1, p2, k3]}``), a path (relative to
        ``root``) of a YAML/JSON file holding that mapping or a rigbuild ``cameras.json``, or None.
    InputError names the file and the camera for unknown cameras and malformed entries.
    """
    import json

    import yaml

    root = Path(root)
    source: Path = root / "session.yaml"
    if raw is None:
        return {}
    if isinstance(raw, str):
        source = Path(raw) if Path(raw).is_absolute() else root / raw
        if not source.is_file():
            raise InputError("intrinsics file not found (session.yaml field 'intrinsics')", path=source,
                             fix="give a YAML/JSON file: camera id -> {K: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "
                             "dist: [k1, k2, p1, p2, k3]}")
        text = source.read_text(encoding="utf-8")
        raw = json.loads(text) if source.suffix.lower() == ".json" else yaml.safe_load(text)
        if isinstance(raw, dict) and isinstance(raw.get("cameras"), list):
            raw = {str(c["id"]): c for c in raw["cameras"]}
    if not isinstance(raw, dict):
        raise InputError("intrinsics must map camera ids to {K, dist}", path=source)
    out = {}
    for cam, entry in raw.items():
        if str(cam) not in cameras:
            raise InputError(f"intrinsics for unknown camera '{cam}'", path=source,
                             fix=f"use camera ids from session.yaml: {', '.join(cameras)}")
        try:
            K = np.asarray(entry["K"], dtype=np.float64).reshape(3, 3)
            dist = np.asarray(entry.get("dist", [0.0] * 5), dtype=np.float64).reshape(-1)
        except (KeyError, TypeError, ValueError):
            raise InputError(f"intrinsics of camera '{cam}': need K (3 x 3) and dist (up to 5 numbers)",
                             path=source) from None
        if dist.size > 5 or not (K[0, 0] > 0 and K[1, 1] > 0) or not np.allclose(K[2], [0, 0, 1]):
            raise InputError(f"intrinsics of camera '{cam}': K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] "
                             "with fx, fy > 0 and dist at most [k1, k2, p1, p2, k3]", path=source)
        out[str(cam)] = (K, np.pad(dist, (0, 5 - dist.size)))
    return out
