# Spacetime expression cloning (Seol et al. 2012): one job per (session, performance, character, method), method in
# SEOL_METHODS (rigbuild/retarget/methods.py). Needs from common.smk: performance_file, CHARACTERS; from
# retarget.smk: _retarget_rom_markers / _retarget_neutral_frames (the tracked ROM markers and their neutral rows),
# actor_rig_take_file;
# characters.smk builds results/{session}/characters/{character}.npz. Params: config["params"]["retarget"]["seol"]
# (rigbuild/retarget/params.py SeolParams). Method seol_actor_rig (SEOL_ACTOR_RIG_METHOD) also reads the
# personalized rig (personalize.smk), the take's marker map on it and the rig at the markers refined on the take
# (rule actor_rig_weights, retarget_actor_rig.smk): its source neutral and expression space
# (rigbuild/retarget/seol/actor_space.py); the seol jobs do not depend on them.
from rigbuild.retarget.methods import SEOL_ACTOR_RIG_METHOD, SEOL_METHODS, SEOL_RIG_METHODS


def _seol_actor_rig(wc):
    """Method seol_actor_rig: the personalized rig whose shapes at the markers are the actor's expression space
    ([] for seol)."""
    return [f"results/{wc.session}/personalize/rig.npz"] if wc.method == SEOL_ACTOR_RIG_METHOD else []


rule retarget_seol:
    """Retarget a marker performance onto a character by movement matching + PCA prior; sec. 7
    per-frame baselines and the fig. 11 velocity-error plot; system.npz for `rigbuild edit`."""
    input:
        performance=lambda wc: performance_file(wc.session, wc.performance),
        rig="results/{session}/characters/{character}.npz",
        neutral=_retarget_rom_markers,  # tracked ROM markers: the actor's neutral (mean of the neutral frames)
        actor_rig=_seol_actor_rig,
        marker_map=lambda wc: actor_rig_take_file(wc, SEOL_RIG_METHODS, "marker_map.json"),
        actor_solve=lambda wc: actor_rig_take_file(wc, SEOL_RIG_METHODS, "solve.npz"),
    output:
        weights="results/{session}/retarget/{method}/{performance}/{character}/weights.csv",
        weights_json="results/{session}/retarget/{method}/{performance}/{character}/weights.json",
        gltf="results/{session}/retarget/{method}/{performance}/{character}/animation.gltf",
        plot="results/{session}/retarget/{method}/{performance}/{character}/velocity_error.png",
        metrics="results/{session}/retarget/{method}/{performance}/{character}/retarget_metrics.json",
        system="results/{session}/retarget/{method}/{performance}/{character}/system.npz",
    params:
        seol=lambda wc: config["params"]["retarget"].get("seol", {}),
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
        mem_mb=2000,
    wildcard_constraints:
        method="|".join(SEOL_METHODS),
        character="|".join(CHARACTERS) or "(?!)",
    conda:
        "../environment.yml"
    script:
        "../scripts/retarget_seol.py"
