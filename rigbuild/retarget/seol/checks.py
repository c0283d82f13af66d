"""Argument checks shared by the spacetime solve: frame indices, weight intervals, shape names."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from rigbuild.errors import InputError

def _frame_indices(frames: Sequence[int], n_frames: int, what: str) -> np.ndarray:
    out = []
    for f in frames:
        fi = int(f)
        if fi < -n_frames or fi >= n_frames:
            raise InputError(
                f"{what}: frame {fi} is outside the sequence (frames 0..{n_frames - 1})",
                fix=f"use frames between 0 and {n_frames - 1} (negative values count from the end)",
            )
        out.append(fi % n_frames)
    return np.asarray(out, dtype=np.int64)


def weight_interval(bounds: Sequence[float]) -> tuple[float, float]:
    """``(lo, hi)`` as floats; :class:`InputError` unless ``lo < hi``."""
    lo, hi = (float(v) for v in bounds)
    if not lo < hi:
        raise InputError(f"weight bounds {list(bounds)} are not an interval", path="config",
                         fix="give [low, high] with low < high, e.g. [0, 1]")
    return lo, hi


def shape_index(shape_names: Sequence[str], name: str) -> int:
    """Index of ``name`` in ``shape_names``; :class:`InputError` listing the known names if absent."""
    try:
        return list(shape_names).index(name)
    except ValueError:
        raise InputError(f"weight name '{name}' is not a shape of the rig",
                         fix=f"use one of: {', '.join(shape_names)}") from None
