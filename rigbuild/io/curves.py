"""Weight-curve files: (F, K) blendshape weights over frames as CSV (``frame,time,<shape names>``) or JSON.

Written by the retargeting stages (``results/<session>/retarget/<method>/<performance>/<character>/``) and
``rigbuild edit``; read by the evaluation and the editor. Times are seconds (``frame / fps``).
"""

from __future__ import annotations

import io
import os
from typing import Mapping, Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.io.atomic import write_json, write_text


def weight_curves_csv_text(weights: np.ndarray, shape_names: Sequence[str], fps: float) -> str:
    """CSV text: header ``frame,time,<shape names>``, one row per frame (time in seconds)."""
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != len(shape_names):
        raise InputError(f"weights must be (F, {len(shape_names)}), got {w.shape}")
    F = w.shape[0]
    table = np.column_stack([np.arange(F), np.arange(F) / float(fps), w])
    buf = io.StringIO()
    buf.write("frame,time," + ",".join(shape_names) + "\n")
    np.savetxt(buf, table, delimiter=",", fmt=["%d", "%.6f"] + ["%.6f"] * w.shape[1])
    return buf.getvalue()


def write_weight_curves_csv(path: str | os.PathLike, weights: np.ndarray, shape_names: Sequence[str], fps: float) -> None:
    """Write weight curves (F, K) as CSV (``frame,time,<shape>...``) atomically."""
    write_text(path, weight_curves_csv_text(weights, shape_names, fps))


def read_weight_curves_csv(path: str | os.PathLike) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Read a CSV written by :func:`write_weight_curves_csv`: weights (F, K), shape names, times (F,)."""
    with open(path, encoding="utf-8") as fh:
        header = fh.readline().strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return data[:, 2:], header[2:], data[:, 1]


def write_weight_curves_json(
    path: str | os.PathLike,
    weights: np.ndarray,
    shape_names: Sequence[str],
    fps: float,
    meta: Mapping | None = None,
) -> None:
    """Write ``{"fps", "n_frames", "shape_names", "weights": {name: [F values]}, "meta"}`` atomically."""
    w = np.asarray(weights, dtype=np.float64)
    write_json(
        path,
        {
            "fps": float(fps),
            "n_frames": int(w.shape[0]),
            "shape_names": list(shape_names),
            "weights": {n: np.round(w[:, k], 6).tolist() for k, n in enumerate(shape_names)},
            "meta": dict(meta or {}),
        },
    )
