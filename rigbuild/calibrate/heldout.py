"""Calibration quality on board poses left out of the fit (how calibration tools are compared).

Every n-th board pose (view-key order) is held out; the rig is calibrated on the others; each held-out
corner seen by two or more cameras is triangulated with the calibrated rig (midpoint of rays,
:func:`rigbuild.track.features.triangulate`, then Gauss-Newton on the pixel error) and reprojected into
the cameras that saw it. Reported: RMS of those reprojection errors per camera and overall (px), and the
board's scale measured on the triangulated corners against its printed square size (%).
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from rigbuild.calibrate.detect import Detection
from rigbuild.camera import Camera
from rigbuild.geometry.rigid import fit_similarity


def split_views(view_keys: Sequence[str], every: int) -> tuple[list[str], list[str]]:
    """(fitted keys, held-out keys): the every-th, 2 every-th, ... key (1-based) is held out."""
    keys = list(view_keys)
    held = [k for i, k in enumerate(keys) if every > 0 and (i + 1) % every == 0]
    return [k for k in keys if k not in held], held


def refine_points(cameras: Sequence[Camera], uv: np.ndarray, X: np.ndarray, iterations: int = 5) -> np.ndarray:
    """Gauss-Newton on each point's pixel reprojection error. uv (C, M, 2) px, NaN = unseen; X (M, 3) mm."""
    X = X.copy()
    seen = np.isfinite(uv).all(axis=2)
    for _ in range(iterations):
        JtJ = np.zeros((X.shape[0], 3, 3))
        Jtr = np.zeros((X.shape[0], 3))
        for c, cam in enumerate(cameras):
            m = seen[c] & np.isfinite(X).all(1)
            if not m.any():
                continue
            r = cam.project(X[m]) - uv[c, m]
            J = np.empty((int(m.sum()), 2, 3))
            for k in range(3):
                h = np.zeros(3)
                h[k] = 1e-4
                J[:, :, k] = (cam.project(X[m] + h) - cam.project(X[m] - h)) / 2e-4
            JtJ[m] += np.einsum("nki,nkj->nij", J, J)
            Jtr[m] += np.einsum("nki,nk->ni", J, r)
        ok = np.isfinite(X).all(1) & (np.linalg.det(JtJ) > 0)
        X[ok] -= np.linalg.solve(JtJ[ok], Jtr[ok][:, :, None])[:, :, 0]
    return X


def heldout_errors(cameras: Sequence[Camera], detections: Mapping[str, Mapping[str, Detection]],
                   held: Sequence[str], board_points: np.ndarray) -> dict:
    """Triangulate and reproject the held-out board poses.

    cameras : the rig calibrated without ``held``; detections : camera id -> view key -> Detection.
    board_points : (P, 3) board-frame corners, mm.
    Returns ``rms_px`` (overall), ``camera_rms_px`` (camera id -> px), ``n_corners`` (triangulated
    corners), ``n_views``, ``scale_deviation_pct`` (median over views of the similarity scale triangulated /
    printed board, minus 1, %; None with no view of 6 or more triangulated corners).
    """
    from rigbuild.track.features import triangulate

    e2: dict[str, list[np.ndarray]] = {c.id: [] for c in cameras}
    scales, n_corners, n_views = [], 0, 0
    for v in held:
        ids = sorted({int(i) for c in cameras for i in detections.get(c.id, {}).get(v, Detection([], [])).ids})
        if not ids:
            continue
        col = {i: k for k, i in enumerate(ids)}
        uv = np.full((len(cameras), len(ids), 2), np.nan)
        for ci, cam in enumerate(cameras):
            d = detections.get(cam.id, {}).get(v)
            if d is not None and len(d):
                uv[ci, [col[int(i)] for i in d.ids]] = d.corners
        X, _, n = triangulate(list(cameras), uv)
        good = n >= 2
        if not good.any():
            continue
        X = refine_points(cameras, uv[:, good], X[good])
        n_views += 1
        n_corners += int(good.sum())
        for ci, cam in enumerate(cameras):
            m = np.isfinite(uv[ci, good]).all(1)
            if m.any():
                e2[cam.id].append(np.sum((cam.project(X[m]) - uv[ci, good][m]) ** 2, axis=1))
        if good.sum() >= 6:
            scales.append(fit_similarity(board_points[np.asarray(ids)[good]], X)[0])
    cam_rms = {c: float(np.sqrt(np.mean(np.concatenate(v)))) if v else float("nan") for c, v in e2.items()}
    every = [a for v in e2.values() for a in v]
    return {
        "rms_px": float(np.sqrt(np.mean(np.concatenate(every)))) if every else float("nan"),
        "camera_rms_px": cam_rms,
        "n_corners": n_corners,
        "n_views": n_views,
        "scale_deviation_pct": float(100 * (np.median(scales) - 1)) if scales else None,
    }
