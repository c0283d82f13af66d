"""Initial guesses g_k of the personalized shapes (Ribera et al. 2017, sec. 4.4; eq. 11's reference).

- :func:`rbf_transfer`: the paper's thin-plate RBF ``s0 -> a0`` applied to the character's displaced markers
  (also the ``rbf`` baseline);
- :func:`deformation_guesses` (option ``guess: deformation`` and the ``deformation`` baseline): deformation
  transfer onto the character's neutral warped into the actor's proportions;
- :func:`rig_marker_guesses` (method ``ribera_fit_actor_rig``, issue 26): the actor's personalized rig sampled
  at the markers, rotated into the frame of the actor's marker space, shape by shape name;
  :func:`combine_guesses` keeps another guess where the rig has no shape or no marker.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.geometry.rigid import fit_rigid_motion
from rigbuild.retarget.proportion import ProportionMap, fit_proportion_map, transfer_displacements_mesh
from rigbuild.rig import Rig

def fit_thin_plate_rbf(centres: np.ndarray, values: np.ndarray) -> ProportionMap:
    """3D thin-plate (biharmonic, ``phi(r) = r``) RBF interpolant with an affine part,
    ``f(x) = sum_i lambda_i |x - c_i| + A x + b`` with ``f(c_i) = y_i``; centres, values : (M, 3) mm.
    (:func:`rigbuild.retarget.proportion.fit_proportion_map` with kernel ``r``; M >= 4, coplanar markers
    get the minimum-norm affine part.)"""
    return fit_proportion_map(centres, values, kernel="r", allow_coplanar=True)


def rbf_transfer(s0: np.ndarray, ds: np.ndarray, a0: np.ndarray) -> np.ndarray:
    """Initial guesses ``dg`` (K, M, 3): the RBF mapping ``s0 -> a0`` applied to the character's shapes.

    ``dg_k = f(s0 + ds_k) - f(s0)`` (= ``f(s0 + ds_k) - a0``), the RBF proportion matching of Seol 2012 /
    Orvalho 2008 used as the initial guess in E_Mesh and as the RBF-transfer baseline.
    """
    f = fit_thin_plate_rbf(s0, a0)
    base = f(s0)
    return f(s0[None] + ds) - base[None]


def deformation_guesses(character: Rig, vertex_ids: np.ndarray, a0: np.ndarray, workers: int = 1) -> np.ndarray:
    """Initial guesses g_k (K, M, 3) mm by deformation transfer (``TransferParams.guess = "deformation"``).

    The thin-plate RBF that maps the character's neutral markers onto the actor's ``a0`` (M, 3) warps the
    character's whole neutral mesh into the actor's proportions; the character's blendshapes are
    deformation-transferred (Sumner and Popovic 2004) onto that proxy and sampled at ``vertex_ids`` (M,).
    Unlike the pointwise RBF guess, this carries a shape's spatial gradients (a jaw hinge that moved, a lip
    roll on a wider mouth) into the new proportions. Uses ``rigbuild.retarget.proportion``. Only the marker
    vertices are solved for (``deformation_transfer(..., sample_vertices=...)``: the support pieces that reach
    a marker; exact, not a truncation). ``workers``: processes for the per-shape solves (same result).
    """
    vid = np.asarray(vertex_ids, dtype=np.int64)
    pmap = fit_proportion_map(character.neutral[vid], np.asarray(a0, float), "r")
    return transfer_displacements_mesh(pmap, character.neutral, character.deltas, character.faces, vid, workers)


@dataclass
class RigAtMarkers:
    """The personalized rig sampled at a take's markers (:func:`rigbuild.retarget.actor_rig.sample_rig_at_markers`):
    neutral (M_r, 3) mm and deltas (K_r, M_r, 3) mm in the rig's (head) frame, marker_names (M_r,) (the marker
    map's), shape_names (K_r,) (the rig's)."""

    neutral: np.ndarray
    deltas: np.ndarray
    marker_names: list[str]
    shape_names: list[str]


@dataclass
class RigMarkerGuesses:
    """Initial guesses g_k from the actor's rig (:func:`rig_marker_guesses`).

    dg (K, M, 3) mm in the frame of the actor's neutral markers ``a0``, the character's shape order and the
    model's marker order (0 where ``shapes`` or ``markers`` is False); shapes (K,) bool: the character shape
    has a rig shape of the same name; markers (M,) bool: the model's marker is on the marker map;
    rotation (3, 3): rig frame -> ``a0``'s frame; alignment_rms_mm: RMS distance (mm) of the rotated and
    translated rig neutral to ``a0`` over the shared markers."""

    dg: np.ndarray
    shapes: np.ndarray
    markers: np.ndarray
    rotation: np.ndarray
    alignment_rms_mm: float


def rig_marker_guesses(rig: RigAtMarkers, a0: np.ndarray, marker_names: Sequence[str],
                       shape_names: Sequence[str]) -> RigMarkerGuesses:
    """Initial guesses g_k of the actor blendshapes from the actor's personalized rig at the markers.

    rig : the rig at the markers (its own frame); a0 (M, 3) mm the actor's neutral markers (the Ribera model's
    marker space, e.g. the capture frame), ``marker_names`` (M,) their names; ``shape_names`` (K,) the
    character's shapes. The rotation ``R`` is the Kabsch fit of the rig's neutral onto ``a0`` over the markers
    both name; g_k of character shape k is ``R`` applied to the rig's shape of the same name (displacements:
    no translation), marker by marker by name. InputError when fewer than 3 markers are shared.
    """
    a0 = np.asarray(a0, dtype=np.float64)
    names = [str(n) for n in marker_names]
    if a0.shape != (len(names), 3):
        raise InputError(f"actor neutral {a0.shape} does not match the {len(names)} marker names")
    b0 = np.asarray(rig.neutral, dtype=np.float64)
    D = np.asarray(rig.deltas, dtype=np.float64)
    rig_marker = {str(n): i for i, n in enumerate(rig.marker_names)}
    rig_shape = {str(n): i for i, n in enumerate(rig.shape_names)}
    on_map = np.array([n in rig_marker for n in names], dtype=bool)
    if on_map.sum() < 3:
        raise InputError(f"only {int(on_map.sum())} of the {len(names)} markers of the actor's marker space are on "
                         f"the personalized rig's marker map (need 3 for its rotation)",
                         fix="place the take's markers on the personalized rig (rule actor_rig_weights) with the "
                             "ROM sequences' marker names")
    rows = np.array([rig_marker[n] for n, ok in zip(names, on_map) if ok], dtype=np.int64)
    R, t = fit_rigid_motion(b0[rows], a0[on_map])
    rms = float(np.sqrt(np.mean(np.sum((b0[rows] @ R.T + t - a0[on_map]) ** 2, axis=1))))
    has = np.array([str(n) in rig_shape for n in shape_names], dtype=bool)
    dg = np.zeros((len(shape_names), len(names), 3))
    k_rig = np.array([rig_shape[str(n)] for n, ok in zip(shape_names, has) if ok], dtype=np.int64)
    if k_rig.size:
        dg[np.ix_(has, on_map)] = D[k_rig][:, rows] @ R.T
    return RigMarkerGuesses(dg, has, on_map, R, rms)


def combine_guesses(rig: RigMarkerGuesses, fallback: np.ndarray | None) -> np.ndarray:
    """g_k (K, M, 3) mm: the rig's guesses where it has the shape and the marker, ``fallback`` (K, M, 3) elsewhere
    (None: only allowed when the rig covers every shape and marker)."""
    covered = rig.shapes[:, None] & rig.markers[None, :]
    if covered.all():
        return rig.dg.copy()
    if fallback is None:
        raise InputError("the personalized rig lacks some shapes or markers and no other guess was given")
    return np.where(covered[..., None], rig.dg, np.asarray(fallback, dtype=np.float64))
