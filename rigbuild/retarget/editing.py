"""Spacetime editing of retargeted weight curves (Seol et al. 2012, sec. 6).

The animator sets new weights (some or all shapes) at one frame and gives a propagation range
``[a, b]``. The frames ``a`` and ``b`` keep their previous values as boundary conditions, the edited
weights become an extra boundary condition, and the movement-matching problem (eq. 4, with its prior
and Sobolev terms) is re-solved on the frames of the range only; frames outside it are untouched.

With the retargeting system (:class:`rigbuild.retarget.seol.SeolSystem`, saved by the stage as
``system.npz``) the edit matches the *source* marker movement, as in the paper. Without it (a bare
weight-curve file) the edit matches the movement of the previous curves themselves, shape by shape
(``B = I``, ``S = W_prev``, no prior): each edited curve becomes the old curve plus a correction that
is linear in time between the pins, and curves that were not edited do not change.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.retarget.seol import SeolSystem, shape_index


def edit_pins(
    shape_names: Sequence[str],
    values: Mapping[str, float] | np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """(K,) bool mask and (K,) values of an edit from ``{shape: value}`` or a full (K,) vector."""
    K = len(shape_names)
    mask = np.zeros(K, bool)
    vals = np.zeros(K)
    if isinstance(values, Mapping):
        if not values:
            raise InputError("the edit sets no weight", fix="give at least one shape=value")
        for name, v in values.items():
            k = shape_index(shape_names, str(name))
            fv = float(v)
            if not np.isfinite(fv):
                raise InputError(f"edit value for '{name}' is not a finite number ({v})")
            mask[k] = True
            vals[k] = fv
    else:
        arr = np.asarray(values, dtype=np.float64).reshape(-1)
        if arr.size != K:
            raise InputError(f"the edit gives {arr.size} weights for {K} shapes",
                             fix="give one value per shape, or a {shape: value} mapping")
        if not np.all(np.isfinite(arr)):
            raise InputError("the edit contains non-finite weights")
        mask[:] = True
        vals[:] = arr
    return mask, vals


def check_edit_range(frame: int, frame_range: Sequence[int], n_frames: int) -> tuple[int, int, int]:
    """Validate an edit; returns ``(frame, a, b)``. Errors name the bad value and the valid range."""
    if len(frame_range) != 2:
        raise InputError(f"the propagation range must be two frames [a, b], got {list(frame_range)}")
    a, b, e = int(frame_range[0]), int(frame_range[1]), int(frame)
    if not 0 <= e < n_frames:
        raise InputError(f"edited frame {e} is outside the sequence (frames 0..{n_frames - 1})",
                         fix=f"pick a frame between 0 and {n_frames - 1}")
    for name, f in (("start", a), ("end", b)):
        if not 0 <= f < n_frames:
            raise InputError(f"range {name} frame {f} is outside the sequence (frames 0..{n_frames - 1})",
                             fix=f"use a range inside 0..{n_frames - 1}")
    if a >= b:
        raise InputError(f"range [{a}, {b}] is empty or reversed", fix="give --range a b with a < b")
    if not a <= e <= b:
        raise InputError(f"range [{a}, {b}] does not contain the edited frame {e}",
                         fix=f"widen the range so that a <= {e} <= b")
    return e, a, b


def curve_system(weights: np.ndarray, shape_names: Sequence[str]) -> SeolSystem:
    """The system of a bare weight-curve file: movement matching of the curves themselves
    (``B = I``, ``S = W_prev``), no prior, no Sobolev term."""
    W = np.asarray(weights, dtype=np.float64)
    K = W.shape[1]
    return SeolSystem(B=np.eye(K), S=W, prior_P=np.zeros((K, K)), prior_p=np.zeros(K), alpha=0.0,
                      ridge=0.0, shape_names=list(shape_names))


def edit_spacetime(
    weights: np.ndarray,
    frame: int,
    values: Mapping[str, float] | np.ndarray,
    frame_range: Sequence[int],
    shape_names: Sequence[str] | None = None,
    system: SeolSystem | None = None,
) -> np.ndarray:
    """Spacetime edit (sec. 6): pin ``values`` at ``frame``, re-solve ``frame_range = [a, b]``.

    Parameters
    ----------
    weights : (F, K) previous weight curves (e.g. the spacetime solution).
    frame : the edited frame.
    values : ``{shape: new weight}`` (only those shapes are pinned; the others at ``frame`` are
        re-solved) or a (K,) vector (every shape pinned).
    frame_range : ``(a, b)`` with ``a <= frame <= b``; frames a and b keep their previous weights
        (except shapes pinned at ``frame`` when ``frame`` is a or b).
    shape_names : K names (default ``system.shape_names``).
    system : the retargeting system (same frames and shapes) for source-movement matching; None
        matches the previous curves' own movement (:func:`curve_system`).

    Returns the new (F, K) curves; rows outside ``[a, b]`` are identical to ``weights``.
    """
    W = np.asarray(weights, dtype=np.float64)
    if W.ndim != 2:
        raise InputError(f"weight curves must be (F, K), got {W.shape}")
    F, K = W.shape
    if shape_names is None:
        if system is None:
            raise InputError("edit_spacetime needs shape_names or a system")
        shape_names = system.shape_names
    shape_names = list(shape_names)
    if len(shape_names) != K:
        raise InputError(f"{len(shape_names)} shape names for {K} weight curves")
    if system is None:
        system = curve_system(W, shape_names)
    else:
        if system.n_frames != F or system.n_shapes != K:
            raise InputError(
                f"the system has {system.n_frames} frames x {system.n_shapes} shapes but the curves are {F} x {K}",
                fix="use the system.npz written with these weight curves",
            )
        if list(system.shape_names) and list(system.shape_names) != shape_names:
            raise InputError("the curves' shape names differ from the system's",
                             fix="edit the weight file that the system was solved for")
    e, a, b = check_edit_range(frame, frame_range, F)
    emask, evals = edit_pins(shape_names, values)
    n = b - a + 1
    mask = np.zeros((n, K), bool)
    vals = np.zeros((n, K))
    mask[[0, -1]] = True
    vals[[0, -1]] = W[[a, b]]
    mask[e - a] |= emask
    vals[e - a] = np.where(emask, evals, vals[e - a])
    out = W.copy()
    if system.bounds is None:
        out[a:b + 1] = system.solve(mask, vals, start=a, stop=b + 1)
    else:  # a bounded (and possibly sparse) solution: the re-solved range stays in the weight range
        out[a:b + 1] = system.solve_bounded(mask, vals, start=a, stop=b + 1)[0]
    return out
