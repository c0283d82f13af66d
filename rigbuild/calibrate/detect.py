"""Board corner detection: ChArUco (OpenCV 5 ``CharucoDetector``) and plain chessboards, subpixel.

Every detector returns a :class:`Detection`: corner ids into ``BoardSpec.corner_points()`` and their
pixel positions (OpenCV convention: pixel centres at integer coordinates). Images are read with
:func:`read_gray`, which turns unreadable, truncated or wrongly sized files into an ``InputError``
naming the file.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Iterable, Mapping

import cv2
import numpy as np

from rigbuild.errors import InputError
from rigbuild.progress import progress
from rigbuild.session import BoardSpec

_PNG_END = b"IEND\xaeB`\x82"
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.1)
_FACE_ON_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 0.001)


@dataclass
class Detection:
    """Board corners found in one image.

    ids : (N,) int corner ids (rows of ``BoardSpec.corner_points()``).
    corners : (N, 2) float64 pixel positions (OpenCV pixel centres).
    """

    ids: np.ndarray
    corners: np.ndarray

    def __post_init__(self) -> None:
        self.ids = np.asarray(self.ids, dtype=np.int64).reshape(-1)
        self.corners = np.asarray(self.corners, dtype=np.float64).reshape(-1, 2)

    def __len__(self) -> int:
        return int(self.ids.size)


def _check_complete(path: Path, data: bytes) -> None:
    """Raise InputError when a PNG/JPEG file is visibly truncated (decoders often only warn)."""
    suffix = path.suffix.lower()
    if suffix == ".png" and not data.rstrip(b"\x00").endswith(_PNG_END):
        raise InputError("truncated PNG (no IEND chunk at the end)", path=path,
                         fix="copy the image again from the capture machine or re-shoot it")
    if suffix in (".jpg", ".jpeg") and b"\xff\xd9" not in data[-64:]:
        raise InputError("truncated JPEG (no end-of-image marker)", path=path,
                         fix="copy the image again from the capture machine or re-shoot it")


def read_gray(path: str | os.PathLike, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """Read an image as (H, W) uint8 grey.

    ``expected_size`` is ``(width, height)``; a different size raises ``InputError`` naming the file.
    Missing, unreadable and truncated files raise ``InputError`` too.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("image not found", path=path, fix="check the session folder layout calib/<cam>/<n>.png")
    data = path.read_bytes()
    if not data:
        raise InputError("empty image file", path=path, fix="copy the image again or re-shoot it")
    _check_complete(path, data)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError("unreadable image (not a PNG/JPEG OpenCV can decode)", path=path,
                         fix="replace the file with the camera's original image")
    if expected_size is not None:
        w, h = int(expected_size[0]), int(expected_size[1])
        if img.shape[1] != w or img.shape[0] != h:
            raise InputError(f"image is {img.shape[1]}x{img.shape[0]} but session.yaml image_size is {w}x{h}",
                             path=path, fix="use images of the size given in session.yaml (or fix image_size)")
    return img


def detect_charuco(gray: np.ndarray, board: BoardSpec, subpix_window: int = 0) -> Detection:
    """ChArUco corners in a grey image.

    OpenCV's ``CharucoDetector`` interpolates corners from the detected ArUco markers and refines them
    with ``cornerSubPix`` (window chosen from the local marker scale). ``subpix_window > 0`` runs one
    more ``cornerSubPix`` pass with that half-window (pixels); 0 keeps OpenCV's refinement.
    """
    det_params = cv2.aruco.DetectorParameters()
    det_params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.CharucoDetector(board.opencv_board(), cv2.aruco.CharucoParameters(), det_params)
    ch_corners, ch_ids, _, _ = detector.detectBoard(gray)
    if ch_ids is None or len(ch_ids) == 0:
        return Detection(np.zeros(0, np.int64), np.zeros((0, 2)))
    corners = ch_corners.reshape(-1, 2).astype(np.float32)
    if subpix_window > 0:
        corners = cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2), (subpix_window, subpix_window), (-1, -1),
                                   _SUBPIX_CRITERIA).reshape(-1, 2)
    order = np.argsort(ch_ids.reshape(-1))
    return Detection(ch_ids.reshape(-1)[order], corners[order])


