# Spacetime expression cloning (Seol et al. 2012): one job per (session, performance, character).
# Needs from common.smk: performance_file, CHARACTERS; from retarget.smk: _retarget_rom_markers /
# _retarget_neutral_frames (the tracked ROM markers and their neutral rows); characters.smk builds
# results/{session}/characters/{character}.npz. Params: config["params"]["retarget"]["seol"]
# (rigbuild/retarget/params.py SeolParams).


rule retarget_seol:
    """Retarget a marker performance onto a character by movement matching + PCA prior; sec. 7
    per-frame baselines and the fig. 11 velocity-error plot; system.npz for `rigbuild edit`."""
    input:
        performance=lambda wc: performance_file(wc.session, wc.performance),
        rig="results/{session}/characters/{character}.npz",
        neutral=_retarget_rom_markers,  # tracked ROM markers: the actor's neutral (mean of the neutral frames)
    output:
        weights="results/{session}/retarget/seol/{performance}/{character}/weights.csv",
        weights_json="results/{session}/retarget/seol/{performance}/{character}/weights.json",
        gltf="results/{session}/retarget/seol/{performance}/{character}/animation.gltf",
        plot="results/{session}/retarget/seol/{performance}/{character}/velocity_error.png",
        metrics="results/{session}/retarget/seol/{performance}/{character}/retarget_metrics.json",
        system="results/{session}/retarget/seol/{performance}/{character}/system.npz",
    params:
        seol=lambda wc: config["params"]["retarget"].get("seol", {}),
        character=lambda wc: wc.character,
        performance=lambda wc: wc.performance,
        neutral_frames=_retarget_neutral_frames,
    log:
        "logs/{session}/retarget/seol.{performance}.{character}.log",
    benchmark:
        "results/{session}/benchmarks/retarget_seol.{performance}.{character}.tsv"
    threads: 1
    resources:
        mem_mb=2000,
    wildcard_constraints:
        character="|".join(CHARACTERS) or "(?!)",
    conda:
        "../environment.yml"
    script:
        "../scripts/retarget_seol.py"
