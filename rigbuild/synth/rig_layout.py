"""Synthetic multi-camera rig around a face, and calibration-board poses it sees.

World frame: the ICT head frame in mm (+y up, the face looks towards +z, face about 160 mm wide and
230 mm tall around the origin). Cameras sit on one or two horizontal arcs around ``target`` and look at
it, framing the face tightly as real head rigs do.
"""

from __future__ import annotations

import numpy as np

from rigbuild.camera import Camera, look_at
from rigbuild.errors import InputError

#: Default look-at point (mm): the middle of the ICT face (chin y = -76, brows y = 63), behind the skin.
DEFAULT_TARGET = (0.0, 5.0, 40.0)


def _rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    import cv2

    a = np.asarray(axis, dtype=np.float64)
    return cv2.Rodrigues(a / np.linalg.norm(a) * angle_rad)[0]


def make_camera_rig(
    n_cameras: int = 8,
    width: int = 1280,
    height: int = 960,
    distance_mm: float = 450.0,
    arc_deg: tuple[float, float] = (-60.0, 60.0),
    rows: int | None = None,
    target=DEFAULT_TARGET,
    focal_px: float | None = None,
    distortion_scale: float = 1.0,
    seed: int = 0,
    frame_height_mm: float = 260.0,
    row_elevation_deg: float = 12.0,
    k3_range: tuple[float, float] = (0.0, 0.0),
) -> list[Camera]:
    """Cameras on an arc (or two stacked arcs) around a face, OpenCV model with small Brown distortion.

    Parameters
    ----------
    n_cameras : number of cameras, ids ``cam00``, ``cam01``, ... (ordered left to right, top row first).
    width, height : image size, pixels.
    distance_mm : nominal distance from each camera centre to ``target`` (jittered by +-2 %).
    arc_deg : azimuth range about the world +y axis, degrees; 0 = straight in front (+z), positive
        towards +x.
    rows : 1 or 2 arcs (None: 1 for up to 10 cameras, else 2). Two rows sit at elevations
        +-``row_elevation_deg`` with staggered azimuths.
    target : (3,) look-at point, mm (each camera's aim is jittered by a few mm).
    focal_px : nominal focal length, pixels (None: the face frame of ``frame_height_mm`` fills the
        image height at ``distance_mm``). Each camera's focal is jittered by +-2 %, fx/fy by +-0.2 %.
    distortion_scale : multiplies the random distortion (k1 in [-0.1, 0.1], k2 in [-2e-3, 2e-3], tangential
        p1, p2 in [-1e-3, 1e-3]).
    k3_range : [lo, hi] of the sixth-order radial term k3, drawn per camera (times ``distortion_scale``) from
        its own generator, so that the rest of the layout does not depend on it; (0, 0): k3 = 0.
    seed : random seed (deterministic layout per seed).
    frame_height_mm : object-space height framed by the nominal focal at ``distance_mm``.
    row_elevation_deg : elevation of the two rows.

    Returns
    -------
    list of :class:`rigbuild.camera.Camera` (world mm, x_cam = R x_world + t).
    """
    n = int(n_cameras)
    if n < 1:
        raise InputError(f"make_camera_rig: n_cameras must be >= 1, got {n}")
    if rows is None:
        rows = 1 if n <= 10 else 2
    if rows not in (1, 2):
        raise InputError(f"make_camera_rig: rows must be 1 or 2, got {rows}")
    rng = np.random.default_rng(seed)
    target = np.asarray(target, dtype=np.float64).reshape(3)
    f_nominal = float(focal_px) if focal_px is not None else distance_mm * height / frame_height_mm

    per_row = [n] if rows == 1 else [(n + 1) // 2, n // 2]
    elevations = [0.0] if rows == 1 else [row_elevation_deg, -row_elevation_deg]
    a0, a1 = float(arc_deg[0]), float(arc_deg[1])
    layout = []  # (azimuth, elevation)
    for r, (m, el) in enumerate(zip(per_row, elevations)):
        if m == 1:
            az = np.array([(a0 + a1) / 2.0])
        else:
            step = (a1 - a0) / (m - 1)
            az = np.linspace(a0, a1, m)
            if rows == 2 and r == 1:  # stagger the lower row by half a step, staying inside the arc
                az = np.clip(az + step / 2.0, a0, a1) if m < per_row[0] else az
        layout += [(float(a), el) for a in az]

    k3_lo, k3_hi = (float(x) for x in k3_range)
    k3 = np.random.default_rng([int(seed) & 0xFFFFFFFF, 3]).uniform(k3_lo, k3_hi, len(layout)) \
        if (k3_lo, k3_hi) != (0.0, 0.0) else np.zeros(len(layout))
    cameras = []
    for i, (az, el) in enumerate(layout):
        azr, elr = np.deg2rad(az), np.deg2rad(el)
        d = distance_mm * (1.0 + rng.uniform(-0.02, 0.02))
        direction = np.array([np.sin(azr) * np.cos(elr), np.sin(elr), np.cos(azr) * np.cos(elr)])
        center = target + d * direction
        aim = target + rng.uniform(-5.0, 5.0, 3)
        R, _ = look_at(center, aim)
        roll = _rotation_about([0.0, 0.0, 1.0], np.deg2rad(rng.uniform(-1.5, 1.5)))
        R = roll @ R
        t = -R @ center
        f = f_nominal * (1.0 + rng.uniform(-0.02, 0.02))
        aspect = 1.0 + rng.uniform(-0.002, 0.002)
        cx = (width - 1) / 2.0 + rng.uniform(-0.01, 0.01) * width
        cy = (height - 1) / 2.0 + rng.uniform(-0.01, 0.01) * height
        K = np.array([[f, 0.0, cx], [0.0, f * aspect, cy], [0.0, 0.0, 1.0]])
        s = float(distortion_scale)
        dist = np.array([rng.uniform(-0.1, 0.1) * s, rng.uniform(-2e-3, 2e-3) * s,
                         rng.uniform(-1e-3, 1e-3) * s, rng.uniform(-1e-3, 1e-3) * s, k3[i] * s])
        cameras.append(Camera(f"cam{i:02d}", width, height, K, dist, R, t))
    return cameras


# ------------------------------------------------------------------ calibration board poses
def board_outline(board_spec) -> np.ndarray:
    """(4, 3) board-frame corners of the printed square area (mm), in OpenCV board coordinates."""
    sq = float(board_spec.square_size_mm)
    if board_spec.type == "charuco":
        x0, y0 = 0.0, 0.0
    else:  # chessboard: the origin is the first inner corner
        x0, y0 = -sq, -sq
    x1, y1 = x0 + board_spec.squares_x * sq, y0 + board_spec.squares_y * sq
    return np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])


