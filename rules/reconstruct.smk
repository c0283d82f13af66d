# Per-frame CPU multi-view stereo of ROM sequences (no ground truth: see rules/eval_reconstruct.smk).
# reconstruct_frame: one job per (session, sequence, frame) -> depth/points/mesh/coverage files + a frame record
#   (a cluster spreads the frames; bundle them with Snakemake's `group` / --group-components if jobs are too small).
# reconstruct_summary: one job per (session, sequence) -> coverage.png, renders/, recon_summary.json,
#   sequence_metrics.json.
# reconstruct_pool: one job per session -> reconstruction_metrics.json (session-level stage keys).
# Uses from common.smk: config["params"]["reconstruct"], session_dir(session), session_spec(session), sequences().
# config["params"]["reconstruct"] keys: rigbuild.reconstruct.params (checked at DAG start).

wildcard_constraints:
    frame=r"\d{6}",


def reconstruct_metric_files(session):
    """The reconstruct stage's metrics fragments of a session (gathered by rule metrics)."""
    return [f"results/{session}/reconstruct/{seq}/sequence_metrics.json" for seq in sequences(session)] + [
        f"results/{session}/reconstruct/reconstruction_metrics.json"]


rule reconstruct_frame:
    input:
        session_yaml=lambda wc: f"{session_dir(wc.session)}/session.yaml",
        cameras="results/{session}/calib/cameras.json",
        images=lambda wc: capture_images(wc.session, [session_spec(wc.session).rom_image(wc.sequence, cam, int(wc.frame))
                                                      for cam in session_spec(wc.session).cameras]),
    output:
        record="results/{session}/reconstruct/{sequence}/frames/{frame}.json",
        depth="results/{session}/reconstruct/{sequence}/depth/{frame}.npz",
        points="results/{session}/reconstruct/{sequence}/points/{frame}.ply",
        mesh="results/{session}/reconstruct/{sequence}/mesh/{frame}.ply",
        coverage="results/{session}/reconstruct/{sequence}/coverage/{frame}.png",
        # full-precision points and mesh for the ground-truth evaluation; removed once no job needs it
        geometry=temp("results/{session}/reconstruct/{sequence}/geometry/{frame}.npz"),
    params:
        reconstruct=lambda wc: config["params"].get("reconstruct", {}),
    log:
        "logs/{session}/reconstruct/{sequence}/{frame}.log",
    benchmark:
        "results/{session}/benchmarks/reconstruct_{sequence}_{frame}.tsv"
    # one core per frame: Poisson, fusion and file I/O are serial, so two frames side by side keep both cores
    # busy where one frame on two would leave one idle (the depth maps are the same at any thread count);
    # a single re-run frame goes faster with --set-threads reconstruct_frame=2
    threads: 1
    resources:
        mem_mb=3000,
    # open3d's multithreaded Poisson solver can segfault at random (not reproducible on rerun); a retry
    # is cheaper than a failed session
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
        # the pictures' frames (neutral, peak) are chosen from the meshes; their depth maps are drawn
        meshes=lambda wc: [f"results/{wc.session}/reconstruct/{wc.sequence}/mesh/{f:06d}.ply"
                           for f in session_spec(wc.session).sequence(wc.sequence).frames],
        depth=lambda wc: [f"results/{wc.session}/reconstruct/{wc.sequence}/depth/{f:06d}.npz"
                          for f in session_spec(wc.session).sequence(wc.sequence).frames],
    output:
        summary="results/{session}/reconstruct/{sequence}/recon_summary.json",
        coverage=report("results/{session}/reconstruct/{sequence}/coverage.png", category="Reconstruction"),
        # <frame>.png at the neutral and the peak frame: reference camera's depth map and the shaded mesh
        renders=directory("results/{session}/reconstruct/{sequence}/renders"),
        metrics="results/{session}/reconstruct/{sequence}/sequence_metrics.json",
    log:
        "logs/{session}/reconstruct/{sequence}/summary.log",
    threads: 1
    resources:
        mem_mb=1000,  # the pictures: one frame's depth maps and mesh, the renderer's context
    conda:
        "../environment.yml"
    script:
        "../scripts/reconstruct.py"


rule reconstruct_pool:
    """Session-level reconstruction.skipped_frames, mean_coverage and stereo_consistency_mm from every sequence."""
    input:
        fragments=lambda wc: [f"results/{wc.session}/reconstruct/{seq}/sequence_metrics.json"
                              for seq in sequences(wc.session)],
    output:
        metrics="results/{session}/reconstruct/reconstruction_metrics.json",
    log:
        "logs/{session}/reconstruct/pool.log",
    threads: 1
    resources:
        mem_mb=500,
    conda:
        "../environment.yml"
    script:
        "../scripts/reconstruct.py"
