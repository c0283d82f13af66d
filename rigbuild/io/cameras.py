"""``cameras.json``: a list of cameras (see :class:`rigbuild.camera.Camera`), mm, OpenCV axes."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Sequence

from rigbuild.camera import Camera
from rigbuild.errors import InputError
from rigbuild.io.atomic import write_json


def read_cameras(path: str | os.PathLike) -> list[Camera]:
    """Read ``cameras.json`` -> list of :class:`Camera` (file order)."""
    path = Path(path)
    if not path.exists():
        raise InputError("camera file not found", path=path, fix="run the calibration rule first")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON ({exc})", path=path) from None
    entries = data["cameras"] if isinstance(data, dict) else data
    cams = [Camera.from_dict(d, source=str(path)) for d in entries]
    ids = [c.id for c in cams]
    if len(set(ids)) != len(ids):
        raise InputError(f"duplicate camera ids {sorted({i for i in ids if ids.count(i) > 1})}", path=path)
    return cams


def write_cameras(path: str | os.PathLike, cameras: Sequence[Camera], **meta) -> None:
    """Write ``cameras.json`` atomically: ``{"units": "mm", "convention": ..., "cameras": [...]}``."""
    write_json(
        path,
        {
            "units": "mm",
            "convention": "x_cam = R x_world + t; OpenCV axes (x right, y down, z forward); "
            "pixel centres at integer coordinates; dist = [k1, k2, p1, p2, k3]",
            **meta,
            "cameras": [c.to_dict() for c in cameras],
        },
    )
