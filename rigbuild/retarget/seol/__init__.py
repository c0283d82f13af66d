"""Spacetime expression cloning for blendshapes (Seol, Lewis, Seo, Choi, Anjyo, Noh 2012).

Every part of the paper, in marker space:

- sec. 3.1 head motion removal by Procrustes against the source neutral, kept for re-synthesis:
  :func:`remove_head_motion`, :func:`head_motion_about_pivot`, :func:`apply_head_motion`;
- sec. 3.2 scale-proportion matching: an RBF warp ``d(x) = sum_i w_i |x - c_i| + q(x)`` (linear
  polynomial ``q``) from the target's neutral markers to the source's, applied to the marker positions
  of every target blendshape: :func:`fit_rbf_warp`, :func:`scale_proportion_match`; options beside it
  (``scale_match`` of :func:`retarget_seol`, :mod:`rigbuild.retarget.proportion`): deformation transfer
  of the target's blendshapes onto the RBF-warped target mesh (``"deformation"``, the inverse of how
  stylized rigs are built), the RBF's Jacobian, per-marker local affine maps, other kernels;
- sec. 4 movement matching ``min_W ||D (B W)^T - D S^T||_F^2`` with boundary frames (pins);
- sec. 5 the PCA prior of the target's blendshapes ``E_prior = v^T Lambda^-1 v``,
  ``v = E^T (B w + n_tgt - t_bar)``: :func:`build_pca_prior`; ``E = E_match + alpha E_prior`` solved as
  one sparse system over all frames: :meth:`SeolSystem.solve`;
- sec. 7 / fig. 11 the per-frame baselines (no constraint, weights in [-0.5, 1.5], PCA prior) and the
  velocity error: :func:`solve_perframe_unconstrained`, :func:`solve_perframe_range`,
  :func:`solve_perframe_prior`, :func:`velocity_error_per_frame`;
- prior strength as a corner frequency (:func:`alpha_from_corner_hz`) and a combination training set
  for the prior (:func:`sparse_combination_weights`); marker gaps left out of the energy
  (``visibility`` of :class:`SeolSystem`, ``gaps="mask"`` of :func:`retarget_seol`);
- sec. 7.1 the Sobolev variant ``+ sum_t (B w_t - s_t)^T diag(beta_t) (B w_t - s_t)``, beta per marker
  (region) and optionally only at chosen frames: ``beta`` of :class:`SeolSystem`, :func:`sobolev_beta`.

Spacetime editing (sec. 6) is in :mod:`rigbuild.retarget.editing` and uses :meth:`SeolSystem.solve`
on a frame window.

The normal equations of ``E`` over frames are block tridiagonal in time (K x K blocks):
``A_t = deg_t G + alpha P + Q_t``, off-diagonal ``-G`` with ``G = B^T B``, ``P = B^T E Lambda^-1 E^T B``,
``Q_t = B^T diag(beta_t) B``. When every pin fixes whole frames and beta does not vary in time the
matrix is the Kronecker sum ``L (x) G + I (x) (alpha P + Q)`` (L the path Laplacian of the free
frames); a generalized eigendecomposition ``U^T G U = I, U^T (alpha P + Q) U = diag(mu)`` decouples it
into K scalar tridiagonal systems ``(L + mu_k I) y_k = ...`` solved with one LAPACK ``gtsv`` call
(:func:`_solve_kronecker`). Otherwise (pins of single shapes, frame-varying beta) a block Thomas
(block LDL^T) recursion is used (:func:`solve_block_tridiagonal`). Both cost O(frames).

Conventions: marker positions in mm; ``S`` is (F, 3M) source displacements from the source neutral
after head motion removal, flattened marker-major (x, y, z per marker); ``B`` is (3M, K), the
columns the target's (deformed) marker blendshape deltas; weights ``W`` are (F, K) (the paper's W^T).

Modules (one concept each):

- :mod:`.head_motion`: sec. 3.1 head motion (and the occlusion bridging);
- :mod:`.scale_match`: sec. 3.2 scale-proportion matching;
- :mod:`.actor_space`: the source side from the actor's personalized rig (method ``seol_actor_rig``);
- :mod:`.prior`: sec. 5 PCA prior and its corner-frequency strength;
- :mod:`.sobolev`: sec. 7.1 Sobolev weights;
- :mod:`.system`: eq. 4 over all frames (:class:`SeolSystem`) and its bounded solve;
- :mod:`.solvers`: the block tridiagonal / Kronecker-sum solvers; :mod:`.checks`: argument checks;
- :mod:`.baselines`: sec. 7 per-frame baselines and the fig. 11 velocity error;
- :mod:`.retarget`: the whole method, :func:`retarget_seol`.

This package re-exports every public name: ``from rigbuild.retarget.seol import X`` keeps working.
"""

from __future__ import annotations

from rigbuild.retarget.params import (  # noqa: F401  (the paper's defaults, re-exported)
    DEFAULT_ALPHA,
    DEFAULT_ALPHA_PERFRAME,
    DEFAULT_WEIGHT_RANGE,
    SeolParams,
)
from rigbuild.retarget.seol.head_motion import (  # noqa: F401
    MIN_VISIBLE_FRACTION,
    apply_head_motion,
    bridge_sparse_frames,
    fill_marker_gaps,
    head_motion_about_pivot,
    min_visible_markers,
    refine_head_motion,
    remove_head_motion,
)
from rigbuild.retarget.seol.scale_match import (  # noqa: F401
    RbfWarp,
    fit_rbf_warp,
    scale_proportion_match,
)
from rigbuild.retarget.seol.prior import (  # noqa: F401
    PcaPrior,
    alpha_from_corner_hz,
    build_pca_prior,
    corner_hz_from_alpha,
    sparse_combination_weights,
)
from rigbuild.retarget.seol.checks import (  # noqa: F401
    shape_index,
    weight_interval,
)
from rigbuild.retarget.seol.sobolev import (  # noqa: F401
    sobolev_beta,
    sobolev_beta_from_corner_hz,
)
from rigbuild.retarget.seol.solvers import (  # noqa: F401
    LOCAL_PASS_FRACTION,
    LOCAL_PASS_HALO,
    REDUCED_FREE_FRACTION,
    solve_block_tridiagonal,
    solve_block_tridiagonal_free,
)
from rigbuild.retarget.seol.system import (  # noqa: F401
    BOUNDED_MAX_PASSES,
    SeolSystem,
)
from rigbuild.retarget.seol.baselines import (  # noqa: F401
    solve_perframe_prior,
    solve_perframe_range,
    solve_perframe_unconstrained,
    velocity_error_per_frame,
)
from rigbuild.retarget.seol.retarget import (  # noqa: F401
    SCALE_MATCH_NEIGHBORS,
    SPACETIME_RIDGE,
    SeolResult,
    retarget_seol,
    target_marker_blendshapes,
)
