"""``config["params"]["retarget"]``: the Ribera 2017 and Seol 2012 parameters, one typed definition each.

The block has two sub-blocks, ``ribera`` (:class:`RiberaParams`, rule ``retarget_ribera``) and ``seol``
(:class:`SeolParams`, rule ``retarget_seol``). :func:`from_config` builds both and does all checking
(unknown keys with "did you mean", enum values, ``primary`` a Ribera variant, interval lengths), so
``rigbuild.params.validate_params`` rejects a bad block at DAG start; :func:`ribera_from_config` and
:func:`seol_from_config` build one sub-block (what each job is given).

The solver-level parameter classes of the Ribera method, :class:`TransferParams` (sec. 4) and
:class:`RetargetParams` (sec. 5), live here too: their fields hold the paper's defaults, and
:class:`RiberaParams` takes its defaults from them (``bounds`` excepted: the pipeline bounds the weights
to [0, 1], the solver does not by default). The method ``ribera`` (:data:`PAPER_METHOD`, reported as
``retarget.ribera_paper``) runs with the paper's constants whatever the block says
(:meth:`RiberaParams.for_method`); the block's values drive the options beside it (``ribera_activation``,
``ribera_fit``, the baselines). Plain dataclasses: cheap to import.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Mapping, Optional

from rigbuild.errors import InputError
from rigbuild.params import from_mapping
from rigbuild.retarget.methods import (PRIMARY_RIBERA_METHOD, RIBERA_FIT_METHODS, SEOL_ACTOR_RIG_METHOD,
                                       check_primary)

WHERE = "params.retarget"

# ----------------------------------------------------------------------------- Ribera et al. 2017
PAPER_ALPHA = 0.01
PAPER_BETA = 0.1
PAPER_R = 15.0
PAPER_MU = 0.3
PAPER_LAMBDA_CM = 0.6
#: squared-length factor between the paper's cm and our mm
CM2_TO_MM2 = 100.0

#: the method that runs Ribera et al. 2017 as written, with the paper's own constants whatever
#: ``params.retarget.ribera`` says (:meth:`RiberaParams.for_method`; metric key ``ribera_paper``)
PAPER_METHOD = "ribera"

#: initial guesses g_k of E_Mesh (``TransferParams.guess``)
GUESSES = ("rbf", "deformation")
#: E_CEG reference (``TransferParams.ceg_reference``)
CEG_REFERENCES = ("character", "rbf")
#: rigid head motion in E_Fit (``RetargetParams.rigid``)
RIGID_MODES = ("joint", "fixed")
#: E_Sparse (``RetargetParams.sparsity``): eq. 16's L1, or the reweighted-L1 log penalty (an option)
SPARSITY_MODES = ("l1", "log")
#: the plausibility options switched on together (``params.retarget.ribera``; :mod:`rigbuild.retarget.ribera.plausible`):
#: the log sparsity penalty and antagonist exclusion (the still-region gate is an option measured off:
#: docs/decisions.md)
PLAUSIBLE = {"sparsity": "log", "antagonists": True}


@dataclass
class TransferParams:
    """Blendshape-transfer parameters (paper values by default).

    alpha : E_Mesh weight (0.01); beta : E_CEG weight (0.1); r : contrast steepness (15).
    ceg_reference : ``"character"`` (eq. 13 as written: ``Lambda(dp - ds)``) or ``"rbf"`` (``Lambda(dp - dg)``).
    epsilon : tiny Tikhonov weight pulling ``dp`` to ``dg``; makes the system positive definite where E_Match
        has no support (E_Mesh and E_CEG leave a common translation free). Negligible otherwise.
    match : ``"faithful"`` (eq. 10 as written), ``"fit"`` (the ROM-fit E_Match, see
        :func:`rigbuild.retarget.ribera.fit_match_transfer`) or ``"activation"``: the activation-aware E_Match
        (see :func:`rigbuild.retarget.ribera.transfer_blendshapes`), ``match_iterations`` alternations.
    solver : ``"kronecker"`` (exact/PCG on the Kronecker-sum structure) or ``"cholmod"`` (sparse Cholesky of
        the assembled (MK x MK) matrix; same answer, slower).
    fit_alpha, fit_lambda_cm, fit_mu, fit_frames : the ``"fit"`` match: its E_Mesh weight (its E_Match has one
        residual per frame, not one per shape and frame, so the balance differs from alpha), the E_Sparse /
        E_Prior weights of the training-frame activations (the section-5 energy with a sparser lambda, for
        cm) and the frames matched (``"all"`` training frames or the ``"keys"`` of sec. 4.2).
    guess : initial guesses g_k for E_Mesh (and the ``rbf`` baseline). ``"rbf"`` (sec. 4.4 as written:
        the thin-plate RBF ``s0 -> a0`` evaluated at the displaced markers) or ``"deformation"`` (the
        character's whole-mesh blendshapes deformation-transferred onto the character's neutral warped by
        that RBF into the actor's proportions, sampled at the markers; needs the character mesh, so
        ``build_model`` computes it).

    Units: E_Match, E_Mesh and E_CEG are all squared marker displacements (the cotangent weights and the
    CEG Laplacian are dimensionless), so alpha and beta are unit-free: the paper's 0.01 / 0.1 (cm) are the
    same numbers in mm.
    """

    alpha: float = PAPER_ALPHA
    beta: float = PAPER_BETA
    r: float = PAPER_R
    ceg_reference: str = "character"
    epsilon: float = 1e-6
    match: str = "faithful"
    match_iterations: int = 2
    fit_alpha: float = 0.3
    fit_lambda_cm: float = 0.2
    fit_mu: float = PAPER_MU
    fit_frames: str = "all"
    solver: str = "kronecker"
    guess: str = "rbf"


@dataclass
class RetargetParams:
    """Retargeting parameters in the paper's units; converted to mm internally.

    mu : E_Prior weight (paper 0.3). lambda_cm : E_Sparse weight for markers in cm (paper 0.6); in mm the
    solver uses ``lambda_cm * 100``. bounds : (lo, hi) weight bounds, either may be None (no bound).
    irls_iterations, irls_eps : IRLS for the L1 term (``|w| ~ w^2 / |w_prev|``). active_set_passes : passes of
    the bound-constrained solve. refine_rigid : extra rounds of rigid head-motion removal against the fitted
    expression.
    rigid : ``"joint"`` (default): E_Fit is minimized jointly over the weights and a residual small rigid
        motion of the stabilized frame (6 unbounded, unpenalized unknowns, eliminated exactly by a Schur
        complement, see :class:`rigbuild.retarget.ribera.RiberaRetargeter`); ``"fixed"``: the stabilized
        frame is taken as is. A rigid fit to the neutral alone absorbs part of every expression (jawOpen
        reads partly as a head tilt).
    take_refine_iterations, take_refine_prior : beyond the paper, rounds of the EM's shape step on the whole take
        after its solve (:func:`rigbuild.retarget.common.refit_rig_at_markers`: the actor blendshapes at the
        markers re-estimated from the take's stabilized frames, held to E_Align's by a prior worth
        ``take_refine_prior`` frames at full weight; the take solved again); 0: off.
    """

    mu: float = PAPER_MU
    lambda_cm: float = PAPER_LAMBDA_CM
    bounds: Optional[tuple[Optional[float], Optional[float]]] = None
    irls_iterations: int = 8
    irls_eps: float = 1e-3
    active_set_passes: int = 6
    refine_rigid: int = 1
    rigid: str = "joint"
    sparsity: str = "l1"
    sparsity_lambda_cm: float = PAPER_LAMBDA_CM
    sparsity_eps: float = 0.1
    antagonists: bool = False
    antagonist_lambda_cm: float = 20.0
    still_gate: bool = False
    still_ratio: float = 0.25
    coherence_frames: float = 4.0
    take_refine_iterations: int = 0
    take_refine_prior: float = 10.0

    @property
    def lambda_mm(self) -> float:
        """Eq. 16's lambda for markers in mm: E_Fit and E_Prior are squared lengths (x100 from cm to mm),
        E_Sparse is unit-free, so the paper's cm value is multiplied by :data:`CM2_TO_MM2` (once, here)."""
        return self.lambda_cm * CM2_TO_MM2

    @property
    def antagonist_lambda_mm(self) -> float:
        """The antagonist penalty's weight in mm units (as :attr:`lambda_mm`)."""
        return self.antagonist_lambda_cm * CM2_TO_MM2

    @property
    def sparsity_lambda_mm(self) -> float:
        """The log sparsity penalty's slope at 0 in mm units (as :attr:`lambda_mm`)."""
        return self.sparsity_lambda_cm * CM2_TO_MM2


