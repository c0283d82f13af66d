# Issue 5: coarse-to-fine Laplacian mesh tracking through ROM sequences (Ma et al. 2016, section 2).
# Needs from common.smk: config["params"]["track"], session_dir(session), session_spec(session), SESSIONS.
# Needs from the reconstruct rules: results/{session}/reconstruct/{sequence}/depth/{frame:06d}.npz.


rule track_neutral:
    input:
        unpack(_track_neutral_inputs),
    output:
        neutral="results/{session}/track/neutral.npz",
    params:
        track=lambda wc: config["params"].get("track", {}),
        session_dir=lambda wc: str(session_dir(wc.session)),
        depth_dir=lambda wc: f"results/{wc.session}/reconstruct/{session_spec(wc.session).rom[0].name}/depth",
        metrics=lambda wc: f"results/{wc.session}/metrics.json",
    log:
        "logs/{session}/track/neutral.log",
    benchmark:
        "results/{session}/benchmarks/track_neutral.tsv"
    threads: 1
    resources:
        mem_mb=3000,
    conda:
        "../environment.yml"
    script:
        "../scripts/track.py"


rule track_sequence:
    input:
        unpack(_track_sequence_inputs),
    output:
        vertices="results/{session}/track/{sequence}/vertices.npz",
        markers="results/{session}/track/{sequence}/markers.npz",
        c3d="results/{session}/track/{sequence}/markers.c3d",
        residuals_csv="results/{session}/track/{sequence}/residuals.csv",
        residuals_png=report("results/{session}/track/{sequence}/residuals.png", category="Tracking"),
        overlay=directory("results/{session}/track/{sequence}/overlay"),
        metrics="results/{session}/track/{sequence}/track_metrics.json",
    params:
        track=lambda wc: config["params"].get("track", {}),
        session_dir=lambda wc: str(session_dir(wc.session)),
        depth_dir=lambda wc: f"results/{wc.session}/reconstruct/{wc.sequence}/depth",
        anchor_depth_dir=lambda wc: f"results/{wc.session}/reconstruct/{session_spec(wc.session).rom[0].name}/depth",
        metrics=lambda wc: f"results/{wc.session}/metrics.json",
    log:
        "logs/{session}/track/{sequence}.log",
    benchmark:
        "results/{session}/benchmarks/track_sequence_{sequence}.tsv"
    threads: 1
    resources:
        mem_mb=4000,
    conda:
        "../environment.yml"
    script:
        "../scripts/track.py"


rule track_metrics:
    input:
        seq_metrics=lambda wc: [f"results/{wc.session}/track/{s.name}/track_metrics.json"
                                for s in session_spec(wc.session).rom],
        vertices=lambda wc: [f"results/{wc.session}/track/{s.name}/vertices.npz" for s in session_spec(wc.session).rom],
        neutral="results/{session}/track/neutral.npz",
        cameras="results/{session}/calib/cameras.json",
    output:
        summary="results/{session}/track/track_summary.json",
    params:
        track=lambda wc: config["params"].get("track", {}),
        session_dir=lambda wc: str(session_dir(wc.session)),
        metrics=lambda wc: f"results/{wc.session}/metrics.json",
    log:
        "logs/{session}/track/metrics.log",
    threads: 1
    resources:
        mem_mb=2000,
    conda:
        "../environment.yml"
    script:
        "../scripts/track.py"
