"""Marker trajectories: C3D (via ezc3d) and npz. Positions in mm; NaN marks a gap (occluded marker)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.io.atomic import atomic_path, save_npz


@dataclass
class MarkerTake:
    """markers (F, M, 3) float64 mm with NaN gaps; names (M,); fps."""

    markers: np.ndarray
    names: list[str]
    fps: float

    @property
    def n_frames(self) -> int:
        return int(self.markers.shape[0])

    def subset(self, names: Sequence[str], source: str | os.PathLike | None = None) -> "MarkerTake":
        """The take restricted to ``names`` (in that order); InputError listing absent markers."""
        index = {n: i for i, n in enumerate(self.names)}
        missing = [n for n in names if n not in index]
        if missing:
            raise InputError(
                f"markers {missing} are not in the take (it has {len(self.names)} markers)",
                path=source,
                fix="use a marker map whose names match the performance's marker labels",
            )
        return MarkerTake(self.markers[:, [index[n] for n in names]], list(names), self.fps)


def write_markers_c3d(path: str | os.PathLike, markers: np.ndarray, names: Sequence[str], fps: float) -> None:
    """Write a C3D file with one point per marker (units mm; gaps as residual -1, per the C3D spec)."""
    import ezc3d

    markers = np.asarray(markers, dtype=np.float64)
    F, M, _ = markers.shape
    if len(names) != M:
        raise ValueError(f"{len(names)} names for {M} markers")
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(fps)]
    c["parameters"]["POINT"]["LABELS"]["value"] = [str(n) for n in names]
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    pts = np.ones((4, M, F))
    pts[:3] = np.transpose(np.nan_to_num(markers, nan=0.0), (2, 1, 0))
    c["data"]["points"] = pts
    gap = np.isnan(markers).any(axis=2).T  # (M, F)
    residuals = np.where(gap, -1.0, 0.0)[None]
    c["data"]["meta_points"] = {"residuals": residuals, "camera_masks": np.zeros((7, M, F), dtype=bool)}
    with atomic_path(path, suffix=".c3d") as tmp:
        c.write(str(tmp))


def write_markers_npz(path: str | os.PathLike, markers: np.ndarray, names: Sequence[str], fps: float, **extra) -> None:
    """Write ``markers`` (F, M, 3) mm, ``marker_names``, ``fps`` (+ extras) to an npz."""
    save_npz(path, markers=np.asarray(markers, np.float32), marker_names=np.asarray(list(names), dtype=str),
             fps=np.float64(fps), **extra)


def read_markers(path: str | os.PathLike) -> MarkerTake:
    """Read a marker take from ``.c3d`` or ``.npz`` (keys ``markers``, ``marker_names``, ``fps``).

    C3D units are converted to mm (m, cm, mm understood); points flagged with a negative residual
    become NaN. Raises InputError naming the file for missing, unreadable or all-gap takes.
    """
    path = Path(path)
    if not path.exists():
        raise InputError("marker file not found", path=path)
    if path.suffix.lower() == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                markers = z["markers"].astype(np.float64)
                names = [str(s) for s in z["marker_names"]]
                fps = float(z["fps"]) if "fps" in z else 30.0
        except (KeyError, ValueError, OSError) as exc:
            raise InputError(f"not a marker npz ({exc})", path=path,
                             fix="the npz needs 'markers' (F x M x 3, mm) and 'marker_names'") from None
    elif path.suffix.lower() == ".c3d":
        import ezc3d

        try:
            c = ezc3d.c3d(str(path))
        except Exception as exc:  # ezc3d raises plain RuntimeError/ValueError on corrupt files
            raise InputError(f"cannot read C3D ({exc})", path=path) from None
        pts = c["data"]["points"]  # (4, M, F)
        markers = np.transpose(pts[:3], (2, 1, 0)).astype(np.float64)
        res = c["data"]["meta_points"].get("residuals") if "meta_points" in c["data"] else None
        if res is not None and res.size:
            markers[np.transpose(res[0], (1, 0)) < 0] = np.nan
        params = c["parameters"]["POINT"]
        names = [str(s).strip() for s in params["LABELS"]["value"]]
        fps = float(params["RATE"]["value"][0])
        unit = (params["UNITS"]["value"] or ["mm"])[0].strip().lower() if "UNITS" in params else "mm"
        scale = {"mm": 1.0, "cm": 10.0, "m": 1000.0}.get(unit)
        if scale is None:
            raise InputError(f"unknown C3D point units '{unit}'", path=path)
        markers *= scale
    else:
        raise InputError("unknown marker file type", path=path, fix="use .c3d or .npz")
    if markers.ndim != 3 or markers.shape[2] != 3 or markers.shape[1] != len(names):
        raise InputError(f"marker array has shape {markers.shape} for {len(names)} names", path=path)
    if markers.shape[0] == 0 or np.isnan(markers).all():
        raise InputError("the take has no valid marker positions (all frames are gaps)", path=path)
    return MarkerTake(markers, names, fps)
