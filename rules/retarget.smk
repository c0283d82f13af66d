# Marker-space retargeting with range-of-motion alignment and a geometric prior (Ribera et al. 2017): one job
# per (session, performance, character, method), method in RIBERA_METHODS (rigbuild/retarget/methods.py: the
# method registry). Needs from common.smk: session_spec, performances, performance_file, CHARACTERS, results();
# characters.smk builds results/{session}/characters/{character}.npz; tracking writes
# results/{session}/track/{sequence}/markers.npz and vertices.npz; rule take_markers (below) reads every sequence at
# the take's own markers (params.retarget.take_markers). Params: config["params"]["retarget"]["ribera"]
# (rigbuild/retarget/params.py RiberaParams). The methods of RIBERA_RIG_METHODS also read a rig of the actor's
# topology and the take's marker map on it: ribera_fit_actor_rig the personalized rig (personalize.smk), the map and
# the rig at the markers refined on the take from rule actor_rig_weights (retarget_actor_rig.smk);
# ribera_fit_template_rig the template rig at the take's markers on the tracked neutral (rule take_markers, the
# template's topology). The other methods' jobs depend on neither.
from rigbuild.retarget.methods import (PIPELINE_METHODS, RIBERA_ACTOR_RIG_METHOD, RIBERA_METHODS,
                                       RIBERA_RIG_METHODS, RIBERA_TEMPLATE_RIG_METHOD)
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


def _guess_rig(wc):
    """The methods of RIBERA_RIG_METHODS: the spec of the rig whose shapes at the markers are E_Align's guesses g_k
    (the personalized rig.npz or the template rig's spec, rule actor_rig_weights' source); "" for the others."""
    source = RIBERA_RIG_METHODS.get(wc.method)
    return rig_of_source(wc, source) if source else ""


def _guess_rig_files(wc):
    """The files of :func:`_guess_rig` (so that a changed rig re-runs the job): the personalized rig.npz (made by
    rule personalize), the template rig's source files; [] for the other methods."""
    source = RIBERA_RIG_METHODS.get(wc.method)
    if source is None:
        return []
    return [_guess_rig(wc)] if source == "actor_rig" else rig_source_files(_guess_rig(wc))


def _guess_rig_marker_map(wc):
    """The take's marker map the guess rig is read at: ribera_fit_actor_rig's from rule actor_rig_weights (the
    markers on the personalized rig), ribera_fit_template_rig's from rule take_markers (on the tracked neutral,
    whose topology is the template rig's); [] for the other methods."""
    if wc.method == RIBERA_TEMPLATE_RIG_METHOD:
        return [f"results/{wc.session}/take_markers/{wc.performance}/marker_map.json"]
    return actor_rig_take_file(wc, {RIBERA_ACTOR_RIG_METHOD: "actor_rig"}, "marker_map.json")


def actor_rig_take_file(wc, rig_methods, name):
    """A file of the take's actor-rig job (rule actor_rig_weights) of the rig a method of ``rig_methods``
    ({method: source}) reads: ``marker_map.json`` (the take's markers placed on that rig) or ``solve.npz`` (its rig
    at the markers, refined on the take); [] for the rule's other methods."""
    source = rig_methods.get(wc.method)
    if source is None:
        return []
    return [f"results/{wc.session}/{source}/{wc.performance}/{name}"]


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
        guess_rig=_guess_rig_files,
        marker_map=_guess_rig_marker_map,
        actor_solve=lambda wc: actor_rig_take_file(wc, {RIBERA_ACTOR_RIG_METHOD: "actor_rig"}, "solve.npz"),
    output:
        weights="results/{session}/retarget/{method}/{performance}/{character}/weights.csv",
        weights_json="results/{session}/retarget/{method}/{performance}/{character}/weights.json",
        gltf="results/{session}/retarget/{method}/{performance}/{character}/animation.gltf",
        preview=report("results/{session}/retarget/{method}/{performance}/{character}/preview.png",
                       category="Retargeting"),
        metrics="results/{session}/retarget/{method}/{performance}/{character}/retarget_metrics.json",
    params:
        ribera=lambda wc: config["params"]["retarget"].get("ribera", {}),
        guess_rig=_guess_rig,
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
