# EM blendshape personalization (Ma et al. 2016, sections 3-4).
# Needs from common.smk: config["params"]["personalize"], session_spec(session), results(session, ...).
# Needs from the track rules: results/{session}/track/{sequence}/vertices.npz (vertices F x V x 3 mm,
# confidence F x V) for every ROM sequence. Ground-truth evaluation: rule eval_personalize (rules/eval.smk).
from rigbuild.io.rigs import resolve_rig_spec, rig_source_files
from rigbuild.personalize.params import from_config as _personalize_from_config


def _personalize_template_rig(wc):
    """The rig spec to personalize: params.personalize.template_rig, else the session's template_rig
    (a path relative to the workflow folder is made absolute)."""
    spec = _personalize_from_config(config["params"]["personalize"]).template_rig
    return resolve_rig_spec(spec or session_spec(wc.session).template_rig, workflow.basedir)


def personalize_metric_files(session):
    """The personalize stage's metrics fragments of a session (for the metrics rule)."""
    return [results(session, "personalize", "personalize_metrics.json")]


rule personalize:
    input:
        tracks=lambda wc: [f"results/{wc.session}/track/{s.name}/vertices.npz" for s in session_spec(wc.session).rom],
        template_rig=lambda wc: rig_source_files(_personalize_template_rig(wc)),  # editing the rig reruns the fit
    output:
        rig="results/{session}/personalize/rig.npz",
        initial_rig="results/{session}/personalize/initial_rig.npz",
        rig_obj=directory("results/{session}/personalize/rig_obj"),
        gltf="results/{session}/personalize/rig.gltf",
        head_frame="results/{session}/personalize/head_frame.json",  # capture -> head frame of the rig files
        weights="results/{session}/personalize/weights.npz",
        fit="results/{session}/personalize/fit.npz",
        objective="results/{session}/personalize/objective.json",
        convergence=report("results/{session}/personalize/convergence.png", category="Personalization"),
        heatmaps=directory("results/{session}/personalize/heatmaps"),
        metrics="results/{session}/personalize/personalize_metrics.json",
    params:
        personalize=lambda wc: config["params"]["personalize"],
        template_rig=_personalize_template_rig,
        sequences=lambda wc: [s.name for s in session_spec(wc.session).rom],
        neutral_frames=lambda wc: {s.name: s.neutral_frame for s in session_spec(wc.session).rom},
    log:
        "logs/{session}/personalize/personalize.log",
    benchmark:
        "results/{session}/benchmarks/personalize.tsv"
    threads: 2  # CHOLMOD's supernodal factorization uses both BLAS threads
    resources:
        mem_mb=6000,
    conda:
        "../environment.yml"
    script:
        "../scripts/personalize.py"
