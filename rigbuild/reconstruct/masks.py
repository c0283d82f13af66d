"""Background masking and bad-image detection for multi-view stereo.

Images are (H, W) float32 grey in [0, 1] (see :func:`rigbuild.reconstruct.stereo.to_gray_float`).
"""

from __future__ import annotations

import cv2
import numpy as np


def border_level(gray: np.ndarray, width_fraction: float = 0.02) -> float:
    """Median intensity of a frame of ``width_fraction`` of the image size along the border."""
    H, W = gray.shape
    b = max(1, int(round(width_fraction * min(H, W))))
    ring = np.concatenate([gray[:b].ravel(), gray[-b:].ravel(), gray[:, :b].ravel(), gray[:, -b:].ravel()])
    return float(np.median(ring))


def foreground_mask(gray: np.ndarray, threshold: float = 0.08, background_level: float | None = None,
                    texture_threshold: float = 0.02, blur_px: float = 2.0, dilate_px: int = 10, erode_px: int = 7,
                    min_area_fraction: float = 0.002) -> np.ndarray:
    """(H, W) bool mask of the subject against a uniform backdrop.

    A pixel is foreground when its blurred intensity (Gaussian sigma ``blur_px``, so speckles inside the
    subject do not punch holes) differs from the backdrop level by more than ``threshold``, or when the
    intensity standard deviation in its 7x7 window exceeds ``texture_threshold`` (textured skin whose
    shade happens to match the backdrop). The backdrop level is ``background_level`` or the median of
    the image border (:func:`border_level`). The mask is dilated by ``dilate_px`` and eroded by
    ``erode_px`` (the Middlebury recipe: conservative, stereo rejects the few background pixels kept),
    holes are filled, and components smaller than ``min_area_fraction`` of the image are dropped.
    ``threshold <= 0`` returns an all-True mask (no masking).
    """
    H, W = gray.shape
    if threshold <= 0:
        return np.ones((H, W), bool)
    gray = gray.astype(np.float32)
    bg = border_level(gray) if background_level is None else float(background_level)
    g = cv2.GaussianBlur(gray, (0, 0), blur_px) if blur_px > 0 else gray
    m = np.abs(g - bg) > threshold
    if texture_threshold > 0:
        mean = cv2.boxFilter(gray, -1, (7, 7))
        var = cv2.boxFilter(gray * gray, -1, (7, 7)) - mean * mean
        m |= var > texture_threshold ** 2
    m = m.astype(np.uint8)
    if dilate_px > 0:
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate_px + 1,) * 2))
    if erode_px > 0:
        m = cv2.erode(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode_px + 1,) * 2))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    keep = np.zeros(n, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= min_area_fraction * H * W
    m = keep[labels]
    # fill holes: background components of the inverted mask that do not touch the border
    inv = (~m).astype(np.uint8)
    n2, lab2 = cv2.connectedComponents(inv, connectivity=4)
    border = np.unique(np.concatenate([lab2[0], lab2[-1], lab2[:, 0], lab2[:, -1]]))
    hole = np.ones(n2, bool)
    hole[border] = False
    hole[0] = False
    return m | hole[lab2]


def pinhole_foreground_mask(image: np.ndarray, camera, threshold: float = 0.08, dilate_px: int = 10,
                            erode_px: int = 7) -> np.ndarray:
    """(H, W) bool :func:`foreground_mask` of a captured (distorted) image, resampled onto the pinhole grid of
    ``camera`` (:func:`rigbuild.reconstruct.stereo.undistort_view`, the grid of the depth maps).

    The mask is found on the image as captured: undistorting first fills the corners outside the lens's
    field with black, which would set the backdrop level and make every pixel foreground. Pinhole pixels
    outside the captured field are background.
    """
    from rigbuild.reconstruct.stereo import to_gray_float, undistort_view

    m = foreground_mask(to_gray_float(image), threshold, dilate_px=dilate_px, erode_px=erode_px)
    return undistort_view(m.astype(np.uint8), camera)[0] > 0


def image_problem(gray: np.ndarray, dark_level: float = 0.03, saturated_level: float = 0.99,
                  max_saturated_fraction: float = 0.5, min_std: float = 0.005) -> str | None:
    """A reason string if an image cannot be used for stereo, else None.

    ``"all black"``: its 99.5th percentile is below ``dark_level``; ``"saturated"``: more than
    ``max_saturated_fraction`` of pixels at or above ``saturated_level``; ``"no contrast"``: standard
    deviation below ``min_std``.
    """
    g = np.asarray(gray, dtype=np.float32)
    if g.size == 0:
        return "empty image"
    if float(np.percentile(g, 99.5)) < dark_level:
        return "all black"
    if float(np.mean(g >= saturated_level)) > max_saturated_fraction:
        return "saturated"
    if float(g.std()) < min_std:
        return "no contrast"
    return None
