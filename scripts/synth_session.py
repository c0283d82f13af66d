"""Snakemake entry point: generate one synthetic capture session (rigbuild.synth.session)."""

from rigbuild.logs import run_logged
from rigbuild.synth.session import generate_session


def main(snakemake):
    timings = generate_session(snakemake.params.folder, snakemake.params.session, snakemake.params.synthetic,
                               progress=print)
    print("generation timings:", timings)


run_logged(snakemake, main)  # noqa: F821 (snakemake is injected by the script directive)