@dataclass(frozen=True)
class FaceOnRefinement:
    """A second sub-pixel pass for ChArUco corners whose board is seen nearly face-on
    (:func:`refine_face_on`; ``params.calibrate.face_on_subpix_*``).

    max_view_angle_deg : corners whose local board plane is seen within this angle of face-on (0 = off);
    blur_px : Gaussian sigma of the image the pass refines on (px; 0 = none);
    window_fraction : ``cornerSubPix`` half-window as a fraction of the corner's local spacing along the
        board's most foreshortened direction (px), clipped to 2..15 px.
    """

    max_view_angle_deg: float = 0.0
    blur_px: float = 1.0
    window_fraction: float = 0.1


def board_foreshortening(board_xy: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local view of the board plane at each detected corner, from the board-to-image homography.

    board_xy (N, 2) mm corner positions on the board plane, corners (N, 2) px (N >= 4, not collinear).
    Returns ``cos_view`` (N,): the smaller over the larger singular value of the homography's Jacobian at
    the corner (1 = face-on; cos of the angle between the board normal and the ray under local weak
    perspective), and ``px_per_mm`` (N,): its smaller singular value (image pixels per board mm along the
    most foreshortened direction).
    """
    H, _ = cv2.findHomography(np.asarray(board_xy, np.float64), np.asarray(corners, np.float64), 0)
    if H is None:
        n = len(corners)
        return np.zeros(n), np.zeros(n)
    q = np.c_[board_xy, np.ones(len(board_xy))] @ H.T  # (N, 3) homogeneous image points
    w = q[:, 2, None, None]
    J = (H[None, :2, :2] * w - q[:, :2, None] * H[None, 2, None, :2]) / w ** 2  # d(u, v) / d(x, y)
    s = np.linalg.svd(J, compute_uv=False)
    return s[:, 1] / np.maximum(s[:, 0], 1e-12), s[:, 1]


def refine_face_on(gray: np.ndarray, det: Detection, board: BoardSpec, refine: FaceOnRefinement) -> Detection:
    """Refine again the ChArUco corners of ``det`` whose board plane is seen within
    ``refine.max_view_angle_deg`` of face-on: ``cornerSubPix`` run to convergence (100 iterations, 0.001 px)
    on the image blurred by ``refine.blur_px``, with a half-window of ``refine.window_fraction`` of the
    corner's local spacing (:func:`board_foreshortening`), so that the window stays inside the corner's
    squares, clear of the markers. Steeper corners keep OpenCV's refinement (a window that is square in
    the image reaches the neighbouring markers there). Fewer than 6 corners: ``det`` unchanged.

    gray (H, W) uint8; returns a new :class:`Detection` (same ids)."""
    if refine.max_view_angle_deg <= 0 or len(det) < 6:
        return det
    cos_view, px_per_mm = board_foreshortening(board.corner_points()[0][det.ids, :2], det.corners)
    sel = cos_view >= np.cos(np.radians(refine.max_view_angle_deg))
    if not sel.any():
        return det
    window = np.clip(np.round(refine.window_fraction * px_per_mm * board.square_size_mm), 2, 15).astype(int)
    img = cv2.GaussianBlur(gray, (0, 0), refine.blur_px) if refine.blur_px > 0 else gray
    corners = det.corners.copy()
    for w in np.unique(window[sel]):
        m = sel & (window == w)
        corners[m] = cv2.cornerSubPix(img, corners[m].astype(np.float32).reshape(-1, 1, 2), (int(w), int(w)),
                                      (-1, -1), _FACE_ON_CRITERIA).reshape(-1, 2)
    return Detection(det.ids, corners)


def chessboard_subpix_window(corners: np.ndarray, nx: int, ny: int) -> int:
    """Half-window (px) for ``cornerSubPix`` from the corner spacing: a fifth of the smallest spacing
    between grid neighbours, clipped to 5..21 px (the window must stay inside the corner's four squares;
    a fixed 5 px leaves 100 px squares of a 1920 px photo refined at 0.6 px RMS instead of 0.2 px)."""
    g = corners.reshape(ny, nx, 2)
    spacing = min(float(np.median(np.linalg.norm(np.diff(g, axis=1), axis=2))) if nx > 1 else np.inf,
                  float(np.median(np.linalg.norm(np.diff(g, axis=0), axis=2))) if ny > 1 else np.inf)
    return int(np.clip(round(0.2 * spacing), 5, 21))


def detect_chessboard(gray: np.ndarray, board: BoardSpec, subpix_window: int | None = 5) -> Detection:
    """Chessboard inner corners (all or none), refined with ``cornerSubPix``.

    Follows OpenCV's calibration test recipe: ``findChessboardCorners`` with default flags, then
    ``cornerSubPix`` with a ``(subpix_window, subpix_window)`` half-window and criteria EPS+COUNT 30, 0.1
    (``subpix_window`` None: :func:`chessboard_subpix_window` from the corner spacing).
    When that finds nothing, ``findChessboardCornersSB`` (exhaustive, accurate: its own subpixel corners).
    The board's printed side faces the camera, so the order is made right-handed in the image (a mirrored
    numbering is flipped row by row); a chessboard is symmetric under a 180 degree turn, so corner 0 is then
    the one nearer the image's top-left (cameras of a rig must be roughly upright; ChArUco has no such limit).
    """
    nx, ny = board.squares_x - 1, board.squares_y - 1
    found, corners = cv2.findChessboardCorners(gray, (nx, ny))
    if found:
        w = chessboard_subpix_window(corners.reshape(-1, 2), nx, ny) if subpix_window is None else subpix_window
        corners = cv2.cornerSubPix(gray, corners, (w, w), (-1, -1), _SUBPIX_CRITERIA)
    else:
        found, corners = cv2.findChessboardCornersSB(gray, (nx, ny), flags=cv2.CALIB_CB_EXHAUSTIVE
                                                     | cv2.CALIB_CB_ACCURACY)
    if not found:
        return Detection(np.zeros(0, np.int64), np.zeros((0, 2)))
    corners = corners.reshape(-1, 2).astype(np.float64)
    a, b = corners[1] - corners[0], corners[nx] - corners[0]  # along a row, to the next row (squares >= 3)
    if a[0] * b[1] - a[1] * b[0] < 0:
        corners = corners.reshape(ny, nx, 2)[:, ::-1].reshape(-1, 2).copy()
    if corners[0].sum() > corners[-1].sum():
        corners = corners[::-1].copy()
    return Detection(np.arange(nx * ny), corners)


def _detect_polarity(gray: np.ndarray, board: BoardSpec, subpix_window: int | None) -> Detection:
    if board.type == "charuco":
        return detect_charuco(gray, board, 0 if subpix_window is None else subpix_window)
    if board.type == "chessboard":
        return detect_chessboard(gray, board, subpix_window)
    raise InputError(f"unknown board type '{board.type}'", fix="use 'charuco' or 'chessboard' in session.yaml board.type")


def detect_board(gray: np.ndarray, board: BoardSpec, subpix_window: int | None = None,
                 face_on: FaceOnRefinement | None = None) -> Detection:
    """Dispatch on ``board.type`` (``charuco`` or ``chessboard``) and ``board.inverted``: ``True`` detects
    in the inverted image (a board printed white on black), ``"auto"`` tries the image as it is and then
    inverted when the first finds no corner. ``face_on``: ChArUco corners seen nearly face-on are refined
    again (:func:`refine_face_on`; None or an angle of 0: off)."""
    if board.inverted is True:
        det = _detect_polarity(255 - gray, board, subpix_window)
    else:
        det = _detect_polarity(gray, board, subpix_window)
        if board.inverted == "auto" and len(det) == 0:
            det = _detect_polarity(255 - gray, board, subpix_window)
    if face_on is not None and board.type == "charuco":
        det = refine_face_on(gray, det, board, face_on)  # gradients: either polarity refines the same
    return det


def board_variants(board: BoardSpec) -> list[tuple[str, BoardSpec]]:
    """Board specs a wrong description is most often confused with, as (session.yaml change, spec):
    the other print polarity, the other ChArUco layout, x and y swapped, squares counted as inner corners."""
    out: list[tuple[str, BoardSpec]] = []
    if board.type == "charuco":
        polarities = [board.inverted] + ([] if board.inverted == "auto" else [not board.inverted])
        layouts = (board.legacy_pattern, not board.legacy_pattern)
        for legacy, swap, inverted in itertools.product(layouts, (False, True), polarities):
            changes = []
            if inverted != board.inverted:
                changes.append(f"inverted: {str(inverted).lower()}")
            if legacy != board.legacy_pattern:
                changes.append(f"legacy_pattern: {str(legacy).lower()}")
            if swap:
                changes.append(f"squares_x: {board.squares_y}, squares_y: {board.squares_x}")
            if changes:
                sx, sy = (board.squares_y, board.squares_x) if swap else (board.squares_x, board.squares_y)
                out.append((", ".join(changes), replace(board, squares_x=sx, squares_y=sy, inverted=inverted,
                                                        legacy_pattern=legacy)))
    else:
        out.append((f"squares_x: {board.squares_x + 1}, squares_y: {board.squares_y + 1} (squares, not inner "
                    "corners)", replace(board, squares_x=board.squares_x + 1, squares_y=board.squares_y + 1)))
        if board.inverted is not True:
            out.append(("inverted: true", replace(board, inverted=True)))
    return out


def count_markers(gray: np.ndarray, board: BoardSpec) -> int:
    """ArUco markers of ``board.dictionary`` found in an image, either polarity (0 for a chessboard)."""
    if board.type != "charuco":
        return 0
    det_params = cv2.aruco.DetectorParameters()
    det_params.detectInvertedMarker = True
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary)), det_params)
    _, ids, _ = det.detectMarkers(gray)
    return 0 if ids is None else int(len(ids))


def describe_board(board: BoardSpec) -> str:
    """One line naming the board as session.yaml describes it."""
    text = f"{board.type} {board.squares_x} x {board.squares_y} squares of {board.square_size_mm:g} mm"
    if board.type == "charuco":
        text += (f", {board.marker_size_mm:g} mm {board.dictionary} markers, inverted: "
                 f"{str(board.inverted).lower()}, legacy_pattern: {str(board.legacy_pattern).lower()}")
    return text


def diagnose_board(grays: Mapping[str, np.ndarray], board: BoardSpec) -> list[str]:
    """Lines explaining a board spec that finds nothing in ``grays`` (image name -> grey image): what was
    tried, which nearby spec finds corners (the fix), markers of the dictionary seen."""
    tried = ["as described" + (" (then inverted)" if board.inverted == "auto" else "")]
    lines = []
    for change, variant in board_variants(board):
        n = sum(len(detect_board(g, variant)) for g in grays.values())
        tried.append(change)
        if n:
            lines.append(f"with {change}: {n} corners in {len(grays)} sample images -> set board.{change}")
    out = [f"tried on {len(grays)} sample images ({', '.join(list(grays)[:3])}): {'; '.join(tried)}"]
    out += lines
    if board.type == "charuco" and not lines:
        n_mk = sum(count_markers(g, board) for g in grays.values())
        out.append(f"{n_mk} {board.dictionary} markers found (either polarity)" + (
            ": the dictionary matches, check squares_x/squares_y, square_size_mm/marker_size_mm ratio"
            if n_mk else ": check board.dictionary (and board.type) against the printed board"))
    return out


def is_usable(det: Detection, board: BoardSpec, min_corners: int) -> bool:
    """At least ``min_corners`` corners that are not all on one line (a homography needs 2-D spread)."""
    if len(det) < max(min_corners, 4):
        return False
    pts = board.corner_points()[0][det.ids, :2]
    sv = np.linalg.svd(pts - pts.mean(0), compute_uv=False)
    return bool(sv[-1] > 0.25 * board.square_size_mm)


def _detect_path(job: tuple) -> Detection:
    path, board, image_size, subpix_window, face_on = job
    return detect_board(read_gray(path, image_size), board, subpix_window, face_on)


def detect_paths(paths: Iterable[str | os.PathLike], board: BoardSpec, image_size: tuple[int, int] | None = None,
                 subpix_window: int | None = None, workers: int = 1, label: str = "board detection",
                 face_on: FaceOnRefinement | None = None) -> list[Detection]:
    """:func:`detect_board` (``subpix_window``, ``face_on``) on each image file, in order, on ``workers``
    threads when > 1 (ArUco and chessboard detection run on one core each and OpenCV releases the GIL, so
    images are detected side by side). Errors (:func:`read_gray`) are raised as in one thread, naming the file.

    Threads, not processes: a child forked from a process whose OpenCV thread pool (or any other thread) was
    running can wait forever inside OpenCV (seen in the test suite: a forked child hung in ``detectBoard``),
    and a spawned one would re-run a Snakemake script's top level."""
    jobs = [(p, board, image_size, subpix_window, face_on) for p in paths]
    workers = int(min(max(workers, 1), len(jobs)))
    if workers > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="detect") as pool:
            return list(progress(pool.map(_detect_path, jobs), label, total=len(jobs), unit="image"))
    return [_detect_path(j) for j in progress(jobs, label, total=len(jobs), unit="image")]