@dataclass
class RiberaParams:
    """``params.retarget.ribera``: one Ribera job's parameters (rule ``retarget_ribera``).

    alpha, beta, r, ceg_reference, fit_alpha, fit_lambda_cm : :class:`TransferParams` (lambda for cm).
    guess : g_k of E_Mesh for ``ribera`` / ``ribera_activation`` (``rbf``, sec. 4.4, or ``deformation``);
    fit_guess : g_k for ``ribera_fit`` (and, for the character shapes the rig lacks, for ``ribera_fit_actor_rig``
        and ``ribera_fit_template_rig``, whose other g_k are the personalized / template rig at the markers).
    rigid, mu, lambda_cm, bounds : :class:`RetargetParams` (``bounds`` [lo, hi] or null).
    allow_empty_frames : frames with fewer than 3 visible markers get interpolated weights (else an error).
    preview_frames : frames drawn in preview.png (the most active ones).
    primary : the Ribera variant also reported as ``retarget.ribera.*``.
    marker_lowpass_hz : zero-phase low-pass of the take's markers (-3 dB, Hz) before solving, or null.
    sparsity, sparsity_lambda_cm, antagonists, antagonist_lambda_cm, still_gate, still_ratio, coherence_frames :
    the plausibility options of :class:`RetargetParams` (off by default; :data:`PLAUSIBLE` switches on the
    ones measured to help on real takes).
    take_refine_iterations, take_refine_prior : :class:`RetargetParams` (the actor blendshapes refined on the take;
    0 rounds by default).
    """

    alpha: float = TransferParams.alpha
    beta: float = TransferParams.beta
    r: float = TransferParams.r
    ceg_reference: str = TransferParams.ceg_reference
    guess: str = TransferParams.guess
    fit_guess: str = "deformation"
    fit_alpha: float = TransferParams.fit_alpha
    fit_lambda_cm: float = TransferParams.fit_lambda_cm
    rigid: str = RetargetParams.rigid
    mu: float = RetargetParams.mu
    lambda_cm: float = RetargetParams.lambda_cm
    bounds: Optional[tuple[float, float]] = (0.0, 1.0)
    allow_empty_frames: bool = True
    preview_frames: int = 4
    primary: str = PRIMARY_RIBERA_METHOD
    marker_lowpass_hz: Optional[float] = None
    sparsity: str = RetargetParams.sparsity
    sparsity_lambda_cm: float = RetargetParams.sparsity_lambda_cm
    antagonists: bool = RetargetParams.antagonists
    antagonist_lambda_cm: float = RetargetParams.antagonist_lambda_cm
    still_gate: bool = RetargetParams.still_gate
    still_ratio: float = RetargetParams.still_ratio
    coherence_frames: float = RetargetParams.coherence_frames
    take_refine_iterations: int = RetargetParams.take_refine_iterations
    take_refine_prior: float = RetargetParams.take_refine_prior

    def for_method(self, method: str) -> "RiberaParams":
        """The parameters ``method`` runs with: these, except for :data:`PAPER_METHOD` (``ribera``), which
        runs the paper as written whatever the config says: alpha 0.01, beta 0.1, r 15 (sec. 4), E_CEG as
        eq. 13 (``ceg_reference: character``), the RBF guesses of sec. 4.4 (``guess: rbf``), mu 0.3 and
        lambda 0.6 for cm (sec. 5), no weight bounds (eq. 16 has none; sec. 3 argues that bounding the weights
        to [0, 1] does not make expressions valid), E_Fit on the stabilized frame (``rigid: fixed``), no
        marker low-pass and no refinement of the actor blendshapes on the take. The job's own settings
        (``allow_empty_frames``, ``preview_frames``, ``primary``) and the other variants' fields are kept."""
        if method != PAPER_METHOD:
            return self
        from dataclasses import replace

        return replace(self, alpha=PAPER_ALPHA, beta=PAPER_BETA, r=PAPER_R, ceg_reference="character",
                       guess="rbf", mu=PAPER_MU, lambda_cm=PAPER_LAMBDA_CM, bounds=None, rigid="fixed",
                       marker_lowpass_hz=None, sparsity="l1", antagonists=False, still_gate=False,
                       take_refine_iterations=0)

    def transfer_params(self, method: str) -> TransferParams:
        """The transfer parameters of ``method`` (the ROM-fit methods take ``fit_guess``, the rig ones for the
        character shapes their rig lacks; ``ribera`` the paper's, :meth:`for_method`)."""
        q = self.for_method(method)
        return TransferParams(alpha=float(q.alpha), beta=float(q.beta), r=float(q.r),
                              ceg_reference=str(q.ceg_reference),
                              guess=str(q.fit_guess if method in RIBERA_FIT_METHODS else q.guess),
                              fit_alpha=float(q.fit_alpha), fit_lambda_cm=float(q.fit_lambda_cm))

    def retarget_params(self, method: str | None = None) -> RetargetParams:
        """The section-5 parameters of ``method`` (``ribera``: the paper's, :meth:`for_method`; None: these)."""
        q = self if method is None else self.for_method(method)
        bounds = None if q.bounds is None else tuple(q.bounds)
        return RetargetParams(mu=float(q.mu), lambda_cm=float(q.lambda_cm), bounds=bounds, rigid=str(q.rigid),
                              sparsity=str(q.sparsity), sparsity_lambda_cm=float(q.sparsity_lambda_cm),
                              antagonists=bool(q.antagonists),
                              antagonist_lambda_cm=float(q.antagonist_lambda_cm), still_gate=bool(q.still_gate),
                              still_ratio=float(q.still_ratio), coherence_frames=float(q.coherence_frames),
                              take_refine_iterations=int(q.take_refine_iterations),
                              take_refine_prior=float(q.take_refine_prior))


