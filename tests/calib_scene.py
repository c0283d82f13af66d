"""Test helper: a small synthetic calibration session rendered by exact per-pixel ray casting onto the
board plane (distortion included), independent of rigbuild.render. Used by tests/test_calibrate_*.py."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from rigbuild.calibrate.simulate import arc_rig, random_board_poses
from rigbuild.camera import Camera
from rigbuild.io.cameras import write_cameras
from rigbuild.session import BoardSpec, write_session

BOARD = BoardSpec("charuco", 7, 5, 24.0, 18.0, "DICT_5X5_100")


def board_canvas(board: BoardSpec, ppmm: float, margin_mm: float) -> np.ndarray:
    """Printed board with a white margin, (H, W) uint8; canvas pixel (u, v) centre = board mm
    ((u + 0.5) / ppmm - margin, (v + 0.5) / ppmm - margin)."""
    w = int(round(board.squares_x * board.square_size_mm * ppmm))
    h = int(round(board.squares_y * board.square_size_mm * ppmm))
    img = board.opencv_board().generateImage((w, h), marginSize=0, borderBits=1)
    m = int(round(margin_mm * ppmm))
    return cv2.copyMakeBorder(img, m, m, m, m, cv2.BORDER_CONSTANT, value=255)


_GRID_CACHE: dict = {}


def _undistorted_grid(cam: Camera, ss: int) -> np.ndarray:
    """(H*ss*W*ss, 2) normalized undistorted coordinates of the supersampled pixel grid (cached per camera)."""
    key = (cam.width, cam.height, ss, cam.K.tobytes(), cam.dist.tobytes())
    if key not in _GRID_CACHE:
        W, H = cam.width, cam.height
        u, v = np.meshgrid((np.arange(W * ss) + 0.5) / ss - 0.5, (np.arange(H * ss) + 0.5) / ss - 0.5)
        _GRID_CACHE[key] = cv2.undistortPoints(
            np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2), cam.K, cam.dist,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)).reshape(-1, 2)
    return _GRID_CACHE[key]


def render_board_image(cam: Camera, board: BoardSpec, R_b: np.ndarray, t_b: np.ndarray, ss: int = 2,
                       noise: float = 1.0, seed: int = 0, ppmm: float = 12.0, margin_mm: float = 6.0) -> np.ndarray:
    """(H, W) uint8 image of the board (board-to-world pose R_b, t_b) through ``cam``, ``ss`` x ``ss``
    supersampled, on a grey background, with Gaussian grey-level noise."""
    canvas = board_canvas(board, ppmm, margin_mm)
    W, H = cam.width, cam.height
    xy = _undistorted_grid(cam, ss)
    R = cam.R @ R_b
    t = cam.R @ t_b + cam.t
    Hb = np.column_stack([R[:, 0], R[:, 1], t])  # board (x, y, 1) -> camera ray
    b = np.linalg.solve(Hb, np.column_stack([xy, np.ones(len(xy))]).T).T
    bx, by = b[:, 0] / b[:, 2], b[:, 1] / b[:, 2]
    mx = ((bx + margin_mm) * ppmm - 0.5).reshape(H * ss, W * ss).astype(np.float32)
    my = ((by + margin_mm) * ppmm - 0.5).reshape(H * ss, W * ss).astype(np.float32)
    behind = (b[:, 2] <= 0).reshape(H * ss, W * ss)
    mx[behind] = -1e6
    img = cv2.remap(canvas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=110)
    img = cv2.resize(img.astype(np.float32), (W, H), interpolation=cv2.INTER_AREA)
    img += np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def make_session(folder: Path, n_cams: int = 4, n_poses: int = 12, size=(640, 480), focal_px: float = 800.0,
                 seed: int = 0, name: str = "calibsynth", board: BoardSpec = BOARD,
                 distance_mm: float = 450.0) -> list[Camera]:
    """Write a session folder (session.yaml, calib/<cam>/<n>.png, ground_truth/cameras.json); return GT cameras."""
    folder = Path(folder)
    cams = arc_rig(n_cams, size[0], size[1], focal_px=focal_px, distance_mm=distance_mm, azimuth_deg=90.0, seed=seed)
    poses = random_board_poses(n_poses, board, seed=seed + 1, max_tilt_deg=35.0, spread_mm=40.0)
    write_session({
        "name": name, "units": "mm", "cameras": [c.id for c in cams], "image_size": list(size),
        "board": {"type": board.type, "squares_x": board.squares_x, "squares_y": board.squares_y,
                  "square_size_mm": board.square_size_mm, "marker_size_mm": board.marker_size_mm,
                  "dictionary": board.dictionary},
    }, folder)
    for cam in cams:
        d = folder / "calib" / cam.id
        d.mkdir(parents=True, exist_ok=True)
        for k, (R, t) in enumerate(poses):
            cv2.imwrite(str(d / f"{k}.png"), render_board_image(cam, board, R, t, seed=seed * 1000 + k))
    write_cameras(folder / "ground_truth" / "cameras.json", cams, session=name)
    return cams
