"""Snakemake entry point of rule ``report``: metrics.json and the stages' pictures -> the session's report.html."""

from rigbuild.logs import run_logged
from rigbuild.report.html import write_report


def main(smk) -> None:
    write_report(smk.input.metrics, smk.params.results_dir, smk.wildcards.session, smk.params.report, smk.output.html,
                 smk.output.assets, smk.params.primary)


run_logged(snakemake, main)  # noqa: F821
