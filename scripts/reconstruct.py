"""Snakemake entry point of rules reconstruct_frame, reconstruct_summary and reconstruct_pool (no __future__)."""

import logging
import os
from pathlib import Path

for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # before numpy loads
    os.environ.setdefault(var, "1")


def main(smk) -> None:
    from rigbuild.reconstruct import stage

    log, out, inp, seq = logging.getLogger("rigbuild.reconstruct"), smk.output, smk.input, smk.wildcards.get("sequence")
    if smk.rule == "reconstruct_pool":
        log.info("reconstruction: %s", stage.run_reconstruct_pool(list(inp.fragments), out.metrics))
    elif smk.rule == "reconstruct_summary":
        s = stage.run_reconstruct_summary(Path(inp.session_yaml).parent, seq, list(inp.records), Path(out.summary).parent,
                                          out.metrics)
        log.info("%d frames, %d skipped, mean coverage %.3f", len(s["frames"]), len(s["skipped"]), s["mean_coverage"])
    else:
        stage.run_reconstruct_frame(Path(inp.session_yaml).parent, seq, int(smk.wildcards.frame), inp.cameras,
                                    smk.params.reconstruct, Path(out.record).parent.parent, smk.threads, log.info)


import cv2  # noqa: E402
from rigbuild.logs import run_logged  # noqa: E402

cv2.setNumThreads(max(1, int(snakemake.threads)))  # noqa: F821
run_logged(snakemake, main)  # noqa: F821