def detect_images(
    images: Mapping[str, Mapping[str, str | os.PathLike]],
    board: BoardSpec,
    image_size: tuple[int, int] | None = None,
    subpix_window: int | None = None,
    workers: int = 1,
    face_on: FaceOnRefinement | None = None,
) -> dict[str, dict[str, Detection]]:
    """Detect the board in every image (:func:`detect_paths`, ``workers`` threads, ``subpix_window`` and
    ``face_on`` as :func:`detect_board`).

    images : camera id -> view key -> image path. The view key names the board pose: images of
        different cameras with the same key were taken at the same instant (synchronized capture).
    image_size : ``(width, height)`` every image must have (InputError naming the file otherwise).

    Returns camera id -> view key -> :class:`Detection` (possibly empty).
    """
    keys = [(cam, key) for cam, views in images.items() for key in views]
    dets = detect_paths([images[c][k] for c, k in keys], board, image_size, subpix_window, workers, face_on=face_on)
    out: dict[str, dict[str, Detection]] = {cam: {} for cam in images}
    for (cam, key), d in zip(keys, dets):
        out[cam][key] = d
    return out


def session_images(spec) -> dict[str, dict[str, Path]]:
    """camera id -> view key (file stem) -> path of the calibration images of a ``SessionSpec``.

    Raises InputError naming the folder when a camera has no calibration images at all.
    """
    out: dict[str, dict[str, Path]] = {}
    for cam in spec.cameras:
        paths = spec.calib_images(cam)
        if not paths:
            raise InputError(f"camera '{cam}' has no calibration images", path=spec.calib_dir(cam),
                             fix=f"put the board images of {cam} as calib/{cam}/<n>.png (or .jpg), or point "
                             "session.yaml calibration.images at their folder")
        out[cam] = {}
        for p in paths:
            key = spec.view_key(p)
            if key in out[cam]:
                raise InputError(f"images {out[cam][key].name} and {p.name} have the same view key '{key}'",
                                 path=p, fix="give each board pose one image per camera (or fix "
                                 "calibration.view_key in session.yaml)")
            out[cam][key] = p
    return out


def count_corners(detections: Mapping[str, Mapping[str, Detection]]) -> int:
    return sum(len(d) for views in detections.values() for d in views.values())


def all_paths(images: Mapping[str, Mapping[str, Path]]) -> Iterable[Path]:
    for views in images.values():
        yield from views.values()
