"""The Sobolev variant of the movement matching (Seol et al. 2012, sec. 7.1): per-marker (region) weights
beta, optionally only at chosen frames, and a uniform beta from a corner frequency."""

from __future__ import annotations

import re
from typing import Mapping, Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.retarget.seol.checks import _frame_indices

def sobolev_beta(marker_names: Sequence[str], region_betas: Mapping[str, float],
                 n_frames: int | None = None, frames: Sequence[int] | None = None) -> np.ndarray:
    """Per-marker Sobolev weights ``beta`` (sec. 7.1) from regions given as name patterns.

    region_betas : ``{regex: beta}`` matched (case-insensitive, ``re.search``) against marker names,
    e.g. ``{"lip|mouth": 1.0, "lid": 0.5}``; a marker takes the largest matching beta, else 0.
    frames : if given (with ``n_frames``), beta applies only at those frames (e.g. where the lips
    must close) and the result is (n_frames, M); otherwise (M,) for every frame.
    """
    beta = np.zeros(len(marker_names))
    for pattern, value in region_betas.items():
        rx = re.compile(pattern, re.IGNORECASE)
        hit = np.array([bool(rx.search(n)) for n in marker_names])
        beta[hit] = np.maximum(beta[hit], float(value))
    if frames is None:
        return beta
    if n_frames is None:
        raise InputError("sobolev_beta: frames given without n_frames")
    out = np.zeros((n_frames, beta.size))
    fr = _frame_indices(frames, n_frames, "Sobolev frames")
    out[fr] = beta
    return out


def sobolev_beta_from_corner_hz(n_markers: int, corner_hz: float, fps: float) -> np.ndarray:
    """(M,) uniform sec. 7.1 Sobolev weights ``beta = (2 pi corner_hz / fps)^2`` for every marker.

    Per temporal frequency ``w`` (radians per frame) the velocity term weighs a residual by
    ``2 - 2 cos w ~ w^2`` and the position term by ``beta``: with this beta, residual motion slower
    than ``corner_hz`` is charged as position error (no drift of the weights over a long take, e.g.
    after a gap or against the prior's pull), faster motion as velocity error (the paper's movement
    matching). Independent of units and marker count; 1 Hz at 60 fps gives 0.011.
    """
    if corner_hz < 0 or fps <= 0:
        raise InputError(f"Sobolev corner {corner_hz} Hz at {fps} fps", fix="use corner_hz >= 0 and fps > 0")
    return np.full(int(n_markers), (2.0 * np.pi * float(corner_hz) / float(fps)) ** 2)