def board_visibility(
    cameras: list[Camera],
    board_spec,
    R_board: np.ndarray,
    t_board: np.ndarray,
    margin_px: float = 15.0,
    max_view_angle_deg: float = 65.0,
) -> list[int]:
    """Indices of the cameras that see a board pose fully.

    Fully = every inner corner and the corners of the printed area project inside the image at least
    ``margin_px`` from its border, the printed side faces the camera (board frame +z points away from
    it), and the angle between the board normal and the viewing ray to the board centre is below
    ``max_view_angle_deg``.
    """
    corners, _ = board_spec.corner_points()
    pts_b = np.vstack([corners, board_outline(board_spec)])
    X = pts_b @ np.asarray(R_board).T + np.asarray(t_board)
    normal = np.asarray(R_board)[:, 2]  # board +z, pointing away from the printed side's viewer
    centre = X.mean(0)
    out = []
    for i, cam in enumerate(cameras):
        view = centre - cam.center
        view /= np.linalg.norm(view)
        cos = float(view @ normal)
        if cos < np.cos(np.deg2rad(max_view_angle_deg)):
            continue
        uv = cam.project(X)
        if not np.all(np.isfinite(uv)):
            continue
        if (uv[:, 0].min() < margin_px or uv[:, 1].min() < margin_px
                or uv[:, 0].max() > cam.width - 1 - margin_px or uv[:, 1].max() > cam.height - 1 - margin_px):
            continue
        out.append(i)
    return out


def _components(n: int, edges: list[tuple[int, int]]) -> np.ndarray:
    parent = list(range(n))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b in edges:
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[ra] = rb
    return np.array([find(i) for i in range(n)])


def view_graph_components(n_cameras: int, seen_by: list[list[int]]) -> np.ndarray:
    """(n_cameras,) component label per camera of the graph linking cameras that see a common pose."""
    edges = [(s[0], c) for s in seen_by if len(s) > 1 for c in s[1:]]
    return _components(n_cameras, edges)


