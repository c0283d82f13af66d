"""The capture-session contract shared by real and synthetic sessions.

A session is a folder::

    session.yaml                         cameras, image size, fps, board, ROM sequences, performances
    calib/<cam>/<n>.png|jpg              calibration board images (n = 0, 1, ... per camera; same n = same instant)
    calib_intrinsics/<cam>/*.png|jpg     optional: boards shot by that camera alone (its intrinsics only)
    rom/<sequence>/<cam>/<frame:06d>.png range-of-motion images
    performances/<name>.c3d              marker performances
    ground_truth/                        synthetic sessions only; never read by pipeline stages

``session.yaml`` is validated against ``workflow/schemas/session.schema.json``
(:func:`read_session`); errors name the file and the field. Its optional ``calibration:`` block points the
calibration images elsewhere (``images``, ``intrinsics_images``: folders with ``{cam}`` and ``{data}`` =
:func:`rigbuild.paths.data_dir`) and says which part of a file name is the board pose (``view_key``, a
regular expression whose first group is kept); ``intrinsics:`` gives known intrinsics per camera (inline
or a YAML/JSON file). A session without ``rom`` and ``performances`` holds calibration only.
"""

from __future__ import annotations

import os
import re

import numpy as np
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from rigbuild.errors import InputError
from rigbuild.paths import PROJECT_ROOT

SESSION_SCHEMA = PROJECT_ROOT / "workflow" / "schemas" / "session.schema.json"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def aruco_dictionaries() -> list[str]:
    """Names of OpenCV's predefined ArUco / AprilTag dictionaries (``DICT_...``, one spelling each)."""
    import cv2

    names = [n for n in dir(cv2.aruco) if n.startswith("DICT_") and isinstance(getattr(cv2.aruco, n), int)]
    seen, out = set(), []
    for n in sorted(names, key=lambda n: (n.upper(), n == n.upper())):  # OpenCV docs spelling: 36h11
        if n.upper() not in seen:
            seen.add(n.upper())
            out.append(n)
    return out


def aruco_dictionary_name(name: str, source: str | os.PathLike = "session.yaml") -> str:
    """The OpenCV name of a predefined dictionary, given case-insensitively and with or without ``DICT_``
    (``4x4_1000`` -> ``DICT_4X4_1000``); InputError listing the names otherwise."""
    key = str(name).strip().upper()
    key = key if key.startswith("DICT_") else "DICT_" + key
    for n in aruco_dictionaries():
        if n.upper() == key:
            return n
    raise InputError(f"field 'board.dictionary': unknown ArUco dictionary '{name}'", path=source,
                     fix=f"use one of OpenCV's predefined dictionaries: {', '.join(aruco_dictionaries())}")


