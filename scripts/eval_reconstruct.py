"""Snakemake entry point of rules eval_reconstruction_sequence and eval_reconstruction (rules/eval_reconstruct.smk)."""

import logging
import os

for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # before numpy loads
    os.environ.setdefault(var, "1")


def main(smk) -> None:
    from rigbuild.eval import reconstruction as ev

    log, inp, out = logging.getLogger("rigbuild.eval"), smk.input, smk.output
    if smk.rule == "eval_reconstruction":
        log.info("reconstruction vs ground truth: %s", ev.run_eval_reconstruction_pool(list(inp.fragments), out.metrics))
        return
    errors = ev.run_eval_reconstruction_sequence(inp.session_yaml, smk.wildcards.sequence, inp.cameras,
                                                 list(inp.records), list(inp.geometry), inp.rom, inp.actor_rig,
                                                 inp.truth_cameras, out.metrics, out.frames, log.info)
    log.info("%s vs ground truth: %s", smk.wildcards.sequence, errors)


from rigbuild.logs import run_logged  # noqa: E402

run_logged(snakemake, main)  # noqa: F821
