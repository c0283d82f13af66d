"""Initial guesses g_k of the personalized shapes (Ribera et al. 2017, sec. 4.4; eq. 11's reference).

- :func:`rbf_transfer`: the paper's thin-plate RBF ``s0 -> a0`` applied to the character's displaced markers
  (also the ``rbf`` baseline);
- :func:`deformation_guesses` (option ``guess: deformation`` and the ``deformation`` baseline): deformation
  transfer onto the character's neutral warped into the actor's proportions.
"""

from __future__ import annotations

import numpy as np

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
