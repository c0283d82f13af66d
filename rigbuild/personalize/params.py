"""``config["params"]["personalize"]``: the EM's parameters and the stage's options, one typed definition.

The block is flat in the config: the :class:`PersonalizeParams` fields (the EM) sit beside the stage options of
:class:`PersonalizeConfig` (held-out sequences, the neutral, the fit region, heat maps, the template rig).
:func:`from_config` builds both and does all checking (unknown keys with "did you mean", enum values,
non-positive lengths), so ``rigbuild.params.validate_params`` rejects a bad block at DAG start.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, replace
from typing import Any, Mapping, Optional

import numpy as np

from rigbuild.errors import InputError
from rigbuild.params import check_keys, from_mapping

#: ``PersonalizeParams.gauge`` values
GAUGES = ("none", "rom_peak")
#: ``PersonalizeParams.qp_method`` values (:func:`rigbuild.personalize.weights.solve_box_qp`)
QP_METHODS = ("active_set", "cvxopt")
#: ``PersonalizeConfig.fit_region`` values: the template's face region, or every vertex
FIT_REGIONS = ("face", "all")
#: ``ExportParams.names`` values: the template's shape names, or ARKit's 52 (rigbuild/assets/arkit52.json)
EXPORT_NAMES = ("rig", "arkit")

WHERE = "params.personalize"


@dataclass
class PersonalizeParams:
    """Parameters of the EM (Ma et al. 2016 values where the paper gives them).

    lambda_s : squared-L1 sparsity weight (paper: 0.1).
    lambda_t : temporal smoothness weight between contiguous frames (the paper gives no value; 0.01 in
        centimetres is 1 mm^2 per unit weight^2).
    lambda_r : deformation-gradient regularization (paper: 0.1).
    lambda_d : displacement regularization towards D* (paper: 0.05).
    lambda_unit_mm : the length unit, in mm, the lambdas are stated in (default 10: centimetres). The
        paper gives its values without a unit; E_g and E_d are squared lengths while E_s, E_t and E_r are
        unitless, so lambda_s, lambda_t and lambda_r weigh differently in mm than in cm (by 100x). Face rigs
        are built in centimetres (the ICT model; Maya's default unit). The solver works in mm with
        lambda_s, lambda_t, lambda_r times ``lambda_unit_mm ** 2`` (:meth:`in_mm`); 1 states them in mm.
    update_neutral : solve the neutral update column (paper: yes).
    max_iterations : EM iterations at most; tolerance : stop when J drops by less than this (relative).
    inner_iterations, weight_tol : joint Gauss-Newton steps per frame in each weights step (then one
        exact rigid and one exact weights step): at most this many, until weights and rotation entries
        move less than ``weight_tol``.
    confidence_threshold : a vertex counts as confident above this; min_confident_vertices : frames
        with fewer are skipped with a warning.
    support_tol_mm : a shape may change only at vertices where its ``D*`` moves more than this (mm);
        elsewhere it keeps ``D*`` exactly (exact zeros stay zero: the paper's local support).
    ring : rings of unconfident vertices around the confident ones that are also solved for.
    qp_method : ``"active_set"`` or ``"cvxopt"``.
    gauge : ``"none"`` (the paper: each shape keeps the amplitude the regularizers pull it to, i.e.
        D*'s) or ``"rom_peak"``: the ROM is performed at full intensity, so each shape's largest
        weight over the fitting frames is 1. Shape amplitude and weight share a scale no frame
        determines (``(a D_k, w_k / a)`` fit identically); with ``"rom_peak"`` the weights are first fitted
        to the D* rig with the box relaxed to ``[0, gauge_max_weight]``, each ``D*_k`` (the prior of
        E_r and E_d) is scaled by its peak weight, the paper's EM runs on that rig, and at the end each
        shape is scaled by its peak weight once more (weights divided by it: the fit is unchanged).
    gauge_max_weight : the relaxed upper bound of the gauge fit (largest amplitude ratio actor / D*
        that can be measured).
    pin_neutral_frames : frames the session names as the actor's neutral (each ROM sequence's
        ``neutral_frame``, passed as ``neutral_mask``) keep all weights at 0 and fit the rigid motion only
        (not in the paper, whose EM leaves them free). The neutral update and "always on" weights are
        otherwise interchangeable: ``d_0`` plus a constant weight on a shape fits every frame as well as
        ``d_0`` alone, and on tracked frames the EM can drift into that. Pinning the frames that are known
        to be neutral anchors ``d_0``.
    """

    lambda_s: float = 0.1
    lambda_t: float = 0.01
    lambda_r: float = 0.1
    lambda_d: float = 0.05
    lambda_unit_mm: float = 10.0
    update_neutral: bool = True
    max_iterations: int = 10
    tolerance: float = 1e-3
    inner_iterations: int = 10
    weight_tol: float = 1e-5
    confidence_threshold: float = 0.0
    min_confident_vertices: int = 100
    support_tol_mm: float = 1.0
    ring: int = 2
    qp_method: str = "active_set"
    gauge: str = "none"
    gauge_max_weight: float = 3.0
    pin_neutral_frames: bool = True

    def check_unit(self) -> None:
        """InputError unless ``lambda_unit_mm`` is a positive finite length."""
        if not (np.isfinite(self.lambda_unit_mm) and self.lambda_unit_mm > 0):
            raise InputError(f"lambda_unit_mm must be a positive length in mm, got {self.lambda_unit_mm}",
                             path="config", fix=f"{WHERE}.lambda_unit_mm: 10 (cm) or 1 (mm)")

    def check(self) -> None:
        """InputError for a bad value: ``lambda_unit_mm``, ``gauge``, ``gauge_max_weight``, ``qp_method``."""
        self.check_unit()
        if self.gauge not in GAUGES:
            raise InputError(f"unknown gauge '{self.gauge}' in {WHERE}", path="config",
                             fix=f"use one of: {', '.join(GAUGES)}")
        if not self.gauge_max_weight >= 1.0:
            raise InputError(f"gauge_max_weight must be >= 1, got {self.gauge_max_weight}", path="config")
        if self.qp_method not in QP_METHODS:
            raise InputError(f"unknown qp_method '{self.qp_method}' in {WHERE}", path="config",
                             fix=f"use one of: {', '.join(QP_METHODS)}")

    def in_mm(self) -> "PersonalizeParams":
        """These parameters with the lambdas for mm data (``lambda_unit_mm`` = 1): lambda_s, lambda_t and
        lambda_r (weights of unitless terms against squared lengths) scaled by ``lambda_unit_mm ** 2``;
        lambda_d (a squared length, like the data term) unchanged."""
        self.check_unit()
        u2 = float(self.lambda_unit_mm) ** 2
        return replace(self, lambda_s=self.lambda_s * u2, lambda_t=self.lambda_t * u2, lambda_r=self.lambda_r * u2,
                       lambda_unit_mm=1.0)


@dataclass
class ExportParams:
    """``params.personalize.export``: how the personalized rig's files (rig.npz, initial_rig.npz, rig_obj/,
    rig.gltf) are written. They are always in the template's head frame (:mod:`rigbuild.personalize.export`).

    names : ``"rig"`` keeps the template's shape names; ``"arkit"`` writes ARKit's 52 names
        (:func:`rigbuild.io.arkit.arkit_rig`; the shapes without an ARKit counterpart are listed in rig.json,
        the glTF's ``asset.extras`` and the log).
    """

    names: str = "rig"

    def check(self) -> None:
        if self.names not in EXPORT_NAMES:
            raise InputError(f"unknown export names '{self.names}' in {WHERE}.export", path="config",
                             fix=f"{WHERE}.export.names: one of {', '.join(EXPORT_NAMES)}")


@dataclass
class PersonalizeConfig:
    """The whole ``params.personalize`` block: the EM's :class:`PersonalizeParams` (``em``, whose fields are
    given at the block's top level) and the stage's options.

    held_out_sequences : ROM sequences left out of the shape update (their weights and rigid motion are
        fitted with the initial and the personalized rig).
    neutral_sequence : the sequence whose neutral frame is the actor's neutral ``b_0`` (None: the first
        fitting sequence).
    neutral_frame : the session frame number of that neutral (None: the sequence's ``neutral_frame``).
    fit_region : ``"face"`` (the template's face region) or ``"all"`` vertices are fitted.
    heatmaps : write one change heat map per shape (the overview is always written).
    template_rig : the rig spec to personalize (None: the session's ``template_rig``); read by the rule.
    export : :class:`ExportParams` (``export: {names: arkit}``).
    """

    em: PersonalizeParams = field(default_factory=PersonalizeParams)
    held_out_sequences: tuple[str, ...] = ()
    neutral_sequence: Optional[str] = None
    neutral_frame: Optional[int] = None
    fit_region: str = "face"
    heatmaps: bool = True
    template_rig: Optional[str] = None
    export: ExportParams = field(default_factory=ExportParams)

    def check(self) -> None:
        """InputError for a bad value of a stage option or of :attr:`em`."""
        if isinstance(self.held_out_sequences, str) or not all(isinstance(s, str) for s in self.held_out_sequences):
            raise InputError(f"{WHERE}.held_out_sequences must be a list of sequence names, got "
                             f"{self.held_out_sequences!r}", path="config")
        if self.fit_region not in FIT_REGIONS:
            raise InputError(f"unknown fit_region '{self.fit_region}' in {WHERE}", path="config",
                             fix=f"use one of: {', '.join(FIT_REGIONS)}")
        if not isinstance(self.export, ExportParams):
            raise InputError(f"{WHERE}.export must be a mapping such as {{names: arkit}}, got {self.export!r}",
                             path="config")
        self.export.check()
        self.em.check()


#: the block's keys that are stage options (the rest are PersonalizeParams fields)
STAGE_KEYS = tuple(f.name for f in dataclasses.fields(PersonalizeConfig) if f.name != "em")
EM_KEYS = tuple(f.name for f in dataclasses.fields(PersonalizeParams))


def from_config(values: Mapping[str, Any] | None) -> PersonalizeConfig:
    """``config["params"]["personalize"]`` -> :class:`PersonalizeConfig`; InputError ("did you mean") on an
    unknown key, on a bad enum value (``gauge``, ``qp_method``, ``fit_region``) and on a non-positive
    ``lambda_unit_mm``."""
    if isinstance(values, PersonalizeConfig):
        values.check()
        return values
    values = dict(values or {})
    check_keys(values, EM_KEYS + STAGE_KEYS, WHERE)
    em = from_mapping(PersonalizeParams, {k: v for k, v in values.items() if k in EM_KEYS}, WHERE)
    cfg = from_mapping(PersonalizeConfig, {k: v for k, v in values.items() if k in STAGE_KEYS}, WHERE)
    cfg = replace(cfg, em=em)
    cfg.check()
    return cfg
