"""Synthetic motion: ROM weight sequences, rigid head motion, speech-like performances, markers."""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from rigbuild.geometry.rigid import apply_rigid
from rigbuild.retarget.plausible import ANTAGONISTS  # shape pairs a ROM never holds at once
from rigbuild.rig import Rig


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6 * x - 15) + 10)


def _bump(t: np.ndarray, start: float, peak: float, end: float) -> np.ndarray:
    """0 before ``start``, eases to 1 at ``peak``, back to 0 at ``end`` (C2 quintic smoothstep)."""
    up = _smoothstep((t - start) / max(peak - start, 1e-9))
    down = _smoothstep((end - t) / max(end - peak, 1e-9))
    return np.where(t <= peak, up, down)


def _hold_bump(t: np.ndarray, start: float, hold_start: int, hold_end: int, end: float) -> np.ndarray:
    """0 before ``start``, eases (C2 quintic) to 1 at frame ``hold_start``, holds 1 through frame ``hold_end``
    (``hold_end - hold_start + 1`` frames), eases back to 0 at ``end``."""
    up = _smoothstep((t - start) / max(hold_start - start, 1e-9))
    down = _smoothstep((end - t) / max(end - hold_end, 1e-9))
    return np.where(t < hold_start, up, np.where(t > hold_end, down, 1.0))


def hold_lengths(w: np.ndarray, tol: float = 1e-12) -> list[int]:
    """Lengths (frames) of the runs where a weight curve ``w`` (F,) sits at its maximum (within ``tol``);
    empty for a curve that is zero throughout."""
    m = float(np.max(w, initial=0.0))
    if m <= 0:
        return []
    at = np.concatenate([[False], np.abs(w - m) <= tol, [False]])
    edges = np.flatnonzero(np.diff(at.astype(np.int8)))
    return (edges[1::2] - edges[::2]).tolist()


#: Shapes defined on top of another one (ARKit's ``mouthClose`` closes the lips *against an open jaw*; with the
#: jaw closed it drives the lips through each other, a pose no actor can hold and no tracker can follow):
#: wherever such a shape is active its base is at least as active.
BASE_SHAPES: dict[str, str] = {"mouthClose": "jawOpen"}


def apply_base_shapes(weights: np.ndarray, shape_names: Sequence[str],
                      bases: Mapping[str, str] | None = None) -> np.ndarray:
    """(F, K) weights with each :data:`BASE_SHAPES` base raised to at least its dependent shape's weight
    (shapes missing from ``shape_names`` are ignored). Returns a new array."""
    W = np.array(weights, dtype=np.float64, copy=True)
    index = {n: i for i, n in enumerate(shape_names)}
    for shape, base in (BASE_SHAPES if bases is None else bases).items():
        if shape in index and base in index:
            W[:, index[base]] = np.maximum(W[:, index[base]], W[:, index[shape]])
    return W


#: Lower-face shapes (jaw, lips, cheek puff): a ROM performs them a few at a time, one after another.
LOWER_FACE_PREFIXES: tuple[str, ...] = ("jaw", "mouth", "cheekPuff", "tongue")


def is_lower_face(name: str) -> bool:
    """True for jaw, lip and cheek-puff shapes (:data:`LOWER_FACE_PREFIXES`)."""
    return name.startswith(LOWER_FACE_PREFIXES)


def antagonist_overlap(weights: np.ndarray, shape_names: Sequence[str]) -> float:
    """Largest weight two :data:`ANTAGONISTS` reach together in one frame: max over frames and pairs of
    ``min(w_a, w_b)`` (0 when no pair is active together). ``weights`` (F, K)."""
    index = {n: i for i, n in enumerate(shape_names)}
    worst = 0.0
    for pair in ANTAGONISTS:
        a, b = sorted(pair)
        if a in index and b in index:
            worst = max(worst, float(np.minimum(weights[:, index[a]], weights[:, index[b]]).max(initial=0.0)))
    return worst


def _conflicts(k: int, group: Sequence[int], shape_names: Sequence[str]) -> bool:
    """Whether shape ``k`` may not join ``group``: already there, or an upper-face antagonist is."""
    if k in group:
        return True
    if is_lower_face(shape_names[k]):
        return False
    return any(frozenset((shape_names[k], shape_names[j])) in ANTAGONISTS for j in group)