# ----------------------------------------------------------------------------- Seol et al. 2012
#: The paper's prior weight for movement matching (sec. 5, fig. 7(f)) and for per-frame matching
#: with the prior (sec. 7, "Prior PF"); the hard range of "Range PF".
DEFAULT_ALPHA = 0.01
DEFAULT_ALPHA_PERFRAME = 0.5
DEFAULT_WEIGHT_RANGE = (-0.5, 1.5)

#: scale-proportion matching modes (``rigbuild.retarget.proportion``) and RBF kernels
SCALE_MATCH_KERNELS = ("r", "r3", "tps")
SCALE_MATCH_MARKER_MODES = ("rbf", "jacobian", "local_affine", "affine", "none")
SCALE_MATCH_MODES = SCALE_MATCH_MARKER_MODES + ("deformation",)
BOUNDARY_VALUES = ("neutral", "perframe")
GAP_MODES = ("mask", "interpolate")
RIGID_WEIGHTS = ("rigidity", "uniform")
SOBOLEV_KEYS = ("regions", "frames")


@dataclass
class SeolParams:
    """``params.retarget.seol``: spacetime expression cloning (:func:`rigbuild.retarget.seol.retarget_seol`).

    alpha : prior weight of eq. (4) (the paper: 0.01 with mm-scale faces); prior_corner_hz : the prior
        strength as a corner frequency (Hz) instead, overriding alpha.
    alpha_perframe : prior weight of the "Prior PF" baseline; weight_range : bounds of the "Range PF" baseline.
    boundary_frames : frames pinned at the boundary values (default first and last); boundary_values :
        ``neutral`` (all weights 0, the paper's protocol) or ``perframe`` (the Range-PF solution there).
    pins : extra boundary conditions ``{frame: {shape: value}}``.
    rigid_weights : ``rigidity`` (markers the target's shapes move little count more in the head-motion
        fit) or ``uniform`` (all markers equally, the paper).
    head_refine_iterations : Gauss-Newton refinements of the head motion with per-frame weights (0 = the
        paper's plain Procrustes).
    sobolev : sec. 7.1 term ``{"regions": {regex: beta}, "frames": [..] or null}``, or null;
        sobolev_corner_hz : a uniform Sobolev term on every marker, ``beta = (2 pi f_c / fps)^2``.
    gaps : ``mask`` (marker gaps left out of the energy) or ``interpolate`` (filled linearly first).
    prior_combinations, prior_combination_density : extra sparse-combination training frames of the PCA prior.
    scale_match, scale_match_kernel : scale-proportion matching (sec. 3.2, ``rbf`` the paper;
        :data:`SCALE_MATCH_MODES`) and the RBF's phi (``r`` the paper, ``r3``, ``tps``).
    marker_lowpass_hz : zero-phase low-pass of the take's markers (-3 dB, Hz) before solving, or null.
    weight_bounds : [lo, hi]: the spacetime solution kept in the rig's weight range, or null (the paper).
    sparsity : L1 weight (mm^2 per unit weight; not in the paper); needs weight_bounds from 0.
    sparsity_mode, sparsity_eps, antagonists, coherence_frames : the plausibility options (not in the paper;
        need weight_bounds from 0): ``sparsity_mode`` ``"l1"`` (the L1 term above) or ``"log"`` (the
        reweighted-L1 log penalty with slope ``sparsity`` at 0 and scale ``sparsity_eps``,
        :mod:`rigbuild.retarget.ribera.plausible`); ``antagonists``: antagonist pairs
        (:data:`rigbuild.retarget.plausible.ANTAGONISTS`) never on together (a penalty
        ``antagonist_weight w_a w_b``, mm^2 per unit weight^2, pushes one to yield; then the weaker, over
        ``coherence_frames``, is pinned at 0 and the spacetime solve re-run).
    actor_rig : fields of this block that method ``seol_actor_rig`` runs with in place of these (:meth:`for_method`;
        its source side is the actor's own rig, not a guessed scale map, so it may match positions more and keep
        the rig's weight range); empty: the same parameters as ``seol``.
    """

    alpha: float = DEFAULT_ALPHA
    alpha_perframe: float = DEFAULT_ALPHA_PERFRAME
    weight_range: tuple[float, float] = DEFAULT_WEIGHT_RANGE
    boundary_frames: tuple[int, ...] = (0, -1)
    boundary_values: str = "neutral"
    pins: dict = field(default_factory=dict)
    rigid_weights: str = "rigidity"
    head_refine_iterations: int = 3
    sobolev: Optional[dict] = None
    sobolev_corner_hz: Optional[float] = None
    gaps: str = "mask"
    prior_corner_hz: Optional[float] = None
    prior_combinations: int = 0
    prior_combination_density: float = 0.15
    scale_match: str = "rbf"
    scale_match_kernel: str = "r"
    marker_lowpass_hz: Optional[float] = None
    weight_bounds: Optional[tuple[float, float]] = None
    sparsity: float = 0.0
    sparsity_mode: str = "l1"
    sparsity_eps: float = 0.1
    antagonists: bool = False
    antagonist_weight: float = 0.0
    coherence_frames: float = 4.0
    actor_rig: dict = field(default_factory=dict)

    def for_method(self, method: str) -> "SeolParams":
        """The parameters ``method`` runs with: for ``seol_actor_rig`` this block with the ``actor_rig`` fields in
        place (InputError, with "did you mean", on an unknown field), for the other methods this block."""
        if method != SEOL_ACTOR_RIG_METHOD or not self.actor_rig:
            return self
        own = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "actor_rig"}
        if "actor_rig" in self.actor_rig:
            raise InputError(f"'{WHERE}.seol.actor_rig' cannot hold another actor_rig block", path="config")
        return from_mapping(SeolParams, {**own, **dict(self.actor_rig)}, f"{WHERE}.seol.actor_rig")


