"""Snakemake entry point of rule ``metrics``: every metrics fragment of a session -> results/<session>/metrics.json."""

from rigbuild.io.atomic import write_json
from rigbuild.io.metrics import gather_metrics
from rigbuild.logs import run_logged


def main(smk) -> None:
    write_json(smk.output.metrics, gather_metrics(list(smk.input)))


run_logged(snakemake, main)  # noqa: F821
