"""Snakemake entry point of rule ``eval_personalize``: the personalized rig vs the actor's ground truth -> a fragment.

input.weights, input.fit (results/{session}/personalize/), input.cameras (calibrated), input.actor_rig
(ground_truth/actor_rig.npz, beside the other ground-truth files); output.metrics.
"""

import logging
from pathlib import Path

from rigbuild.eval.personalization import run_eval_personalize
from rigbuild.logs import run_logged


def main(smk) -> None:
    gt_dir = Path(smk.input.actor_rig).parent
    m = run_eval_personalize(gt_dir, smk.input.weights, smk.input.fit, smk.input.cameras, smk.output.metrics)
    logging.info("personalization vs ground truth: %s", m)


run_logged(snakemake, main)  # noqa: F821