# ----------------------------------------------------------------------------- the actor's own rig
@dataclass
class ActorRigParams:
    """Marker-space weights from the personalized rig (``params.retarget.actor_rig``, rule ``actor_rig_weights``;
    :mod:`rigbuild.retarget.actor_rig`).

    lambda_t : temporal coherence ``lambda_t sum ||w_f - w_(f-1)||^2`` (mm^2, against the data term's squared
        marker residuals in mm^2); lambda_velocity : the same term independent of the take's frame rate, on the
        weights' velocities: ``lambda_velocity sum ||(w_f - w_(f-1)) fps||^2`` (mm^2 s^2), i.e.
        :meth:`temporal_weight` ``= lambda_t + lambda_velocity fps^2``; lambda_l1 : sparsity ``lambda_l1 sum_k w_k``
        (mm^2; the L1 norm, linear because ``w >= 0``); lambda_s : Ma et al. 2016's ``lambda_s (1^T w)^2`` (mm^2);
    bounds : [lo, hi] of the weights; sweeps, tol : the Gauss-Newton solve stops when no weight moves more
        than ``tol`` in a sweep (at most ``sweeps``);
    marker_lowpass_hz : zero-phase Gaussian low-pass of the markers before the solve (-3 dB, Hz; None: off);
    map_frames : frames of the take spread evenly over it that place the markers on the rig; map_iterations :
        rounds of (solve those frames, move each marker to its closest point on the posed rig);
    observable_mm : a shape that moves no marker this much at weight 1 is held at 0;
    max_surface_distance_mm : a marker whose placed point is farther from the rig's skin is reported (warning);
    refine_iterations : rounds of the EM's shape step in marker space after the solve (the rig at the markers
        re-estimated from the take's frames, the weights solved again; 0: off, the plain solve;
        :func:`rigbuild.retarget.actor_rig.solve_actor_weights_refined`); refine_prior : how many frames at full
        weight the personalized rig at the markers counts for against the take (dimensionless).
    """

    lambda_t: float = 0.0
    lambda_velocity: float = 0.0
    lambda_l1: float = 0.5
    lambda_s: float = 0.0
    marker_lowpass_hz: Optional[float] = 8.0
    bounds: list = field(default_factory=lambda: [0.0, 1.0])
    sweeps: int = 60
    tol: float = 1e-4
    map_frames: int = 120
    map_iterations: int = 4
    observable_mm: float = 0.05
    max_surface_distance_mm: float = 8.0
    refine_iterations: int = 0
    refine_prior: float = 10.0

    def temporal_weight(self, fps: float) -> float:
        """The solve's ``lambda_t`` (mm^2 per squared weight step between frames) for a take at ``fps`` Hz:
        ``lambda_t + lambda_velocity * fps^2``."""
        return float(self.lambda_t) + float(self.lambda_velocity) * float(fps) ** 2


