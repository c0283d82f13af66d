"""Snakemake dry runs for the DAG tests: run one, and read the planned jobs out of its listing."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from rigbuild.paths import PROJECT_ROOT


def snakemake_dry_run(folder: Path, *args: str, configfile: Path | None = None) -> str:
    """``snakemake -n`` of the project's Snakefile in ``folder`` (its ``config.yaml`` unless ``configfile``);
    the listing (stdout + stderr); asserts that it succeeded."""
    exe = str(Path(sys.executable).with_name("snakemake"))
    r = subprocess.run([exe, "-n", "--configfile", str(configfile or folder / "config.yaml"), "--directory",
                        str(folder), "--snakefile", str(PROJECT_ROOT / "Snakefile"), "--cores", "1", *args],
                       capture_output=True, text=True, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"}, timeout=600)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out[-3000:]
    return out


def planned_jobs(out: str) -> list[tuple[str, dict]]:
    """(rule, wildcards) of every job of a dry run's listing."""
    jobs = []
    for block in re.split(r"\n(?=(?:localrule|rule) \w+:)", out):
        m = re.match(r"(?:localrule|rule) (\w+):", block)
        if not m:
            continue
        wc = re.search(r"^\s+wildcards: (.*)$", block, re.M)
        pairs = [p.split("=", 1) for p in wc.group(1).split(", ")] if wc else []
        jobs.append((m.group(1), dict(pairs)))
    return jobs
