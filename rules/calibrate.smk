# Multi-camera rig calibration from ChArUco / chessboard images.
# Uses from common.smk: config["params"]["calibrate"], session_yaml(session), calib_images(session) (rig images,
# calib_intrinsics images, an intrinsics file). A failed quality gate keeps a copy of the outputs in
# results/{session}/calib_diagnostics/ (Snakemake deletes a failed job's outputs).
# config["params"]["calibrate"] keys: rigbuild.calibrate.params.CalibrationOptions fields (checked at DAG start).


def calibrate_metric_files(session):
    """The calibrate stage's metrics fragments of a session (gathered by rule metrics)."""
    return [f"results/{session}/calib/calib_metrics.json"]


rule calibrate:
    input:
        session_yaml=lambda wc: session_yaml(wc.session),
        images=lambda wc: calib_images(wc.session),
    output:
        cameras="results/{session}/calib/cameras.json",
        colmap_cameras="results/{session}/calib/colmap/cameras.txt",
        colmap_images="results/{session}/calib/colmap/images.txt",
        colmap_points="results/{session}/calib/colmap/points3D.txt",
        per_image="results/{session}/calib/reprojection_per_image.csv",
        per_camera="results/{session}/calib/reprojection_per_camera.csv",
        residuals_png=report("results/{session}/calib/residuals.png", category="Calibration"),
        layout_png=report("results/{session}/calib/camera_layout.png", category="Calibration"),
        detections=directory("results/{session}/calib/detections"),  # one board-detection picture per camera
        metrics="results/{session}/calib/calib_metrics.json",
    params:
        calibrate=lambda wc: config["params"].get("calibrate", {}),
    log:
        "logs/{session}/calib/calibrate.log",
    benchmark:
        "results/{session}/benchmarks/calibrate.tsv"
    threads: 2  # board detection, one thread per core
    resources:
        mem_mb=2000,
    conda:
        "../environment.yml"
    script:
        "../scripts/calibrate.py"
