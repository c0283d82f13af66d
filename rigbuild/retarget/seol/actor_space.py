"""Seol's source side from the actor's personalized rig (method ``seol_actor_rig``, issue 26).

Seol et al. 2012 (sec. 3.2) carry each target blendshape ``b_j`` into the source's proportions with one RBF
``d`` fitted between the two neutrals, ``b*_j = d(b_j)``: a map *guessed* from the neutrals, the same for every
shape. The movement matching (sec. 4) then explains the source displacements ``S`` (from the source neutral) by
``B* W``. When the actor has a personalized rig, the actor's own expression space is known at the markers: the
rig's shape ``k`` there (:func:`rigbuild.retarget.actor_rig.sample_rig_at_markers`) is what the character's shape
of the same name looks like on the actor's face. The scale map of shape ``k`` is then the one that takes the
character's shape ``k`` to the actor's shape ``k``, computed shape by shape from corresponding shapes, and
``b*_k`` is the actor's shape, rotated into the take's frame by the Kabsch fit of the rig's neutral at the
markers onto the take's neutral markers; the source neutral ``n_src`` is that fitted rig neutral, so ``S`` is
measured from the same neutral the shapes are displacements of. A character shape the rig lacks (or a marker
the marker map lacks) keeps the neutral-guessed map (``scale_match``).

:func:`actor_expression_space` builds the rotated rig at the markers; :func:`actor_space_blendshapes` puts it in
place of the guessed ``b*``. Units: mm. Shapes: M markers, K character shapes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.retarget.ribera.guesses import RigAtMarkers, rig_marker_guesses


@dataclass
class ActorExpressionSpace:
    """The actor's personalized rig at the markers in the take's frame.

    neutral (M, 3) mm: the rig's neutral at the markers, rigidly fitted onto the take's neutral markers (the take's
    measured neutral where the marker map lacks the marker); deltas (K, M, 3) mm: the rig's shape of each character
    shape's name, rotated into the take's frame (0 where ``shapes`` or ``markers`` is False); shapes (K,) bool: the
    character shape has a rig shape of the same name; markers (M,) bool: the marker is on the marker map;
    rotation (3, 3), translation (3,) mm: rig frame -> take frame; alignment_rms_mm: RMS distance (mm) of the
    fitted rig neutral to the take's neutral over the mapped markers."""

    neutral: np.ndarray
    deltas: np.ndarray
    shapes: np.ndarray
    markers: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    alignment_rms_mm: float

    @property
    def covered(self) -> np.ndarray:
        """(K, M) bool: the rig gives shape k at marker m."""
        return self.shapes[:, None] & self.markers[None, :]


def actor_expression_space(rig: RigAtMarkers, take_neutral: np.ndarray, marker_names: Sequence[str],
                           shape_names: Sequence[str]) -> ActorExpressionSpace:
    """The actor's expression space at the markers, in the frame of the take's neutral.

    rig : the personalized rig at the markers (its own frame, :func:`rigbuild.retarget.stage.load_rig_at_markers`);
    take_neutral (M, 3) mm: the actor's measured neutral markers (the ROM neutral, or the take's first frame) in
    ``marker_names`` order; shape_names (K,): the character's shapes. The rotation and translation are the Kabsch fit
    of the rig's neutral onto ``take_neutral`` over the markers both name
    (:func:`rigbuild.retarget.ribera.guesses.rig_marker_guesses`; InputError below 3 shared markers).
    """
    Y = np.asarray(take_neutral, dtype=np.float64)
    g = rig_marker_guesses(rig, Y, marker_names, shape_names)
    index = {str(n): i for i, n in enumerate(rig.marker_names)}
    rows = np.array([index[str(n)] for n, ok in zip(marker_names, g.markers) if ok], dtype=np.int64)
    b0 = np.asarray(rig.neutral, dtype=np.float64)[rows]
    t = Y[g.markers].mean(0) - g.rotation @ b0.mean(0)  # the Kabsch translation (centroids)
    neutral = Y.copy()
    neutral[g.markers] = b0 @ g.rotation.T + t
    return ActorExpressionSpace(neutral, g.dg, g.shapes, g.markers, g.rotation, t, g.alignment_rms_mm)


def actor_space_blendshapes(space: ActorExpressionSpace, guessed: np.ndarray | None) -> np.ndarray:
    """``b*`` (K, M, 3) mm: the actor's rig shape where the rig has the shape and the marker, the neutral-guessed
    ``guessed`` (K, M, 3) (``scale_match``) elsewhere; ``guessed`` may be None only when the rig covers all."""
    covered = space.covered
    if covered.all():
        return space.deltas.copy()
    if guessed is None:
        raise InputError("the personalized rig lacks some of the character's shapes or markers and no "
                         "scale-matched shapes were given for them")
    return np.where(covered[..., None], space.deltas, np.asarray(guessed, dtype=np.float64))
