"""Snakemake entry point of rule ``eval_retarget``: one job's weight curves vs a synthetic session's ground truth.

input: weights (.csv of a retarget job), truth (ground_truth/performances/<perf>.npz), actor_rig
(ground_truth/actor_rig.npz). output: metrics (retarget_metrics.json fragment), details (every metric, .json).
params: method, character, ribera (params.retarget.ribera: its ``primary``).
"""

import logging

from rigbuild.eval.retarget import run_eval_retarget
from rigbuild.logs import run_logged


def main(smk) -> None:
    m = run_eval_retarget(smk.input.weights, smk.input.truth, smk.input.actor_rig, str(smk.params.method),
                          str(smk.params.character), smk.params.get("ribera", None), smk.output.metrics,
                          smk.output.details)
    logging.info("%s %s vs ground truth: weight MAE %.4f, mean correlation %.3f", smk.params.method,
                 smk.params.character, m["weight_mae"], m["mean_correlation"])


run_logged(snakemake, main)  # noqa: F821
