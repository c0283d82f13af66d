"""Scale-proportion matching (Seol et al. 2012, sec. 3.2): the RBF warp from the target's neutral
markers to the source's, applied to the target's marker blendshapes (the options beside it are in
:mod:`rigbuild.retarget.proportion`)."""

from __future__ import annotations

import numpy as np

from rigbuild.retarget.proportion import ProportionMap, fit_proportion_map

#: ``d(x) = sum_i w_i |x - c_i| + a_0 + A x`` (sec. 3.2): a :class:`~rigbuild.retarget.proportion.ProportionMap`
#: with ``phi(r) = r`` (centers (n, 3); weights (n, 3); affine (4, 3) rows [1, x, y, z]).
RbfWarp = ProportionMap


def fit_rbf_warp(centers: np.ndarray, targets: np.ndarray) -> RbfWarp:
    """Fit the interpolating RBF with ``phi(r) = r`` plus a linear polynomial: ``d(c_i) = targets_i``.

    centers : (n, 3) target-neutral marker positions; targets : (n, 3) source-neutral positions.
    Solves ``[[Phi, P], [P^T, 0]] [w; a] = [targets; 0]`` (n + 4 unknowns per coordinate); ``d``
    reproduces affine maps exactly. Needs n >= 4 non-coplanar centers.
    (:func:`rigbuild.retarget.proportion.fit_proportion_map` with ``kernel="r"``.)
    """
    return fit_proportion_map(centers, targets, "r")


def scale_proportion_match(
    target_neutral: np.ndarray, target_deltas: np.ndarray, source_neutral: np.ndarray
) -> tuple[np.ndarray, np.ndarray, RbfWarp]:
    """Deform the target's marker blendshapes to the source's scale and proportion (sec. 3.2).

    target_neutral : (M, 3) target neutral markers; target_deltas : (K, M, 3) marker deltas of the
    target's shapes; source_neutral : (M, 3) source neutral markers (all mm).
    Returns ``neutral* = d(n)`` (= source_neutral up to round-off), ``deltas*_k = d(n + b_k) - d(n)``
    (K, M, 3), and the warp ``d``.
    """
    warp = fit_rbf_warp(target_neutral, source_neutral)
    n_star = warp(target_neutral)
    shapes_star = warp(np.asarray(target_neutral)[None] + np.asarray(target_deltas))
    return n_star, shapes_star - n_star[None], warp
