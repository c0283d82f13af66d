"""Snakemake entry point of rule ``character_rig``: build one character rig (config ``characters:``).

params.character: the character's config entry {rig, kind, markers?}; output.rig: results/{session}/characters/
{character}.npz (rigbuild.synth.retarget_scenes.run_character_rig).
"""

from rigbuild.logs import run_logged
from rigbuild.synth.retarget_scenes import run_character_rig


def main(smk) -> None:
    run_character_rig(dict(smk.params.character), str(smk.wildcards.character), smk.output.rig)


run_logged(snakemake, main)  # noqa: F821
