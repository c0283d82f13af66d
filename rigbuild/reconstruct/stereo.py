"""Per-view depth and confidence by coarse-to-fine multi-view plane sweep with NCC (CPU).

Conventions
-----------
Images are undistorted first (:func:`undistort_view`) onto a pinhole grid with the *same* ``K`` (pixel
centres at integer coordinates, OpenCV); depth maps live on that grid and hold the camera-frame ``z``
in mm (0 = no depth). ``rigbuild.reconstruct.lift.depth_at`` maps original (distorted) pixels to 3-D.

Algorithm (per reference view ``r`` with neighbour views ``j``)
---------------------------------------------------------------
For a reference pixel ``x`` (homogeneous) with inverse depth ``q = 1/z``, its image in view ``j`` is
``p ~ a(x) + q e`` with ``a = K_j R_rj K_r^-1 x`` and ``e = K_j t_rj`` (``X_j = R_rj X_r + t_rj``), i.e.
linear in ``q``. A Gaussian pyramid is swept coarse to fine:

1. coarsest level: every pixel tests the same inverse depths (fronto-parallel planes uniformly spaced in
   ``q`` so that the largest image displacement between planes is ``sweep_step_px``);
2. finer levels: the upsampled map ``q0`` is refined by testing ``q0 + k dq`` for ``k = -R..R``; each
   hypothesis shifts the whole current surface, so windows follow its slant;
3. at every level the matching cost of a hypothesis is the normalized cross-correlation (NCC) of the
   reference window with the neighbour image warped through the hypothesis, averaged over the ``top_k``
   best neighbours (occlusion robustness), and the best hypothesis is refined to sub-step precision by a
   parabola through the scores at ``k-1, k, k+1``.

Everything is vectorized over the pixels of a region of interest (the foreground mask's bounding box).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import cv2
import numpy as np

from rigbuild.camera import Camera
from rigbuild.errors import InputError
from rigbuild.reconstruct.params import StereoParams  # noqa: F401 (the parameters of compute_depth_map)


# ----------------------------------------------------------------------------------------- images
def to_gray_float(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) uint8/uint16/float image -> (H, W) float32 grey in [0, 1]."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.shape[2] == 3 else img[..., 0]
    if img.dtype == np.uint8:
        return img.astype(np.float32) / 255.0
    if img.dtype == np.uint16:
        return img.astype(np.float32) / 65535.0
    return img.astype(np.float32)


def pinhole(camera: Camera) -> Camera:
    """The same camera without distortion (the grid depth maps and undistorted images live on)."""
    return Camera(camera.id, camera.width, camera.height, camera.K, np.zeros(5), camera.R, camera.t)


def undistort_view(image: np.ndarray, camera: Camera) -> tuple[np.ndarray, Camera]:
    """Resample a distorted image onto the pinhole grid of the same ``K``.

    Returns the undistorted image (same shape and dtype) and :func:`pinhole` ``(camera)``.
    """
    if image.shape[0] != camera.height or image.shape[1] != camera.width:
        raise InputError(f"image is {image.shape[1]}x{image.shape[0]} but camera {camera.id} is "
                         f"{camera.width}x{camera.height}", fix="check cameras.json against the session images")
    if not np.any(camera.dist):
        return image, pinhole(camera)
    m1, m2 = cv2.initUndistortRectifyMap(camera.K, camera.dist, None, camera.K, (camera.width, camera.height),
                                         cv2.CV_32FC1)
    return cv2.remap(image, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT), pinhole(camera)


# ------------------------------------------------------------------------------------ view layout
def optical_axis(camera: Camera) -> np.ndarray:
    """(3,) unit viewing direction in world coordinates."""
    return camera.R[2].copy()


def convergence_point(cameras: Sequence[Camera]) -> np.ndarray:
    """(3,) world point (mm) closest in least squares to all optical axes."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in cameras:
        d = optical_axis(c)
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    return np.linalg.lstsq(A, b, rcond=None)[0]


def select_neighbours(cameras: Sequence[Camera], n_neighbours: int, min_angle_deg: float = 5.0,
                      max_angle_deg: float = 50.0) -> list[list[int]]:
    """For each camera the indices of up to ``n_neighbours`` others, nearest in optical-axis angle.

    Cameras closer than ``min_angle_deg`` (too small a baseline) or farther than ``max_angle_deg`` are
    not used.
    """
    D = np.stack([optical_axis(c) for c in cameras])
    ang = np.degrees(np.arccos(np.clip(D @ D.T, -1, 1)))
    out = []
    for i in range(len(cameras)):
        order = [j for j in np.argsort(ang[i]) if j != i and min_angle_deg <= ang[i, j] <= max_angle_deg]
        out.append([int(j) for j in order[:n_neighbours]])
    return out


