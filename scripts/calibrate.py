"""Snakemake entry point of rule ``calibrate``: session folder -> results/{session}/calib/.

input.session_yaml (its folder is the session); output.cameras (the other outputs sit beside it);
params.calibrate: config["params"]["calibrate"]. (No `from __future__`: Snakemake prepends a preamble.)
"""

import logging
import sys
from pathlib import Path


def main(smk) -> None:
    from rigbuild.calibrate.stage import run_calibrate

    metrics = run_calibrate(Path(smk.input.session_yaml).parent, Path(smk.output.cameras).parent,
                            smk.params.calibrate, smk.threads)
    logging.info("calibration: %s", metrics)


if "snakemake" in globals():
    from rigbuild.logs import run_logged

    run_logged(snakemake, main)  # noqa: F821
else:
    sys.exit("scripts/calibrate.py is run by Snakemake (rule calibrate)")
