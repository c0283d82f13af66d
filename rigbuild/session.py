"""The capture-session contract shared by real and synthetic sessions.

A session is a folder::

    session.yaml                         cameras, image size, fps, board, ROM sequences, performances
    calib/<cam>/<n>.png                  calibration board images (n = 0, 1, ... per camera)
    rom/<sequence>/<cam>/<frame:06d>.png range-of-motion images
    performances/<name>.c3d              marker performances
    ground_truth/                        synthetic sessions only; never read by pipeline stages

``session.yaml`` is validated against ``workflow/schemas/session.schema.json``
(:func:`read_session`); errors name the file and the field.
"""

from __future__ import annotations

import os

import numpy as np
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from rigbuild.errors import InputError
from rigbuild.paths import PROJECT_ROOT

SESSION_SCHEMA = PROJECT_ROOT / "workflow" / "schemas" / "session.schema.json"


@dataclass
class BoardSpec:
    """Calibration board.

    type : ``"charuco"`` or ``"chessboard"``.
    squares_x, squares_y : number of squares along x and y (chessboard inner corners are one fewer).
    square_size_mm : side of one square (sets the metric scale).
    marker_size_mm : ArUco marker side (ChArUco only).
    dictionary : OpenCV predefined dictionary name, e.g. ``DICT_5X5_100`` (ChArUco only).
    """

    type: str = "charuco"
    squares_x: int = 7
    squares_y: int = 5
    square_size_mm: float = 30.0
    marker_size_mm: float = 22.0
    dictionary: str = "DICT_5X5_100"

    def opencv_board(self):
        """The ``cv2.aruco.CharucoBoard`` (OpenCV 5 API) for a ChArUco spec."""
        import cv2

        if self.type != "charuco":
            raise ValueError("opencv_board() is for ChArUco boards")
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_size_mm, self.marker_size_mm, d)

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
    raw: dict[str, Any] = field(default_factory=dict)

    # ----------------------------------------------------------------- paths
    def calib_dir(self, cam: str) -> Path:
        return self.root / "calib" / cam

    def calib_images(self, cam: str) -> list[Path]:
        """Calibration images of ``cam`` sorted by their integer name."""
        d = self.calib_dir(cam)
        return sorted(d.glob("*.png"), key=lambda p: int(p.stem) if p.stem.isdigit() else p.stem)

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
        import cv2

        if not hasattr(cv2.aruco, board.dictionary):
            raise InputError(f"field 'board.dictionary': unknown ArUco dictionary '{board.dictionary}'",
                             path=source, fix="use an OpenCV name such as DICT_5X5_100")
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
        raw=data,
    )


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
