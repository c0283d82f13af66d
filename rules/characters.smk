# Target characters for retargeting (config `characters:`), built once per session so that their
# marker maps match the session's marker set (rigbuild/synth/retarget_scenes.py run_character_rig).


rule character_rig:
    """Build a character rig (template copy or stylized variant by deformation transfer) as an npz."""
    output:
        rig="results/{session}/characters/{character}.npz",
    params:
        character=lambda wc: config["characters"][wc.character],
    log:
        "logs/{session}/characters/{character}.log",
    benchmark:
        "results/{session}/benchmarks/character_rig.{character}.tsv"
    threads: 1
    resources:
        mem_mb=3000,
    wildcard_constraints:
        character="|".join(CHARACTERS) or "(?!)",
    conda:
        "../environment.yml"
    script:
        "../scripts/make_character.py"
