# Target characters for retargeting (config `characters:`), built once per session so that their
# marker maps match the session's marker set (rigbuild/synth/retarget_scenes.py run_character_rig).
# The rig's files (and the marker map) are the rule's inputs: editing a character's OBJs rebuilds it and
# everything retargeted onto it. Relative paths are relative to the workflow folder (as the DAG-start check).
from rigbuild.io.rigs import resolve_rig_spec, rig_source_files


def _character_entry(wc):
    """The character's config entry with its rig and marker-map paths resolved."""
    entry = dict(config["characters"][wc.character])
    for key in ("rig", "markers"):
        if entry.get(key):
            entry[key] = resolve_rig_spec(entry[key], workflow.basedir)
    return entry


def _character_sources(wc):
    entry = _character_entry(wc)
    return rig_source_files(entry["rig"]) + ([entry["markers"]] if entry.get("markers") else [])


rule character_rig:
    """Build a character rig (template copy or stylized variant by deformation transfer) as an npz."""
    input:
        sources=_character_sources,
    output:
        rig="results/{session}/characters/{character}.npz",
    params:
        character=_character_entry,
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
