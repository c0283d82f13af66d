"""Level 2: robust sparse features (OpenCV SIFT) matched between a source and a target frame per view.

Following Ma et al. 2016 s. 2.1, matching and registration are iterated: every round predicts where
each source keypoint lands (the rendered motion field of the current mesh estimate), searches target
keypoints only inside a radius around the prediction, and accepts the best by descriptor distance under
a threshold (plus Lowe's ratio test among the candidates). Across rounds the search radius shrinks while
the descriptor threshold and the data weight lambda grow (:class:`SparseSchedule`).
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from rigbuild.track.matches import Matches, Source, ViewFrame, lift_matches
from rigbuild.track.params import SparseSchedule


def sift_features(frame: ViewFrame, schedule: SparseSchedule | None = None) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints (N, 2) px and descriptors (N, 128) float32 of a view (cached on the frame);
    only where the depth map has surface (detected on the box around it)."""
    if frame._sift is None:
        s = schedule or SparseSchedule()
        sift = cv2.SIFT_create(nfeatures=s.max_features, contrastThreshold=s.contrast_threshold,
                               edgeThreshold=s.edge_threshold)
        fin = np.isfinite(frame.depth)
        rows, cols = np.flatnonzero(fin.any(1)), np.flatnonzero(fin.any(0))
        if rows.size == 0:
            frame._sift = (np.zeros((0, 2)), np.zeros((0, 128), np.float32))
            return frame._sift
        y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
        mask = fin[y0:y1, x0:x1].astype(np.uint8) * 255
        gray = np.ascontiguousarray(frame.gray[y0:y1, x0:x1])
        sc = float(s.image_scale)
        if sc != 1.0:
            size = (max(int(round(gray.shape[1] * sc)), 16), max(int(round(gray.shape[0] * sc)), 16))
            gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
            mask = cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST)
        kps, desc = sift.detectAndCompute(gray, mask)
        pts = np.array([k.pt for k in kps], dtype=np.float64).reshape(-1, 2)
        if sc != 1.0:  # OpenCV pixel centres: x_full = (x_small + 0.5) / scale - 0.5
            pts = (pts + 0.5) * [(x1 - x0) / gray.shape[1], (y1 - y0) / gray.shape[0]] - 0.5
        pts = pts + [x0, y0]
        frame._sift = (pts, np.zeros((0, 128), np.float32) if desc is None else desc.astype(np.float32))
    return frame._sift


def match_guided(src_pts: np.ndarray, src_desc: np.ndarray, predicted: np.ndarray, tgt_pts: np.ndarray,
                 tgt_desc: np.ndarray, radius_px: float, threshold: float, ratio: float, k: int = 8
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Guided descriptor matching.

    For each source keypoint with a predicted target position (N, 2) (NaN = skip), the target keypoints
    within ``radius_px`` are candidates; the nearest in descriptor space is accepted if its distance is
    below ``threshold`` and below ``ratio`` times the second best candidate's. Mutual uniqueness: a target
    keypoint keeps only its best source. Returns source indices (n,), target indices (n,), distances (n,).
    """
    ok = np.isfinite(predicted).all(1)
    if not ok.any() or tgt_pts.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    idx = np.flatnonzero(ok)
    kk = min(k, tgt_pts.shape[0])
    d, j = cKDTree(tgt_pts).query(predicted[idx], k=kk, distance_upper_bound=radius_px)
    d = d.reshape(idx.size, kk)
    j = j.reshape(idx.size, kk)
    valid = np.isfinite(d)
    jj = np.where(valid, j, 0)
    dd = np.linalg.norm(tgt_desc[jj] - src_desc[idx][:, None, :], axis=2)
    dd[~valid] = np.inf
    order = np.argsort(dd, axis=1)
    best = np.take_along_axis(dd, order[:, :1], 1)[:, 0]
    second = np.take_along_axis(dd, order[:, 1:2], 1)[:, 0] if kk > 1 else np.full(idx.size, np.inf)
    bj = np.take_along_axis(jj, order[:, :1], 1)[:, 0]
    acc = np.isfinite(best) & (best < threshold) & (best < ratio * second)
    s, t, dist = idx[acc], bj[acc], best[acc]
    # keep the best source per target keypoint
    o = np.lexsort((dist, t))
    s, t, dist = s[o], t[o], dist[o]
    first = np.ones(t.size, dtype=bool)
    first[1:] = t[1:] != t[:-1]
    return s[first], t[first], dist[first]


def sparse_matches(source: Source, targets: list[ViewFrame], estimate: np.ndarray, round_index: int,
                   schedule: SparseSchedule, max_prediction_error_mm: float = 6.0, workers: int = 1) -> Matches:
    """SIFT matches source -> target in every view for round ``round_index`` of the schedule, lifted to
    barycentric constraints. Weight = ``1 - distance / threshold``. ``workers`` threads share the views."""
    from rigbuild.track.matches import concat, map_views

    r = min(round_index, len(schedule.radius_px) - 1)

    def view_matches(v: int) -> Matches:
        tgt = targets[v]
        sv = source.views[v]
        scale = tgt.camera.width / 1280.0
        sp, sd = sift_features(sv.frame, schedule)
        tp, td = sift_features(tgt, schedule)
        if sv.cache.get("sift") is None:  # the source keypoints' surface points and anchors, once per source
            surface = sv.surface_points(sp)
            sv.cache["sift"] = (surface, sv.anchored(sp, surface=surface))
        (tri, bary, okp), anchored = sv.cache["sift"]
        pred = np.full((sp.shape[0], 2), np.nan)
        if okp.any():
            pred[okp] = source.predict(v, tri[okp], bary[okp], estimate)
        si, ti, dist = match_guided(sp, sd, pred, tp, td, schedule.radius_px[r] * max(scale, 0.25),
                                    schedule.descriptor_threshold[r], schedule.ratio)
        w = np.clip(1.0 - dist / schedule.descriptor_threshold[r], 0.05, 1.0)
        return lift_matches(source, v, anchored.subset(si), tp[ti], tgt, w, "sparse", estimate=estimate,
                            max_prediction_error_mm=max_prediction_error_mm)

    return concat(map_views(view_matches, len(targets), workers), "sparse")