#: where the methods without the personalized rig read the range of motion (``params.retarget.take_markers.rom``)
ROM_MARKERS = ("take", "marker_set")


@dataclass
class TakeMarkerParams:
    """The range of motion at a take's own markers (``params.retarget.take_markers``, rule ``take_markers``;
    :func:`rigbuild.retarget.actor_rig.place_markers_on_neutral`).

    rom : ``take``: the methods that do not use the personalized rig (Ribera's and Seol's) read the tracked
        range of motion at the take's markers placed on the tracked neutral's skin (hand-placed markers sit
        where the hand put them); ``marker_set``: at the template's marker-set vertices (the tracked
        ``markers.npz``);
    neutral_fraction, min_frames : the share of the take's frames (at least ``min_frames``) closest to the
        neutral expression (smallest rigid residual) that place the markers; iterations : placing rounds;
    trim : a marker whose rigid residual exceeds this many times the frame's median is left out of the frame's fit.
    """

    rom: str = "take"
    neutral_fraction: float = 0.05
    min_frames: int = 10
    iterations: int = 3
    trim: float = 2.5


@dataclass
class RetargetStageParams:
    """The whole ``params.retarget`` block."""

    ribera: RiberaParams = field(default_factory=RiberaParams)
    seol: SeolParams = field(default_factory=SeolParams)
    actor_rig: ActorRigParams = field(default_factory=ActorRigParams)
    take_markers: TakeMarkerParams = field(default_factory=TakeMarkerParams)


