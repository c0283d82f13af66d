"""Plausibility options of the retargeting solve (not in Ribera et al. 2017; beside eq. 16, off by default).

What animators expect of a solve, as per-frame terms and bounds of the bounded problem ``lo <= w <= hi``
(weights from 0: every option needs ``bounds`` with lo >= 0):

- **sparsity** ``"log"``: eq. 16's ``(lambda/K)|w|_1`` is linear for w >= 0 (it shifts the right-hand side and
  the bounded solve is exact; the paper's IRLS never runs). The option replaces it by the concave log penalty
  ``(lambda/K) sum_k eps log(1 + w_k / eps)`` (reweighted L1, Candes, Wakin and Boyd 2008): the same slope
  lambda/K at 0, so a shape must explain at least that much fit to switch on, but a slope
  ``lambda/K / (1 + w/eps)`` that falls off once it is on, so the shapes that carry the expression are not
  shrunk. Minimized by majorize-minimize: each pass is the exact bounded solve with the linear term
  :func:`reweighted_slopes` of the previous pass's weights (:data:`REWEIGHT_PASSES` passes).
- **antagonists**: no frame holds both shapes of an antagonist pair
  (:data:`rigbuild.retarget.plausible.ANTAGONISTS`). First a penalty ``gamma w_a w_b`` linearized at the
  previous pass's (smoothed) weights pushes one of each pair to yield (:func:`antagonist_slopes`, in the same
  majorize-minimize passes); then where both are still on, the weaker (over a short temporal window) is
  pinned at 0 and the frame re-solved (:func:`antagonist_pins`), until no pair is on together. Measured on the
  AnimFace takes: pins alone make the curves rougher (RMS second difference 0.0065 -> 0.0138), the push
  first keeps them smooth (0.0043; docs/decisions.md).
- **still regions**: a shape whose markers (its support: markers it moves by at least half its largest
  displacement, :func:`support_masks`) show no motion above noise in a frame is held at 0 there. "Noise" for
  marker m is ``still_ratio`` of the marker's range over the training (ROM) sequence (99th percentile of its
  displacement, :func:`marker_ranges`): skin slide, stabilization residual and sensor noise move a marker
  by a small fraction of what its expressions do. The shape's upper bound ramps from 0 (its support's largest
  motion at 1x that level) to the rig's bound (2x): :func:`still_upper_bounds`.
- **temporal coherence**: every decision above (reweighting slopes, which antagonist yields, the still-region
  evidence) is taken on weights / motion smoothed over ``coherence_frames`` (Gaussian sigma, frames), so a
  choice does not flip from one frame to the next. The solve itself stays per frame.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d

from rigbuild.retarget.common import visible_mask

#: majorize-minimize passes of the log sparsity penalty (at most; they stop once no weight moves by more
#: than REWEIGHT_TOLERANCE)
REWEIGHT_PASSES = 3
REWEIGHT_TOLERANCE = 1e-4
#: rounds of antagonist exclusion (each pins the weaker shape of every pair still on together)
ANTAGONIST_ROUNDS = 4
#: a shape moves a marker of its support by at least this fraction of its largest marker displacement
SUPPORT_LEVEL = 0.5
#: marker range over the training sequence: this percentile of its displacement (mm)
RANGE_PERCENTILE = 99.0
#: weights above this count as "on" for the antagonist exclusion
ON_LEVEL = 1e-3


def smooth_time(x: np.ndarray, frames: float) -> np.ndarray:
    """``x`` (F, ...) smoothed along axis 0 with a Gaussian of sigma ``frames`` (unchanged for <= 0 or F = 1)."""
    if frames <= 0 or x.shape[0] < 2:
        return x
    return gaussian_filter1d(x, frames, axis=0, mode="nearest")


def reweighted_slopes(w: np.ndarray, lam: float, eps: float, coherence_frames: float) -> np.ndarray:
    """(F, K) linear coefficients of the log penalty's majorizer at weights w (F, K):
    ``lam / (1 + w~ / eps)``, w~ = w smoothed over ``coherence_frames``."""
    ws = np.maximum(smooth_time(w, coherence_frames), 0.0)
    return lam / (1.0 + ws / eps)


def support_masks(dp: np.ndarray, level: float = SUPPORT_LEVEL) -> np.ndarray:
    """(K, M) bool: the markers each shape dp (K, M, 3) moves by at least ``level`` of its largest one."""
    n = np.linalg.norm(dp, axis=2)
    mx = n.max(1, keepdims=True)
    return (n >= level * mx) & (mx > 1e-9)


def marker_ranges(da: np.ndarray, percentile: float = RANGE_PERCENTILE) -> np.ndarray:
    """(M,) the range of each marker over stabilized training displacements da (F, M, 3) (NaN gaps): the
    ``percentile`` of its displacement length, mm (0 for a marker never seen)."""
    d = np.linalg.norm(da, axis=2)
    out = np.zeros(d.shape[1])
    for m in range(d.shape[1]):
        v = d[:, m][np.isfinite(d[:, m])]
        out[m] = float(np.percentile(v, percentile)) if v.size else 0.0
    return out


def still_upper_bounds(da: np.ndarray, support: np.ndarray, noise: np.ndarray, hi: float,
                       coherence_frames: float) -> np.ndarray:
    """(F, K) upper bounds from the still-region test: da (F, M, 3) stabilized displacements (NaN gaps),
    support (K, M) bool, noise (M,) mm (the "no motion" level of each marker), hi the rig's upper bound.

    Evidence of shape k in frame f: the largest ``|da_fm| / noise_m`` over its visible support markers
    (smoothed over ``coherence_frames``); the bound is ``hi * clip(evidence - 1, 0, 1)``. A shape whose
    support is hidden in a frame keeps ``hi`` (no evidence either way)."""
    vis = visible_mask(da)
    ratio = np.where(vis, np.linalg.norm(np.nan_to_num(da), axis=2) / np.maximum(noise, 1e-6)[None], -np.inf)
    ev = np.max(np.where(support[None], ratio[:, None, :], -np.inf), axis=2)  # (F, K)
    unseen = ~np.isfinite(ev)
    ev = smooth_time(np.where(unseen, 2.0, ev), coherence_frames)
    return hi * np.clip(ev - 1.0, 0.0, 1.0)


def antagonist_slopes(w: np.ndarray, pairs: np.ndarray, gamma: float, coherence_frames: float) -> np.ndarray:
    """(F, K) linear coefficients of the antagonist penalty ``gamma sum_pairs w_a w_b`` linearized at the
    weights w (F, K) smoothed over ``coherence_frames``: shape a pays ``gamma w~_b`` per unit weight (the
    push that makes one of the pair yield before :func:`antagonist_pins` has to)."""
    out = np.zeros(w.shape)
    if pairs.size == 0 or gamma <= 0:
        return out
    ws = np.maximum(smooth_time(w, coherence_frames), 0.0)
    a, b = pairs[:, 0], pairs[:, 1]
    np.add.at(out.T, a, gamma * ws[:, b].T)
    np.add.at(out.T, b, gamma * ws[:, a].T)
    return out


def antagonist_pins(w: np.ndarray, pairs: np.ndarray, coherence_frames: float) -> np.ndarray:
    """(F, K) bool: shapes to pin at 0 so that no antagonist pair (P, 2) is on together in w (F, K): in each
    frame where both are above :data:`ON_LEVEL`, the one with the smaller weight smoothed over
    ``coherence_frames`` yields, there and in the frames within ``2 coherence_frames`` around where it is
    still the smaller one (so it does not switch back on the next frame)."""
    pin = np.zeros(w.shape, bool)
    if pairs.size == 0:
        return pin
    ws = smooth_time(w, coherence_frames)
    a, b = pairs[:, 0], pairs[:, 1]
    both = (w[:, a] > ON_LEVEL) & (w[:, b] > ON_LEVEL)  # (F, P)
    b_loses = ws[:, a] >= ws[:, b]  # (F, P)
    r = int(np.ceil(2 * coherence_frames))
    if r > 0 and w.shape[0] > 1:
        from scipy.ndimage import binary_dilation

        near = binary_dilation(both, structure=np.ones((2 * r + 1, 1), bool))
    else:
        near = both
    pin_b = near & b_loses
    pin_a = near & ~b_loses
    f, p = np.nonzero(pin_b)
    pin[f, b[p]] = True
    f, p = np.nonzero(pin_a)
    pin[f, a[p]] = True
    return pin
