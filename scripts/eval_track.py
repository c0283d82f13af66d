"""Snakemake entry point of rule eval_track (rules/eval_track.smk): tracking accuracy of a synthetic session
against its declared ground_truth/ files (no `from __future__`: Snakemake prepends its preamble)."""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def main(smk) -> None:
    from rigbuild.eval.tracking import run_eval_tracking

    i = smk.input
    run_eval_tracking(smk.params.session_dir, i.gt_cameras, list(i.gt_sequences), i.cameras, i.neutral,
                      list(i.vertices), smk.params.track, smk.output.metrics,
                      detail_path=smk.output.curves)


if "snakemake" in globals():
    from rigbuild.logs import run_logged

    run_logged(snakemake, main)  # noqa: F821