@dataclass
class BoardSpec:
    """Calibration board.

    type : ``"charuco"`` or ``"chessboard"``.
    squares_x, squares_y : number of squares along x and y (chessboard inner corners are one fewer).
    square_size_mm : side of one square (sets the metric scale).
    marker_size_mm : ArUco marker side (ChArUco only).
    dictionary : OpenCV predefined dictionary name, e.g. ``DICT_5X5_100`` (ChArUco only).
    inverted : ``True`` for a board printed inverted (white markers and squares on black), ``False`` for the
        usual print, ``"auto"`` to try both in every image.
    legacy_pattern : ChArUco layout of OpenCV < 4.6 (differs for an even number of rows); most older board
        generators (and calib.io's "legacy" boards) use it.
    """

    type: str = "charuco"
    squares_x: int = 7
    squares_y: int = 5
    square_size_mm: float = 30.0
    marker_size_mm: float = 22.0
    dictionary: str = "DICT_5X5_100"
    inverted: bool | str = False
    legacy_pattern: bool = False

    def opencv_board(self):
        """The ``cv2.aruco.CharucoBoard`` (OpenCV 5 API) for a ChArUco spec."""
        import cv2

        if self.type != "charuco":
            raise ValueError("opencv_board() is for ChArUco boards")
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        board = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_size_mm, self.marker_size_mm, d)
        board.setLegacyPattern(bool(self.legacy_pattern))
        return board

    def n_markers(self) -> int:
        """ArUco markers on a ChArUco board (half of the squares)."""
        return (self.squares_x * self.squares_y) // 2

    def corner_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Board-frame 3-D corner positions (N, 3) in mm (z = 0) and their ids (N,).

        ChArUco: the inner chessboard corners in OpenCV's id order; chessboard: inner corners row-major.
        """
        import numpy as np

        if self.type == "charuco":
            pts = np.asarray(self.opencv_board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
        else:
            nx, ny = self.squares_x - 1, self.squares_y - 1
            gx, gy = np.meshgrid(np.arange(nx), np.arange(ny))
            pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(nx * ny)], 1) * self.square_size_mm
        return pts, np.arange(pts.shape[0])


@dataclass
class SequenceSpec:
    """A ROM sequence: frames ``start..end`` inclusive; ``neutral_frame`` is where tracking starts."""

    name: str
    start: int
    end: int
    neutral_frame: int

    @property
    def frames(self) -> list[int]:
        return list(range(self.start, self.end + 1))


@dataclass
class PerformanceSpec:
    """A marker performance file (C3D or npz), path relative to the session folder."""

    name: str
    file: str


@dataclass
class SessionSpec:
    """A parsed, validated ``session.yaml``."""

    name: str
    root: Path
    cameras: list[str]
    width: int
    height: int
    fps: float
    board: BoardSpec
    rom: list[SequenceSpec]
    performances: list[PerformanceSpec] = field(default_factory=list)
    units: str = "mm"
    template_rig: str = "procedural"
    dot_stencil_mm: float | None = None  # spacing of the painted stencil dots (rigbuild.dots), None: markers only
    painted_dots: bool = True  # session.yaml ``dots``: ``painted`` (default) or ``none`` (an unpainted face)
    raw: dict[str, Any] = field(default_factory=dict)

    # ----------------------------------------------------------------- paths
    def _folder(self, key: str, default: str, cam: str) -> Path:
        from rigbuild.paths import data_dir

        pattern = str((self.raw.get("calibration") or {}).get(key, default))
        p = Path(pattern.replace("{cam}", cam).replace("{data}", str(data_dir())))
        return p if p.is_absolute() else self.root / p

    def calib_dir(self, cam: str) -> Path:
        """Folder of ``cam``'s rig calibration images (``calibration.images``, default ``calib/<cam>``)."""
        return self._folder("images", "calib/{cam}", cam)

    def intrinsics_dir(self, cam: str) -> Path:
        """Folder of ``cam``'s own intrinsics images (``calibration.intrinsics_images``, default
        ``calib_intrinsics/<cam>``); it may not exist."""
        return self._folder("intrinsics_images", "calib_intrinsics/{cam}", cam)

    def view_key(self, path: str | os.PathLike) -> str:
        """The board-pose key of a calibration image: its file stem, or the first group of the
        ``calibration.view_key`` expression searched in it (``-(\\d+)$``: ``top-0224-15.jpg`` -> ``15``)."""
        stem = Path(path).stem
        rx = (self.raw.get("calibration") or {}).get("view_key")
        if not rx:
            return stem
        m = re.search(rx, stem)
        if m is None:
            raise InputError(f"field 'calibration.view_key': '{rx}' does not match image name '{stem}'",
                             path=self.root / "session.yaml", fix="give an expression whose first group "
                             "is the frame number in every calibration image name")
        return m.group(1) if m.groups() else m.group(0)

    @staticmethod
    def _images_in(d: Path, key) -> list[Path]:
        if not d.is_dir():
            return []
        files = [p for p in d.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()]
        return sorted(files, key=lambda p: (0, int(key(p)), "") if key(p).isdigit() else (1, 0, key(p)))

    def calib_images(self, cam: str) -> list[Path]:
        """Calibration images (PNG/JPEG) of ``cam`` sorted by their view key (numbers numerically)."""
        return self._images_in(self.calib_dir(cam), self.view_key)

    def intrinsics_images(self, cam: str) -> list[Path]:
        """``cam``'s own intrinsics images (PNG/JPEG, sorted by name); [] when it has none."""
        return self._images_in(self.intrinsics_dir(cam), lambda p: p.stem)

    @property
    def calibration_only(self) -> bool:
        """No ROM sequences and no performances: the session is calibrated, nothing else."""
        return not self.rom and not self.performances

    def rom_image(self, seq: str, cam: str, frame: int) -> Path:
        return self.root / "rom" / seq / cam / f"{frame:06d}.png"

    def performance_path(self, name: str) -> Path:
        for p in self.performances:
            if p.name == name:
                return self.root / p.file
        raise InputError(f"no performance '{name}' in session.yaml", path=self.root / "session.yaml")

    def sequence(self, name: str) -> SequenceSpec:
        for s in self.rom:
            if s.name == name:
                return s
        raise InputError(f"no ROM sequence '{name}'", path=self.root / "session.yaml",
                         fix=f"use one of {[s.name for s in self.rom]}")

    @property
    def ground_truth_dir(self) -> Path:
        return self.root / "ground_truth"


