"""Level 3: dense optical flow per view, guided by the motion field rendered from the current mesh.

The target image is warped back by the rendered motion field (so only the residual motion is left),
DIS optical flow (OpenCV, coarse to fine on a Gaussian pyramid with patch-based inverse search) measures
the residual from the source image to the warped target, and the total flow is residual + motion field
at the residually displaced position. A backward flow gives a forward-backward consistency error that
weights each match. Matches are taken on a regular grid of source pixels inside the rendered mesh.
"""

from __future__ import annotations

import cv2
import numpy as np

from rigbuild.track.features import sample_bilinear
from rigbuild.track.matches import (
    Matches,
    Source,
    SourcePoints,
    SourceView,
    ViewFrame,
    concat,
    lift_matches,
    map_views,
)
from rigbuild.track.params import FlowParams

_PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
            "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}


def guided_flow(src_gray: np.ndarray, tgt_gray: np.ndarray, motion: np.ndarray, preset: str = "medium"
                ) -> tuple[np.ndarray, np.ndarray]:
    """Total flow (H, W, 2) px from source to target and forward-backward error (H, W) px.

    motion (H, W, 2): guide displacement (NaN = none, treated as 0).
    """
    H, W = src_gray.shape
    m = np.nan_to_num(motion, nan=0.0).astype(np.float32)
    gx, gy = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    warped = cv2.remap(tgt_gray, gx + m[..., 0], gy + m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    dis = cv2.DISOpticalFlow_create(_PRESETS[preset])
    fwd = dis.calc(src_gray, warped, None)
    bwd = dis.calc(warped, src_gray, None)
    # forward-backward consistency of the residual flow
    bx = cv2.remap(bwd, gx + fwd[..., 0], gy + fwd[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    fb = np.linalg.norm(fwd + bx, axis=2)
    # total: x -> x + r(x) in the warped image -> x + r + m(x + r) in the target
    mr = cv2.remap(m, gx + fwd[..., 0], gy + fwd[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return fwd + mr, fb


def m_at(guide: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """Guide displacement (H, W, 2) sampled at x + flow(x) (bilinear, replicated border)."""
    H, W = guide.shape[:2]
    gx, gy = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    return cv2.remap(guide, gx + flow[..., 0], gy + flow[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def residual_flow(src_gray: np.ndarray, warped_gray: np.ndarray, preset: str, scale: float = 1.0,
                  backward: bool = True, patch_stride: int = 0) -> tuple[np.ndarray, np.ndarray | None]:
    """DIS flow (H, W, 2) px from ``src_gray`` to the guide-warped target and its forward-backward error
    (H, W) px. ``scale`` < 1 computes the flow on images resized by ``scale`` (the residual after the guide
    is small and smooth) and brings it back to full resolution. ``backward=False`` skips the backward flow
    (the error is then None)."""
    H, W = src_gray.shape
    if scale < 1.0:
        size = (max(int(round(W * scale)), 8), max(int(round(H * scale)), 8))
        a = cv2.resize(src_gray, size, interpolation=cv2.INTER_AREA)
        b = cv2.resize(warped_gray, size, interpolation=cv2.INTER_AREA)
    else:
        a, b = src_gray, warped_gray
    dis = cv2.DISOpticalFlow_create(_PRESETS[preset])
    if patch_stride > 0:
        dis.setPatchStride(int(patch_stride))
    fwd = dis.calc(a, b, None)
    h, w = a.shape
    fb = None
    if backward:
        bwd = dis.calc(b, a, None)
        gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        bx = cv2.remap(bwd, gx + fwd[..., 0], gy + fwd[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        e = fwd + bx
        fb = cv2.magnitude(np.ascontiguousarray(e[..., 0]), np.ascontiguousarray(e[..., 1]))
    if scale < 1.0:
        fwd = cv2.resize(fwd, (W, H), interpolation=cv2.INTER_LINEAR) * np.float32(W / w)
        if fb is not None:
            fb = cv2.resize(fb, (W, H), interpolation=cv2.INTER_LINEAR) * np.float32(W / w)
    return fwd, fb


def points_flow(src_gray: np.ndarray, tgt_gray: np.ndarray, points: np.ndarray, scale: float = 0.5,
                pad_px: int = 160, preset: str = "medium") -> np.ndarray:
    """Image motion (N, 2) px of ``points`` (N, 2) px from ``src_gray`` to ``tgt_gray`` (H, W): DIS flow
    (unguided, coarse to fine) over the box around the points padded by ``pad_px``, computed at ``scale``
    and sampled bilinearly; NaN points stay NaN (and give NaN)."""
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    out = np.full(pts.shape, np.nan)
    ok = np.isfinite(pts).all(1)
    if not ok.any():
        return out
    H, W = src_gray.shape
    x0, y0 = np.maximum(np.floor(pts[ok].min(0)).astype(int) - pad_px, 0)
    x1, y1 = np.minimum(np.ceil(pts[ok].max(0)).astype(int) + pad_px + 1, [W, H])
    if x1 - x0 < 8 or y1 - y0 < 8:
        return out
    flow, _ = residual_flow(np.ascontiguousarray(src_gray[y0:y1, x0:x1]),
                            np.ascontiguousarray(tgt_gray[y0:y1, x0:x1]), preset, scale, backward=False)
    q = pts[ok] - [x0, y0]
    out[ok, 0] = sample_bilinear(np.ascontiguousarray(flow[..., 0]), q)
    out[ok, 1] = sample_bilinear(np.ascontiguousarray(flow[..., 1]), q)
    return out


def flow_grid(sv: SourceView, box: tuple[int, int, int, int], step: int) -> tuple[np.ndarray, SourcePoints]:
    """The dense level's source pixels of one view: the grid ``box`` origin + ``step // 2`` + ``step`` k
    (uv (gy, gx, 2) px) and their anchors on the source mesh, cached on the view (the anchor source is
    matched on every frame of a sequence; its grid is anchored once). The surface points come from the
    motion field's grid where that grid contains this one."""
    key = ("flow_grid", tuple(int(b) for b in box), step)
    if key not in sv.cache:
        grid, tri, bary, ok = sv.grid_surface_points(key[1], step, offset=step // 2)
        sv.cache[key] = (grid, sv.anchored(grid.reshape(-1, 2), surface=(tri, bary, ok)))
    return sv.cache[key]


def flow_matches(source: Source, targets: list[ViewFrame], estimate: np.ndarray, params: FlowParams,
                 max_prediction_error_mm: float = 3.0, workers: int = 1) -> Matches:
    """Dense guided-flow matches source -> target in every view, lifted to barycentric constraints.
    Weight = ``exp(-fb^2 / (2 sigma^2))``. Only the box around the source's observed surface is processed;
    the guide (motion field) is sampled every ``motion_step`` px, the flow runs at ``scale``. ``workers``
    threads share the views."""

    def view_matches(v: int) -> Matches | None:
        tgt = targets[v]
        sv = source.views[v]
        box = sv.surface_box(pad=16)
        if box is None:
            return None
        y0, y1, x0, x1 = box
        motion = source.motion_field(v, estimate, step=params.motion_step, box=box)
        # the target crop is the source crop moved by the guide; remap works in full-image coordinates
        gx, gy = np.meshgrid(np.arange(x0, x1, dtype=np.float32), np.arange(y0, y1, dtype=np.float32))
        m = np.nan_to_num(motion, nan=0.0).astype(np.float32)
        warped = cv2.remap(tgt.gray, gx + m[..., 0], gy + m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        flow, fb = residual_flow(np.ascontiguousarray(sv.frame.gray[y0:y1, x0:x1]), warped, params.preset, params.scale,
                                  patch_stride=params.patch_stride)
        flow = flow + m_at(m, flow)  # total = residual + guide at the residually displaced position
        step = max(2, int(round(params.grid_px * tgt.camera.width / 1280.0)))
        grid, anchored = flow_grid(sv, box, step)
        xs = grid[..., 0].astype(np.int64).ravel() - x0
        ys = grid[..., 1].astype(np.int64).ravel() - y0
        sel = np.isfinite(motion[ys, xs, 0]) & (fb[ys, xs] <= params.max_fb_px) & anchored.ok
        idx = np.flatnonzero(sel)
        xs, ys = xs[idx], ys[idx]
        tgt_uv = grid.reshape(-1, 2)[idx] + flow[ys, xs].astype(np.float64)
        w = np.exp(-fb[ys, xs].astype(np.float64) ** 2 / (2 * params.fb_sigma_px ** 2))
        return lift_matches(source, v, anchored.subset(idx), tgt_uv, tgt, w, "flow", estimate=estimate,
                            max_prediction_error_mm=max_prediction_error_mm)

    out = [m for m in map_views(view_matches, len(targets), workers) if m is not None]
    return concat(out, "flow")
