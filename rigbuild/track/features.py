"""Level 1 (face features): painted-dot detection, multi-view triangulation and lifting with depth maps.

The paper initializes with a facial landmark predictor: :mod:`rigbuild.track.landmarks` (the 468-point face
mesh network) and :mod:`rigbuild.track.landmarks3d` provide it for the neutral registration
(``registration.coarse: landmarks``). The default coarse level uses painted marker dots (the synthetic sessions
paint them near the rig's marker vertices; real sessions paint dots on the actor): dark, colourless discs on
skin, which are detected as connected components of pixels much darker than their neighbourhood and nearly
grey (skin and speckle are reddish).
"""

from __future__ import annotations

import cv2
import numpy as np

from rigbuild.camera import Camera
from rigbuild.track.params import ContrastDotParams, DotParams


def _mask_box(mask: np.ndarray, pad: int) -> tuple[int, int, int, int] | None:
    """(y0, y1, x0, x1): the box of ``mask``'s (H, W) True pixels grown by ``pad`` px and clipped to the image;
    None when the mask is empty."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if rows.size == 0:
        return None
    H, W = mask.shape
    return max(rows[0] - pad, 0), min(rows[-1] + pad + 1, H), max(cols[0] - pad, 0), min(cols[-1] + pad + 1, W)


def _on_mask_box(detect, image_rgb: np.ndarray, p, mask: np.ndarray, pad: int
                 ) -> tuple[np.ndarray, np.ndarray] | None:
    """``detect(image, p, mask)`` on the box of ``mask``'s pixels grown by ``pad`` px (a detector's filters
    reach that far), its centres shifted back to the whole image: (centres (N, 2), areas (N,)); no dots for an
    empty mask; None when the box is the whole image (the caller detects on it as it is)."""
    box = _mask_box(mask, pad)
    if box is None:
        return np.zeros((0, 2)), np.zeros(0)
    if box == (0, mask.shape[0], 0, mask.shape[1]):
        return None
    y0, y1, x0, x1 = box
    c, a = detect(np.asarray(image_rgb)[y0:y1, x0:x1], p, mask[y0:y1, x0:x1])
    return c + [x0, y0], a


def detect_dots(image_rgb: np.ndarray, params: DotParams | None = None, mask: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Detect painted dots in an RGB image (H, W, 3) uint8 with ``params.detector``: ``threshold`` (dark grey
    pixels below a fixed fraction of the local background, :func:`_detect_threshold`) or ``contrast`` (blobs of
    the contrast against the local skin at several scales, :func:`_detect_contrast`).

    mask : optional (H, W) bool region to search (e.g. where the face is).
    Returns centres (N, 2) float64 px (OpenCV pixel centres) and areas (N,) px.
    """
    p = params or DotParams()
    if np.ndim(image_rgb) != 3 or np.shape(image_rgb)[2] != 3:
        raise ValueError("detect_dots expects an (H, W, 3) RGB image")
    if p.detector == "contrast":
        return _detect_contrast(image_rgb, p.contrast, mask)
    return _detect_threshold(image_rgb, p, mask)


