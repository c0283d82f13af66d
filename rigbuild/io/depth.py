"""Per-frame depth-map files of the reconstruct stage: one compressed npz per frame, all cameras.

Keys (N cameras, H x W pinhole grids: the calibrated camera with distortion removed, same K, R, t):

- ``camera_ids`` (N,) str; ``K`` (N, 3, 3); ``R`` (N, 3, 3); ``t`` (N, 3) mm; ``width``, ``height``.
- ``depth_q`` (N, H, W) uint16: camera z quantized as ``z = depth_offset_mm[i] + (q - 1) * depth_step_mm[i]``,
  0 = no depth (steps of about 0.005 mm: quantization error <= 0.0025 mm, well under the stereo noise,
  and it compresses far better than float32).
- ``confidence`` (N, H, W) uint8: NCC score * 255 (0 where no depth); ``n_views`` (N, H, W) uint8 views
  that agreed on the pixel.
- ``frame`` int; ``skipped`` bool and ``reason`` str (a frame skipped for bad input: all depth empty).

:func:`read_depth` returns a dict with float32 ``depth`` (N, H, W) mm (0 = none), float32 ``confidence``
in [0, 1] and the other keys decoded; :func:`read_depth_frame` the same as a :class:`DepthFrame`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from rigbuild.camera import Camera
from rigbuild.errors import InputError
from rigbuild.io.atomic import save_npz

FORMAT_VERSION = 1


@dataclass
class DepthFrame:
    """Decoded depth file. depth (N, H, W) float32 mm (0 = none); confidence (N, H, W) float32 [0, 1];
    n_views (N, H, W) uint8; cameras: pinhole cameras of the grids (dist = 0)."""

    camera_ids: list[str]
    depth: np.ndarray
    confidence: np.ndarray
    n_views: np.ndarray
    cameras: list[Camera]
    frame: int
    skipped: bool = False
    reason: str = ""

    def index(self, camera_id: str) -> int:
        if camera_id not in self.camera_ids:
            raise InputError(f"no depth map for camera {camera_id}", fix=f"cameras in the file: {self.camera_ids}")
        return self.camera_ids.index(camera_id)


def quantize_depth(depth: np.ndarray, step_mm: float = 0.005) -> tuple[np.ndarray, float, float]:
    """(H, W) float depth (0/NaN = none) -> (uint16 codes, offset_mm, step_mm); the step grows if the
    depth range does not fit 65534 steps."""
    d = np.nan_to_num(np.asarray(depth, dtype=np.float64), nan=0.0)
    valid = d > 0
    if not valid.any():
        return np.zeros(d.shape, np.uint16), 0.0, float(step_mm)
    lo, hi = float(d[valid].min()), float(d[valid].max())
    offset = np.floor(lo)
    step = max(float(step_mm), (hi - offset) / 65533.0)
    q = np.zeros(d.shape, np.uint16)
    q[valid] = (np.rint((d[valid] - offset) / step) + 1).astype(np.uint16)
    return q, float(offset), float(step)


def write_depth(path: str | os.PathLike, cameras: Sequence[Camera], depth: np.ndarray, confidence: np.ndarray,
                n_views: np.ndarray | None = None, frame: int = 0, skipped: bool = False, reason: str = "",
                step_mm: float = 0.005) -> None:
    """Write one frame's depth maps atomically (see the module docstring for the layout).

    cameras : the N pinhole cameras of the grids; depth (N, H, W) mm (0/NaN = none); confidence (N, H, W)
    in [0, 1]; n_views (N, H, W) or None.
    """
    depth = np.asarray(depth)
    N = len(cameras)
    if depth.shape[0] != N:
        raise ValueError(f"depth has {depth.shape[0]} maps for {N} cameras")
    qs, offs, steps = [], [], []
    for d in depth:
        q, o, s = quantize_depth(d, step_mm)
        qs.append(q)
        offs.append(o)
        steps.append(s)
    conf = np.rint(np.clip(np.nan_to_num(np.asarray(confidence, np.float64)), 0, 1) * 255).astype(np.uint8)
    conf[np.stack(qs) == 0] = 0
    nv = np.zeros(depth.shape, np.uint8) if n_views is None else np.asarray(n_views, np.uint8)
    save_npz(
        path,
        format_version=np.int32(FORMAT_VERSION),
        camera_ids=np.array([c.id for c in cameras]),
        K=np.stack([c.K for c in cameras]),
        R=np.stack([c.R for c in cameras]),
        t=np.stack([c.t for c in cameras]),
        width=np.int32(depth.shape[2]),
        height=np.int32(depth.shape[1]),
        depth_q=np.stack(qs),
        depth_offset_mm=np.asarray(offs),
        depth_step_mm=np.asarray(steps),
        confidence=conf,
        n_views=nv,
        frame=np.int64(frame),
        skipped=np.bool_(skipped),
        reason=np.array(reason),
    )


def read_depth(path: str | os.PathLike) -> dict:
    """Decode a depth file -> dict: ``depth`` (N, H, W) float32 mm (0 = none), ``confidence`` float32
    [0, 1], ``n_views`` uint8, ``camera_ids`` list, ``K``, ``R``, ``t``, ``frame``, ``skipped``, ``reason``."""
    path = Path(path)
    if not path.exists():
        raise InputError("depth file not found", path=path, fix="run the reconstruct stage for this sequence")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:  # corrupt/truncated npz
        raise InputError(f"unreadable depth file ({exc})", path=path, fix="re-run the reconstruct stage") from None
    missing = [k for k in ("camera_ids", "K", "R", "t", "depth_q", "depth_offset_mm", "depth_step_mm") if k not in data]
    if missing:
        raise InputError(f"not a rigbuild depth file (lacks {missing})", path=path, fix="re-run the reconstruct stage")
    q = data["depth_q"]
    off = data["depth_offset_mm"].astype(np.float64)[:, None, None]
    step = data["depth_step_mm"].astype(np.float64)[:, None, None]
    depth = np.where(q > 0, off + (q.astype(np.float64) - 1) * step, 0.0).astype(np.float32)
    return {
        "depth": depth,
        "confidence": data["confidence"].astype(np.float32) / 255.0,
        "n_views": data["n_views"],
        "camera_ids": [str(c) for c in data["camera_ids"]],
        "K": data["K"],
        "R": data["R"],
        "t": data["t"],
        "frame": int(data.get("frame", 0)),
        "skipped": bool(data.get("skipped", False)),
        "reason": str(data.get("reason", "")),
    }


def read_depth_frame(path: str | os.PathLike) -> DepthFrame:
    """:func:`read_depth` as a :class:`DepthFrame` (with the pinhole cameras rebuilt)."""
    d = read_depth(path)
    H, W = d["depth"].shape[1:]
    cams = [Camera(cid, W, H, d["K"][i], np.zeros(5), d["R"][i], d["t"][i]) for i, cid in enumerate(d["camera_ids"])]
    return DepthFrame(d["camera_ids"], d["depth"], d["confidence"], d["n_views"], cams, d["frame"],
                      d["skipped"], d["reason"])


def camera_depth_maps(path: str | os.PathLike, camera_ids: Sequence[str]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per camera of ``camera_ids`` (in that order): its depth map (H, W) float32 camera z mm on the file's
    undistorted pinhole grid (0 = none) and that grid's K (3, 3). A camera is found by its id in the file,
    else by its position in ``camera_ids``; InputError when the file has no map for it."""
    d = read_depth(path)
    ids, depth, K = d["camera_ids"], d["depth"], np.asarray(d["K"])
    out = []
    for i, cid in enumerate(camera_ids):
        j = ids.index(cid) if cid in ids else i
        if j >= depth.shape[0]:
            raise InputError(f"no depth map for camera {cid}", path=path, fix="re-run reconstruct")
        out.append((depth[j], K[j]))
    return out
