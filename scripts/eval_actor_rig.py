"""Snakemake entry point of rule ``eval_actor_rig``: actor weights and marker map vs a synthetic session's truth.

input: weights (actor_rig weights.csv), marker_map (.json), truth (ground_truth/performances/<perf>.npz),
actor_rig (ground_truth/actor_rig.npz), solve (the job's solve.npz). output: metrics (fragment), details (.json).
"""

import logging

from rigbuild.eval.retarget import run_eval_actor_rig
from rigbuild.logs import run_logged


def main(smk) -> None:
    i = smk.input
    m = run_eval_actor_rig(i.weights, i.marker_map, i.truth, i.actor_rig, smk.output.metrics, smk.output.details,
                           source=str(smk.params.source), solve_npz=i.solve)
    logging.info("%s weights vs ground truth: MAE %.4f, mean correlation %.3f; marker map %.2f mm mean",
                 smk.params.source, m["weight_mae"], m["mean_correlation"], m["marker_map_error_mm"])


run_logged(snakemake, main)  # noqa: F821