def _detect_threshold(image_rgb: np.ndarray, p: DotParams, mask: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The ``threshold`` detector: a pixel is a dot pixel when its brightest channel is below ``darkness`` times
    the local background and its red-minus-blue below ``chroma`` times it; components of [min_area, max_area]
    px and fill ratio >= ``min_fill`` are dots (darkness-weighted centroids)."""
    if mask is not None:  # work on the mask's box, padded past the blur and background filters' reach
        found = _on_mask_box(_detect_threshold, image_rgb, p, mask,
                             p.background_px + int(np.ceil(4 * p.blur_sigma)) + 2)
        if found is not None:
            return found
    img = np.asarray(image_rgb, dtype=np.float32)
    b = cv2.GaussianBlur(img, (0, 0), p.blur_sigma) if p.blur_sigma > 0 else img
    mx = np.maximum(np.maximum(b[..., 0], b[..., 1]), b[..., 2])
    bg = cv2.dilate(mx, np.ones((p.background_px, p.background_px), np.uint8))
    cand = (mx < p.darkness * bg) & ((b[..., 0] - b[..., 2]) < p.chroma * bg) & (bg > 20)
    if mask is not None:
        cand &= mask
    n, lab, stats, _ = cv2.connectedComponentsWithStats(cand.astype(np.uint8), 8)
    if n <= 1:
        return np.zeros((0, 2)), np.zeros(0)
    area = stats[1:, cv2.CC_STAT_AREA]
    fill = area / np.maximum(stats[1:, cv2.CC_STAT_WIDTH] * stats[1:, cv2.CC_STAT_HEIGHT], 1)
    ok = (area >= p.min_area) & (area <= p.max_area) & (fill >= p.min_fill)
    # darkness-weighted centroids
    wgt = np.clip(bg - mx, 0, None) * (lab > 0)
    ys, xs = np.nonzero(lab)
    labs = lab[ys, xs]
    ww = wgt[ys, xs]
    sw = np.bincount(labs, weights=ww, minlength=n)
    cx = np.bincount(labs, weights=ww * xs, minlength=n) / np.maximum(sw, 1e-9)
    cy = np.bincount(labs, weights=ww * ys, minlength=n) / np.maximum(sw, 1e-9)
    keep = np.flatnonzero(ok) + 1
    return np.stack([cx[keep], cy[keep]], axis=1), area[keep - 1].astype(np.float64)


def _fill_small_holes(mask: np.ndarray, max_area: int) -> np.ndarray:
    """``mask`` (H, W) bool with its holes (False components not touching the border) of at most
    ``max_area`` px set: a stereo reconstruction leaves such holes on dark, textureless painted dots."""
    inv = (~mask).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(inv, 4)
    if n <= 1:
        return mask
    H, W = mask.shape
    x, y = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    inner = (x > 0) & (y > 0) & (x + stats[:, cv2.CC_STAT_WIDTH] < W) & (y + stats[:, cv2.CC_STAT_HEIGHT] < H)
    fill = inner & (stats[:, cv2.CC_STAT_AREA] <= max_area)
    fill[0] = False
    return mask | fill[lab] & (inv > 0)


def dot_contrast(image_rgb: np.ndarray, params: ContrastDotParams | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Relative darkness of every pixel against its local background: ``C = 1 - I / B`` (H, W) float32,
    clipped to [0, 1], with I the brightest channel (Gaussian blur ``blur_sigma``) and B its grey-level
    closing by a disc of ``background_px`` (the surrounding skin: a closing removes dark marks narrower
    than the disc and follows the shading and highlights of the face, so C is a contrast that does not
    depend on the illumination). Also returns I and B."""
    p = params or ContrastDotParams()
    img = np.asarray(image_rgb, dtype=np.float32)
    b = cv2.GaussianBlur(img, (0, 0), p.blur_sigma) if p.blur_sigma > 0 else img
    mx = np.maximum(np.maximum(b[..., 0], b[..., 1]), b[..., 2])
    k = int(p.background_px) | 1
    bg = cv2.morphologyEx(mx, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    C = np.clip(1.0 - mx / np.maximum(bg, 1.0), 0.0, 1.0).astype(np.float32)
    return C, mx, bg


def _detect_contrast(image_rgb: np.ndarray, p: ContrastDotParams, mask: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The ``contrast`` dot detector on an RGB image (H, W, 3) uint8.

    A dot is a small, round dark blob. On the contrast image :func:`dot_contrast` (relative darkness
    against the local skin, so shading and highlights do not matter) the detector takes the local maxima
    of the scale-normalized Laplacian-of-Gaussian response ``R = -s^2 LoG_s * C`` over ``scales_px``
    (a disc of contrast c and radius r gives ``R = 2c/e`` at ``s = r / sqrt 2``: R / (2/e) estimates the
    dot's contrast whatever its size). A peak is a dot when that contrast estimate reaches
    ``max(1 - darkness, noise_sigmas x noise)`` (noise: the robust spread of R over the search region,
    which adapts the threshold to sensor noise and skin texture), the ratio of its two principal
    curvatures is at most ``max_elongation`` (eyebrows, lid creases, hair strands and lip lines are ridges,
    not blobs) and the pixels around it darker than half its contrast (its blob) number
    [min_area, max_area]. With ``chroma`` > 0 the blob's darkest pixel must also be less saturated
    ((R - B) / max(R, G, B)) than ``chroma`` times the background (grey paint under white light; off by
    default: under tinted light, Bayer demosaicing and JPEG chroma subsampling dark paint takes the skin's
    hue).

    mask : optional (H, W) bool region to search (e.g. where the face is); it is closed by a
    ``background_px`` disc and its holes of at most ``max_area`` px are filled (a stereo reconstruction
    leaves holes on the dark, textureless dots themselves, and notches where they sit at its edge).
    Returns centres (N, 2) float64 px (OpenCV pixel centres; contrast-weighted centroids of the blobs)
    and blob areas (N,) px.
    """
    if mask is not None:  # work on the mask's box, padded past the blur and background filters' reach
        k = int(p.background_px) | 1  # the dots' stereo holes and notches at the edge are searched too
        mask = cv2.morphologyEx(np.asarray(mask, np.uint8), cv2.MORPH_CLOSE,
                                cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0
        mask = _fill_small_holes(mask, p.max_area)
        found = _on_mask_box(_contrast_peaks, image_rgb, p, mask,
                             p.background_px + int(np.ceil(4 * (p.blur_sigma + max(p.scales_px)))) + 2)
        if found is not None:
            return found
    return _contrast_peaks(image_rgb, p, mask)


def _hessian(S: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    dxx = cv2.Sobel(S, cv2.CV_32F, 2, 0, ksize=1, borderType=cv2.BORDER_REFLECT)
    dyy = cv2.Sobel(S, cv2.CV_32F, 0, 2, ksize=1, borderType=cv2.BORDER_REFLECT)
    dxy = cv2.Sobel(S, cv2.CV_32F, 1, 1, ksize=3, borderType=cv2.BORDER_REFLECT) / 4.0
    return dxx, dyy, dxy


_DISC_PEAK = 2.0 / np.e  # scale-normalized LoG response of a unit-contrast disc at its best scale


def _contrast_peaks(image_rgb: np.ndarray, p: ContrastDotParams, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    C, mx, bg = dot_contrast(image_rgb, p)
    region = (bg > 20) if mask is None else (mask & (bg > 20))
    if not region.any():
        return np.zeros((0, 2)), np.zeros(0)
    best = np.full(C.shape, -np.inf, np.float32)
    ratio = np.zeros(C.shape, np.float32)
    scale = np.zeros(C.shape, np.float32)
    noise = 0.0
    for s in p.scales_px:
        S = cv2.GaussianBlur(C, (0, 0), s)
        dxx, dyy, dxy = _hessian(S)
        R = -(s * s) * (dxx + dyy) / _DISC_PEAK  # contrast units
        vals = R[region]
        noise = max(noise, 1.4826 * float(np.median(np.abs(vals - np.median(vals)))))
        # principal curvatures (of -S: positive on a blob); their ratio
        tr, det = -(dxx + dyy), dxx * dyy - dxy * dxy
        disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0))
        k1, k2 = tr / 2 + disc, tr / 2 - disc
        rt = np.where(k2 > 0, k1 / np.maximum(k2, 1e-12), np.inf).astype(np.float32)
        up = R > best
        best[up], ratio[up], scale[up] = R[up], rt[up], s
    thr = max(1.0 - p.darkness, p.noise_sigmas * noise)
    peak = (best >= thr) & (best >= cv2.dilate(best, np.ones((3, 3), np.uint8))) & region
    peak &= ratio <= p.max_elongation
    ys, xs = np.nonzero(peak)
    if ys.size == 0:
        return np.zeros((0, 2)), np.zeros(0)
    H, W = C.shape
    img = np.asarray(image_rgb, dtype=np.float32) if p.chroma > 0 else None
    out, areas, taken = [], [], np.zeros(C.shape, bool)
    for i in np.argsort(-best[ys, xs]):
        y, x = int(ys[i]), int(xs[i])
        if taken[y, x]:
            continue
        r = int(np.ceil(2.5 * scale[y, x])) + 1
        ya, yb, xa, xb = max(y - r, 0), min(y + r + 1, H), max(x - r, 0), min(x + r + 1, W)
        win = C[ya:yb, xa:xb]
        c0 = float(win[max(y - ya - 1, 0):y - ya + 2, max(x - xa - 1, 0):x - xa + 2].max())
        blob = (win >= 0.5 * c0).astype(np.uint8)
        n, lab = cv2.connectedComponents(blob, connectivity=8)
        L = lab[y - ya, x - xa]
        if L == 0:
            continue
        comp = lab == L
        area = int(comp.sum())
        if area < p.min_area or area > p.max_area:
            continue
        touches = comp[0].any() or comp[-1].any() or comp[:, 0].any() or comp[:, -1].any()
        if touches and area > 0.5 * comp.size:  # part of a larger dark region, not a dot
            continue
        if img is not None:
            wy, wx = np.unravel_index(np.argmax(np.where(comp, win, -1)), win.shape)
            pix = img[ya + wy, xa + wx]
            ring = img[ya:yb, xa:xb][~comp & (win < 0.25 * c0)]
            if ring.shape[0]:
                sk = np.median(ring, axis=0)
                cp = (pix[0] - pix[2]) / max(pix.max(), 1.0)
                cs = (sk[0] - sk[2]) / max(sk.max(), 1.0)
                if cp >= p.chroma * max(cs, 0.05):
                    continue
        w = np.where(comp, win - 0.5 * c0, 0.0).astype(np.float64)
        gy, gx = np.mgrid[ya:yb, xa:xb]
        sw = max(w.sum(), 1e-12)
        out.append(((w * gx).sum() / sw, (w * gy).sum() / sw))
        areas.append(area)
        taken[ya:yb, xa:xb] |= comp
    if not out:
        return np.zeros((0, 2)), np.zeros(0)
    return np.asarray(out, np.float64), np.asarray(areas, np.float64)


def _pixel_cells(shape: tuple[int, int], uv: np.ndarray):
    """For pixels uv (N, 2) in an (H, W) image: the in-image mask (N,) and, for those, the top-left
    corner (u0, v0) of their 2x2 cell and the fractional offsets (du, dv)."""
    H, W = shape
    u = np.asarray(uv, dtype=np.float64)[:, 0]
    v = np.asarray(uv, dtype=np.float64)[:, 1]
    ok = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (v >= 0) & (u <= W - 1) & (v <= H - 1)
    u0 = np.minimum(np.floor(u[ok]).astype(np.int64), W - 2)
    v0 = np.minimum(np.floor(v[ok]).astype(np.int64), H - 2)
    return ok, u0, v0, u[ok] - u0, v[ok] - v0


def _bilinear_in_cells(img: np.ndarray, cells) -> np.ndarray:
    ok, u0, v0, du, dv = cells
    out = np.full(ok.shape, np.nan)
    c00, c01 = img[v0, u0].astype(np.float64), img[v0, u0 + 1].astype(np.float64)
    c10, c11 = img[v0 + 1, u0].astype(np.float64), img[v0 + 1, u0 + 1].astype(np.float64)
    out[ok] = (1 - du) * (1 - dv) * c00 + du * (1 - dv) * c01 + (1 - du) * dv * c10 + du * dv * c11
    return out


def _spread_in_cells(d: np.ndarray, cells) -> np.ndarray:
    ok, u0, v0, _, _ = cells
    out = np.full(ok.shape, np.nan)
    a, b, c, e = d[v0, u0], d[v0, u0 + 1], d[v0 + 1, u0], d[v0 + 1, u0 + 1]
    hi = np.maximum(np.maximum(a, b), np.maximum(c, e))  # NaN anywhere -> NaN, as a max over the four
    lo = np.minimum(np.minimum(a, b), np.minimum(c, e))
    out[ok] = hi.astype(np.float64) - lo.astype(np.float64)
    return out


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear sample of a (H, W) float image at pixels uv (N, 2); NaN outside or next to NaN."""
    img = np.asarray(image)  # indexed first, converted after (no full-image float64 copy per call)
    return _bilinear_in_cells(img, _pixel_cells(img.shape, uv))


def depth_discontinuity(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Max minus min of the 2x2 depth neighbourhood at uv (N,) (mm); NaN where any is NaN/outside."""
    d = np.asarray(depth)
    return _spread_in_cells(d, _pixel_cells(d.shape, uv))


def window_median_depth(depth: np.ndarray, uv: np.ndarray, radius_px: int, max_spread_mm: float) -> np.ndarray:
    """(N,) median of the valid depths in the (2r+1)^2 window around each pixel uv (N, 2); NaN where the
    window has fewer than a quarter valid pixels or their 10-90 percentile spread exceeds ``max_spread_mm``
    (a depth edge). For small holes a stereo reconstruction leaves on dark, textureless marks such as
    painted dots: the surrounding skin gives the depth."""
    d = np.asarray(depth, dtype=np.float64)
    H, W = d.shape
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    out = np.full(uv.shape[0], np.nan)
    r = int(radius_px)
    for i, (u, v) in enumerate(uv):
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        x0, y0 = int(round(u)), int(round(v))
        win = d[max(y0 - r, 0):min(y0 + r + 1, H), max(x0 - r, 0):min(x0 + r + 1, W)]
        vals = win[np.isfinite(win)]
        if vals.size < max(win.size // 4, 1):
            continue
        lo, hi = np.percentile(vals, [10, 90])
        if hi - lo <= max_spread_mm:
            out[i] = float(np.median(vals))
    return out


def lift(camera: Camera, depth: np.ndarray, uv: np.ndarray, max_step_mm: float = 2.0,
         fill_radius_px: int = 0) -> np.ndarray:
    """Lift pixels uv (N, 2) to world points (N, 3) mm with a camera-z depth map (H, W) mm (NaN = none).

    Points on a depth discontinuity (2x2 neighbourhood spread > ``max_step_mm``) or without depth are NaN;
    with ``fill_radius_px`` > 0 those without depth take :func:`window_median_depth` instead (spread up to
    twice ``max_step_mm``).
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    z = sample_bilinear(depth, uv)
    step = depth_discontinuity(depth, uv)
    z[~(step <= max_step_mm)] = np.nan
    if fill_radius_px > 0:
        hole = ~np.isfinite(z)
        if hole.any():
            z[hole] = window_median_depth(depth, uv[hole], fill_radius_px, 2.0 * max_step_mm)
    out = np.full((uv.shape[0], 3), np.nan)
    ok = np.isfinite(z)
    if ok.any():
        xy = camera.undistort_points(uv[ok])
        Xc = np.hstack([xy, np.ones((xy.shape[0], 1))]) * z[ok, None]
        out[ok] = (Xc - camera.t) @ camera.R  # R^T (Xc - t)
    return out


def triangulate(cameras: list[Camera], uv: np.ndarray, valid: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares multi-view triangulation of M points seen in C views (midpoint of rays, exact
    for consistent rays).

    cameras : C cameras; uv : (C, M, 2) px (NaN = not seen); valid : optional (C, M) bool.
    Returns X (M, 3) mm (NaN where fewer than 2 views), reprojection RMS (M,) px, views used (M,).
    """
    uv = np.asarray(uv, dtype=np.float64)
    C, M, _ = uv.shape
    ok = np.isfinite(uv).all(axis=2) if valid is None else (np.asarray(valid) & np.isfinite(uv).all(axis=2))
    A = np.zeros((M, 3, 3))
    b = np.zeros((M, 3))
    for c, cam in enumerate(cameras):
        m = ok[c]
        if not m.any():
            continue
        d = cam.rays(uv[c, m])
        P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
        A[m] += P
        b[m] += P @ cam.center
    n = ok.sum(0)
    X = np.full((M, 3), np.nan)
    good = n >= 2
    if good.any():
        X[good] = np.linalg.solve(A[good], b[good][:, :, None])[:, :, 0]
    err = np.zeros((M,))
    cnt = np.zeros(M)
    for c, cam in enumerate(cameras):
        m = ok[c] & good
        if m.any():
            e = np.linalg.norm(cam.project(X[m]) - uv[c, m], axis=1)
            err[m] += e ** 2
            cnt[m] += 1
    rms = np.where(cnt > 0, np.sqrt(err / np.maximum(cnt, 1)), np.nan)
    return X, rms, n


def assign_detections(predicted: np.ndarray, detections: np.ndarray, radius_px: float,
                      ambiguity_ratio: float = 1.5) -> np.ndarray:
    """Label detections by predicted positions: (M,) index into detections (N, 2) for each prediction (M, 2)
    (NaN predictions allowed), or -1. One-to-one (Hungarian), gated at ``radius_px``; an assignment is
    dropped when another detection (or another prediction) is within ``ambiguity_ratio`` times its distance
    (ambiguous)."""
    from scipy.optimize import linear_sum_assignment

    M = predicted.shape[0]
    out = np.full(M, -1, dtype=np.int64)
    okp = np.isfinite(predicted).all(1)
    if not okp.any() or detections.shape[0] == 0:
        return out
    idx = np.flatnonzero(okp)
    cost = np.linalg.norm(predicted[idx, None, :] - detections[None], axis=2)
    r, c = linear_sum_assignment(np.minimum(cost, 10 * radius_px))
    d1 = cost[r, c]
    good = d1 <= radius_px
    if ambiguity_ratio > 1.0:
        other_det = cost[r].copy()
        other_det[np.arange(r.size), c] = np.inf
        other_pred = cost[:, c].copy()
        other_pred[r, np.arange(r.size)] = np.inf
        second = np.minimum(other_det.min(1) if other_det.shape[1] else np.inf,
                            other_pred.min(0) if other_pred.shape[0] else np.inf)
        good &= second > ambiguity_ratio * np.maximum(d1, 0.5)
    out[idx[r[good]]] = c[good]
    return out


def cluster_lifted_dots(points_per_view: list[np.ndarray], radius_mm: float = 2.5, min_views: int = 2
                        ) -> list[list[tuple[int, int]]]:
    """Group dots lifted to 3-D in several views into physical dots (unlabeled, first frame).

    points_per_view : C arrays (N_c, 3) mm (NaN rows ignored). Greedy clustering: each dot takes, from every
    other view, the nearest lifted dot within ``radius_mm``. Returns clusters as lists of (view, index) with
    at least ``min_views`` members.
    """
    from scipy.spatial import cKDTree

    trees = [cKDTree(np.nan_to_num(p, nan=1e12)) if p.shape[0] else None for p in points_per_view]
    used = [np.zeros(p.shape[0], dtype=bool) for p in points_per_view]
    clusters = []
    for c, pts in enumerate(points_per_view):
        for i in range(pts.shape[0]):
            if used[c][i] or not np.isfinite(pts[i]).all():
                continue
            members = [(c, i)]
            for c2, tree in enumerate(trees):
                if c2 == c or tree is None:
                    continue
                d, j = tree.query(pts[i])
                if d <= radius_mm and not used[c2][j]:
                    members.append((c2, int(j)))
            if len(members) >= min_views:
                for cc, ii in members:
                    used[cc][ii] = True
                clusters.append(members)
    return clusters


def image_to_pinhole_cells(camera: Camera, K_pinhole: np.ndarray, pinhole_shape: tuple[int, int]):
    """Where each pixel of ``camera``'s distorted (H, W) image grid falls on its undistorted pinhole grid
    (intrinsics ``K_pinhole`` (3, 3), grid ``pinhole_shape`` (H', W')): the 2x2 cells and bilinear offsets
    (:func:`_pixel_cells`) of the H * W pixels. Constant per camera: :func:`depth_to_image_grid` reuses it for
    every frame (``cells=``)."""
    K = np.asarray(K_pinhole, dtype=np.float64)
    H, W = camera.height, camera.width
    ys, xs = np.mgrid[0:H, 0:W]
    uv = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    xy = camera.undistort_points(uv)
    pu = xy[:, 0] * K[0, 0] + xy[:, 1] * K[0, 1] + K[0, 2]
    pv = xy[:, 1] * K[1, 1] + K[1, 2]
    return _pixel_cells(tuple(pinhole_shape), np.stack([pu, pv], 1))


def depth_to_image_grid(depth_pinhole: np.ndarray, camera: Camera, K_pinhole: np.ndarray | None = None,
                        max_step_mm: float = 2.0, cells=None) -> np.ndarray:
    """Resample a depth map computed on the undistorted pinhole grid of ``camera`` (same R, t; intrinsics
    ``K_pinhole``, default ``camera.K``; 0 or NaN = none) onto the camera's distorted image grid, so it is
    aligned with the images. Returns (H, W) float32 camera z in mm, NaN where none (or across a jump).
    ``cells``: :func:`image_to_pinhole_cells` of this camera, computed once for a sequence (None: here)."""
    d = np.asarray(depth_pinhole, dtype=np.float32).copy()
    d[~(d > 0)] = np.nan
    if not np.any(camera.dist):
        if K_pinhole is None or np.allclose(K_pinhole, camera.K):
            return d
    if cells is None:
        cells = image_to_pinhole_cells(camera, camera.K if K_pinhole is None else K_pinhole, d.shape)
    z = _bilinear_in_cells(np.nan_to_num(d, nan=0.0), cells)
    step = _spread_in_cells(d, cells)
    z[~(step <= max_step_mm)] = np.nan
    z[~(z > 0)] = np.nan
    return z.reshape(camera.height, camera.width).astype(np.float32)


def surface_neighbours(vertices: np.ndarray, faces: np.ndarray, sources: np.ndarray, k: int = 5,
                       limit_mm: float = 60.0) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` nearest other sources of each source vertex along the mesh's edges (geodesic-like: the
    lips are far apart through the mouth corners although close in space).

    vertices (V, 3) mm, faces (F, 3), sources (S,) vertex ids. Returns neighbours (S, k) indices into
    ``sources`` (-1 where fewer than k lie within ``limit_mm``) and their distances (S, k) mm (inf there).
    """
    import igl
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra

    V = np.asarray(vertices, np.float64)
    e = np.asarray(igl.edges(np.asarray(faces, np.int64)), np.int64)  # unique undirected edges
    w = np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1)
    G = sp.coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(V.shape[0],) * 2).tocsr()
    src = np.asarray(sources, np.int64)
    D = dijkstra(G, indices=src, limit=limit_mm)[:, src]
    np.fill_diagonal(D, np.inf)
    order = np.argsort(D, axis=1)[:, :k]
    dist = np.take_along_axis(D, order, 1)
    return np.where(np.isfinite(dist), order, -1), dist


def consistent_displacements(displacements: np.ndarray, present: np.ndarray, neighbours: np.ndarray,
                             tolerance_mm: float, min_neighbours: int = 1) -> np.ndarray:
    """Which labeled points move like their neighbours: (S,) bool.

    displacements (S, 3) mm (target minus predicted position; rows where ``present`` is False are ignored);
    neighbours (S, k) from :func:`surface_neighbours`. A present point is inconsistent when its displacement
    differs from the per-axis median of its present neighbours' displacements by more than ``tolerance_mm``
    (a dot assigned to its neighbour's detection after a large motion is off by about one dot spacing);
    points with fewer than ``min_neighbours`` present neighbours are kept.
    """
    d = np.asarray(displacements, np.float64)
    present = np.asarray(present, bool)
    nb = np.asarray(neighbours, np.int64)
    ok_nb = (nb >= 0) & present[np.maximum(nb, 0)]
    vals = np.where(ok_nb[..., None], d[np.maximum(nb, 0)], np.nan)
    enough = ok_nb.sum(1) >= min_neighbours
    med = np.full(d.shape, np.nan)
    if enough.any():
        med[enough] = np.nanmedian(vals[enough], axis=1)
    dev = np.linalg.norm(d - med, axis=1)
    return present & (~enough | (dev <= tolerance_mm))
