"""Marker trajectories: C3D (via ezc3d) and npz. Positions in mm; NaN marks a gap (occluded marker).

Every take is checked on load (:func:`validate_take`): non-finite positions and jumps faster than a face marker
moves (:data:`MAX_MARKER_SPEED_MM_S`, in mm per frame at the take's rate) become gaps, with a warning naming the
file, the marker and the frames; a take that is mostly gaps (:data:`MAX_GAP_FRACTION`) and a C3D file shorter
than its header's frame count (a truncated copy) are :class:`~rigbuild.errors.InputError`.
"""

from __future__ import annotations

import logging
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.io.atomic import atomic_path, save_npz

log = logging.getLogger(__name__)

#: The fastest a face marker is taken to move, mm/s. Jaw opening and lip motion peak at a few hundred mm/s and
#: a fast head turn moves a marker 150 mm from the neck's axis at about 1 m/s; twice that is the limit. A faster
#: step is a glitch (a swapped label, a reflection, a corrupt block); at 30 fps it is 66.7 mm per frame.
MAX_MARKER_SPEED_MM_S = 2000.0
#: A take whose marker samples are more than this fraction gaps (after the checks) is refused.
MAX_GAP_FRACTION = 0.5


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


def write_marker_sequences(path: str | os.PathLike, sequences: Mapping[str, tuple[np.ndarray, np.ndarray]],
                           names: Sequence[str], fps: float) -> None:
    """Several takes of the same markers in one npz (the range of motion at a take's markers, rule
    ``take_markers``): ``sequences`` name -> (markers (F, M, 3) mm with NaN gaps, frame numbers (F,)). Keys
    ``sequence_names``, ``marker_names``, ``fps`` and ``markers__<name>``, ``frames__<name>`` per sequence."""
    arrays = {}
    for name, (markers, frames) in sequences.items():
        arrays[f"markers__{name}"] = np.asarray(markers, np.float32)
        arrays[f"frames__{name}"] = np.asarray(frames, np.int64)
    save_npz(path, sequence_names=np.asarray(list(sequences), dtype=str),
             marker_names=np.asarray(list(names), dtype=str), fps=np.float64(fps), **arrays)


def is_marker_sequences(path: str | os.PathLike) -> bool:
    """Whether ``path`` is an npz of several sequences (:func:`write_marker_sequences`)."""
    if Path(path).suffix.lower() != ".npz" or not Path(path).exists():
        return False
    with np.load(path, allow_pickle=False) as z:
        return "sequence_names" in z.files


