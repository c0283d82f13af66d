"""Calibration accuracy against ground truth (synthetic sessions only; pipeline stages never call this).

The calibrated world frame (reference camera, see :mod:`rigbuild.calibrate.rig`) differs from the ground
truth's by a similarity, found by Umeyama on the camera centres (``fit_similarity``); orientations are
compared after that alignment. The similarity's scale is reported as ``scale_error_pct`` (metric scale
comes from the board, so it should be ~0).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from rigbuild.calibrate.bundle import ray_angle_deg
from rigbuild.camera import Camera, distort_normalized
from rigbuild.errors import InputError
from rigbuild.geometry.rigid import fit_similarity, rotation_angle_deg


def distortion_error_px(est: Camera, truth: Camera, n: int = 21) -> float:
    """Largest pixel difference of the two cameras' distortion over an image grid (n x n), px.

    Both cameras' distortion is applied to the same normalized rays (the truth camera's undistorted grid)
    and mapped through the truth K, so only the distortion coefficients differ.
    """
    u, v = np.meshgrid(np.linspace(0, truth.width - 1, n), np.linspace(0, truth.height - 1, n))
    xy = truth.undistort_points(np.stack([u.ravel(), v.ravel()], 1))
    xe, ye = distort_normalized(xy[:, 0], xy[:, 1], est.dist)
    xt, yt = distort_normalized(xy[:, 0], xy[:, 1], truth.dist)
    d = np.stack([(xe - xt) * truth.K[0, 0], (ye - yt) * truth.K[1, 1]], 1)
    return float(np.linalg.norm(d, axis=1).max())


def compare_cameras(estimated: Sequence[Camera], truth: Sequence[Camera]) -> dict[str, float]:
    """Errors of calibrated cameras against ground truth, matched by id.

    Returns a dict (max over cameras unless named ``*_mean``): ``focal_error_pct`` (|f - f_gt| / f_gt of fx
    and fy, %), ``principal_point_error_px``, ``center_error_mm`` (after similarity alignment),
    ``center_error_mm_mean``, ``rotation_error_deg`` (after alignment), ``rotation_error_deg_mean``,
    ``scale_error_pct`` (estimated / true length - 1, %), ``distortion_error_px``, ``n_cameras``.
    """
    gt = {c.id: c for c in truth}
    missing = [c.id for c in estimated if c.id not in gt]
    if missing:
        raise InputError(f"cameras {missing} are not in the ground truth")
    est = list(estimated)
    tru = [gt[c.id] for c in est]
    ce = np.stack([c.center for c in est])
    cg = np.stack([c.center for c in tru])
    s, Rs, ts = fit_similarity(ce, cg)
    aligned = s * ce @ Rs.T + ts
    dc = np.linalg.norm(aligned - cg, axis=1)
    rot = np.array([rotation_angle_deg(g.R @ (e.R @ Rs.T).T) for e, g in zip(est, tru)])
    fe = np.array([[abs(e.K[0, 0] - g.K[0, 0]) / g.K[0, 0], abs(e.K[1, 1] - g.K[1, 1]) / g.K[1, 1]]
                   for e, g in zip(est, tru)]) * 100
    pp = np.array([np.hypot(e.K[0, 2] - g.K[0, 2], e.K[1, 2] - g.K[1, 2]) for e, g in zip(est, tru)])
    return {
        "focal_error_pct": float(fe.max()),
        "focal_error_pct_mean": float(fe.mean()),
        "principal_point_error_px": float(pp.max()),
        "center_error_mm": float(dc.max()),
        "center_error_mm_mean": float(dc.mean()),
        "rotation_error_deg": float(rot.max()),
        "rotation_error_deg_mean": float(rot.mean()),
        "scale_error_pct": float((1.0 / s - 1.0) * 100),
        "distortion_error_px": float(max(distortion_error_px(e, g) for e, g in zip(est, tru))),
        "n_cameras": len(est),
    }


def corner_localisation_errors(detections, truth: Sequence[Camera], board, poses) -> dict[str, np.ndarray]:
    """Detected corners minus the true projections of the board corners (synthetic sessions).

    detections : camera id -> view key (``"0"``, ``"1"``, ... = index into ``poses``) -> Detection
        (:func:`rigbuild.calibrate.detect.detect_images`).
    truth : ground-truth cameras; board : :class:`rigbuild.session.BoardSpec`;
    poses : [(R (3, 3), t (3,) mm)] board-to-world poses (``ground_truth/board_poses.npz``).

    Returns dict with ``errors`` (N, 2) px (detected - ``camera.project`` of the true corner), ``camera``
    (N,) camera index and ``view_angle_deg`` (N,) angle between the board normal and the viewing ray to
    the corner (0 = frontal), for every detected corner.
    """
    pts, _ = board.corner_points()
    errs, cam_idx, angles = [], [], []
    for ci, cam in enumerate(truth):
        for key, det in detections.get(cam.id, {}).items():
            if len(det) == 0:
                continue
            R, t = np.asarray(poses[int(key)][0]), np.asarray(poses[int(key)][1])
            X = pts[det.ids] @ R.T + t
            errs.append(det.corners - cam.project(X))
            cam_idx.append(np.full(len(det), ci))
            angles.append(ray_angle_deg(X - cam.center, R[:, 2]))
    if not errs:
        return {"errors": np.zeros((0, 2)), "camera": np.zeros(0, np.int64), "view_angle_deg": np.zeros(0)}
    return {"errors": np.vstack(errs), "camera": np.concatenate(cam_idx), "view_angle_deg": np.concatenate(angles)}


def corner_error_summary(errors: np.ndarray) -> dict[str, float]:
    """Summary of (N, 2) corner errors, px: ``rms`` (of the 2-D error), ``bias_u``, ``bias_v`` (means),
    ``p99``, ``max`` (of the 2-D error norm) and ``n``."""
    e = np.asarray(errors, dtype=np.float64).reshape(-1, 2)
    n = np.linalg.norm(e, axis=1)
    return {"rms": float(np.sqrt(np.mean(n ** 2))), "bias_u": float(e[:, 0].mean()), "bias_v": float(e[:, 1].mean()),
            "p99": float(np.percentile(n, 99)), "max": float(n.max()), "n": int(len(e))}


def run_eval_calibration(cameras_json, truth_json, out_path) -> dict[str, float]:
    """Rule ``eval_calibration``: calibrated ``cameras.json`` vs ``ground_truth/cameras.json`` ->
    the fragment ``{"calibration": compare_cameras(...)}`` at ``out_path``; returns the errors."""
    from rigbuild.io.cameras import read_cameras
    from rigbuild.io.metrics import write_metrics_fragment

    errors = compare_cameras(read_cameras(cameras_json), read_cameras(truth_json))
    write_metrics_fragment(out_path, "calibration", errors)
    return errors
