# Marker-space retargeting with range-of-motion alignment and a geometric prior (Ribera et al. 2017): one job
# per (session, performance, character, method), method in RIBERA_METHODS (rigbuild/retarget/methods.py: the
# method registry). Needs from common.smk: session_spec, performances, performance_file, CHARACTERS, results();
# characters.smk builds results/{session}/characters/{character}.npz; tracking writes
# results/{session}/track/{sequence}/markers.npz and vertices.npz; rule take_markers (below) reads every sequence at
# the take's own markers (params.retarget.take_markers). Params: config["params"]["retarget"]["ribera"]
# (rigbuild/retarget/params.py RiberaParams). Method ribera_fit_actor_rig (RIBERA_ACTOR_RIG_METHOD) also reads the
# personalized rig (personalize.smk), the take's marker map on it and the rig at the markers refined on the take
# (rule actor_rig_weights, retarget_actor_rig.smk); the other methods' jobs do not depend on them.
from rigbuild.retarget.methods import PIPELINE_METHODS, RIBERA_ACTOR_RIG_METHOD, RIBERA_METHODS
from rigbuild.retarget.methods import wildcard as _method_wildcard


def _retarget_rom_markers(wc):
    """The actor's tracked ROM markers (session order): with params.retarget.take_markers.rom 'take' (default),
    every sequence read at the take's own markers on the tracked neutral (rule take_markers, one file); with
    'marker_set', one file per sequence at the template's marker vertices; method ribera_fit_actor_rig: the
    tracked vertices, sampled at the take's marker map on the personalized rig."""
    if getattr(wc, "method", None) == RIBERA_ACTOR_RIG_METHOD:
        return [f"results/{wc.session}/track/{seq.name}/vertices.npz" for seq in session_spec(wc.session).rom]
    if _take_markers_params().rom == "take":
        return [f"results/{wc.session}/take_markers/{wc.performance}/rom_markers.npz"]
    return [f"results/{wc.session}/track/{seq.name}/markers.npz" for seq in session_spec(wc.session).rom]


def _take_markers_params():
    from rigbuild.retarget.params import take_markers_from_config

    return take_markers_from_config(config["params"]["retarget"].get("take_markers", {}))


def _retarget_neutral_frames(wc):
    """The neutral row of each tracked markers.npz (its rows start at the sequence's first frame)."""
    return [int(seq.neutral_frame) - int(seq.start) for seq in session_spec(wc.session).rom]


def _retarget_actor_rig(wc):
    """Method ribera_fit_actor_rig: the personalized rig whose shapes at the markers are E_Align's guesses g_k
    ([] for the other methods)."""
    return [f"results/{wc.session}/personalize/rig.npz"] if wc.method == RIBERA_ACTOR_RIG_METHOD else []


def actor_rig_take_file(wc, method, name):
    """A file of the take's actor-rig job (rule actor_rig_weights): ``marker_map.json`` (the take's markers
    placed on the personalized rig) or ``solve.npz`` (its rig at the markers, refined on the take), for the
    actor-rig ``method`` of a rule; [] for the rule's other methods."""
    if wc.method != method:
        return []
    return [f"results/{wc.session}/actor_rig/{wc.performance}/{name}"]


def retarget_metric_files(session):
    """The retargeting jobs' metrics fragments of a session (every method, every character). Metric keys name
    the method and the character, not the performance: only the first performance's jobs are gathered."""
    take = [results(session, "take_markers", perf, "take_markers_metrics.json") for perf in performances(session)[:1]
            if _take_markers_params().rom == "take"]
    return [results(session, "retarget", method, perf, character, "retarget_metrics.json")
            for perf in performances(session)[:1] for character in CHARACTERS for method in PIPELINE_METHODS] + \
        actor_rig_metric_files(session) + take


rule take_markers:
    """Place the take's markers on the tracked neutral's skin (marker_map.json) and read every tracked ROM
    sequence there (rom_markers.npz): the range of motion where the performance's hand-placed markers sit."""
    input:
        performance=lambda wc: performance_file(wc.session, wc.performance),
        session_yaml=lambda wc: f"{session_dir(wc.session)}/session.yaml",
        neutral="results/{session}/track/neutral.npz",
        vertices=lambda wc: [f"results/{wc.session}/track/{seq.name}/vertices.npz"
                             for seq in session_spec(wc.session).rom],
    output:
        marker_map="results/{session}/take_markers/{performance}/marker_map.json",
        rom_markers="results/{session}/take_markers/{performance}/rom_markers.npz",
        metrics="results/{session}/take_markers/{performance}/take_markers_metrics.json",
    params:
        session_dir=lambda wc: session_dir(wc.session),
        track=lambda wc: config["params"].get("track", {}),
        take_markers=lambda wc: config["params"]["retarget"].get("take_markers", {}),
    log:
        "logs/{session}/take_markers/{performance}.log",
    benchmark:
        "results/{session}/benchmarks/take_markers.{performance}.tsv"
    threads: 1
    resources:
        mem_mb=3000,
    conda:
        "../environment.yml"
    script:
        "../scripts/take_markers.py"


rule retarget_ribera:
    """Transfer the character's blendshapes to the actor's range of motion (sec. 4), then retarget the
    performance with E_Fit + mu E_Prior + lambda E_Sparse (sec. 5)."""
    input:
        performance=lambda wc: performance_file(wc.session, wc.performance),
        training=_retarget_rom_markers,
        rig="results/{session}/characters/{character}.npz",
        actor_rig=_retarget_actor_rig,
        marker_map=lambda wc: actor_rig_take_file(wc, RIBERA_ACTOR_RIG_METHOD, "marker_map.json"),
        actor_solve=lambda wc: actor_rig_take_file(wc, RIBERA_ACTOR_RIG_METHOD, "solve.npz"),
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
        neutral_frames=_retarget_neutral_frames,
    log:
        "logs/{session}/retarget/{method}.{performance}.{character}.log",
    benchmark:
        "results/{session}/benchmarks/retarget_{method}.{performance}.{character}.tsv"
    threads: 1
    resources:
        mem_mb=3000,
    wildcard_constraints:
        method=_method_wildcard(RIBERA_METHODS),
        character="|".join(CHARACTERS) or "(?!)",
    conda:
        "../environment.yml"
    script:
        "../scripts/retarget.py"
