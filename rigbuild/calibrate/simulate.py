"""Synthetic board observations with exact ground truth (for solver tests and the benchmark).

Projects ``BoardSpec.corner_points()`` through known :class:`Camera` objects at known board poses and
adds Gaussian pixel noise; the result has the same type as image detections
(camera -> view key -> :class:`Detection`), so it runs through the same calibration code. Images are not
rendered here (that is ``rigbuild.render``); this isolates the solver from the detector.
"""

from __future__ import annotations

import numpy as np

from rigbuild.calibrate.detect import Detection
from rigbuild.calibrate.rotations import rodrigues
from rigbuild.camera import Camera, look_at
from rigbuild.session import BoardSpec


def arc_rig(n_cams: int, width: int = 1280, height: int = 960, focal_px: float = 2400.0,
            distance_mm: float = 800.0, azimuth_deg: float = 140.0, seed: int = 0) -> list[Camera]:
    """Face-capture layout: cameras on two rows of an arc around the origin, looking at it.

    Cameras sit at ``distance_mm`` (+-5 %) from the origin, spread over ``azimuth_deg`` around the +z
    axis (the actor faces +z, world y is up), alternating 150 mm above and below the face. Intrinsics vary
    per camera (focal +-3 %, principal point +-15 px) with mild Brown distortion.
    """
    rng = np.random.default_rng(seed)
    az = np.radians(np.linspace(-azimuth_deg / 2, azimuth_deg / 2, n_cams))
    cams = []
    for i, a in enumerate(az):
        d = distance_mm * (1 + rng.uniform(-0.05, 0.05))
        h = 150.0 if i % 2 == 0 else -150.0
        c = np.array([d * np.sin(a), h, d * np.cos(a)])
        R, t = look_at(c, np.array([0.0, 0.0, 0.0]) + rng.normal(0, 10, 3), up=(0.0, 1.0, 0.0))
        f = focal_px * (1 + rng.uniform(-0.03, 0.03))
        K = np.array([[f, 0, width / 2 - 0.5 + rng.uniform(-15, 15)],
                      [0, f * (1 + rng.uniform(-1e-3, 1e-3)), height / 2 - 0.5 + rng.uniform(-15, 15)],
                      [0, 0, 1]])
        dist = np.array([rng.uniform(-0.15, 0.05), rng.uniform(-0.1, 0.2), rng.uniform(-5e-4, 5e-4),
                         rng.uniform(-5e-4, 5e-4), 0.0])
        cams.append(Camera(f"cam{i:02d}", width, height, K, dist, R, t))
    return cams


def random_board_poses(n_poses: int, board: BoardSpec, seed: int = 0, max_tilt_deg: float = 40.0,
                       spread_mm: float = 80.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board-to-world poses (R, t): board centred near the origin, facing +z (the cameras), tilted.

    The board's printed side faces +z (board z axis along world -z); each pose turns it by up to
    ``max_tilt_deg`` about the world x and y axes (the yaw sweeps across the arc so that side cameras
    see it too) and +-20 degrees in plane, and moves its centre by up to ``spread_mm``.
    """
    rng = np.random.default_rng(seed)
    pts, _ = board.corner_points()
    centre = pts.mean(0)
    base = np.diag([1.0, -1.0, -1.0])
    yaws = np.linspace(-60.0, 60.0, n_poses)
    rng.shuffle(yaws)
    poses = []
    for k in range(n_poses):
        tilt = np.radians([rng.uniform(-max_tilt_deg, max_tilt_deg) * 0.6, yaws[k], rng.uniform(-20, 20)])
        Rx = rodrigues(np.array([tilt[0], 0, 0]))
        Ry = rodrigues(np.array([0, tilt[1], 0]))
        Rz = rodrigues(np.array([0, 0, tilt[2]]))
        R = Ry @ Rx @ base @ Rz
        c = rng.uniform(-spread_mm, spread_mm, 3) * np.array([1.0, 1.0, 1.5])
        poses.append((R, c - R @ centre))
    return poses


def simulate_detections(cameras: list[Camera], board: BoardSpec, poses: list[tuple[np.ndarray, np.ndarray]],
                        noise_px: float = 0.1, seed: int = 0, margin_px: float = 8.0,
                        max_view_angle_deg: float = 70.0) -> dict[str, dict[str, Detection]]:
    """Noisy corner observations: camera id -> view key (``"0"``, ``"1"``, ...) -> Detection.

    A corner is observed when it lies in front of the camera, at least ``margin_px`` inside the image
    and the board faces the camera within ``max_view_angle_deg``. Noise is i.i.d. Gaussian per coordinate.
    """
    rng = np.random.default_rng(seed)
    pts, ids = board.corner_points()
    out: dict[str, dict[str, Detection]] = {}
    for cam in cameras:
        out[cam.id] = {}
        for k, (R, t) in enumerate(poses):
            Xw = pts @ R.T + t
            normal = R[:, 2]  # board z axis in the world (points away from the printed side)
            view_dir = Xw.mean(0) - cam.center
            cosang = normal @ view_dir / np.linalg.norm(view_dir)
            if cosang < np.cos(np.radians(max_view_angle_deg)):
                out[cam.id][str(k)] = Detection(np.zeros(0, np.int64), np.zeros((0, 2)))
                continue
            uv = cam.project(Xw)
            ok = np.isfinite(uv).all(1) & (uv[:, 0] >= margin_px) & (uv[:, 1] >= margin_px) & \
                (uv[:, 0] <= cam.width - 1 - margin_px) & (uv[:, 1] <= cam.height - 1 - margin_px)
            noisy = uv[ok] + rng.normal(0.0, noise_px, (int(ok.sum()), 2))
            out[cam.id][str(k)] = Detection(ids[ok], noisy)
    return out
