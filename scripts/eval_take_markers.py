"""Snakemake entry point of rule ``eval_take_markers``: a take's markers on the tracked neutral vs their true points.

input: marker_map (take_markers/<perf>/marker_map.json), truth (ground_truth/performances/<perf>.npz), actor_rig
(ground_truth/actor_rig.npz). output: metrics (fragment).
"""

import logging

from rigbuild.eval.retarget import run_eval_take_markers
from rigbuild.logs import run_logged


def main(smk) -> None:
    i = smk.input
    m = run_eval_take_markers(i.marker_map, i.truth, i.actor_rig, smk.output.metrics)
    logging.info("take markers on the tracked neutral: %.2f mm from their true skin points (marker set %.2f mm)",
                 m["marker_map_skin_error_mm"], m["marker_set_skin_error_mm"])


run_logged(snakemake, main)  # noqa: F821