def make_board_poses(
    cameras: list[Camera],
    board_spec,
    n_poses: int = 24,
    seed: int = 0,
    center=DEFAULT_TARGET,
    spread_mm=(50.0, 40.0, 80.0),
    max_tilt_deg: float = 35.0,
    margin_px: float = 15.0,
    max_view_angle_deg: float = 65.0,
    min_cameras: int = 2,
    n_candidates: int | None = None,
) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[list[str]]]:
    """Board poses in front of the face volume for calibrating ``cameras``.

    The board (OpenCV board frame, ``X_world = R @ x_board + t``) is centred at ``center`` plus a uniform
    offset within +-``spread_mm``, faces a random point of the rig's arc, is tilted by up to
    +-``max_tilt_deg`` in yaw and pitch and rolled by up to +-25 deg. From a pool of random candidates, poses
    are chosen greedily so that every pose is seen fully (:func:`board_visibility`) by at least
    ``min_cameras`` cameras, the view graph (cameras linked by a shared pose) becomes connected, cameras
    with few poses get more, and board orientations are diverse.

    Returns
    -------
    poses : list of ``(R (3, 3), t (3,) mm)``, ``n_poses`` long.
    seen_by : per pose, the ids of the cameras that see it fully.

    Raises
    ------
    InputError if no such set exists among the candidates (board too large for the framing, ...).
    """
    rng = np.random.default_rng(seed)
    n_cams = len(cameras)
    if n_cams < min_cameras:
        raise InputError(f"make_board_poses: {n_cams} cameras, need at least {min_cameras}")
    center = np.asarray(center, dtype=np.float64)
    spread = np.asarray(spread_mm, dtype=np.float64)
    outline = board_outline(board_spec)
    board_mid = outline.mean(0)
    # azimuth range of the rig as seen from the centre
    az = np.array([np.degrees(np.arctan2(*(c.center - center)[[0, 2]])) for c in cameras])
    el = np.array([np.degrees(np.arcsin((c.center - center)[1] / np.linalg.norm(c.center - center))) for c in cameras])
    n_candidates = n_candidates or max(20 * n_poses, 300)

    cands, vis = [], []
    for _ in range(n_candidates):
        # face a random point of the rig's arc, then tilt (yaw, pitch) and roll the board
        a = np.deg2rad(rng.uniform(az.min(), az.max()))
        e = np.deg2rad(rng.uniform(el.min(), el.max()))
        towards = np.array([np.sin(a) * np.cos(e), np.sin(e), np.cos(a) * np.cos(e)])  # printed side -> rig
        z = -towards  # board +z points away from the viewers
        x = np.cross(z, [0.0, 1.0, 0.0])  # board x along the rig's image x (upright board)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)  # board y points down (image rows)
        R = np.stack([x, y, z], 1)
        R = (R @ _rotation_about([0.0, 1.0, 0.0], np.deg2rad(rng.uniform(-max_tilt_deg, max_tilt_deg)))
             @ _rotation_about([1.0, 0.0, 0.0], np.deg2rad(rng.uniform(-max_tilt_deg, max_tilt_deg)))
             @ _rotation_about([0.0, 0.0, 1.0], np.deg2rad(rng.uniform(-25.0, 25.0))))
        c = center + rng.uniform(-1.0, 1.0, 3) * spread
        t = c - R @ board_mid
        v = board_visibility(cameras, board_spec, R, t, margin_px, max_view_angle_deg)
        if len(v) >= min_cameras:
            cands.append((R, t))
            vis.append(v)
    if len(cands) < n_poses:
        raise InputError(f"make_board_poses: only {len(cands)} of {n_candidates} random board poses are seen "
                         f"fully by >= {min_cameras} cameras",
                         fix="use a smaller board (square_size_mm), a wider framing or fewer cameras")

    chosen: list[int] = []
    count = np.zeros(n_cams)
    normals = np.array([R[:, 2] for R, _ in cands])
    for _ in range(n_poses):
        labels = view_graph_components(n_cams, [vis[i] for i in chosen])
        if chosen:  # orientation diversity: angle to the closest chosen board normal, in tilt units
            cosines = np.clip(normals @ normals[chosen].T, -1.0, 1.0)
            novelty = np.degrees(np.arccos(cosines.max(1))) / max_tilt_deg
        else:
            novelty = np.zeros(len(cands))
        best, best_score = -1, -np.inf
        for j, v in enumerate(vis):
            if j in chosen:
                continue
            merged = len(set(labels[v])) - 1
            score = (10.0 * merged + float(np.mean(1.0 / (1.0 + count[v]))) * 2.0 + min(novelty[j], 1.0)
                     + 0.1 * rng.random())
            if score > best_score:
                best, best_score = j, score
        chosen.append(best)
        count[vis[best]] += 1
    labels = view_graph_components(n_cams, [vis[i] for i in chosen])
    if len(set(labels)) > 1 or np.any(count == 0):
        missing = [cameras[i].id for i in np.flatnonzero(count == 0)]
        raise InputError(f"make_board_poses: the view graph is not connected (cameras without poses: {missing})",
                         fix="increase n_poses or n_candidates, or use a smaller board")
    poses = [cands[i] for i in chosen]
    seen_by = [[cameras[k].id for k in vis[i]] for i in chosen]
    return poses, seen_by
