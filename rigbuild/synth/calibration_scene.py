"""Synthetic calibration data with exact ground truth (for tests and the benchmark).

- :func:`simulate_detections` projects ``BoardSpec.corner_points()`` through known :class:`Camera` objects
  at known board poses and adds Gaussian pixel noise; the result has the same type as image detections
  (camera -> view key -> :class:`Detection`), so it runs through the same calibration code and isolates
  the solver from the detector.
- :func:`render_calibration_session` writes the calibration images of a synthetic session rendered by the
  project renderer (``rigbuild.render.board``) exactly as ``rigbuild.synth.session.generate_session``
  does, without the ROM images, performances and rigs: the image-based tests and the benchmark use it.
  With ``intrinsics_poses`` it also writes each camera's own close-up boards, ``calib_intrinsics/<cam>/``
  (:func:`intrinsics_board_poses`; off by default, so the session is unchanged).
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


def intrinsics_board_poses(camera: Camera, board: BoardSpec, n_poses: int, seed: int = 0, fill: float = 0.6,
                           max_tilt_deg: float = 40.0, margin_px: float = 15.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Close-up board poses for one camera alone (its own intrinsics set, ``calib_intrinsics/<cam>/``).

    The board is held in front of ``camera`` so that it spans about ``fill`` of the image width (x 0.8-1.25),
    its centre spread over the middle 60 % of the image (the board reaching towards the corners), tilted by
    up to ``max_tilt_deg`` about both board axes and rolled by up to 30 degrees; every pose is seen fully
    (:func:`rigbuild.synth.rig_layout.board_visibility` with ``margin_px``). ``X_world = R x_board + t``, mm.
    """
    from rigbuild.synth.rig_layout import _rotation_about, board_outline, board_visibility

    rng = np.random.default_rng(seed)
    outline = board_outline(board)
    mid = outline.mean(0)
    d0 = camera.K[0, 0] * float(np.ptp(outline[:, 0])) / (fill * camera.width)
    poses: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(200 * n_poses):
        if len(poses) == n_poses:
            break
        uv = np.array([[rng.uniform(0.2, 0.8) * camera.width, rng.uniform(0.2, 0.8) * camera.height]])
        centre = camera.center + camera.rays(uv)[0] * d0 * rng.uniform(0.8, 1.25)
        tilt = (_rotation_about(np.array([1.0, 0, 0]), np.deg2rad(rng.uniform(-max_tilt_deg, max_tilt_deg)))
                @ _rotation_about(np.array([0, 1.0, 0]), np.deg2rad(rng.uniform(-max_tilt_deg, max_tilt_deg)))
                @ _rotation_about(np.array([0, 0, 1.0]), np.deg2rad(rng.uniform(-30.0, 30.0))))
        R = camera.R.T @ tilt  # board axes along the camera's (printed side towards it), then tilted
        t = centre - R @ mid
        if board_visibility([camera], board, R, t, margin_px=margin_px, max_view_angle_deg=60.0):
            poses.append((R, t))
    if len(poses) < n_poses:
        raise ValueError(f"intrinsics_board_poses: {len(poses)} of {n_poses} close-up poses found for {camera.id}")
    return poses


