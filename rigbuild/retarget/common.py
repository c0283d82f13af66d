"""Pieces shared by the marker-space retargeting methods (Ribera 2017, Seol 2012).

Conventions
-----------
- Markers are ``(F, M, 3)`` float arrays in mm, NaN where a marker is not visible (a gap).
- Sparse blendshapes are ``(K, M, 3)`` marker displacements at weight 1 (``rig.deltas[:, vertex_ids]``).
- Weight curves are ``(F, K)`` float arrays, one column per shape name.

Contents: marker-to-character mapping by marker name (with clear errors), marker-set checks for
performances, zero-phase low-pass filtering of marker trajectories, per-frame rigid stabilization of marker
frames, the actor's averaged neutral and the markers' rigidity weights. Weight-curve files:
:mod:`rigbuild.io.curves`; ground-truth metrics: :mod:`rigbuild.eval.retarget`.
"""

from __future__ import annotations

import os
from typing import Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.rig import Rig

# ----------------------------------------------------------------------------------- marker mapping
def map_markers_to_vertices(
    marker_names: Sequence[str],
    map_names: Sequence[str],
    map_vertices: Sequence[int] | np.ndarray,
    character: str = "character",
    source: str | os.PathLike | None = None,
) -> np.ndarray:
    """Vertex id on the character for each named marker.

    Parameters
    ----------
    marker_names : M marker names of the actor's marker set (in the order of the marker arrays).
    map_names, map_vertices : the character's marker-to-vertex map (names and (M',) vertex ids).
    character : character name, for messages.
    source : file the map came from, for messages.

    Returns
    -------
    (M,) int64 vertex ids in ``marker_names`` order.

    Raises
    ------
    InputError naming every marker that the character map lacks.
    """
    lookup = {str(n): int(v) for n, v in zip(map_names, np.asarray(map_vertices).reshape(-1))}
    check_marker_overlap(marker_names, list(lookup), "the actor's marker set", source, character)
    missing = [n for n in marker_names if n not in lookup]
    if missing:
        raise InputError(
            f"character '{character}' has no vertex for {len(missing)} of {len(marker_names)} markers: "
            f"{', '.join(missing[:12])}{' ...' if len(missing) > 12 else ''}",
            path=source,
            fix="add these marker names to the character's marker map (name -> vertex id), or drop the "
            "markers from the take",
        )
    return np.array([lookup[n] for n in marker_names], dtype=np.int64)


def _examples(names: Sequence[str], n: int = 4) -> str:
    names = [str(x) for x in names]
    return ", ".join(names[:n]) + (", ..." if len(names) > n else "")


def check_marker_overlap(take_names: Sequence[str], map_names: Sequence[str], what: str = "the take",
                         path: str | os.PathLike | None = None, character: str = "character") -> None:
    """InputError (naming ``path``) when none of ``take_names`` is in the marker map's ``map_names``: the take
    was captured with another marker naming than the character's map (e.g. an AnimFace take onto a
    character mapped for the synthetic ICT marker set)."""
    if set(map(str, take_names)) & set(map(str, map_names)):
        return
    raise InputError(
        f"none of {what}'s {len(take_names)} marker names ({_examples(take_names)}) is in the marker map of "
        f"'{character}' ({len(map_names)} markers: {_examples(map_names)})", path=path,
        fix="retarget with a marker map made for this take's marker set (for AnimFace takes: "
        "rigbuild/assets/marker_sets/animface_ict.json, or build one with "
        "rigbuild.retarget.marker_maps.build_landmark_marker_map), or rename the take's markers to the map's")


