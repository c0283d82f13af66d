# Ground-truth evaluation (synthetic sessions only): one rule per stage output it scores, each declaring the
# ground_truth/ files it reads as inputs and writing metrics fragments under results/{session}/eval/. No stage
# job reads ground truth; the `metrics` rule (report.smk) gathers these fragments with the stages' own.
# Each section defines eval_<stage>_metric_files(session), the fragments it adds ([] for a real session).


# ---------------------------------------------------------------------------- calibrate
# Ground-truth evaluation of the calibration (synthetic sessions only).


def eval_calibrate_metric_files(session):
    """The calibration's ground-truth metrics fragments of a session ([] for a real session)."""
    return [f"results/{session}/eval/calibration_metrics.json"] if is_synthetic(session) else []


rule eval_calibration:
    """Calibrated cameras vs ground_truth/cameras.json: calibration.focal_error_pct, center_error_mm, ..."""
    input:
        cameras="results/{session}/calib/cameras.json",
        truth=lambda wc: ground_truth_file(wc.session, "cameras.json"),
    output:
        metrics="results/{session}/eval/calibration_metrics.json",
    log:
        "logs/{session}/eval/calibration.log",
    threads: 1
    resources:
        mem_mb=500,
    conda:
        "../environment.yml"
    script:
        "../scripts/eval_calibrate.py"


# ---------------------------------------------------------------------------- reconstruct
# Ground-truth evaluation of the reconstruction (synthetic sessions only): one job per sequence scores its
# frames (the ground-truth ROM of a sequence is read once), one job per session pools the sequences.


def eval_reconstruct_metric_files(session):
    """The reconstruction's ground-truth metrics fragments of a session ([] for a real session)."""
    if not is_synthetic(session):
        return []
    return [f"results/{session}/eval/reconstruct/{seq}/sequence_metrics.json" for seq in sequences(session)] + [
        f"results/{session}/eval/reconstruction_metrics.json"]


def _eval_reconstruction_inputs(wc):
    frames = session_spec(wc.session).sequence(wc.sequence).frames
    base = f"results/{wc.session}/reconstruct/{wc.sequence}"
    return {
        "session_yaml": f"{session_dir(wc.session)}/session.yaml",
        "cameras": f"results/{wc.session}/calib/cameras.json",
        "records": [f"{base}/frames/{f:06d}.json" for f in frames],
        "geometry": [f"{base}/geometry/{f:06d}.npz" for f in frames],
        "rom": ground_truth_file(wc.session, f"rom/{wc.sequence}.npz"),
        "actor_rig": ground_truth_file(wc.session, "actor_rig.npz"),
        "truth_cameras": ground_truth_file(wc.session, "cameras.json"),
    }


rule eval_reconstruction_sequence:
    """Every reconstructed frame of a sequence vs its ground-truth mesh: reconstruction.sequences.<seq>.*."""
    input:
        unpack(_eval_reconstruction_inputs),
    output:
        metrics="results/{session}/eval/reconstruct/{sequence}/sequence_metrics.json",
        frames="results/{session}/eval/reconstruct/{sequence}/frames.json",
    log:
        "logs/{session}/eval/reconstruct/{sequence}.log",
    threads: 1
    resources:
        mem_mb=2000,
    conda:
        "../environment.yml"
    script:
        "../scripts/eval_reconstruct.py"


rule eval_reconstruction:
    """Session-level reconstruction.median_error_mm, p90_error_mm, completeness: the worst sequence."""
    input:
        fragments=lambda wc: [f"results/{wc.session}/eval/reconstruct/{seq}/sequence_metrics.json"
                              for seq in sequences(wc.session)],
    output:
        metrics="results/{session}/eval/reconstruction_metrics.json",
    log:
        "logs/{session}/eval/reconstruction.log",
    threads: 1
    resources:
        mem_mb=500,
    conda:
        "../environment.yml"
    script:
        "../scripts/eval_reconstruct.py"