# ----------------------------------------------------------------------------------------- checks
def _one_of(value: Any, allowed: tuple, where: str) -> None:
    if value not in allowed:
        raise InputError(f"'{where}' is {value!r}", path="config", fix=f"use one of {list(allowed)}")


def _choices(p: Any, where: str, **allowed) -> None:
    """:func:`_one_of` for each field of ``p`` named in ``allowed`` (field -> its allowed values)."""
    for field_name, values in allowed.items():
        _one_of(getattr(p, field_name), values, f"{where}.{field_name}")


def _interval(value: Any, where: str, optional: bool) -> None:
    if value is None and optional:
        return
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise InputError(f"'{where}' must be [lo, hi], got {value!r}", path="config")


def check_ribera(p: RiberaParams, where: str = f"{WHERE}.ribera") -> RiberaParams:
    _choices(p, where, guess=GUESSES, fit_guess=GUESSES, ceg_reference=CEG_REFERENCES, rigid=RIGID_MODES,
             sparsity=SPARSITY_MODES)
    plausible = p.sparsity != "l1" or p.antagonists or p.still_gate
    if plausible and (p.bounds is None or p.bounds[0] is None or p.bounds[0] < 0):
        raise InputError(f"'{where}': sparsity, antagonists and still_gate need bounds from 0, got {p.bounds!r}",
                         path="config", fix="set bounds: [0, 1]")
    _interval(p.bounds, f"{where}.bounds", optional=True)
    check_primary(p.primary)
    n = p.take_refine_iterations
    if not isinstance(n, int) or isinstance(n, bool) or n < 0:
        raise InputError(f"'{where}.take_refine_iterations' must be an integer >= 0, got {n!r}", path="config",
                         fix="0 turns the refinement off")
    v = p.take_refine_prior
    if not isinstance(v, (int, float)) or isinstance(v, bool) or v < 0:
        raise InputError(f"'{where}.take_refine_prior' must be a number >= 0, got {v!r}", path="config")
    return p


