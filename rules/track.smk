# Issue 5: coarse-to-fine Laplacian mesh tracking through ROM sequences (Ma et al. 2016, section 2).
# Needs from common.smk: config["params"]["track"], session_dir(session), session_spec(session), SESSIONS.
# Needs from the reconstruct rules: results/{session}/reconstruct/{sequence}/depth/{frame:06d}.npz.
# Metrics: each job writes its own `tracking` fragment (*_metrics.json); track_metric_files() lists them.
# params.track.registration.coarse: landmarks runs the face networks that `make setup` installs into the venv
# (python -m rigbuild.assets.face_models install) with the template's committed landmark table.


def _track_frame_images(session, seq_name, frames):
    spec = session_spec(session)
    return capture_images(session, [spec.rom_image(seq_name, cam, f) for cam in spec.cameras for f in frames])


def track_neutral_inputs(wc):
    """The global neutral frame (first ROM sequence's neutral_frame): images, depth map, cameras."""
    seq = session_spec(wc.session).rom[0]
    return {
        "session_yaml": f"{session_dir(wc.session)}/session.yaml",
        "cameras": f"results/{wc.session}/calib/cameras.json",
        "images": _track_frame_images(wc.session, seq.name, [seq.neutral_frame]),
        "depth": f"results/{wc.session}/reconstruct/{seq.name}/depth/{seq.neutral_frame:06d}.npz",
    }


def track_sequence_inputs(wc):
    """One ROM sequence from its neutral frame on, plus the anchor (global neutral frame) and neutral.npz."""
    spec = session_spec(wc.session)
    seq = next(s for s in spec.rom if s.name == wc.sequence)
    frames = [f for f in seq.frames if f >= seq.neutral_frame]
    anchor = spec.rom[0]
    return {
        "session_yaml": f"{session_dir(wc.session)}/session.yaml",
        "cameras": f"results/{wc.session}/calib/cameras.json",
        "neutral": f"results/{wc.session}/track/neutral.npz",
        "images": _track_frame_images(wc.session, seq.name, frames),
        "depth": [f"results/{wc.session}/reconstruct/{seq.name}/depth/{f:06d}.npz" for f in frames],
        "anchor_images": _track_frame_images(wc.session, anchor.name, [anchor.neutral_frame]),
        "anchor_depth": f"results/{wc.session}/reconstruct/{anchor.name}/depth/{anchor.neutral_frame:06d}.npz",
    }


def track_sequence_metric_files(session):
    """The per-sequence tracking fragments of a session."""
    return [f"results/{session}/track/{s.name}/track_metrics.json" for s in session_spec(session).rom]


def track_metric_files(session):
    """Every tracking fragment of a session (stage jobs only; eval_track_metric_files lists ground truth's)."""
    return [f"results/{session}/track/neutral_metrics.json", f"results/{session}/track/summary_metrics.json"] + \
        track_sequence_metric_files(session)


rule track_neutral:
    input:
        unpack(track_neutral_inputs),
    output:
        neutral="results/{session}/track/neutral.npz",
        metrics="results/{session}/track/neutral_metrics.json",
    params:
        track=lambda wc: config["params"].get("track", {}),
        session_dir=lambda wc: str(session_dir(wc.session)),
        depth_dir=lambda wc: f"results/{wc.session}/reconstruct/{session_spec(wc.session).rom[0].name}/depth",
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
        unpack(track_sequence_inputs),
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


rule track_summary:
    input:
        sequence_metrics=lambda wc: track_sequence_metric_files(wc.session),
    output:
        summary="results/{session}/track/track_summary.json",
        metrics="results/{session}/track/summary_metrics.json",
    log:
        "logs/{session}/track/summary.log",
    threads: 1
    resources:
        mem_mb=500,
    conda:
        "../environment.yml"
    script:
        "../scripts/track.py"