def _lane_bumps(lanes: list[list[int]], F: int, K: int, amplitude: np.ndarray,
                rng: np.random.Generator, hold: np.ndarray | None = None, min_ease: int = 2) -> np.ndarray:
    """(F, K) weights for shapes performed in turn. Lane ``i`` of ``n`` performs its shapes one after another
    in equal windows, staggered by ``i / n`` of a window against lane 0 (so two lanes never peak together);
    each bump overlaps its neighbours' by a third of a window, with jittered onset and release, and peaks
    at an integer frame. With ``hold`` (K,) integer frames, shape k holds its peak for ``hold[k]`` frames
    centred on its window (ease in and out over at least ``min_ease`` frames each strictly between 0 and
    the peak)."""
    last = F - 1
    t = np.arange(F, dtype=np.float64)
    W = np.zeros((F, K))
    n = len(lanes)
    for i, lane in enumerate(lanes):
        length = last / (len(lane) + (n - 1) / n)
        for j, k in enumerate(lane):
            centre = (j + 0.5 + i / n) * length
            peak = float(np.clip(np.round(centre), 1, last - 1))
            start = max(centre - (0.5 + 1 / 3 + rng.uniform(-0.15, 0.15)) * length, 0.0)
            end = min(centre + (0.5 + 1 / 3 + rng.uniform(-0.15, 0.15)) * length, float(last))
            if hold is None:
                W[:, k] = np.maximum(W[:, k], amplitude[k] * _bump(t, min(start, peak - 1), peak, max(end, peak + 1)))
                continue
            h = int(hold[k])
            h0 = int(np.round(centre - (h - 1) / 2))
            h0 = int(np.clip(h0, min_ease + 1, last - min_ease - h))
            h1 = h0 + h - 1
            curve = _hold_bump(t, min(start, h0 - min_ease - 1), h0, h1, max(end, h1 + min_ease + 1))
            W[:, k] = np.maximum(W[:, k], amplitude[k] * curve)
    return W


