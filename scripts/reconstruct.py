"""Snakemake entry points of rules ``reconstruct_frame`` and ``reconstruct_summary``.

reconstruct_frame (one job per session x sequence x frame):
  snakemake.input.session_yaml, snakemake.input.cameras (results/{session}/calib/cameras.json)
  snakemake.output.record : results/{session}/reconstruct/{sequence}/frames/{frame}.json (depth/, points/,
      mesh/, coverage/ files of the frame sit in sibling folders)
  snakemake.wildcards.frame; snakemake.params.reconstruct : config["params"]["reconstruct"]
reconstruct_summary (one job per session x sequence):
  snakemake.input.records : every frame record of the sequence
  snakemake.output.metrics : results/{session}/reconstruct/{sequence}/recon_metrics.json (coverage.png beside it)
  snakemake.params.metrics : results/{session}/metrics.json
(no `from __future__` import: Snakemake prepends its preamble to this file)
"""

import logging
import sys
from pathlib import Path


def main(smk) -> None:
    from rigbuild.reconstruct.sequence import run_frame_job, run_sequence_summary

    log = logging.getLogger("rigbuild.reconstruct")
    session_dir = Path(smk.input.session_yaml).parent
    seq = smk.wildcards.sequence
    if smk.rule == "reconstruct_summary":
        out_dir = Path(smk.output.metrics).parent
        s = run_sequence_summary(session_dir, seq, list(smk.input.records), out_dir, smk.params.metrics)
        log.info("reconstruct %s: %d frames, %d skipped, mean coverage %.3f", seq, len(s["frames"]),
                 len(s["skipped"]), s["mean_coverage"])
    else:
        out_dir = Path(smk.output.record).parent.parent
        params = dict(smk.params.reconstruct or {})
        params.setdefault("threads", int(smk.threads))
        run_frame_job(session_dir, seq, [int(smk.wildcards.frame)], smk.input.cameras, params, out_dir, log=log.info)


if "snakemake" in globals():
    import os

    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    import cv2

    cv2.setNumThreads(max(1, int(snakemake.threads)))  # noqa: F821
    from rigbuild.logs import run_logged

    run_logged(snakemake, main)  # noqa: F821
else:
    sys.exit("scripts/reconstruct.py is run by Snakemake (rules reconstruct_frame / reconstruct_summary)")
