"""Snakemake entry point of rule ``calibrate``: session folder -> results/{session}/calib/ + metrics.json.

snakemake.input.session_yaml : the session's session.yaml (its folder is the session)
snakemake.output.cameras : results/{session}/calib/cameras.json (the other outputs sit beside it)
snakemake.params.calibrate : config["params"]["calibrate"]
snakemake.params.metrics : results/{session}/metrics.json
(no `from __future__` import: Snakemake prepends its preamble to this file)
"""


import logging
import sys
from pathlib import Path


def main(smk) -> None:
    from rigbuild.calibrate.session import run_calibration

    session_dir = Path(smk.input.session_yaml).parent
    out_dir = Path(smk.output.cameras).parent
    metrics = run_calibration(session_dir, out_dir, dict(smk.params.calibrate or {}), smk.params.metrics)
    logging.info("calibration: %s", metrics)


if "snakemake" in globals():
    from rigbuild.logs import run_logged

    run_logged(snakemake, main)  # noqa: F821
else:
    sys.exit("scripts/calibrate.py is run by Snakemake (rule calibrate)")