def make_rom_weights(
    shape_names: Sequence[str],
    n_sequences: int,
    frames_per_sequence: int,
    seed: int = 0,
    coverage: int = 2,
    peak_range: tuple[float, float] = (1.0, 1.0),
    lower_face_lanes: int = 2,
    antagonist_limit: float = 0.1,
    hold_frames: tuple[int, int] | None = None,
    min_ease_frames: int = 2,
) -> list[np.ndarray]:
    """Range-of-motion weight sequences.

    Every sequence starts and ends at neutral (all weights 0). A ROM is performed at full intensity: by
    default every shape's bump peaks at weight 1 (the actor's extreme of that expression); ``peak_range``
    draws the peaks uniformly from a range instead. Shapes are dealt to sequences so that
    each shape peaks in ``coverage`` different sequences with different partners.

    Inside a sequence the upper-face shapes (brows, eyes, cheeks, nose) each follow their own eased bump
    (own onset, peak frame and release), so the poses are sparse, varying combinations rather than one
    shape scaled (which would make shapes that share a sequence indistinguishable). The lower-face shapes
    (:func:`is_lower_face`) are performed in turn, as an actor does a ROM: they are dealt to
    ``lower_face_lanes`` lanes, and each lane performs its shapes one after another, so at most that many
    are near their extremes at once (stacking five full-intensity mouth shapes drives the lips through each
    other: no actor holds it, no stereo sees it). Timings are redrawn until no :data:`ANTAGONISTS` pair
    exceeds ``antagonist_limit`` together. A shape with a base (:data:`BASE_SHAPES`, e.g. ``mouthClose``
    on ``jawOpen``) is performed on it.

    ``hold_frames`` (opt-in; None: each bump touches its peak at one frame): ``(lo, hi)`` integer frames;
    each shape's bump then holds its peak for ``h ~ U{lo..hi}`` consecutive captured frames, with an ease in
    and an ease out of at least ``min_ease_frames`` frames each (at the capture rate: one weight per frame).
    A sequence too short to hold ``hi`` frames raises ValueError with the length needed.

    Returns a list of ``n_sequences`` arrays (F, K) in [0, 1].
    """
    rng = np.random.default_rng(seed)
    K = len(shape_names)
    F = int(frames_per_sequence)
    if F < 5:
        raise ValueError("a ROM sequence needs at least 5 frames (neutral, ease in, peak, ease out, neutral)")
    if lower_face_lanes < 1:
        raise ValueError("lower_face_lanes must be at least 1")
    groups: list[list[int]] = [[] for _ in range(n_sequences)]
    for rep in range(coverage):
        order = rng.permutation(K)
        for i, k in enumerate(order):
            s = (i + rep * 7) % n_sequences
            # a sequence holds a shape once; upper-face antagonists (bumps that span the sequence) go apart
            for step in range(n_sequences):
                if not _conflicts(int(k), groups[(s + step) % n_sequences], shape_names):
                    s = (s + step) % n_sequences
                    break
            else:
                s = (s + 1) % n_sequences if k in groups[s] else s
            groups[s].append(int(k))
    t = np.arange(F, dtype=np.float64)
    last = F - 1
    if hold_frames is not None:
        _check_holds(hold_frames, min_ease_frames, F, groups, shape_names, lower_face_lanes)
    seqs = []
    for g in groups:
        amplitude = rng.uniform(*peak_range, size=K)
        hold = None if hold_frames is None else rng.integers(int(hold_frames[0]), int(hold_frames[1]) + 1, size=K)
        lower = [k for k in g if is_lower_face(shape_names[k])]
        upper = [k for k in g if k not in lower]
        best, best_overlap = None, np.inf
        for _attempt in range(200):
            W = np.zeros((F, K))
            for k in upper:
                start = rng.uniform(0.0, 0.25) * last
                end = last - rng.uniform(0.0, 0.25) * last
                if hold is not None:
                    W[:, k] = np.maximum(W[:, k], amplitude[k] * _upper_hold(t, start, end, int(hold[k]),
                                                                             min_ease_frames, rng))
                    continue
                # the extreme is held at a captured frame (an integer frame: sampled bumps reach their peak)
                peak = float(np.round(rng.uniform(start + 0.25 * (end - start), end - 0.25 * (end - start))))
                W[:, k] = np.maximum(W[:, k], amplitude[k] * _bump(t, start, peak, end))
            order = [lower[i] for i in rng.permutation(len(lower))]
            n_lanes = min(lower_face_lanes, len(order))
            if n_lanes:
                W += _lane_bumps([order[i::n_lanes] for i in range(n_lanes)], F, K, amplitude, rng, hold,
                                 min_ease_frames)
            W = apply_base_shapes(W, shape_names)
            W[0] = 0.0
            W[-1] = 0.0
            overlap = antagonist_overlap(W, shape_names)
            if overlap < best_overlap:
                best, best_overlap = W, overlap
            if overlap <= antagonist_limit:
                break
        seqs.append(best)
    return seqs


def _upper_hold(t: np.ndarray, start: float, end: float, h: int, min_ease: int,
                rng: np.random.Generator) -> np.ndarray:
    """An upper-face bump over [start, end] that holds 1 for ``h`` frames placed at random in its middle half
    (ease in and out over at least ``min_ease`` frames strictly between 0 and the peak)."""
    last = int(t[-1])
    lo = int(np.ceil(max(start + min_ease + 1, start + 0.25 * (end - start) - (h - 1) / 2, min_ease + 1)))
    hi = int(np.floor(min(end - min_ease - 1, end - 0.25 * (end - start) + (h - 1) / 2, last - min_ease - 1)
                      - (h - 1)))
    if hi < lo:  # the middle half is too short: centre the hold between the eases
        lo = hi = int(np.clip(np.round((start + end) / 2 - (h - 1) / 2), min_ease + 1, last - min_ease - h))
    h0 = int(rng.integers(lo, hi + 1))
    h1 = h0 + h - 1
    return _hold_bump(t, min(start, h0 - min_ease - 1), h0, h1, max(end, h1 + min_ease + 1))


def rom_frames_needed(hold_frames: tuple[int, int], n_lane_shapes: int, lower_face_lanes: int = 2,
                      min_ease_frames: int = 2) -> int:
    """Fewest frames per ROM sequence that fit ``n_lane_shapes`` lower-face shapes per lane, each holding
    ``hold_frames[1]`` frames inside its own window (so holds in a lane never overlap) and easing in and out
    over at least ``min_ease_frames`` (the ease reaches into the neighbouring windows by their overlap, at
    least ``(1/2 + 1/3 - 0.15)`` of a window from the window's centre: :func:`_lane_bumps`)."""
    n = max(int(lower_face_lanes), 1)
    hi = int(hold_frames[1])
    window = max(hi, (int(min_ease_frames) + 1 + (hi - 1) / 2) / (0.5 + 1 / 3 - 0.15))
    return int(np.ceil(window * (max(n_lane_shapes, 1) + (n - 1) / n))) + 1


