"""Marker-space retargeting with range-of-motion alignment and a geometric prior (Ribera et al. 2017).

Notation (paper section 3): the character has neutral marker positions ``s0`` (M, 3) and sparse delta
blendshapes ``ds`` (K, M, 3) (its deltas at the marker vertices); the actor has neutral markers ``a0``
(M, 3) and a training (range-of-motion) sequence ``a`` (F, M, 3). Blendshape transfer (section 4) computes
personalized sparse actor blendshapes ``dp`` (K, M, 3); retargeting (section 5) finds per-frame weights
``w`` (K,) from actor marker displacements ``da = a_f - a0`` with the character's dense deltas in the
geometric prior.

Section 4 terms, all implemented here:

- correlations ``c_kf`` (eq. 5) :func:`correlations`; trust values ``t_k`` (eq. 6) :func:`trust_values`;
  contrast enhancement (eq. 7-8, r = 15) :func:`enhance_similarity`;
- key expression extraction (3-frame Gaussian low-pass, summed rows, local peaks) :func:`key_expressions`;
- soft masks ``u_k`` (eq. 10) :func:`soft_masks`; E_Match (eq. 10);
- E_Mesh (eq. 11): thin-plate RBF initial guesses ``g_k`` (:func:`fit_thin_plate_rbf`, :func:`rbf_transfer`),
  cotangent Laplacian of a triangulation of the markers in a 2D parameterization with extra eyelid / lip
  contact edges (:func:`marker_triangulation`, :func:`marker_laplacian`);
- E_CEG (eq. 12-13): signed graph Laplacian of the between-blendshape correlations
  (:func:`cross_expression_laplacian`);
- alpha = 0.01, beta = 0.1; three sparse (MK x MK) systems, one per coordinate, sharing one CHOLMOD
  factorization (:func:`transfer_blendshapes`).

Section 5: ``E_Fit + mu E_Prior + lambda E_Sparse`` (eq. 16) with ``E_Prior = (1/N) |L dV w|^2`` on the full
character mesh (``L dV`` precomputed, :func:`prior_matrix`) solved by iteratively reweighted least squares
with optional weight bounds (:class:`RiberaRetargeter`).

Units. Everything here works in mm. The paper recommends mu = 0.3 and lambda = 0.6 "for markers in cm and
the face rig uniformly scaled to roughly match the actor's head". E_Fit and E_Prior are squared lengths and
E_Sparse is unit-free, so in mm the same balance needs ``lambda_mm = lambda_cm * 100`` (mu unchanged), and
the prior is evaluated on the character scaled by ``head_scale`` = RMS radius of the actor's neutral markers
/ RMS radius of the character's (:func:`head_scale`). :class:`RetargetParams` takes the paper's values and
converts them. E_Align's alpha and beta need no conversion: E_Match, E_Mesh and E_CEG are all squared marker
displacements (cotangent and CEG weights are dimensionless), so 0.01 / 0.1 mean the same in mm.

Beyond the paper (options; the faithful path stays):

- ``RetargetParams.rigid = "joint"`` (default): E_Fit also minimizes over a residual small rigid motion of
  each stabilized frame (eliminated exactly, :class:`RiberaRetargeter`); a rigid fit to the neutral alone
  absorbs part of every expression. ``"fixed"``: the stabilized frame as is.
- ``TransferParams.match = "fit"`` (method ``ribera_fit``, :func:`fit_match_transfer`): E_Match matches every
  training frame with all shapes at their solved (sparse) activations instead of eq. 10's similarity-weighted
  mean of masked keys, which shrinks the shapes.
- Method ``ribera_fit_actor_rig`` (issue 26): ``ribera_fit`` with the guesses g_k (E_Mesh's reference) of the
  actor blendshapes taken from the actor's personalized rig sampled at the markers and rotated into ``a0``'s
  frame (:func:`rig_marker_guesses`), so the ROM alignment corrects the personalization instead of starting
  from the character; a character shape the rig lacks keeps the ``fit_guess`` guess.
- ``TransferParams.guess = "deformation"`` (and method ``deformation``, the guesses used directly): g_k by
  deformation transfer onto the character's neutral warped into the actor's proportions
  (:func:`deformation_guesses`), instead of the pointwise thin-plate RBF.
- Plausibility options of eq. 16 (:mod:`.plausible`, off by default): ``RetargetParams.sparsity = "log"``
  (E_Sparse as a reweighted-L1 log penalty: with w >= 0 eq. 16's L1 term is linear and changes nothing but
  the right-hand side), ``antagonists`` (antagonist pairs never on together), ``still_gate`` (shapes whose
  markers show no motion above noise held at 0), their decisions smoothed over ``coherence_frames``.

Modules (one concept each; each function names its equation):

- :mod:`.similarity`: eq. 5-8 and the key expressions of sec. 4.2;
- :mod:`.guesses`: the initial guesses g_k (sec. 4.4; RBF as written, deformation transfer as an option);
- :mod:`.marker_mesh`: E_Mesh's marker triangulation and cotangent Laplacian (eq. 11);
- :mod:`.align_terms`: E_Align = E_Match (eq. 10) + alpha E_Mesh (eq. 11) + beta E_CEG (eq. 12-13) as normal
  equations; :mod:`.solvers`: their Kronecker-sum and CHOLMOD solves;
- :mod:`.transfer`: the transfer of sec. 4 (eq. 4) and its E_Match options;
- :mod:`.prior`: the geometric prior (eq. 14-15); :mod:`.bounded`: the batched box-constrained solves;
- :mod:`.retargeter`: per-frame retargeting (eq. 16); :mod:`.plausible`: the plausibility options beside it
  (reweighted sparsity, antagonist exclusion, still-region gating, temporal coherence);
- :mod:`.model`: the end-to-end model (:func:`build_model`).

This package re-exports every name, so ``from rigbuild.retarget.ribera import X`` and
``ribera.X`` keep working.
"""

