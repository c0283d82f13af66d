"""Snakemake entry point of rule ``eval_calibration``: calibrated vs ground-truth cameras -> a metrics fragment.

input.cameras (results/{session}/calib/cameras.json), input.truth (ground_truth/cameras.json);
output.metrics (results/{session}/eval/calibration_metrics.json).
"""

import logging

from rigbuild.eval.calibration import run_eval_calibration
from rigbuild.logs import run_logged


def main(smk) -> None:
    errors = run_eval_calibration(smk.input.cameras, smk.input.truth, smk.output.metrics)
    logging.info("calibration vs ground truth: %s", errors)


run_logged(snakemake, main)  # noqa: F821
