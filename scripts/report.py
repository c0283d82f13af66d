"""Snakemake entry point: the self-contained HTML session report."""

from pathlib import Path

from rigbuild.io.atomic import write_text
from rigbuild.io.metrics import read_metrics
from rigbuild.logs import run_logged
from rigbuild.report.html import build_report


def main(snakemake):
    results_dir = Path(snakemake.params.results_dir)
    metrics = read_metrics(results_dir / "metrics.json")
    thresholds = {k: tuple(v) for k, v in snakemake.params.thresholds.items()}
    write_text(snakemake.output.html, build_report(results_dir, snakemake.wildcards.session, metrics, thresholds))


run_logged(snakemake, main)  # noqa: F821