def read_marker_sequences(path: str | os.PathLike) -> list[tuple[str, MarkerTake]]:
    """The sequences of a :func:`write_marker_sequences` file as (name, take) in the file's order, each checked
    as :func:`read_markers` checks a take (InputError naming the file and the sequence)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            seqs = [str(s) for s in z["sequence_names"]]
            names = [str(s) for s in z["marker_names"]]
            fps = float(z["fps"])
            data = [(z[f"markers__{s}"].astype(np.float64), z[f"frames__{s}"].astype(np.int64)) for s in seqs]
    except (KeyError, ValueError, OSError) as exc:
        raise InputError(f"not a marker-sequences npz ({exc})", path=path,
                         fix="re-run rule take_markers for this performance") from None
    out = []
    for s, (markers, frames) in zip(seqs, data):
        where = f"{path} (sequence {s})"
        if markers.ndim != 3 or markers.shape[1:] != (len(names), 3):
            raise InputError(f"sequence {s}: marker array has shape {markers.shape} for {len(names)} names",
                             path=path, fix="re-run rule take_markers for this performance")
        out.append((s, MarkerTake(validate_take(markers, names, fps, where, frames), names, fps)))
    return out


def frame_ranges(frames: Sequence[int], max_ranges: int = 12) -> str:
    """``[97, 98, 99, 105]`` -> ``"97-99, 105"``; past ``max_ranges`` ranges the rest is counted, so that a log
    line stays short."""
    out: list[list[int]] = []
    frames = sorted({int(x) for x in frames})
    for f in frames:
        if out and f == out[-1][1] + 1:
            out[-1][1] = f
        else:
            out.append([f, f])
    text = ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in out[:max_ranges])
    if len(out) > max_ranges:
        rest = sum(b - a + 1 for a, b in out[max_ranges:])
        text += f" and {rest} more ({len(frames)} frames)"
    return text


def _speed_outliers(p: np.ndarray, t: np.ndarray, max_speed: float) -> np.ndarray:
    """(N,) bool: the samples of one marker's valid positions ``p`` (N, 3) mm at times ``t`` (N,) s that cannot
    be reached from the trusted samples at ``max_speed`` mm/s. The walk starts at the sample nearest the marker's
    median position (inside the take's bulk) and goes forwards and backwards, each sample compared with the last
    trusted one, so a whole block of wild values is caught, not only its edges."""
    n = p.shape[0]
    bad = np.zeros(n, dtype=bool)
    if n < 2 or np.all(np.linalg.norm(np.diff(p, axis=0), axis=1) <= max_speed * np.diff(t)):
        return bad
    anchor = int(np.argmin(np.linalg.norm(p - np.median(p, axis=0), axis=1)))
    for order in (range(anchor + 1, n), range(anchor - 1, -1, -1)):
        last = anchor
        for i in order:
            if np.linalg.norm(p[i] - p[last]) <= max_speed * abs(t[i] - t[last]):
                last = i
            else:
                bad[i] = True
    return bad


def validate_take(markers: np.ndarray, names: Sequence[str], fps: float, source: str | os.PathLike,
                  frames: np.ndarray | None = None, max_speed_mm_s: float = MAX_MARKER_SPEED_MM_S,
                  max_gap_fraction: float = MAX_GAP_FRACTION) -> np.ndarray:
    """The take's markers (F, M, 3) mm with non-finite positions and jumps faster than ``max_speed_mm_s`` made
    gaps (NaN), each logged as a warning naming ``source``, the marker and the frames (``frames`` (F,): the
    take's frame numbers, default 0..F-1; their differences over ``fps`` are the time steps). A marker that is a
    gap in every frame is warned about. InputError naming ``source`` when more than ``max_gap_fraction`` of the
    samples are gaps, or ``fps`` is not positive."""
    m = np.array(markers, dtype=np.float64)
    F = m.shape[0]
    fr = np.arange(F) if frames is None else np.asarray(frames, dtype=np.int64).reshape(-1)
    if fr.shape[0] != F:
        raise InputError(f"{fr.shape[0]} frame numbers for {F} frames", path=source)
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"frame rate {fps} is not a positive number", path=source,
                         fix="set the take's rate (C3D POINT:RATE; npz 'fps')")
    t = fr / float(fps)
    limit = f"{max_speed_mm_s:g} mm/s ({max_speed_mm_s / fps:.1f} mm per frame at {fps:g} fps)"
    for j, name in enumerate(names):
        bad = ~np.isfinite(m[:, j]).all(1) & ~np.isnan(m[:, j]).all(1)
        if bad.any():
            log.warning("%s: marker '%s': non-finite positions at frames %s become gaps", source, name,
                        frame_ranges(fr[bad]))
            m[bad, j] = np.nan
        ok = np.flatnonzero(np.isfinite(m[:, j]).all(1))
        if ok.size == 0:
            log.warning("%s: marker '%s' is a gap in every frame", source, name)
            continue
        jump = ok[_speed_outliers(m[ok, j], t[ok], max_speed_mm_s)]
        if jump.size:
            log.warning("%s: marker '%s': positions at frames %s move faster than %s and become gaps", source,
                        name, frame_ranges(fr[jump]), limit)
            m[jump, j] = np.nan
    gaps = float(np.isnan(m).any(axis=2).mean()) if m.size else 1.0
    if gaps > max_gap_fraction:
        raise InputError(f"the take is mostly gaps: {100 * gaps:.0f}% of its marker samples are missing or invalid "
                         f"(at most {100 * max_gap_fraction:.0f}% are accepted)", path=source,
                         fix="re-export the take with its markers labelled, or give a take where they are seen")
    return m


def c3d_header_frames(path: str | os.PathLike) -> int | None:
    """The frame count a C3D file's header block states (last - first + 1), or None when it cannot be read.
    Byte 1 of the header points at the parameter block, whose 4th byte is the processor type (84 Intel, 85 DEC:
    little-endian words; 86 MIPS: big-endian); header words 4 and 5 are the first and the last frame."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(512)
            if len(head) < 12:
                return None
            fh.seek(max(head[0] - 1, 0) * 512)
            param = fh.read(4)
    except OSError:
        return None
    order = ">" if len(param) == 4 and param[3] == 86 else "<"
    first, last = struct.unpack_from(order + "HH", head, 6)
    return int(last) - int(first) + 1 if last >= first else None


def read_markers(path: str | os.PathLike) -> MarkerTake:
    """Read a marker take from ``.c3d`` or ``.npz`` (keys ``markers``, ``marker_names``, ``fps``).

    C3D units are converted to mm (m, cm, mm understood); points flagged with a negative residual
    become NaN. Raises InputError naming the file for missing, unreadable, truncated or mostly-gap takes;
    non-finite positions and jumps become gaps (:func:`validate_take`). An npz may carry ``frames`` (the take's
    frame numbers, as the track stage writes them), which set the time steps of the speed check.
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
                frames = z["frames"].astype(np.int64) if "frames" in z else None
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
        stated = c3d_header_frames(path)
        if stated is not None and pts.shape[2] < stated:
            raise InputError(f"truncated C3D: the header states {stated} frames, the file holds {pts.shape[2]}",
                             path=path, fix="copy or export the take again (the file is cut short)")
        frames = None
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
    return MarkerTake(validate_take(markers, names, fps, path, frames), names, fps)