def validate_session_dict(data: dict[str, Any], source: str | os.PathLike) -> dict[str, Any]:
    """Validate (and fill defaults of) a session dict against the JSON schema; InputError naming the field."""
    import json

    import jsonschema

    schema = json.loads(SESSION_SCHEMA.read_text())
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(data), key=lambda e: list(e.absolute_path))
    if errors:
        e = errors[0]
        where = ".".join(str(p) for p in e.absolute_path) or "(top level)"
        raise InputError(f"field '{where}': {e.message}", path=source,
                         fix="see workflow/schemas/session.schema.json for the session.yaml format")
    return data


def session_from_dict(data: dict[str, Any], root: str | os.PathLike, source: str | os.PathLike | None = None) -> SessionSpec:
    """Build a :class:`SessionSpec` from a (validated) dict; ``root`` is the session folder."""
    root = Path(root)
    source = source or root / "session.yaml"
    validate_session_dict(data, source)
    cams = [str(c) for c in data["cameras"]]
    if len(set(cams)) != len(cams):
        dup = sorted({c for c in cams if cams.count(c) > 1})
        raise InputError(f"field 'cameras': duplicate camera ids {dup}", path=source)
    rom = []
    for i, s in enumerate(data.get("rom", [])):
        start, end = int(s["frames"][0]), int(s["frames"][1])
        nf = int(s.get("neutral_frame", start))
        if end < start or not start <= nf <= end:
            raise InputError(f"field 'rom.{i}': frames [{start}, {end}] must be ascending and contain "
                             f"neutral_frame {nf}", path=source)
        rom.append(SequenceSpec(str(s["name"]), start, end, nf))
    names = [s.name for s in rom]
    if len(set(names)) != len(names):
        raise InputError("field 'rom': duplicate sequence names", path=source)
    board = BoardSpec(**data["board"])
    if board.type == "charuco":
        check_charuco(board, source)
    return SessionSpec(
        name=str(data["name"]),
        root=root,
        cameras=cams,
        width=int(data["image_size"][0]),
        height=int(data["image_size"][1]),
        fps=float(data.get("fps", 30.0)),
        board=board,
        rom=rom,
        performances=[PerformanceSpec(str(p["name"]), str(p["file"])) for p in data.get("performances", [])],
        units=str(data.get("units", "mm")),
        template_rig=str(data.get("template_rig", "procedural")),
        dot_stencil_mm=float(data["dot_stencil_mm"]) if data.get("dot_stencil_mm") is not None else None,
        painted_dots=data.get("dots", "painted") != "none",
        raw=data,
    )


def check_charuco(board: BoardSpec, source: str | os.PathLike) -> None:
    """Normalize ``board.dictionary`` to OpenCV's name (in place) and check that it holds enough markers."""
    import cv2

    board.dictionary = aruco_dictionary_name(board.dictionary, source)
    size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary)).bytesList.shape[0]
    if size < board.n_markers():
        raise InputError(f"field 'board.dictionary': {board.dictionary} has {size} markers, a "
                         f"{board.squares_x} x {board.squares_y} ChArUco board needs {board.n_markers()}",
                         path=source, fix="check squares_x/squares_y and the dictionary printed on the board")
    if board.marker_size_mm >= board.square_size_mm:
        raise InputError(f"field 'board.marker_size_mm': {board.marker_size_mm} mm is not smaller than the "
                         f"square ({board.square_size_mm} mm)", path=source,
                         fix="give the side of the black ArUco marker inside a white square")


def read_session(folder: str | os.PathLike) -> SessionSpec:
    """Read and validate ``<folder>/session.yaml``."""
    folder = Path(folder)
    path = folder / "session.yaml"
    if not path.exists():
        raise InputError("session.yaml not found", path=path,
                         fix="create it with 'rigbuild init-session <folder>' or generate a synthetic session")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise InputError(f"not valid YAML ({exc})", path=path) from None
    if not isinstance(data, dict):
        raise InputError("session.yaml must be a mapping", path=path)
    return session_from_dict(data, folder, path)


def write_session(spec_dict: dict[str, Any], folder: str | os.PathLike) -> None:
    """Write a session dict as ``<folder>/session.yaml`` atomically (validated first)."""
    from rigbuild.io.atomic import write_text

    folder = Path(folder)
    validate_session_dict(spec_dict, folder / "session.yaml")
    write_text(folder / "session.yaml", yaml.safe_dump(spec_dict, sort_keys=False))