# ------------------------------------------------------------------ rendered calibration sessions
def _write_png(path, img: np.ndarray) -> None:
    """An RGB render as a PNG (fast compression), atomically."""
    import cv2

    from rigbuild.io.atomic import atomic_path

    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(img[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise OSError(f"could not write {path}")


def render_calibration_session(folder, name: str, synthetic: dict | None, target=None,
                               render_options: dict | None = None, intrinsics_poses: int = 0) -> dict:
    """Write the calibration part of a synthetic session, rendered by the project renderer.

    The same functions and seeds as :func:`rigbuild.synth.session.generate_session` (``make_camera_rig``
    aimed at the actor's face centre, ``make_board_poses``, ``render_board``), so ``calib/<cam>/<n>.png``
    and ``ground_truth/cameras.json`` are identical to the generator's for the same ``synthetic`` block;
    only the ROM images, performances and rigs are skipped (``session.yaml`` lists no sequences).

    Parameters
    ----------
    folder : session folder to write (``session.yaml``, ``calib/<cam>/<n>.png``,
        ``ground_truth/cameras.json``, ``ground_truth/board_poses.npz``).
    name : session name.
    synthetic : the ``synthetic:`` block of a config entry (defaults from ``SYNTH_DEFAULTS``).
    target : (3,) camera look-at point, mm (None: the actor's face centre, as the generator computes it;
        giving it skips building the actor rig, for fast tests).
    render_options : extra keyword arguments for ``render_board`` (e.g. ``msaa``); None = the generator's.
    intrinsics_poses : > 0: also render that many close-up boards per camera, seen by it alone, as
        ``calib_intrinsics/<cam>/<n>.png`` (:func:`intrinsics_board_poses`); 0 (default): none.

    Returns
    -------
    dict with ``cameras`` (ground-truth :class:`Camera` list), ``poses`` [(R (3, 3), t (3,) mm)],
    ``seen_by`` (per pose, camera ids that see it fully), ``params`` (the filled synthetic block),
    ``seconds`` (render time).
    """
    import time
    from pathlib import Path

    from rigbuild.io.atomic import save_npz
    from rigbuild.io.cameras import write_cameras
    from rigbuild.render.board import render_board
    from rigbuild.session import session_from_dict, write_session
    from rigbuild.synth.rig_layout import make_board_poses, make_camera_rig
    from rigbuild.synth.session import plan_session, synth_params

    folder = Path(folder)
    p = synth_params(synthetic)
    plan = plan_session(name, synthetic)
    plan["rom"], plan["performances"] = [], []
    spec = session_from_dict(plan, folder)
    seed = int(p["seed"])
    if target is None:
        from rigbuild.io.rigs import load_rig
        from rigbuild.paths import ict_dir
        from rigbuild.synth.actor import make_actor_rig

        template = load_rig(p["template_rig"])
        actor, _ = make_actor_rig(template, seed=seed, identity_folder=ict_dir() if p["template_rig"] == "ict" else None,
                                  intensity_range=tuple(p["actor"]["intensity_range"]),
                                  asymmetry=p["actor"]["asymmetry"], crosstalk=p["actor"]["crosstalk"],
                                  warp=p["actor"]["warp"])
        target = actor.neutral[actor.face_vertices].mean(0)
    target = np.asarray(target, dtype=np.float64)
    cameras = make_camera_rig(n_cameras=len(spec.cameras), width=spec.width, height=spec.height,
                              distance_mm=float(p["camera_distance_mm"]), arc_deg=tuple(p["camera_arc_deg"]),
                              rows=int(p["camera_rows"]), target=target,
                              distortion_scale=float(p["distortion_scale"]), seed=seed)
    poses, seen_by = make_board_poses(cameras, spec.board, n_poses=int(p["calib_poses"]), seed=seed + 1,
                                      center=target)
    t0 = time.perf_counter()
    for cam in cameras:
        for n, (Rb, tb) in enumerate(poses):
            img = render_board(cam, spec.board, Rb, tb, noise_sigma=float(p["noise_sigma"]), seed=seed * 1000 + n,
                               **(render_options or {}))
            _write_png(folder / "calib" / cam.id / f"{n}.png", img)
    for cam in cameras if intrinsics_poses > 0 else []:
        close = intrinsics_board_poses(cam, spec.board, intrinsics_poses, seed=seed * 1000 + 500 + cameras.index(cam))
        for n, (Rb, tb) in enumerate(close):
            img = render_board(cam, spec.board, Rb, tb, noise_sigma=float(p["noise_sigma"]),
                               seed=seed * 1000 + 500 + 50 * cameras.index(cam) + n, **(render_options or {}))
            _write_png(folder / "calib_intrinsics" / cam.id / f"{n}.png", img)
    seconds = time.perf_counter() - t0
    write_session(plan, folder)
    write_cameras(folder / "ground_truth" / "cameras.json", cameras, session=name)
    save_npz(folder / "ground_truth" / "board_poses.npz", R=np.array([r for r, _ in poses]),
             t=np.array([t for _, t in poses]))
    return {"cameras": cameras, "poses": poses, "seen_by": seen_by, "params": p, "seconds": seconds}
