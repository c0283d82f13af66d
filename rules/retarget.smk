# Marker-space retargeting with range-of-motion alignment and a geometric prior (Ribera et al. 2017):
# one job per (session, performance, character, method); method in RIBERA_METHODS
# (ribera = the paper as written, ribera_activation = the activation-aware E_Match option, ribera_fit = the
# ROM-fit E_Match option (recommended with guess: deformation), rbf = the RBF-transfer baseline,
# deformation = the deformation-transfer guesses used directly). Needs from common.smk: session_spec, session_dir, CHARACTERS, results(), is_synthetic;
# characters.smk builds results/{session}/characters/{character}.npz; tracking writes
# results/{session}/track/{sequence}/markers.npz. Params: config["params"]["retarget"]["ribera"]
# (keys: scripts/retarget.py PARAMS).


rule retarget_ribera:
    """Transfer the character's blendshapes to the actor's range of motion (sec. 4), then retarget the
    performance with E_Fit + mu E_Prior + lambda E_Sparse (sec. 5)."""
    input:
        performance=lambda wc: performance_file(wc.session, wc.performance),
        training=_ribera_training,
        rig="results/{session}/characters/{character}.npz",
    output:
        weights="results/{session}/retarget/{method}/{performance}/{character}/weights.csv",
        weights_json="results/{session}/retarget/{method}/{performance}/{character}/weights.json",
        gltf="results/{session}/retarget/{method}/{performance}/{character}/animation.gltf",
        preview=report("results/{session}/retarget/{method}/{performance}/{character}/preview.png",
                       category="Retargeting"),
        metrics="results/{session}/retarget/{method}/{performance}/{character}/retarget_metrics.json",
    params:
        ribera=lambda wc: config["params"]["retarget"].get("ribera", {}),
        method=lambda wc: wc.method,
        character=lambda wc: wc.character,
        performance=lambda wc: wc.performance,
        neutral_frames=_ribera_neutral_frames,
        metrics_path=lambda wc: results(wc.session, "metrics.json"),
    log:
        "logs/{session}/retarget/{method}.{performance}.{character}.log",
    benchmark:
        "results/{session}/benchmarks/retarget_{method}.{performance}.{character}.tsv"
    threads: 1
    resources:
        mem_mb=3000,
    wildcard_constraints:
        method="|".join(RIBERA_METHODS),
        character="|".join(CHARACTERS) or "(?!)",
    conda:
        "../environment.yml"
    script:
        "../scripts/retarget.py"


rule retarget_eval:
    """Score a synthetic session's retargeted curves (any method) against the ground-truth weights."""
    input:
        weights="results/{session}/retarget/{method}/{performance}/{character}/weights.csv",
        truth=lambda wc: ground_truth_file(wc.session, f"performances/{wc.performance}.npz"),
        actor_rig=lambda wc: ground_truth_file(wc.session, "actor_rig.npz"),
    output:
        metrics="results/{session}/retarget/{method}/{performance}/{character}/eval_metrics.json",
    params:
        method=lambda wc: wc.method,
        character=lambda wc: wc.character,
        metrics_path=lambda wc: results(wc.session, "metrics.json"),
        ribera=lambda wc: config["params"]["retarget"].get("ribera", {}),
    log:
        "logs/{session}/retarget/{method}_eval.{performance}.{character}.log",
    threads: 1
    resources:
        mem_mb=1000,
    wildcard_constraints:
        method="|".join(RIBERA_METHODS + ["seol"]),
        character="|".join(CHARACTERS) or "(?!)",
    conda:
        "../environment.yml"
    script:
        "../scripts/retarget_eval.py"