# ---------------------------------------------------------------------------- track
# Ground-truth evaluation of the tracking stage (synthetic sessions only): reads the tracked meshes and the
# session's ground_truth/ (declared below), writes the `tracking` fragment results/{session}/eval/tracking_metrics.json.
# Needs from common.smk: is_synthetic, ground_truth_file, session_dir, session_spec, config["params"]["track"].


def eval_track_inputs(wc):
    """The tracked meshes and every ground-truth file the evaluation reads (true cameras, each ROM sequence)."""
    rom = session_spec(wc.session).rom
    return {
        "session_yaml": f"{session_dir(wc.session)}/session.yaml",
        "cameras": f"results/{wc.session}/calib/cameras.json",
        "neutral": f"results/{wc.session}/track/neutral.npz",
        "vertices": [f"results/{wc.session}/track/{s.name}/vertices.npz" for s in rom],
        "gt_cameras": ground_truth_file(wc.session, "cameras.json"),
        "gt_sequences": [ground_truth_file(wc.session, f"rom/{s.name}.npz") for s in rom],
    }


def eval_track_metric_files(session):
    """The tracking ground-truth fragment of a session ([] for a real session)."""
    return [f"results/{session}/eval/tracking_metrics.json"] if is_synthetic(session) else []


rule eval_track:
    input:
        unpack(eval_track_inputs),
    output:
        metrics="results/{session}/eval/tracking_metrics.json",
        curves="results/{session}/eval/tracking_curves.json",
    params:
        track=lambda wc: config["params"].get("track", {}),
        session_dir=lambda wc: str(session_dir(wc.session)),
    log:
        "logs/{session}/eval/tracking.log",
    threads: 1
    resources:
        mem_mb=2000,
    conda:
        "../environment.yml"
    script:
        "../scripts/eval_track.py"


# ---------------------------------------------------------------------------- personalize
# Ground-truth evaluation of the personalized rig (synthetic sessions only).
# Needs from common.smk: is_synthetic(session), session_spec(session), ground_truth_file(session, relpath),
# results(session, ...). Reads the personalize rule's weights.npz and fit.npz and the calibrated cameras.


def eval_personalize_metric_files(session):
    """The personalization's ground-truth metrics fragments of a session ([] for a real session)."""
    return [results(session, "eval", "personalization_metrics.json")] if is_synthetic(session) else []


def _eval_personalize_gt(session, relpath):
    if not is_synthetic(session):
        raise InputError(f"session '{session}' has no ground truth: eval_personalize runs on synthetic "
                         "sessions only", path="config")
    return ground_truth_file(session, relpath)


rule eval_personalize:
    input:
        weights="results/{session}/personalize/weights.npz",
        fit="results/{session}/personalize/fit.npz",
        cameras="results/{session}/calib/cameras.json",
        gt_cameras=lambda wc: _eval_personalize_gt(wc.session, "cameras.json"),
        actor_rig=lambda wc: _eval_personalize_gt(wc.session, "actor_rig.npz"),
        gt_rom=lambda wc: [_eval_personalize_gt(wc.session, f"rom/{s.name}.npz") for s in session_spec(wc.session).rom],
    output:
        metrics="results/{session}/eval/personalization_metrics.json",
    log:
        "logs/{session}/eval/personalization.log",
    threads: 1
    resources:
        mem_mb=3000,
    conda:
        "../environment.yml"
    script:
        "../scripts/eval_personalize.py"


# ---------------------------------------------------------------------------- retarget
# Ground-truth evaluation of the retargeted weight curves (synthetic sessions only): every method's curves vs
# ground_truth/performances/<performance>.npz, with the actor's rig (ground_truth/actor_rig.npz) deciding which
# shapes the markers observe. Needs from common.smk: ground_truth_file, is_synthetic, performances, CHARACTERS;
# from retarget.smk: PIPELINE_METHODS.


