"""Snakemake entry point of rule ``personalize``: tracked ROM sequences -> results/{session}/personalize/.

snakemake.input.tracks : results/{session}/track/{sequence}/vertices.npz for every ROM sequence (session order)
snakemake.output.rig : results/{session}/personalize/rig.npz (rig_obj/, rig.gltf, weights.npz,
    convergence.png, heatmaps/, objective.json, personalize_metrics.json sit beside it)
snakemake.params.personalize : config["params"]["personalize"]
snakemake.params.template_rig : rig spec (params.personalize.template_rig or session.yaml template_rig)
snakemake.params.sequences : ROM sequence names (order of input.tracks)
snakemake.params.neutral_frames : {sequence: neutral_frame}
snakemake.params.session_dir : the session folder (ground_truth/ is read only by rigbuild.eval)
snakemake.params.metrics : results/{session}/metrics.json
(no `from __future__` import: Snakemake prepends its preamble to this file)
"""


import logging
import sys
from pathlib import Path


def main(smk) -> None:
    from rigbuild.io.rigs import load_rig
    from rigbuild.paths import ict_dir
    from rigbuild.personalize.stage import run_personalization

    spec = str(smk.params.template_rig)
    template = load_rig(ict_dir() if spec == "ict" else spec)
    tracks = dict(zip(list(smk.params.sequences), list(smk.input.tracks)))
    metrics = run_personalization(tracks, template, Path(smk.output.rig).parent, dict(smk.params.personalize or {}),
                                  smk.params.metrics, smk.params.session_dir, dict(smk.params.neutral_frames),
                                  cameras_json=smk.input.cameras, workers=int(smk.threads))
    logging.info("personalization: %s", metrics)


if "snakemake" in globals():
    from rigbuild.logs import run_logged

    run_logged(snakemake, main)  # noqa: F821
else:
    sys.exit("scripts/personalize.py is run by Snakemake (rule personalize)")
