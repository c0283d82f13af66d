"""What animators expect of a solve, as data and as numbers: antagonistic shape pairs, facial regions of
shapes, and the plausibility metrics of a weight sequence (no ground truth needed; reported by the
retargeting jobs and by ``benchmarks/bench_retarget_real.py``).

- :data:`ANTAGONISTS`: shape pairs that pull the same tissue opposite ways (or put the lips through each
  other); a performance never holds both. The ARKit/ICT shape names.
- :func:`shape_region`: the facial region of a shape name (``eyes``, ``brows``, ``nose``, ``cheeks``,
  ``jaw``, ``mouth``).
- :func:`plausibility_metrics`: fraction of frames with an antagonist pair both above 0.3, mean number of
  shapes above 0.1 per frame, RMS second difference, and for named still regions the fraction of frames
  with one of their shapes above 0.2.

The solver options that use these (sparsity reweighting, antagonist exclusion, still-region gating) are in
:mod:`rigbuild.retarget.ribera.plausible`.
"""

from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np

#: unsided antagonist pairs
_CENTRE_PAIRS = [("mouthLeft", "mouthRight"), ("jawLeft", "jawRight"), ("mouthFunnel", "mouthRollLower"),
                 ("mouthFunnel", "mouthRollUpper"), ("mouthPucker", "mouthRollLower"), ("mouthPucker", "mouthRollUpper"),
                 ("mouthClose", "mouthFunnel"), ("mouthRollLower", "mouthShrugLower"),
                 ("mouthRollUpper", "mouthShrugUpper")]
#: a centre shape against both sides of a sided one (``mouthPucker`` vs ``mouthStretch_L`` and ``_R``)
_CENTRE_SIDED = [("mouthPucker", "mouthStretch"), ("mouthPucker", "mouthSmile"), ("mouthFunnel", "mouthPress"),
                 ("mouthClose", "mouthLowerDown"), ("mouthClose", "mouthUpperUp"), ("mouthRollLower", "mouthLowerDown"),
                 ("mouthRollUpper", "mouthUpperUp")]
#: sided shapes against each other on the same side (``eyeBlink_L`` vs ``eyeWide_L``)
_SAME_SIDE = [("mouthSmile", "mouthFrown"), ("mouthPress", "mouthLowerDown"), ("eyeBlink", "eyeWide"),
              ("eyeSquint", "eyeWide"), ("eyeLookUp", "eyeLookDown"), ("eyeLookIn", "eyeLookOut"),
              ("browDown", "browInnerUp"), ("browDown", "browOuterUp")]
#: Shape pairs that pull the same tissue opposite ways (or put the lips through each other): a performance
#: never holds both at once. (The project's one table; ``rigbuild.synth.motion`` uses it for its ROMs.)
ANTAGONISTS: frozenset[frozenset[str]] = frozenset(
    [frozenset(p) for p in _CENTRE_PAIRS]
    + [frozenset((c, f"{s}_{side}")) for c, s in _CENTRE_SIDED for side in "LR"]
    + [frozenset((f"{a}_{side}", f"{b}_{side}")) for a, b in _SAME_SIDE for side in "LR"]
)

#: shape-name prefix -> facial region (first match wins; ARKit / ICT names)
REGION_PREFIXES: tuple[tuple[str, str], ...] = (
    ("eye", "eyes"), ("brow", "brows"), ("nose", "nose"), ("cheek", "cheeks"), ("jaw", "jaw"),
    ("mouth", "mouth"), ("tongue", "mouth"))

#: thresholds of the plausibility metrics (weight units)
ANTAGONIST_LEVEL = 0.3
ACTIVE_LEVEL = 0.1
STILL_LEVEL = 0.2


def shape_region(name: str) -> str:
    """Facial region of a shape name (:data:`REGION_PREFIXES`), ``"other"`` when none matches."""
    for prefix, region in REGION_PREFIXES:
        if name.startswith(prefix):
            return region
    return "other"


def antagonist_pairs(shape_names: Sequence[str]) -> np.ndarray:
    """(P, 2) index pairs into ``shape_names`` of the :data:`ANTAGONISTS` both present (sorted rows)."""
    index = {n: i for i, n in enumerate(shape_names)}
    pairs = sorted(tuple(sorted(index[n] for n in p)) for p in ANTAGONISTS if all(n in index for n in p))
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def antagonist_frames(weights: np.ndarray, shape_names: Sequence[str], level: float = ANTAGONIST_LEVEL) -> np.ndarray:
    """(F,) bool: frames of ``weights`` (F, K) where some antagonist pair is above ``level`` together."""
    p = antagonist_pairs(shape_names)
    if p.size == 0:
        return np.zeros(weights.shape[0], bool)
    return (np.minimum(weights[:, p[:, 0]], weights[:, p[:, 1]]) > level).any(1)


def plausibility_metrics(weights: np.ndarray, shape_names: Sequence[str],
                         still_regions: Iterable[str] = ()) -> dict[str, float]:
    """Plausibility numbers of a weight sequence ``weights`` (F, K):

    ``antagonist_fraction`` (frames with an antagonist pair both above 0.3), ``worst_antagonist_pair`` and its
    fraction, ``mean_active`` (shapes above 0.1 per frame, mean over frames), ``second_difference_rms`` (per
    frame^2), and ``still_fraction`` (frames where a shape of ``still_regions`` is above 0.2; absent when no
    region is given), with ``still_max`` the largest such weight.
    """
    W = np.asarray(weights, float)
    names = list(shape_names)
    p = antagonist_pairs(names)
    out: dict[str, float] = {"frames": int(W.shape[0])}
    if p.size:
        both = np.minimum(W[:, p[:, 0]], W[:, p[:, 1]]) > ANTAGONIST_LEVEL  # (F, P)
        out["antagonist_fraction"] = float(both.any(1).mean())
        j = int(np.argmax(both.mean(0)))
        out["worst_antagonist_pair"] = f"{names[p[j, 0]]}+{names[p[j, 1]]}"
        out["worst_antagonist_pair_fraction"] = float(both[:, j].mean())
    else:
        out["antagonist_fraction"] = 0.0
    out["mean_active"] = float((W > ACTIVE_LEVEL).sum(1).mean())
    out["second_difference_rms"] = float(np.sqrt(np.mean(np.diff(W, 2, axis=0) ** 2))) if W.shape[0] > 2 else 0.0
    regions = set(still_regions)
    if regions:
        k = [i for i, n in enumerate(names) if shape_region(n) in regions]
        sub = W[:, k] if k else np.zeros((W.shape[0], 0))
        out["still_fraction"] = float((sub > STILL_LEVEL).any(1).mean()) if k else 0.0
        out["still_max"] = float(sub.max(initial=0.0))
    return out
