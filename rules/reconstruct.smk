# Issue 4: per-frame CPU multi-view stereo of ROM sequences.
# reconstruct_frame: one job per (session, sequence, frame) -> depth/points/mesh/coverage files + a frame record
#   (a cluster spreads the frames; bundle them with Snakemake's `group` / --group-components if jobs are too small).
# reconstruct_summary: one job per (session, sequence) -> coverage.png, recon_metrics.json, reconstruction.* in
#   results/{session}/metrics.json.
# Uses from common.smk: config["params"]["reconstruct"], session_dir(session), session_spec(session).
# config["params"]["reconstruct"] keys: rigbuild.reconstruct.frame.ReconstructParams fields (unknown keys fail).

wildcard_constraints:
    frame=r"\d{6}",


rule reconstruct_frame:
    input:
        session_yaml=lambda wc: f"{session_dir(wc.session)}/session.yaml",
        cameras="results/{session}/calib/cameras.json",
        images=lambda wc: [str(session_spec(wc.session).rom_image(wc.sequence, cam, int(wc.frame)))
                           for cam in session_spec(wc.session).cameras],
    output:
        record="results/{session}/reconstruct/{sequence}/frames/{frame}.json",
        depth="results/{session}/reconstruct/{sequence}/depth/{frame}.npz",
        points="results/{session}/reconstruct/{sequence}/points/{frame}.ply",
        mesh="results/{session}/reconstruct/{sequence}/mesh/{frame}.ply",
        coverage="results/{session}/reconstruct/{sequence}/coverage/{frame}.png",
    params:
        reconstruct=lambda wc: config["params"].get("reconstruct", {}),
    log:
        "logs/{session}/reconstruct/{sequence}/{frame}.log",
    benchmark:
        "results/{session}/benchmarks/reconstruct_{sequence}_{frame}.tsv"
    threads: 2
    resources:
        mem_mb=3000,
    # open3d's multithreaded Poisson solver has segfaulted once in ~100 frames here (not reproducible
    # on rerun); a retry is cheaper than a failed session
    retries: 2
    conda:
        "../environment.yml"
    script:
        "../scripts/reconstruct.py"


rule reconstruct_summary:
    input:
        session_yaml=lambda wc: f"{session_dir(wc.session)}/session.yaml",
        records=lambda wc: [f"results/{wc.session}/reconstruct/{wc.sequence}/frames/{f:06d}.json"
                            for f in session_spec(wc.session).sequence(wc.sequence).frames],
    output:
        metrics="results/{session}/reconstruct/{sequence}/recon_metrics.json",
        coverage=report("results/{session}/reconstruct/{sequence}/coverage.png", category="Reconstruction"),
    params:
        metrics=lambda wc: f"results/{wc.session}/metrics.json",
    log:
        "logs/{session}/reconstruct/{sequence}/summary.log",
    threads: 1
    resources:
        mem_mb=500,
    conda:
        "../environment.yml"
    script:
        "../scripts/reconstruct.py"
