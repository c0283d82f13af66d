"""The retargeting methods the pipeline runs and their metric keys: the one registry.

``rules/common.smk`` imports :data:`PIPELINE_METHODS` and :data:`RIBERA_METHODS` (targets, wildcard
constraints); ``rigbuild.retarget.ribera`` checks its ``method`` against :data:`RIBERA_METHODS`; the stage
and evaluation jobs write their numbers under :func:`metric_prefixes` (``retarget.<prefix>.<character>.*``).
Plain Python, no imports: cheap at DAG start.
"""

from __future__ import annotations

from typing import Any, Mapping

#: the ROM-fit Ribera variant whose E_Align initial guesses g_k (and E_Mesh reference) of the actor blendshapes
#: are the personalized rig sampled at the markers (issue 26), not the RBF / deformation-transfer guesses
#: from the character; its rule ``retarget_ribera`` jobs also read the personalized rig and the take's
#: marker map (rule ``actor_rig_weights``)
RIBERA_ACTOR_RIG_METHOD = "ribera_fit_actor_rig"
#: the same with the guesses from the template rig the personalization starts from (the tracking's topology and the
#: actor's shape names) at the take's markers on the tracked neutral (rule ``take_markers``): the character's shapes
#: then enter only the geometric prior, so a character whose shapes differ from the actor's (sculpted, another
#: topology) does not decide how the range of motion is read; its jobs do not read the personalization
RIBERA_TEMPLATE_RIG_METHOD = "ribera_fit_template_rig"
#: Ribera methods whose guesses g_k come from a rig of the actor's topology -> that rig (the ``actor_rig_weights``
#: source of the same name, :data:`ACTOR_RIG_SOURCES`)
RIBERA_RIG_METHODS = {RIBERA_ACTOR_RIG_METHOD: "actor_rig", RIBERA_TEMPLATE_RIG_METHOD: "template_rig"}
#: methods of rule ``retarget_ribera`` (Ribera et al. 2017 as written with the paper's constants, its
#: activation-aware and ROM-fit E_Match options, the ROM-fit option from the personalized and from the template
#: rig's guesses, the RBF-transfer and deformation-transfer baselines)
RIBERA_METHODS = ["ribera", "ribera_activation", "ribera_fit", RIBERA_ACTOR_RIG_METHOD, RIBERA_TEMPLATE_RIG_METHOD,
                  "rbf", "deformation"]
#: the methods that run the ROM-fit E_Match (``TransferParams.match = "fit"``, guesses from ``fit_guess``)
RIBERA_FIT_METHODS = ("ribera_fit", RIBERA_ACTOR_RIG_METHOD, RIBERA_TEMPLATE_RIG_METHOD)
#: the method of rule ``retarget_seol`` (Seol et al. 2012 spacetime expression cloning)
SEOL_METHOD = "seol"
#: the Seol variant whose source side (the actor's neutral and expression space at the markers, hence the scale
#: map shape by shape) comes from the personalized rig (issue 26, :mod:`rigbuild.retarget.seol.actor_space`); its
#: rule ``retarget_seol`` jobs also read the personalized rig and the take's marker map (rule ``actor_rig_weights``)
SEOL_ACTOR_RIG_METHOD = "seol_actor_rig"
#: Seol methods whose source side comes from a rig -> the ``actor_rig_weights`` source placing the markers on it
SEOL_RIG_METHODS = {SEOL_ACTOR_RIG_METHOD: "actor_rig"}
#: methods of rule ``retarget_seol``
SEOL_METHODS = [SEOL_METHOD, SEOL_ACTOR_RIG_METHOD]
#: the method of rule ``retarget_semantic``: the actor weights solved from the personalized rig
#: (rule ``actor_rig_weights``) carried to a character by shape name
SEMANTIC_METHOD = "semantic_actor_rig"
#: the rigs rule ``actor_rig_weights`` solves the actor weights from: the personalized rig, and the template rig
#: it started from (the baseline without personalization); metric keys ``retarget.<source>_weights``
ACTOR_RIG_SOURCES = ["actor_rig", "template_rig"]
#: every method run per (performance, character), in report order
PIPELINE_METHODS = RIBERA_METHODS + SEOL_METHODS + [SEMANTIC_METHOD]
#: the Ribera variants one of which is ``params.retarget.ribera.primary``
RIBERA_VARIANTS = ("ribera", "ribera_activation", "ribera_fit", RIBERA_ACTOR_RIG_METHOD, RIBERA_TEMPLATE_RIG_METHOD)
#: the Ribera variant whose numbers are also reported as ``retarget.ribera.*`` (the default of ``primary``)
PRIMARY_RIBERA_METHOD = "ribera_fit"
#: the metric prefix under which the primary variant is reported a second time
PRIMARY_PREFIX = "ribera"