def check_seol(p: SeolParams, where: str = f"{WHERE}.seol") -> SeolParams:
    _choices(p, where, boundary_values=BOUNDARY_VALUES, gaps=GAP_MODES, rigid_weights=RIGID_WEIGHTS,
             scale_match=SCALE_MATCH_MODES, scale_match_kernel=SCALE_MATCH_KERNELS, sparsity_mode=SPARSITY_MODES)
    if (p.sparsity_mode != "l1" or p.antagonists) and (p.weight_bounds is None or p.weight_bounds[0] < 0):
        raise InputError(f"'{where}': sparsity_mode log and antagonists need weight_bounds from 0, got "
                         f"{p.weight_bounds!r}", path="config", fix="set weight_bounds: [0, 1.5]")
    _interval(p.weight_range, f"{where}.weight_range", optional=False)
    _interval(p.weight_bounds, f"{where}.weight_bounds", optional=True)
    if p.sobolev:
        if not isinstance(p.sobolev, Mapping):
            raise InputError(f"'{where}.sobolev' must be a mapping {{regions, frames}}", path="config")
        from rigbuild.params import check_keys

        check_keys(p.sobolev, SOBOLEV_KEYS, f"{where}.sobolev")
    if not isinstance(p.pins or {}, Mapping):
        raise InputError(f"'{where}.pins' must be a mapping {{frame: {{shape: value}}}}", path="config")
    if not isinstance(p.actor_rig or {}, Mapping):
        raise InputError(f"'{where}.actor_rig' must be a mapping of this block's fields", path="config")
    if p.actor_rig:
        check_seol(p.for_method(SEOL_ACTOR_RIG_METHOD), f"{where}.actor_rig")
    return p