def _check_holds(hold_frames, min_ease: int, F: int, groups: list[list[int]], shape_names: Sequence[str],
                 lanes: int) -> None:
    lo, hi = int(hold_frames[0]), int(hold_frames[1])
    if not (1 <= lo <= hi):
        raise ValueError(f"hold_frames must be 1 <= lo <= hi frames, got {hold_frames}")
    if min_ease < 1:
        raise ValueError("min_ease_frames must be at least 1")
    per_lane = max((int(np.ceil(sum(is_lower_face(shape_names[k]) for k in g) / lanes)) for g in groups), default=0)
    need = max(rom_frames_needed((lo, hi), per_lane, lanes, min_ease), hi + 2 * min_ease + 2)
    if F < need:
        raise ValueError(f"frames_per_sequence={F} is too short for hold_frames={list(hold_frames)} with "
                         f"{per_lane} lower-face shapes per lane: use at least {need} frames (or more sequences)")


def make_head_motion(n_frames: int, seed: int = 0, max_rotation_deg: float = 3.0,
                     max_translation_mm: float = 5.0, bound: str = "per_axis", neutral_pose_deg: float = 0.0,
                     neutral_pose_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Smooth rigid head motion ``x' = R x + t``.

    Returns R (F, 3, 3), t (F, 3) mm. Each rotation-vector and translation component is a random
    low-frequency sinusoid mix that is 0 at frame 0.

    ``bound``: ``"per_axis"`` (default): each component is scaled to reach ``max_rotation_deg`` /
    ``max_translation_mm`` (so the rotation angle reaches up to sqrt(3) times the bound); ``"total"``: the
    rotation angle ``|rotvec|`` and the translation length ``|t|`` of the motion reach exactly the bounds at
    their largest frame.

    ``neutral_pose_deg``, ``neutral_pose_mm`` (opt-in; 0: frame 0 is the identity): frame 0 is a pose
    ``(R0, t0)`` rotated by exactly ``neutral_pose_deg`` about a random axis and shifted by exactly
    ``neutral_pose_mm`` in a random direction (an actor never sits at the rig's origin), and the motion is
    applied on top of it: ``R_f = M_f R0``, ``t_f = t0 + m_f``, so the bounds hold for the motion relative to
    the neutral frame (``R_f R0^T``, ``t_f - t0``).
    """
    from scipy.spatial.transform import Rotation

    if bound not in ("per_axis", "total"):
        raise ValueError(f"unknown head-motion bound '{bound}' (use per_axis or total)")
    rng = np.random.default_rng(seed)
    u = np.linspace(0, 1, n_frames)

    def curve() -> np.ndarray:
        c = np.zeros(n_frames)
        for _ in range(3):
            c += rng.normal() * np.sin(np.pi * u * rng.uniform(0.5, 2.0))
        m = np.abs(c).max()
        return c / m if m > 0 else c

    if bound == "per_axis":
        rv = np.stack([curve() for _ in range(3)], 1) * np.radians(max_rotation_deg)
        t = np.stack([curve() for _ in range(3)], 1) * max_translation_mm
    else:
        def total(c: np.ndarray, limit: float) -> np.ndarray:
            m = np.linalg.norm(c, axis=1).max(initial=0.0)
            return c * (limit / m) if m > 0 else c

        rv = total(np.stack([curve() for _ in range(3)], 1), np.radians(max_rotation_deg))
        t = total(np.stack([curve() for _ in range(3)], 1), float(max_translation_mm))
    R = Rotation.from_rotvec(rv).as_matrix()
    if neutral_pose_deg == 0 and neutral_pose_mm == 0:
        return R, t
    R0, t0 = neutral_pose(seed, neutral_pose_deg, neutral_pose_mm)
    return R @ R0, t + t0


def neutral_pose(seed: int, angle_deg: float, shift_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The neutral frame's head pose: a rotation (3, 3) by exactly ``angle_deg`` about a random axis and a
    translation (3,) of length exactly ``shift_mm`` (mm) in a random direction (own random stream of
    ``seed``)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng([int(seed), 0x4E50])
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    return Rotation.from_rotvec(np.radians(angle_deg) * axis).as_matrix(), float(shift_mm) * direction


def make_performance_weights(shape_names: Sequence[str], n_frames: int, fps: float, seed: int = 0,
                             active_fraction: float = 0.8) -> np.ndarray:
    """Speech-like smooth random weight curves (F, K) in [0, 1] (bases of :data:`BASE_SHAPES` follow their shapes).

    Mouth and jaw shapes get syllable-rate events (3-6 per second, 0.12-0.4 s long); brows, cheeks
    and nose get slower expression events (0.3 per second, 0.5-2 s); blinks happen every 2-6 s
    for 0.15-0.25 s on both eyes at once. A random ``1 - active_fraction`` of the non-blink shapes
    stay at zero. Events are raised-cosine bumps; overlapping events saturate smoothly
    (``1 - exp(-2x)`` scaled to reach 1).
    """
    rng = np.random.default_rng(seed)
    K = len(shape_names)
    t = np.arange(n_frames) / fps
    dur = n_frames / fps
    W = np.zeros((n_frames, K))

    def add_events(k: int, rate: float, length: tuple[float, float], amp: tuple[float, float]) -> None:
        n = rng.poisson(rate * dur)
        for _ in range(n):
            c = rng.uniform(0, dur)
            half = rng.uniform(*length) / 2
            a = rng.uniform(*amp)
            x = np.clip((t - c) / half, -1, 1)
            W[:, k] += a * 0.5 * (1 + np.cos(np.pi * x))

    blink_idx = [k for k, n in enumerate(shape_names) if n.startswith("eyeBlink")]
    others = [k for k in range(K) if k not in blink_idx]
    active = set(rng.choice(others, size=int(round(active_fraction * len(others))), replace=False).tolist()) if others else set()
    for k in others:
        if k not in active:
            continue
        n = shape_names[k]
        if n.startswith(("jaw", "mouth")):
            add_events(k, rng.uniform(0.5, 1.5), (0.12, 0.4), (0.2, 0.9))
        else:
            add_events(k, 0.3, (0.5, 2.0), (0.2, 0.8))
    if blink_idx:
        c = rng.uniform(0.5, 3.0)
        while c < dur:
            half = rng.uniform(0.15, 0.25) / 2
            x = np.clip((t - c) / half, -1, 1)
            W[:, blink_idx] += 0.5 * (1 + np.cos(np.pi * x))[:, None]
            c += rng.uniform(2.0, 6.0)
    W = (1 - np.exp(-2 * W)) / (1 - np.exp(-2.0))
    return apply_base_shapes(np.clip(W, 0.0, 1.0), shape_names)


def markers_from_rig(rig: Rig, weights: np.ndarray, R: np.ndarray | None = None, t: np.ndarray | None = None,
                     noise_mm: float = 0.0, gap_fraction: float = 0.0, seed: int = 0) -> np.ndarray:
    """Marker trajectories (F, M, 3) mm at ``rig.marker_vertices`` for weights (F, K).

    ``R`` (F, 3, 3), ``t`` (F, 3): rigid head motion applied after the expression. ``noise_mm``:
    isotropic Gaussian noise. ``gap_fraction``: about this fraction of samples become NaN, in runs of
    3-20 frames per marker (occlusions).
    """
    rng = np.random.default_rng(seed)
    if rig.marker_vertices.size == 0:
        raise ValueError(f"rig '{rig.name}' has no marker set")
    W = np.asarray(weights, dtype=np.float64)
    D = rig.deltas[:, rig.marker_vertices].reshape(rig.n_shapes, -1)
    m = (rig.neutral[rig.marker_vertices].reshape(-1) + W @ D).reshape(W.shape[0], -1, 3)
    if R is not None:
        m = np.einsum("fij,fmj->fmi", R, m) + (0 if t is None else np.asarray(t)[:, None, :])
    if noise_mm > 0:
        m = m + rng.normal(scale=noise_mm, size=m.shape)
    if gap_fraction > 0:
        F, M = m.shape[:2]
        target = gap_fraction * F * M
        gapped = 0
        while gapped < target:
            j = rng.integers(M)
            L = int(rng.integers(3, 21))
            s = int(rng.integers(0, max(F - L, 1)))
            gapped += np.count_nonzero(~np.isnan(m[s:s + L, j, 0]))
            m[s:s + L, j] = np.nan
    return m