#: method -> metric prefix of its own numbers (``retarget.<prefix>.<character>.*``); ``ribera`` runs the paper
#: with its own constants (:meth:`rigbuild.retarget.params.RiberaParams.for_method`): ``ribera_paper``
METHOD_KEYS = {"ribera": "ribera_paper", "ribera_activation": "ribera_activation", "ribera_fit": "ribera_fit",
               RIBERA_ACTOR_RIG_METHOD: "ribera_fit_actor_rig", RIBERA_TEMPLATE_RIG_METHOD: "ribera_fit_template_rig",
               "rbf": "rbf_baseline",
               "deformation": "deformation_baseline", "seol": "seol", SEOL_ACTOR_RIG_METHOD: "seol_actor_rig",
               "semantic_actor_rig": "semantic_actor_rig"}
#: Seol job: result (spacetime solution or sec. 7 baseline) -> metric prefix
SEOL_RESULT_KEYS = {
    "spacetime": "seol",
    "no_constraint": "noconst",
    "perframe_range": "perframe_range",
    "perframe_prior": "perframe_prior",
    "spacetime_paper": "seol_paper",
}


def check_primary(primary: str) -> None:
    """Raise InputError unless ``primary`` is a Ribera variant."""
    if primary not in RIBERA_VARIANTS:
        from rigbuild.errors import InputError

        raise InputError(f"params.retarget.ribera.primary '{primary}' is not a Ribera variant", path="config",
                         fix=f"use one of {list(RIBERA_VARIANTS)}")


def metric_prefixes(method: str, primary: str = PRIMARY_RIBERA_METHOD) -> list[str]:
    """Prefixes under which ``method``'s numbers are reported: its own key, plus ``ribera`` when it is the
    primary Ribera variant."""
    check_primary(primary)
    return [METHOD_KEYS[method]] + ([PRIMARY_PREFIX] if method == primary else [])


def method_metrics(method: str, character: str, values: Mapping[str, Any],
                   primary: str = PRIMARY_RIBERA_METHOD) -> dict[str, dict[str, dict[str, Any]]]:
    """``{prefix: {character: values}}`` for every prefix of ``method`` (the ``retarget`` fragment's body)."""
    return {prefix: {str(character): dict(values)} for prefix in metric_prefixes(method, primary)}


def seol_result_prefix(name: str, method: str = SEOL_METHOD) -> str:
    """Metric prefix of a Seol job's result ``name`` (:data:`SEOL_RESULT_KEYS`): the spacetime solution under the
    method's key; a baseline of ``seol_actor_rig`` under the baseline's key with ``_actor_rig`` appended."""
    if name == "spacetime":
        return METHOD_KEYS[method]
    key = SEOL_RESULT_KEYS.get(name, name)
    return key if method == SEOL_METHOD else f"{key}_actor_rig"


def seol_result_metrics(per_result: Mapping[str, Mapping[str, Any]], character: str,
                        method: str = SEOL_METHOD) -> dict[str, dict[str, dict[str, Any]]]:
    """``{prefix: {character: values}}`` of a Seol job's results (:func:`seol_result_prefix`)."""
    return {seol_result_prefix(name, method): {str(character): dict(values)} for name, values in per_result.items()}


def wildcard(methods: list[str]) -> str:
    """A Snakemake wildcard constraint matching exactly these method names."""
    return "|".join(methods) or "(?!)"