def eval_retarget_metric_files(session):
    """The retargeting's ground-truth metrics fragments of a session ([] for a real session); like
    retarget_metric_files, the first performance only (the keys do not name the performance)."""
    if not is_synthetic(session):
        return []
    return [f"results/{session}/eval/retarget/{method}/{perf}/{character}/retarget_metrics.json"
            for perf in performances(session)[:1] for character in CHARACTERS for method in PIPELINE_METHODS] + \
        [f"results/{session}/eval/{source}/{perf}/actor_rig_metrics.json" for perf in performances(session)[:1]
         for source in ACTOR_RIG_SOURCES] + \
        [f"results/{session}/eval/take_markers/{perf}/take_markers_metrics.json" for perf in performances(session)[:1]
         if _take_markers_params().rom == "take"]


rule eval_take_markers:
    """The take's markers placed on the tracked neutral vs their true skin points (and the marker set's vertices
    they started from): retarget.take_markers.{marker_map_skin_error_mm, marker_set_skin_error_mm}."""
    input:
        marker_map="results/{session}/take_markers/{performance}/marker_map.json",
        truth=lambda wc: ground_truth_file(wc.session, f"performances/{wc.performance}.npz"),
        actor_rig=lambda wc: ground_truth_file(wc.session, "actor_rig.npz"),
    output:
        metrics="results/{session}/eval/take_markers/{performance}/take_markers_metrics.json",
    log:
        "logs/{session}/eval/take_markers/{performance}.log",
    threads: 1
    resources:
        mem_mb=1000,
    conda:
        "../environment.yml"
    script:
        "../scripts/eval_take_markers.py"


rule eval_actor_rig:
    """The actor weights solved from the personalized (or the template) rig vs the true performance weights, and
    the marker map vs the markers' true skin points: retarget.<source>_weights.{weight_mae, mean_correlation,
    marker_map_error_mm}."""
    input:
        weights="results/{session}/{source}/{performance}/weights.csv",
        marker_map="results/{session}/{source}/{performance}/marker_map.json",
        solve="results/{session}/{source}/{performance}/solve.npz",
        truth=lambda wc: ground_truth_file(wc.session, f"performances/{wc.performance}.npz"),
        actor_rig=lambda wc: ground_truth_file(wc.session, "actor_rig.npz"),
    output:
        metrics="results/{session}/eval/{source}/{performance}/actor_rig_metrics.json",
        details="results/{session}/eval/{source}/{performance}/actor_rig_eval.json",
    params:
        source=lambda wc: wc.source,
    log:
        "logs/{session}/eval/{source}/{performance}.log",
    wildcard_constraints:
        source="|".join(ACTOR_RIG_SOURCES),
    threads: 1
    resources:
        mem_mb=1000,
    conda:
        "../environment.yml"
    script:
        "../scripts/eval_actor_rig.py"


rule eval_retarget:
    """Weight MAE and per-shape correlation of one retarget job vs the ground-truth weights:
    retarget.<method key>.<character>.weight_mae, mean_correlation, unobservable_mae."""
    input:
        weights="results/{session}/retarget/{method}/{performance}/{character}/weights.csv",
        truth=lambda wc: ground_truth_file(wc.session, f"performances/{wc.performance}.npz"),
        actor_rig=lambda wc: ground_truth_file(wc.session, "actor_rig.npz"),
    output:
        metrics="results/{session}/eval/retarget/{method}/{performance}/{character}/retarget_metrics.json",
        details="results/{session}/eval/retarget/{method}/{performance}/{character}/retarget_eval.json",
    params:
        method=lambda wc: wc.method,
        character=lambda wc: wc.character,
        ribera=lambda wc: config["params"]["retarget"].get("ribera", {}),
    log:
        "logs/{session}/eval/retarget/{method}.{performance}.{character}.log",
    threads: 1
    resources:
        mem_mb=1000,
    wildcard_constraints:
        method=_method_wildcard(PIPELINE_METHODS),
        character="|".join(CHARACTERS) or "(?!)",
    conda:
        "../environment.yml"
    script:
        "../scripts/eval_retarget.py"
