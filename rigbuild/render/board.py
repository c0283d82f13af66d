"""Calibration boards (ChArUco or chessboard) rendered as textured planar quads with a white margin.

Board frame = OpenCV's board coordinates (mm, z = 0 on the board, x along the squares' columns, y down
the rows; :meth:`rigbuild.session.BoardSpec.corner_points` gives the inner corners in this frame), mapped
to the world by ``X = R_board @ x_board + t_board``. The printed side is seen from the board's -z side; a
camera on the +z side sees the blank back.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from rigbuild.camera import Camera
from rigbuild.render.mesh import TexturedMesh

#: Texture resolution of one board square, texels.
PX_PER_SQUARE = 128
BACK_GREY = 215


def _spec_key(board_spec) -> tuple:
    return (board_spec.type, int(board_spec.squares_x), int(board_spec.squares_y), float(board_spec.square_size_mm),
            float(board_spec.marker_size_mm), str(board_spec.dictionary))


def board_extent(board_spec, margin_mm: float | None = None) -> tuple[float, float, float, float, float]:
    """``(x0, y0, x1, y1, margin)``: board-frame rectangle of the printed squares (mm) and the white margin."""
    sq = float(board_spec.square_size_mm)
    margin = 0.5 * sq if margin_mm is None else float(margin_mm)
    x0 = y0 = 0.0 if board_spec.type == "charuco" else -sq
    return x0, y0, x0 + board_spec.squares_x * sq, y0 + board_spec.squares_y * sq, margin


@lru_cache(maxsize=8)
def _board_texture(key: tuple, margin_px: int, px_per_square: int) -> np.ndarray:
    import cv2

    from rigbuild.session import BoardSpec

    spec = BoardSpec(type=key[0], squares_x=key[1], squares_y=key[2], square_size_mm=key[3],
                     marker_size_mm=key[4], dictionary=key[5])
    w, h = spec.squares_x * px_per_square, spec.squares_y * px_per_square
    if spec.type == "charuco":
        img = spec.opencv_board().generateImage((w, h), marginSize=0, borderBits=1)
    elif spec.type == "chessboard":
        idx_x = np.arange(w) // px_per_square
        idx_y = np.arange(h) // px_per_square
        img = np.where((idx_x[None, :] + idx_y[:, None]) % 2 == 0, 0, 255).astype(np.uint8)
    else:
        from rigbuild.errors import InputError

        raise InputError(f"board type must be 'charuco' or 'chessboard', got {spec.type!r}")
    img = cv2.copyMakeBorder(img, margin_px, margin_px, margin_px, margin_px, cv2.BORDER_CONSTANT, value=255)
    tex = np.repeat(img[..., None], 3, axis=2)
    tex.setflags(write=False)
    return tex


def board_texture(board_spec, margin_mm: float | None = None, px_per_square: int = PX_PER_SQUARE) -> tuple[np.ndarray, float]:
    """(texture (H, W, 3) uint8, margin_mm actually used): the printed board with its white margin.

    The margin is rounded to whole texels; the same array object is returned for the same arguments
    (the GL renderer caches its upload).
    """
    sq = float(board_spec.square_size_mm)
    margin = board_extent(board_spec, margin_mm)[4]
    margin_px = int(round(margin / sq * px_per_square))
    return _board_texture(_spec_key(board_spec), margin_px, int(px_per_square)), margin_px * sq / px_per_square


@lru_cache(maxsize=8)
def _blank_texture(grey: int) -> np.ndarray:
    t = np.full((4, 4, 3), grey, dtype=np.uint8)
    t.setflags(write=False)
    return t


def board_mesh(board_spec, R_board: np.ndarray, t_board: np.ndarray, margin_mm: float | None = None,
               px_per_square: int = PX_PER_SQUARE, back: bool = False) -> TexturedMesh:
    """The board as a two-triangle textured quad in world mm (``back=True``: the blank back side)."""
    tex, margin = board_texture(board_spec, margin_mm, px_per_square)
    x0, y0, x1, y1, _ = board_extent(board_spec)
    x0, y0, x1, y1 = x0 - margin, y0 - margin, x1 + margin, y1 + margin
    quad = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    # texture row 0 (top of the image) is board y0; OBJ-convention v = 1 at the top row
    uvs = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    X = quad @ np.asarray(R_board, dtype=np.float64).T + np.asarray(t_board, dtype=np.float64)
    if back:
        tex = _blank_texture(BACK_GREY)
    return TexturedMesh(X, faces, uvs, faces, tex)


def render_board(
    camera: Camera,
    board_spec,
    R_board: np.ndarray,
    t_board: np.ndarray,
    light_dir=None,
    margin_mm: float | None = None,
    output: str = "srgb8",
    **render_options,
) -> np.ndarray:
    """Render a calibration board through ``camera`` (with distortion) on a grey background.

    Parameters
    ----------
    camera : the camera.
    board_spec : :class:`rigbuild.session.BoardSpec` (ChArUco or chessboard).
    R_board, t_board : (3, 3), (3,) board-to-world pose, mm: ``X = R_board @ x_board + t_board``.
    light_dir : world direction towards the light (None: from the camera towards the board centre,
        i.e. a light at the camera, as rig lights are).
    margin_mm : white margin around the squares (None: half a square).
    output : ``"srgb8"`` (the image with noise) or ``"linear"`` (float32 radiance, white = 1, for a sensor model).
    render_options : ``ambient``, ``background``, ``noise_sigma``, ``seed``, ``msaa``, ``backend``, as
        :func:`rigbuild.render.render_mesh`.

    Returns
    -------
    (H, W, 3) uint8 RGB image, or float32 linear radiance with ``output="linear"``.
    """
    from rigbuild.render import render_mesh

    R_board = np.asarray(R_board, dtype=np.float64)
    t_board = np.asarray(t_board, dtype=np.float64)
    x0, y0, x1, y1, _ = board_extent(board_spec)
    centre = R_board @ np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0]) + t_board
    back = float((centre - camera.center) @ R_board[:, 2]) < 0.0  # camera on the board's +z side
    mesh = board_mesh(board_spec, R_board, t_board, margin_mm, back=back)
    if light_dir is None:
        light_dir = camera.center - centre
    res = render_mesh(camera, mesh, light_dir=light_dir, with_geometry=False, output=output, **render_options)
    return res.linear if output == "linear" else res.color
