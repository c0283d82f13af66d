"""Snakemake entry point of rules track_neutral, track_sequence and track_summary (rules/track.smk):
passes the rule's paths and ``params.track`` to rigbuild.track.stage (no `from __future__`: Snakemake
prepends its preamble)."""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def main(smk) -> None:
    from rigbuild.track import stage

    i, p, o = smk.input, smk.params, smk.output
    if smk.rule == "track_neutral":
        stage.run_track_neutral(p.session_dir, i.cameras, p.depth_dir, p.track, o.neutral, o.metrics)
    elif smk.rule == "track_sequence":
        stage.run_track_sequence(smk.wildcards.session, p.session_dir, i.cameras, i.neutral, smk.wildcards.sequence,
                                 p.depth_dir, p.anchor_depth_dir, p.track, int(smk.threads), dict(o.items()))
    elif smk.rule == "track_summary":
        stage.run_track_summary(list(i.sequence_metrics), o.summary, o.metrics)
    else:
        raise ValueError(f"scripts/track.py does not handle rule {smk.rule}")


if "snakemake" in globals():
    from rigbuild.logs import run_logged

    run_logged(snakemake, main)  # noqa: F821