def character_sparse_blendshapes(rig: Rig, vertex_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Neutral marker positions and sparse blendshapes of a character.

    Returns ``s0`` (M, 3) and ``ds`` (K, M, 3) = ``rig.deltas[:, vertex_ids]``, in the rig's units.
    """
    vid = np.asarray(vertex_ids, dtype=np.int64)
    return rig.neutral[vid].copy(), rig.deltas[:, vid].copy()


def reorder_markers(
    markers: np.ndarray,
    names: Sequence[str],
    expected: Sequence[str],
    what: str = "performance",
    path: str | os.PathLike | None = None,
) -> np.ndarray:
    """Reorder ``markers`` (F, M', 3) with ``names`` into the order of ``expected`` (M names).

    Extra markers in the take are dropped. Raises :class:`InputError` if any expected marker is missing
    (a performance recorded with a different marker set than the training sequence).
    """
    names = [str(n) for n in names]
    idx = {n: i for i, n in enumerate(names)}
    missing = [n for n in expected if n not in idx]
    if missing:
        raise InputError(
            f"{what} has a different marker set: {len(missing)} of the {len(expected)} training markers are "
            f"absent ({', '.join(missing[:12])}{' ...' if len(missing) > 12 else ''})",
            path=path,
            fix="use a performance captured with the same marker set as the training (ROM) sequence, or "
            "retrain on a sequence with this marker set",
        )
    m = np.asarray(markers, dtype=np.float64)
    if m.ndim != 3 or m.shape[2] != 3 or m.shape[1] != len(names):
        raise InputError(f"{what}: markers must be (F, {len(names)}, 3), got {m.shape}", path=path)
    return m[:, [idx[n] for n in expected]]


def visible_mask(markers: np.ndarray) -> np.ndarray:
    """(F, M) bool: marker has finite x, y and z."""
    return np.all(np.isfinite(markers), axis=-1)


def check_frames(
    markers: np.ndarray,
    min_visible: int = 3,
    what: str = "performance",
    path: str | os.PathLike | None = None,
    allow_empty: bool = False,
) -> np.ndarray:
    """Check gaps in ``markers`` (F, M, 3); return the (F,) bool of frames with enough visible markers.

    Frames with fewer than ``min_visible`` visible markers cannot be solved. With ``allow_empty=False`` they
    raise :class:`InputError` listing them; with True they are reported as False so the caller can
    interpolate the weights. A take with no usable frame always raises.
    """
    vis = visible_mask(markers)
    n_vis = vis.sum(1)
    ok = n_vis >= min_visible
    if not ok.any():
        raise InputError(
            f"{what}: no frame has {min_visible} or more visible markers ({markers.shape[0]} frames, all gaps)",
            path=path,
            fix="check the marker file (units, labelling); NaN marks a gap",
        )
    if not ok.all() and not allow_empty:
        bad = np.flatnonzero(~ok)
        raise InputError(
            f"{what}: {bad.size} frame(s) have fewer than {min_visible} visible markers "
            f"(first: {', '.join(map(str, bad[:10]))})",
            path=path,
            fix="fill the gaps in the take, trim those frames, or allow empty frames (their weights are then "
            "interpolated from the neighbouring frames)",
        )
    return ok


def lowpass_sigma_frames(fps: float, cutoff_hz: float) -> float:
    """Standard deviation (frames) of the Gaussian whose response is 1/sqrt(2) (-3 dB) at ``cutoff_hz``:
    ``H(f) = exp(-2 pi^2 sigma_t^2 f^2)``, so ``sigma_t = sqrt(ln 2) / (2 pi f_c)`` = 0.1325 / f_c s."""
    fps, cutoff_hz = float(fps), float(cutoff_hz)
    if not (fps > 0 and 0 < cutoff_hz < fps / 2):
        raise InputError(f"marker low-pass cutoff {cutoff_hz} Hz must lie in (0, {fps / 2:g}) Hz (half the {fps:g} fps)",
                         path="config", fix="set marker_lowpass_hz below the Nyquist frequency, or null to disable it")
    return float(np.sqrt(np.log(2.0)) / (2.0 * np.pi * cutoff_hz) * fps)


def lowpass_markers(markers: np.ndarray, fps: float | None, cutoff_hz: float) -> np.ndarray:
    """Zero-phase Gaussian low-pass of marker trajectories, as mocap pipelines filter before solving.

    markers : (F, M, 3) mm, NaN gaps; fps : frames per second; cutoff_hz : -3 dB frequency
    (:func:`lowpass_sigma_frames`). Gaps stay NaN and do not leak into their neighbours: each sample is the
    Gaussian-weighted mean of the *visible* samples around it (normalized convolution). Sensor noise is
    white while facial motion lives below ~10 Hz, so a 5-8 Hz cutoff removes most of the noise and keeps
    the motion (an offline filter: it needs the frames after the current one).
    Returns (F, M, 3) mm.
    """
    from scipy.ndimage import gaussian_filter1d

    X = np.asarray(markers, dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != 3:
        raise InputError(f"markers must be (frames, markers, 3), got {X.shape}")
    if fps is None:
        raise InputError("marker_lowpass_hz needs the performance's fps", fix="pass fps=")
    sigma = lowpass_sigma_frames(fps, cutoff_hz)
    seen = np.isfinite(X).all(axis=2, keepdims=True)
    num = gaussian_filter1d(np.where(seen, X, 0.0), sigma, axis=0, mode="nearest", truncate=4.0)
    den = gaussian_filter1d(seen.astype(np.float64), sigma, axis=0, mode="nearest", truncate=4.0)
    out = num / np.maximum(den, 1e-12)
    out[~np.broadcast_to(seen, X.shape)] = np.nan
    return out


def interpolate_missing_rows(values: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Linear interpolation over frames of rows of ``values`` (F, K) where ``ok`` (F,) is False."""
    out = np.array(values, dtype=np.float64, copy=True)
    if ok.all():
        return out
    f = np.arange(out.shape[0])
    good = np.flatnonzero(ok)
    for k in range(out.shape[1]):
        out[~ok, k] = np.interp(f[~ok], good, out[good, k])
    return out


# ------------------------------------------------------------------------------------ stabilization
def batched_rigid_fit(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame weighted Kabsch: ``R_f, t_f`` minimizing ``sum_m w_fm |R_f src_fm + t_f - dst_fm|^2``.

    src, dst : (F, M, 3) (either may be (M, 3), broadcast over frames); weights : (F, M) non-negative (0 for gaps; NaN entries
    of src/dst must carry weight 0). Returns R (F, 3, 3), t (F, 3).
    """
    w = np.asarray(weights, dtype=np.float64)
    shape = w.shape + (3,)
    dst = np.broadcast_to(np.asarray(dst, dtype=np.float64), shape)
    src = np.broadcast_to(np.asarray(src, dtype=np.float64), shape)
    src0 = np.where(w[..., None] > 0, src, 0.0)
    dst0 = np.where(w[..., None] > 0, dst, 0.0)
    ws = np.maximum(w.sum(1), 1e-300)
    mu_s = np.einsum("fm,fmc->fc", w, src0) / ws[:, None]
    mu_d = np.einsum("fm,fmc->fc", w, dst0) / ws[:, None]
    a = np.where(w[..., None] > 0, src0 - mu_s[:, None], 0.0)
    b = np.where(w[..., None] > 0, dst0 - mu_d[:, None], 0.0)
    cov = np.einsum("fm,fmi,fmj->fij", w, b, a)
    U, _, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    D = np.zeros_like(cov)
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = U @ D @ Vt
    t = mu_d - np.einsum("fij,fj->fi", R, mu_s)
    return R, t


def bridge_rigid_motion(R: np.ndarray, t: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Head motion R (F, 3, 3), t (F, 3) with the frames where ``ok`` (F,) is False (too few markers for a
    fit) bridged from the fitted ones: rotations by spherical linear interpolation, translations linearly,
    the ends held at the nearest fitted frame. Needs at least one fitted frame. Returns new arrays."""
    from scipy.spatial.transform import Rotation, Slerp

    ok = np.asarray(ok, bool)
    R = np.array(R, dtype=np.float64, copy=True)
    t = np.array(t, dtype=np.float64, copy=True)
    if ok.all():
        return R, t
    frames = np.arange(ok.size, dtype=np.float64)
    known = np.flatnonzero(ok)
    miss = np.flatnonzero(~ok)
    for c in range(3):
        t[miss, c] = np.interp(frames[miss], frames[known], t[known, c])
    if known.size == 1:
        R[miss] = R[known[0]]
        return R, t
    q = np.clip(frames[miss], frames[known[0]], frames[known[-1]])
    R[miss] = Slerp(frames[known], Rotation.from_matrix(R[known]))(q).as_matrix()
    return R, t


def stabilize(
    markers: np.ndarray, reference: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Remove per-frame rigid head motion: map each frame onto ``reference`` (M, 3) or (F, M, 3).

    markers : (F, M, 3) with NaN gaps; weights : (M,) or (F, M) per-marker rigidity weights (default 1).
    Returns stabilized markers (F, M, 3) (NaN kept), R (F, 3, 3), t (F, 3) with ``stable = R x + t``.
    """
    vis = visible_mask(markers)
    w = np.ones(vis.shape) if weights is None else np.broadcast_to(np.asarray(weights, float), vis.shape)
    w = np.where(vis, w, 0.0)
    R, t = batched_rigid_fit(markers, reference, w)
    stable = np.einsum("fij,fmj->fmi", R, np.nan_to_num(markers)) + t[:, None, :]
    stable[~vis] = np.nan
    return stable, R, t


def refit_rig_at_markers(prior_b0: np.ndarray, prior_D: np.ndarray, markers_in_rig_frame: np.ndarray,
                         weights: np.ndarray, prior: float) -> tuple[np.ndarray, np.ndarray]:
    """The shape step of Ma et al. 2016's EM (section 3) in marker space: a rig at the markers re-estimated from
    a take's frames and their solved weights, held to a prior rig.

    prior_b0 (M, 3), prior_D (K, M, 3) mm: the rig the estimate is held to; markers_in_rig_frame (F, M, 3) mm: the
    take with its head motion removed (NaN: a gap); weights (F, K). Each marker m on its own (closed form, the
    neutral as a shape of weight 1)::

        min_(b0_m, D_m)  sum_f v_fm ||b0_m + D_m^T w_f - q_fm||^2
                         + prior (||b0_m - prior_b0_m||^2 + ||D_m - prior_D_m||^2)

    ``prior`` counts as that many frames at full weight (dimensionless; 0: the take alone). Returns (b0 (M, 3),
    D (K, M, 3)) mm."""
    q = np.asarray(markers_in_rig_frame, dtype=np.float64)
    vis = np.isfinite(q).all(2)
    v = vis.astype(np.float64)
    q = np.where(vis[..., None], q, 0.0)
    Wa = np.concatenate([np.asarray(weights, dtype=np.float64), np.ones((q.shape[0], 1))], axis=1)
    X0 = np.concatenate([np.asarray(prior_D, dtype=np.float64), np.asarray(prior_b0, dtype=np.float64)[None]],
                        axis=0).transpose(1, 0, 2)  # (M, K + 1, 3)
    A = np.einsum("fm,fk,fl->mkl", v, Wa, Wa, optimize=True) + float(prior) * np.eye(Wa.shape[1])
    B = np.einsum("fm,fk,fmc->mkc", v, Wa, q, optimize=True) + float(prior) * X0
    ridge = 1e-9 * max(1.0, float(np.abs(A).max(initial=0.0)))
    X = np.linalg.solve(A + ridge * np.eye(Wa.shape[1]), B)  # (M, K + 1, 3)
    return X[:, -1], X[:, :-1].transpose(1, 0, 2)


def average_neutral(frames: np.ndarray, rounds: int = 2) -> np.ndarray:
    """The actor's neutral (M, 3) mm as the mean of several neutral frames (N, M, 3) (NaN gaps).

    Each frame is rigidly aligned (uniform weights: all frames show the same expression) onto the current
    mean, starting from the frame with the most visible markers, and the aligned frames are averaged per
    marker over the frames where it is visible. With N frames the marker noise of the neutral drops by
    sqrt(N); every displacement ``a_f - a0`` carries that noise as a constant offset otherwise.
    Raises :class:`InputError` if a marker is visible in no frame.
    """
    X = np.asarray(frames, dtype=np.float64)
    if X.ndim == 2:
        X = X[None]
    vis = visible_mask(X)
    never = ~vis.any(0)
    if never.any():
        raise InputError(f"markers {np.flatnonzero(never).tolist()} are missing in every neutral frame",
                         fix="choose neutral frames where every marker is visible at least once")
    ref = X[int(np.argmax(vis.sum(1)))]
    for _ in range(max(rounds, 1)):
        ok = np.isfinite(ref).all(1)
        stable, _, _ = stabilize(X, np.where(ok[:, None], ref, 0.0), np.broadcast_to(ok, vis.shape))
        n = vis.sum(0)
        ref = np.where(vis[..., None], stable, 0.0).sum(0) / np.maximum(n, 1)[:, None]
    return ref


def rigidity_weights(sparse_deltas: np.ndarray, floor: float = 0.05) -> np.ndarray:
    """(M,) weights for stabilization: high for markers the expressions move little.

    ``w_m = 1 / (floor + r_m)^2`` with ``r_m`` = largest displacement of marker m over the K sparse
    blendshapes (K, M, 3), relative to the largest over all markers.
    """
    r = np.linalg.norm(sparse_deltas, axis=2).max(0)
    r = r / max(r.max(), 1e-12)
    w = 1.0 / (floor + r) ** 2
    return w / w.max()
