# Issue 6: EM blendshape personalization (Ma et al. 2016, sections 3-4).
# Needs from common.smk: config["params"]["personalize"], session_dir(session), session_spec(session).
# Needs from the track rules: results/{session}/track/{sequence}/vertices.npz (vertices F x V x 3 mm,
# confidence F x V) for every ROM sequence.


rule personalize:
    input:
        tracks=lambda wc: [f"results/{wc.session}/track/{s.name}/vertices.npz" for s in session_spec(wc.session).rom],
        cameras="results/{session}/calib/cameras.json",
    output:
        rig="results/{session}/personalize/rig.npz",
        initial_rig="results/{session}/personalize/initial_rig.npz",
        rig_obj=directory("results/{session}/personalize/rig_obj"),
        gltf="results/{session}/personalize/rig.gltf",
        weights="results/{session}/personalize/weights.npz",
        objective="results/{session}/personalize/objective.json",
        convergence=report("results/{session}/personalize/convergence.png", category="Personalization"),
        heatmaps=directory("results/{session}/personalize/heatmaps"),
        metrics="results/{session}/personalize/personalize_metrics.json",
    params:
        personalize=lambda wc: {k: v for k, v in config["params"].get("personalize", {}).items() if k != "template_rig"},
        template_rig=_personalize_template,
        sequences=lambda wc: [s.name for s in session_spec(wc.session).rom],
        neutral_frames=lambda wc: {s.name: s.neutral_frame for s in session_spec(wc.session).rom},
        session_dir=lambda wc: str(session_dir(wc.session)),
        metrics=lambda wc: f"results/{wc.session}/metrics.json",
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
