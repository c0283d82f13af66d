"""Board detection pictures, one per camera (``results/<session>/calib/detections/<cam>.jpg``): what a
technician checks before accepting a calibration.

Each picture is the camera's image with the most detected corners, dimmed, with

- every corner the camera detected in any image it was calibrated on (small cyan dots): where in the frame the
  board was seen; grid cells no corner reached are shaded red (lens distortion there is extrapolated);
- that image's detected corners (green rings) and the calibrated rig's reprojection of them (red crosses);
- a header line: camera, images used and dropped, corners, RMS reprojection error, image coverage.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

DETECTIONS_DIR = "detections"
#: columns x rows of the image grid whose cells count towards :func:`image_coverage`
COVERAGE_CELLS = (8, 6)


def detection_files(camera_ids: Sequence[str]) -> list[str]:
    """Paths (relative to the calib folder) of the detection pictures of ``camera_ids``."""
    return [f"{DETECTIONS_DIR}/{c}.jpg" for c in camera_ids]


def covered_cells(uv: np.ndarray, width: int, height: int, cells: tuple[int, int] = COVERAGE_CELLS) -> np.ndarray:
    """(rows, cols) bool: the cells of a ``cells`` = (cols, rows) grid over a ``width`` x ``height`` image that
    hold at least one of the pixels ``uv`` (N, 2) (OpenCV pixel centres; points outside are ignored)."""
    cols, rows = cells
    uv = np.asarray(uv, float).reshape(-1, 2)
    ok = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= -0.5) & (uv[:, 0] < width - 0.5) \
        & (uv[:, 1] >= -0.5) & (uv[:, 1] < height - 0.5)
    cx = np.clip(((uv[ok, 0] + 0.5) * cols / width).astype(int), 0, cols - 1)
    cy = np.clip(((uv[ok, 1] + 0.5) * rows / height).astype(int), 0, rows - 1)
    grid = np.zeros((rows, cols), bool)
    grid[cy, cx] = True
    return grid


def image_coverage(uv: np.ndarray, width: int, height: int, cells: tuple[int, int] = COVERAGE_CELLS) -> float:
    """Fraction (0..1) of the image grid's cells reached by the corners ``uv`` (N, 2) px."""
    return float(covered_cells(uv, width, height, cells).mean())


def draw_detections(gray: np.ndarray | None, width: int, height: int, detected: np.ndarray,
                    reprojected: np.ndarray, all_detected: np.ndarray, header: str,
                    max_width: int = 960) -> np.ndarray:
    """The detection picture (h, w, 3) uint8 BGR, scaled to at most ``max_width`` px wide.

    gray : the camera's image (height, width) uint8 as the detector read it, or None (a grey canvas).
    detected, reprojected : (N, 2) px of the shown image's corners and their reprojection by the rig.
    all_detected : (M, 2) px of every corner the camera detected (coverage).
    """
    import cv2

    s = min(1.0, max_width / float(width))
    size = (round(width * s), round(height * s))
    if gray is None:
        canvas = np.full((size[1], size[0], 3), 96, np.uint8)
    else:
        canvas = cv2.cvtColor(cv2.resize(gray, size, interpolation=cv2.INTER_AREA), cv2.COLOR_GRAY2BGR)
    canvas = (canvas.astype(np.float32) * 0.6).astype(np.uint8)
    h, w = canvas.shape[:2]
    grid = covered_cells(all_detected, width, height)
    rows, cols = grid.shape
    shade = np.zeros_like(canvas)
    for r, c in zip(*np.nonzero(~grid)):
        shade[r * h // rows:(r + 1) * h // rows, c * w // cols:(c + 1) * w // cols] = (0, 0, 90)
    canvas = cv2.add(canvas, shade)

    def px(uv):
        uv = np.asarray(uv, float).reshape(-1, 2)
        uv = uv[np.all(np.isfinite(uv), axis=1)]
        return np.round((uv + 0.5) * s - 0.5).astype(int)

    for u, v in px(all_detected):
        cv2.circle(canvas, (u, v), 1, (255, 255, 0), -1)
    for u, v in px(detected):
        cv2.circle(canvas, (u, v), 5, (0, 230, 0), 1, cv2.LINE_AA)
    for u, v in px(reprojected):
        cv2.drawMarker(canvas, (u, v), (0, 0, 255), cv2.MARKER_CROSS, 6, 1)
    scale = max(0.4, w / 1600.0)
    cv2.rectangle(canvas, (0, 0), (w, int(26 * scale / 0.6)), (0, 0, 0), -1)
    cv2.putText(canvas, header, (6, int(19 * scale / 0.6)), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1,
                cv2.LINE_AA)
    return canvas


def write_detection_pictures(result, out_dir: str | os.PathLike,
                             image_paths: Mapping[str, Mapping[str, str | os.PathLike]] | None = None,
                             quality: int = 90) -> list[str]:
    """One :func:`draw_detections` picture per camera of a :class:`rigbuild.calibrate.rig.RigCalibration`
    into ``out_dir/detections/<cam>.jpg``. image_paths : camera id -> view key -> the calibration image
    (:func:`rigbuild.calibrate.detect.session_images`), read as the detector reads it (a grey canvas where
    none is given or it cannot be read). Returns the paths written, relative to ``out_dir``."""
    import cv2

    from rigbuild.calibrate.detect import read_gray
    from rigbuild.errors import InputError
    from rigbuild.io.atomic import atomic_path

    out_dir = Path(out_dir)
    (out_dir / DETECTIONS_DIR).mkdir(parents=True, exist_ok=True)
    rms = result.camera_rms()
    files = detection_files([c.id for c in result.cameras])
    for i, (cam, rel) in enumerate(zip(result.cameras, files)):
        mine = np.nonzero(result.obs.cam == i)[0]
        views, counts = np.unique(result.obs.view[mine], return_counts=True)
        image, detected, reprojected = None, np.zeros((0, 2)), np.zeros((0, 2))
        if len(views):
            best = int(views[np.argmax(counts)])
            sel = mine[result.obs.view[mine] == best]
            detected = result.obs.uv[sel]
            reprojected = cam.project(result.corner_world(result.obs.view[sel], result.obs.corner[sel]))
            path = (image_paths or {}).get(cam.id, {}).get(result.view_keys[best])
            if path is not None:
                try:
                    image = read_gray(path, (cam.width, cam.height))
                except InputError:
                    image = None
        uv = result.obs.uv[mine]
        header = (f"{cam.id}: {len(views)} images used, {len(result.dropped.get(cam.id, []))} dropped, "
                  f"{len(mine)} corners, RMS {rms.get(cam.id, float('nan')):.3f} px, "
                  f"image coverage {100 * image_coverage(uv, cam.width, cam.height):.0f} %")
        pic = draw_detections(image, cam.width, cam.height, detected, reprojected, uv, header)
        with atomic_path(out_dir / rel, suffix=".jpg") as tmp:
            if not cv2.imwrite(str(tmp), pic, [cv2.IMWRITE_JPEG_QUALITY, int(quality)]):
                raise OSError(f"could not write {out_dir / rel}")
    return files