def auto_depth_range(camera: Camera, cameras: Sequence[Camera], radius_mm: float) -> tuple[float, float]:
    """``(near, far)`` z range of ``camera``: its depth of the convergence point +- ``radius_mm``."""
    z = float(camera.world_to_camera(convergence_point(cameras))[2])
    return max(z - radius_mm, 0.1 * z), z + radius_mm


# ------------------------------------------------------------------------------------------- NCC
class _RefStats:
    """Box-filter statistics of a reference image crop for NCC with window ``w``."""

    def __init__(self, ref: np.ndarray, w: int):
        self.w = w
        self.ref = ref
        self.mean = cv2.boxFilter(ref, -1, (w, w), borderType=cv2.BORDER_REFLECT)
        var = cv2.boxFilter(ref * ref, -1, (w, w), borderType=cv2.BORDER_REFLECT) - self.mean ** 2
        self.std = np.sqrt(np.maximum(var, 0.0))


def ncc(stats: _RefStats, warped: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Windowed NCC between the reference of ``stats`` and ``warped`` (same shape), in [-1, 1].

    ``valid`` (bool, same shape): where False (sample outside the neighbour image) the score is -1.
    """
    w = stats.w
    box = (w, w)
    mw = cv2.boxFilter(warped, -1, box, borderType=cv2.BORDER_REFLECT)
    mww = cv2.boxFilter(cv2.multiply(warped, warped), -1, box, borderType=cv2.BORDER_REFLECT)
    mrw = cv2.boxFilter(cv2.multiply(stats.ref, warped), -1, box, borderType=cv2.BORDER_REFLECT)
    var_w = cv2.subtract(mww, cv2.multiply(mw, mw))
    np.maximum(var_w, 0.0, out=var_w)
    den = cv2.multiply(stats.std, cv2.sqrt(var_w))
    den += 1e-6
    s = cv2.divide(cv2.subtract(mrw, cv2.multiply(stats.mean, mw)), den)
    if valid is not None:
        s[~valid] = -1.0
    return s


class _PairGeometry:
    """Precomputed ``a = K_j R_rj K_r^-1 x`` (per pixel of a crop) and ``e = K_j t_rj`` for one level."""

    def __init__(self, ref: Camera, nbr: Camera, scale: float, us: np.ndarray, vs: np.ndarray):
        S = np.diag([scale, scale, 1.0])
        Kr, Kj = S @ ref.K, S @ nbr.K
        R_rj = nbr.R @ ref.R.T
        t_rj = nbr.t - R_rj @ ref.t
        M = (Kj @ R_rj @ np.linalg.inv(Kr)).astype(np.float64)
        self.e = (Kj @ t_rj).astype(np.float32)
        U, V = np.meshgrid(us.astype(np.float64), vs.astype(np.float64))
        self.a = [(M[i, 0] * U + M[i, 1] * V + M[i, 2]).astype(np.float32) for i in range(3)]

    def project(self, q: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Neighbour pixel coordinates (mapx, mapy) float32 for inverse depth ``q`` and in-front flag."""
        e = self.e
        den = self.a[2] + q * e[2]
        front = den > 1e-9
        inv = np.reciprocal(np.maximum(den, np.float32(1e-9)))
        mx = self.a[0] + q * e[0]
        mx *= inv
        my = self.a[1] + q * e[1]
        my *= inv
        return mx, my, front

    def displacement_per_q(self, q: float) -> float:
        """Largest |d(pixel)/dq| over the crop's corners and centre at inverse depth ``q`` (pixels per 1/mm)."""
        h = 1e-7
        x0, y0, _ = self.project(q)
        x1, y1, _ = self.project(q + h)
        d = np.hypot(x1 - x0, y1 - y0) / h
        H, W = d.shape
        pts = [d[0, 0], d[0, -1], d[-1, 0], d[-1, -1], d[H // 2, W // 2]]
        return float(np.max(pts))


def _warp(img: np.ndarray, mapx: np.ndarray, mapy: np.ndarray, interp: int) -> tuple[np.ndarray, np.ndarray]:
    H, W = img.shape
    valid = (mapx >= 0) & (mapx <= W - 1) & (mapy >= 0) & (mapy <= H - 1)
    return cv2.remap(img, mapx, mapy, interp, borderMode=cv2.BORDER_REPLICATE), valid


def _aggregate(scores: list[np.ndarray], top_k: int) -> np.ndarray:
    if len(scores) == 1:
        return scores[0]
    k = min(top_k, len(scores))
    if k == 1:
        acc = scores[0].copy()
        for s in scores[1:]:
            np.maximum(acc, s, out=acc)
        return acc
    if k == len(scores):
        acc = scores[0].copy()
        for s in scores[1:]:
            acc += s
        return acc * np.float32(1.0 / k)
    s = np.sort(np.stack(scores), axis=0)
    return s[-k:].mean(axis=0)


def _parabola_offset(s_m: np.ndarray, s_0: np.ndarray, s_p: np.ndarray) -> np.ndarray:
    """Sub-step offset in [-0.5, 0.5] of the maximum of a parabola through scores at -1, 0, +1."""
    den = s_m - 2 * s_0 + s_p
    off = np.where(den < -1e-9, 0.5 * (s_m - s_p) / np.where(den < -1e-9, den, -1.0), 0.0)
    return np.clip(off, -0.5, 0.5)


def _fill_weak(q: np.ndarray, score: np.ndarray, min_score: float, sigma_px: float) -> np.ndarray:
    """Replace weak estimates (``score < min_score``) by a normalized Gaussian convolution of the
    strong ones (the finer level then refines from a plausible surface instead of noise); strong
    pixels are median-filtered (3x3) against isolated errors."""
    strong = (score >= min_score).astype(np.float32)
    q = cv2.medianBlur(q.astype(np.float32), 3)
    if sigma_px <= 0:
        return q
    num = cv2.GaussianBlur(q * strong, (0, 0), sigma_px)
    den = cv2.GaussianBlur(strong, (0, 0), sigma_px)
    filled = np.where(den > 1e-3, num / np.maximum(den, 1e-3), q)
    return np.where(strong > 0, q, filled).astype(np.float32)


# ------------------------------------------------------------------------------------ main entry
@dataclass
class DepthResult:
    """depth (H, W) float32 z in mm on the pinhole grid (0 = none); score (H, W) float32 best NCC;
    roi (x0, y0, x1, y1) of the computed region; neighbours used (camera indices)."""

    depth: np.ndarray
    score: np.ndarray
    roi: tuple[int, int, int, int]
    neighbours: list[int] = field(default_factory=list)


def _mask_roi(mask: np.ndarray | None, shape: tuple[int, int], margin: int) -> tuple[int, int, int, int]:
    H, W = shape
    if mask is None or not mask.any():
        return 0, 0, W, H
    ys, xs = np.nonzero(mask)
    return (max(int(xs.min()) - margin, 0), max(int(ys.min()) - margin, 0),
            min(int(xs.max()) + margin + 1, W), min(int(ys.max()) + margin + 1, H))


def compute_depth_map(ref_index: int, images: Sequence[np.ndarray], cameras: Sequence[Camera],
                      neighbours: Sequence[int], params: StereoParams, mask: np.ndarray | None = None,
                      depth_range: tuple[float, float] | None = None) -> DepthResult:
    """Depth and NCC score of view ``ref_index``.

    Parameters
    ----------
    images : per camera (H, W) float32 grey in [0, 1], already undistorted (:func:`undistort_view`).
    cameras : per camera the pinhole :class:`Camera` of those images (mm).
    neighbours : indices of the views matched against the reference.
    mask : (H, W) bool foreground of the reference (None = everything).
    depth_range : (near, far) z in mm of the reference camera; default from ``params``.

    Returns
    -------
    :class:`DepthResult`; pixels outside ``mask``, below ``min_ncc``/``min_texture`` or outside the
    depth range have depth 0.
    """
    ref_cam = cameras[ref_index]
    H, W = images[ref_index].shape
    if not neighbours:
        return DepthResult(np.zeros((H, W), np.float32), np.zeros((H, W), np.float32), (0, 0, 0, 0), [])
    if depth_range is None:
        depth_range = params.depth_range_mm or auto_depth_range(ref_cam, cameras, params.auto_depth_radius_mm)
    near, far = depth_range
    q_near, q_far = 1.0 / near, 1.0 / far
    levels = max(int(params.levels), 1)
    interp_final = cv2.INTER_CUBIC if params.interpolation == "cubic" else cv2.INTER_LINEAR

    pyr = {}
    for idx in [ref_index, *neighbours]:
        p = [images[idx]]
        for _ in range(levels - 1):
            p.append(cv2.pyrDown(p[-1]))
        pyr[idx] = p
    x0, y0, x1, y1 = _mask_roi(mask, (H, W), margin=2 ** levels * 4)

    q = None  # inverse depth on the current level's crop
    score = None
    for lev in range(levels - 1, -1, -1):
        s = 0.5 ** lev
        ref_l = pyr[ref_index][lev]
        Hl, Wl = ref_l.shape
        lx0, ly0 = int(np.floor(x0 * s)), int(np.floor(y0 * s))
        lx1, ly1 = min(int(np.ceil((x1 - 1) * s)) + 1, Wl), min(int(np.ceil((y1 - 1) * s)) + 1, Hl)
        us, vs = np.arange(lx0, lx1), np.arange(ly0, ly1)
        stats = _RefStats(np.ascontiguousarray(ref_l[ly0:ly1, lx0:lx1]), params.window)
        geos = [_PairGeometry(ref_cam, cameras[j], s, us, vs) for j in neighbours]
        nbr_imgs = [pyr[j][lev] for j in neighbours]
        interp = interp_final if lev == 0 else cv2.INTER_LINEAR

        def score_of(qh):
            sc = []
            for g, img in zip(geos, nbr_imgs):
                mx, my, front = g.project(qh)
                wimg, valid = _warp(img, mx, my, interp)
                sc.append(ncc(stats, wimg, valid & front))
            return _aggregate(sc, params.top_k)

        q_mid = 0.5 * (q_near + q_far)
        disp = max(g.displacement_per_q(q_mid) for g in geos)
        if q is None:
            n_planes = max(int(np.ceil((q_near - q_far) * disp / params.sweep_step_px)) + 1, 3)
            planes = np.linspace(q_far, q_near, n_planes)
            best = np.full(stats.ref.shape, -2.0, np.float32)
            best_i = np.zeros(stats.ref.shape, np.int32)
            vol = np.empty((n_planes,) + stats.ref.shape, np.float32)
            for i, qp in enumerate(planes):
                vol[i] = score_of(np.float32(qp))
                better = vol[i] > best
                best[better] = vol[i][better]
                best_i[better] = i
            im = np.clip(best_i - 1, 0, n_planes - 1)
            ip = np.clip(best_i + 1, 0, n_planes - 1)
            sm = np.take_along_axis(vol, im[None], 0)[0]
            sp = np.take_along_axis(vol, ip[None], 0)[0]
            off = _parabola_offset(sm, best, sp)
            off[(best_i == 0) | (best_i == n_planes - 1)] = 0.0
            dq = planes[1] - planes[0]
            q = (planes[best_i] + off * dq).astype(np.float32)
            score = best
        else:
            # upsample the previous level's map onto this level's crop (pyrDown: pixel i <-> 2i)
            pu = (us / 2.0 - prev_origin[0]).astype(np.float32)
            pv = (vs / 2.0 - prev_origin[1]).astype(np.float32)
            PU, PV = np.meshgrid(pu, pv)
            q = cv2.remap(q, PU, PV, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            score = cv2.remap(score, PU, PV, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
            steps = [(params.refine_step_px, params.refine_radius)]
            if lev == 0 and params.final_step_px > 0:
                steps.append((params.final_step_px, 1))
            for step_px, radius in steps:
                dq = np.float32(step_px / disp)
                ks = np.arange(-radius, radius + 1)
                vol = np.stack([score_of(q + np.float32(k) * dq) for k in ks])
                bi = np.argmax(vol, axis=0)
                best = np.take_along_axis(vol, bi[None], 0)[0]
                sm = np.take_along_axis(vol, np.clip(bi - 1, 0, len(ks) - 1)[None], 0)[0]
                sp = np.take_along_axis(vol, np.clip(bi + 1, 0, len(ks) - 1)[None], 0)[0]
                off = _parabola_offset(sm, best, sp)
                edge = (bi == 0) | (bi == len(ks) - 1)
                off[edge] = 0.0
                q = q + (ks[bi] + off).astype(np.float32) * dq
                score = best
        if lev > 0:
            q = _fill_weak(q, score, params.min_ncc, params.fill_sigma_px)
        prev_origin = (lx0, ly0)

    depth = np.zeros((H, W), np.float32)
    sc_full = np.zeros((H, W), np.float32)
    with np.errstate(divide="ignore"):
        z = np.where(q > 0, 1.0 / q, 0.0).astype(np.float32)
    ok = (score >= params.min_ncc) & (stats.std >= params.min_texture) & (z >= near) & (z <= far)
    if mask is not None:
        ok &= mask[y0:y1, x0:x1]
    depth[y0:y1, x0:x1] = np.where(ok, z, 0.0)
    sc_full[y0:y1, x0:x1] = np.where(ok, score, 0.0)
    return DepthResult(depth, sc_full, (x0, y0, x1, y1), list(neighbours))
