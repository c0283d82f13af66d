# The personalized rig feeding retargeting (rigbuild/retarget/actor_rig.py): each performance's markers placed on
# the actor's personalized rig and the actor's weights solved from it (rule actor_rig_weights, one job per
# (session, performance)), then carried to every character by shape name (rule retarget_semantic, method
# SEMANTIC_METHOD of rigbuild/retarget/methods.py). Needs from common.smk: performance_file, performances,
# CHARACTERS, results(); personalize.smk writes results/{session}/personalize/rig.npz; characters.smk
# results/{session}/characters/{character}.npz. Params: config["params"]["retarget"]["actor_rig"]
# (rigbuild/retarget/params.py ActorRigParams). Ground truth: rule eval_actor_rig (eval.smk).
from rigbuild.retarget.methods import ACTOR_RIG_SOURCES, SEMANTIC_METHOD


def actor_rig_metric_files(session):
    """The actor-rig jobs' metrics fragments, personalized and template rig (keys name no performance: the
    first performance's jobs)."""
    return [results(session, source, perf, "actor_rig_metrics.json") for perf in performances(session)[:1]
            for source in ACTOR_RIG_SOURCES]


def rig_of_source(wc, source):
    """The rig of an actor_rig_weights ``source`` (ACTOR_RIG_SOURCES): the personalized rig, or (the baseline
    without personalization) the template rig the personalization started from (rules/personalize.smk)."""
    if source == "actor_rig":
        return f"results/{wc.session}/personalize/rig.npz"
    return _personalize_template_rig(wc)


def _actor_rig_spec(wc):
    """The rig an actor_rig_weights job reads (:func:`rig_of_source` of its source)."""
    return rig_of_source(wc, wc.source)


rule actor_rig_weights:
    """Place the take's markers on the personalized rig (marker_map.json) and solve the actor's weights and
    head motion from that rig, every frame at once; source template_rig: the same with the template rig."""
    input:
        performance=lambda wc: performance_file(wc.session, wc.performance),
        rig=lambda wc: [_actor_rig_spec(wc)] if wc.source == "actor_rig" else rig_source_files(_actor_rig_spec(wc)),
    output:
        marker_map="results/{session}/{source}/{performance}/marker_map.json",
        weights="results/{session}/{source}/{performance}/weights.csv",
        weights_json="results/{session}/{source}/{performance}/weights.json",
        solve="results/{session}/{source}/{performance}/solve.npz",
        metrics="results/{session}/{source}/{performance}/actor_rig_metrics.json",
    params:
        actor_rig=lambda wc: config["params"]["retarget"].get("actor_rig", {}),
        performance=lambda wc: wc.performance,
        rig=_actor_rig_spec,
        source=lambda wc: wc.source,
    log:
        "logs/{session}/{source}/{performance}.log",
    benchmark:
        "results/{session}/benchmarks/{source}.{performance}.tsv"
    wildcard_constraints:
        source="|".join(ACTOR_RIG_SOURCES),
    threads: 1
    resources:
        mem_mb=2000,
    conda:
        "../environment.yml"
    script:
        "../scripts/actor_rig.py"


rule retarget_semantic:
    """Carry the actor weights to a character whose shape names match the personalized rig's."""
    input:
        weights="results/{session}/actor_rig/{performance}/weights.csv",
        solve="results/{session}/actor_rig/{performance}/solve.npz",
        actor_rig="results/{session}/personalize/rig.npz",
        rig="results/{session}/characters/{character}.npz",
    output:
        weights=f"results/{{session}}/retarget/{SEMANTIC_METHOD}/{{performance}}/{{character}}/weights.csv",
        weights_json=f"results/{{session}}/retarget/{SEMANTIC_METHOD}/{{performance}}/{{character}}/weights.json",
        gltf=f"results/{{session}}/retarget/{SEMANTIC_METHOD}/{{performance}}/{{character}}/animation.gltf",
        preview=f"results/{{session}}/retarget/{SEMANTIC_METHOD}/{{performance}}/{{character}}/preview.png",
        metrics=f"results/{{session}}/retarget/{SEMANTIC_METHOD}/{{performance}}/{{character}}/retarget_metrics.json",
    params:
        character=lambda wc: wc.character,
        performance=lambda wc: wc.performance,
    log:
        f"logs/{{session}}/retarget/{SEMANTIC_METHOD}.{{performance}}.{{character}}.log",
    threads: 1
    resources:
        mem_mb=1000,
    wildcard_constraints:
        character="|".join(CHARACTERS) or "(?!)",
    conda:
        "../environment.yml"
    script:
        "../scripts/retarget_semantic.py"