from __future__ import annotations

from rigbuild.retarget.params import (  # noqa: F401  (re-exported: the solver's parameter classes)
    CM2_TO_MM2,
    PAPER_ALPHA,
    PAPER_BETA,
    PAPER_LAMBDA_CM,
    PAPER_MU,
    PAPER_R,
    RetargetParams,
    TransferParams,
)
from rigbuild.retarget.ribera.align_terms import (  # noqa: F401
    align_system,
    align_terms,
    cross_expression_laplacian,
    match_terms,
    soft_masks,
)
from rigbuild.retarget.ribera.bounded import _solve_free  # noqa: F401
from rigbuild.retarget.ribera.guesses import (  # noqa: F401
    RigAtMarkers,
    RigMarkerGuesses,
    combine_guesses,
    deformation_guesses,
    fit_thin_plate_rbf,
    rbf_transfer,
    rig_marker_guesses,
)
from rigbuild.retarget.ribera.marker_mesh import (  # noqa: F401
    MarkerTriangulation,
    marker_laplacian,
    marker_triangulation,
    planar_parameterization,
)
from rigbuild.retarget.ribera.model import METHODS, RiberaModel, build_model  # noqa: F401
from rigbuild.retarget.ribera.prior import head_scale, mesh_cotangent_laplacian, prior_matrix  # noqa: F401
from rigbuild.retarget.ribera.retargeter import RiberaRetargeter, rigid_jacobian  # noqa: F401
from rigbuild.retarget.ribera.similarity import (  # noqa: F401
    contrast,
    correlations,
    enhance_similarity,
    key_expressions,
    shape_correlation_matrix,
    trust_values,
)
from rigbuild.retarget.ribera.solvers import _cholmod_solve, kron_sum_solve  # noqa: F401
from rigbuild.retarget.ribera.transfer import (  # noqa: F401
    TransferResult,
    fit_match_transfer,
    key_activations,
    training_displacements,
    transfer_blendshapes,
)