def check_actor_rig(p: ActorRigParams, where: str = f"{WHERE}.actor_rig") -> ActorRigParams:
    _interval(p.bounds, f"{where}.bounds", optional=False)
    if not p.bounds[0] < p.bounds[1]:
        raise InputError(f"'{where}.bounds' must have lo < hi, got {p.bounds!r}", path="config", fix="e.g. [0, 1]")
    for name in ("lambda_t", "lambda_velocity", "lambda_l1", "lambda_s", "tol", "observable_mm",
                 "max_surface_distance_mm", "refine_prior"):
        v = getattr(p, name)
        if not isinstance(v, (int, float)) or isinstance(v, bool) or v < 0:
            raise InputError(f"'{where}.{name}' must be a number >= 0, got {v!r}", path="config")
    for name in ("sweeps", "map_frames", "map_iterations"):
        v = getattr(p, name)
        if not isinstance(v, int) or v < 1:
            raise InputError(f"'{where}.{name}' must be an integer >= 1, got {v!r}", path="config")
    if not isinstance(p.refine_iterations, int) or isinstance(p.refine_iterations, bool) or p.refine_iterations < 0:
        raise InputError(f"'{where}.refine_iterations' must be an integer >= 0, got {p.refine_iterations!r}",
                         path="config", fix="0 turns the refinement off")
    return p


def check_take_markers(p: TakeMarkerParams, where: str = f"{WHERE}.take_markers") -> TakeMarkerParams:
    _one_of(p.rom, ROM_MARKERS, f"{where}.rom")
    if not 0.0 < float(p.neutral_fraction) <= 1.0:
        raise InputError(f"'{where}.neutral_fraction' is {p.neutral_fraction!r}", path="config",
                         fix="give the share of the take's frames that place the markers, in (0, 1]")
    for name in ("min_frames", "iterations"):
        v = getattr(p, name)
        if not isinstance(v, int) or v < 1:
            raise InputError(f"'{where}.{name}' must be an integer >= 1, got {v!r}", path="config")
    if not float(p.trim) > 1.0:
        raise InputError(f"'{where}.trim' is {p.trim!r}", path="config",
                         fix="give a multiple of the frame's median residual above 1 (2.5 leaves out outliers)")
    return p


def take_markers_from_config(values: Mapping[str, Any] | None) -> TakeMarkerParams:
    """``params.retarget.take_markers`` -> :class:`TakeMarkerParams` (checked)."""
    if isinstance(values, TakeMarkerParams):
        return check_take_markers(values)
    return check_take_markers(from_mapping(TakeMarkerParams, values, f"{WHERE}.take_markers"))


def actor_rig_from_config(values: Mapping[str, Any] | None) -> ActorRigParams:
    """``params.retarget.actor_rig`` -> :class:`ActorRigParams` (checked)."""
    if isinstance(values, ActorRigParams):
        return check_actor_rig(values)
    return check_actor_rig(from_mapping(ActorRigParams, values, f"{WHERE}.actor_rig"))


def ribera_from_config(values: Mapping[str, Any] | None) -> RiberaParams:
    """``params.retarget.ribera`` -> :class:`RiberaParams` (checked)."""
    if isinstance(values, RiberaParams):
        return check_ribera(values)
    return check_ribera(from_mapping(RiberaParams, values, f"{WHERE}.ribera"))


def seol_from_config(values: Mapping[str, Any] | None) -> SeolParams:
    """``params.retarget.seol`` -> :class:`SeolParams` (checked)."""
    if isinstance(values, SeolParams):
        return check_seol(values)
    return check_seol(from_mapping(SeolParams, values, f"{WHERE}.seol"))


def from_config(values: Mapping[str, Any] | None) -> RetargetStageParams:
    """``config["params"]["retarget"]`` ({ribera: ..., seol: ...}) -> :class:`RetargetStageParams`; InputError
    ("did you mean") on an unknown key of the block or of either sub-block, and on a bad value."""
    p = from_mapping(RetargetStageParams, {k: (v or {}) for k, v in dict(values or {}).items()}, WHERE)
    check_ribera(p.ribera)
    check_seol(p.seol)
    check_actor_rig(p.actor_rig)
    check_take_markers(p.take_markers)
    return p
