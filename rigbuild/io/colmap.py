"""COLMAP text model writer (cameras.txt, images.txt, points3D.txt) for known cameras and 2D-3D tracks.

Conventions: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), OpenCV (and rigbuild) at (0, 0),
so principal points and 2-D observations are shifted by +0.5 px on writing. Camera model ``OPENCV``
(fx fy cx cy k1 k2 p1 p2) when k3 == 0, else ``FULL_OPENCV`` (fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6 with
k4 = k5 = k6 = 0, the same Brown model). Image poses are world-to-camera quaternions (qw qx qy qz) and
translations in the world unit (mm). Every file is written atomically.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from rigbuild.camera import Camera
from rigbuild.io.atomic import write_text


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) unit quaternion (w, x, y, z), w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    m = np.array([
        [R[0, 0] - R[1, 1] - R[2, 2], 0, 0, 0],
        [R[0, 1] + R[1, 0], R[1, 1] - R[0, 0] - R[2, 2], 0, 0],
        [R[0, 2] + R[2, 0], R[1, 2] + R[2, 1], R[2, 2] - R[0, 0] - R[1, 1], 0],
        [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], R[0, 0] + R[1, 1] + R[2, 2]],
    ]) / 3.0
    w, v = np.linalg.eigh(m)
    q = v[[3, 0, 1, 2], np.argmax(w)]
    return q if q[0] >= 0 else -q


def colmap_camera_line(camera_id: int, cam: Camera) -> str:
    """One ``cameras.txt`` line for a :class:`Camera` (see module doc for the model and +0.5 shift)."""
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2] + 0.5, cam.K[1, 2] + 0.5
    k1, k2, p1, p2, k3 = cam.dist
    if k3 == 0.0:
        model, params = "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    else:
        model, params = "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
    return f"{camera_id} {model} {cam.width} {cam.height} " + " ".join(f"{float(p):.17g}" for p in params)


def write_colmap_text(
    folder: str | os.PathLike,
    cameras: Sequence[Camera],
    image_names: Sequence[str],
    image_camera: np.ndarray,
    points_xyz: np.ndarray,
    obs_image: np.ndarray,
    obs_point: np.ndarray,
    obs_uv: np.ndarray,
    point_errors: np.ndarray | None = None,
) -> None:
    """Write a COLMAP text model.

    cameras : C cameras (COLMAP camera_id = index + 1).
    image_names : I image names; image_camera : (I,) camera index of each image (the image's pose is its
        camera's pose: a static rig).
    points_xyz : (P, 3) world points, mm (point3D_id = index + 1).
    obs_image (N,), obs_point (N,), obs_uv (N, 2): 2-D observations (OpenCV pixels) of point obs_point[k]
        in image obs_image[k].
    point_errors : (P,) mean reprojection error of each point (px), written in the ERROR column.
    """
    folder = Path(folder)
    image_camera = np.asarray(image_camera, dtype=np.int64)
    obs_image = np.asarray(obs_image, dtype=np.int64)
    obs_point = np.asarray(obs_point, dtype=np.int64)
    obs_uv = np.asarray(obs_uv, dtype=np.float64) + 0.5
    P = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
    errs = np.zeros(len(P)) if point_errors is None else np.asarray(point_errors, dtype=np.float64)

    cam_txt = io.StringIO()
    cam_txt.write("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
    cam_txt.write(f"# Number of cameras: {len(cameras)}\n")
    for i, cam in enumerate(cameras):
        cam_txt.write(colmap_camera_line(i + 1, cam) + "\n")

    # 2-D point index of every observation inside its image
    order = np.argsort(obs_image, kind="stable")
    point2d_idx = np.empty(obs_image.size, dtype=np.int64)
    counts = np.bincount(obs_image, minlength=len(image_names))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    point2d_idx[order] = np.arange(obs_image.size) - np.repeat(starts, counts)

    img_txt = io.StringIO()
    img_txt.write("# Image list with two lines of data per image:\n"
                  "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
                  "#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
    img_txt.write(f"# Number of images: {len(image_names)}, mean observations per image: "
                  f"{obs_image.size / max(len(image_names), 1):.1f}\n")
    for i, name in enumerate(image_names):
        cam = cameras[int(image_camera[i])]
        q = rotation_to_quaternion(cam.R)
        img_txt.write(f"{i + 1} " + " ".join(f"{float(v):.17g}" for v in (*q, *cam.t)) +
                      f" {int(image_camera[i]) + 1} {name}\n")
        sel = order[starts[i]: starts[i] + counts[i]]
        img_txt.write(" ".join(f"{obs_uv[k, 0]:.17g} {obs_uv[k, 1]:.17g} {obs_point[k] + 1}" for k in sel) + "\n")

    pt_txt = io.StringIO()
    pt_txt.write("# 3D point list with one line of data per point:\n"
                 "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
    pt_txt.write(f"# Number of points: {len(P)}\n")
    by_point = np.argsort(obs_point, kind="stable")
    pcounts = np.bincount(obs_point, minlength=len(P))
    pstarts = np.concatenate([[0], np.cumsum(pcounts)[:-1]])
    for p in range(len(P)):
        sel = by_point[pstarts[p]: pstarts[p] + pcounts[p]]
        track = " ".join(f"{obs_image[k] + 1} {point2d_idx[k]}" for k in sel)
        pt_txt.write(f"{p + 1} {P[p, 0]:.17g} {P[p, 1]:.17g} {P[p, 2]:.17g} 255 255 255 {errs[p]:.17g} {track}\n")

    write_text(folder / "cameras.txt", cam_txt.getvalue())
    write_text(folder / "images.txt", img_txt.getvalue())
    write_text(folder / "points3D.txt", pt_txt.getvalue())
