"""Snakemake entry point of rule ``personalize``: tracked ROM sequences -> results/{session}/personalize/.

input.tracks: vertices.npz per ROM sequence (order of params.sequences); output.rig: rig.npz (the other
outputs sit beside it); params.personalize: the raw config block; params.template_rig: the resolved rig spec.
(no `from __future__` import: Snakemake prepends its preamble to this file)
"""

import logging
import sys
from pathlib import Path


def main(smk) -> None:
    from rigbuild.personalize.stage import run_personalize

    tracks = dict(zip(list(smk.params.sequences), list(smk.input.tracks)))
    metrics = run_personalize(tracks, str(smk.params.template_rig), Path(smk.output.rig).parent,
                              dict(smk.params.personalize or {}), dict(smk.params.neutral_frames), int(smk.threads))
    logging.info("personalization: %s", metrics)


if "snakemake" in globals():
    from rigbuild.logs import run_logged

    run_logged(snakemake, main)  # noqa: F821
else:
    sys.exit("scripts/personalize.py is run by Snakemake (rule personalize)")
