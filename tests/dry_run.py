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


def jobs_after_touching_the_personalized_rig(folder: Path, targets: list[str]) -> list[tuple[str, dict]]:
    """The jobs a dry run plans for ``targets`` of the demo session (config/config.yaml, session folder under
    ``folder``) once every file of their DAG is up to date at one time and then ``personalize/rig.npz`` is
    touched (``--rerun-triggers mtime``). The files are empty stand-ins (``session.yaml``: the generator's plan,
    read at DAG start); files outside ``folder`` (data, code) are only checked to exist."""
    import time

    import yaml

    from rigbuild.synth.session import plan_session

    cfg = yaml.safe_load((PROJECT_ROOT / "config" / "config.yaml").read_text())
    cfg["sessions"] = {"demo": {**cfg["sessions"]["demo"], "path": str(folder / "demo")}}
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg))
    listing = snakemake_dry_run(folder, "--forceall", *targets)
    files = set()
    for line in re.findall(r"^\s+(?:input|output): (.*)$", listing, re.M):
        files.update(p.strip() for p in line.split(", ") if p.strip())
    now = time.time() + 5  # later than any file outside the folder the DAG reads (the data, the code)
    made = 0
    for f in sorted(files):
        p = Path(f) if os.path.isabs(f) else folder / f
        if folder not in p.parents:
            assert p.exists(), p  # outside the test's folder: read, never written
            continue
        p.parent.mkdir(parents=True, exist_ok=True)
        if p.name == "session.yaml":
            p.write_text(yaml.safe_dump(plan_session("demo", cfg["sessions"]["demo"]["synthetic"])))
        elif p.suffix:
            p.touch()
        else:  # directory() outputs (no suffix: calib, rom, overlay, heatmaps, rig_obj)
            p.mkdir(exist_ok=True)
        made += 1
    for f in sorted(files):
        p = Path(f) if os.path.isabs(f) else folder / f
        if folder in p.parents:
            os.utime(p, (now, now))
    assert made > 50
    assert "Nothing to be done" in snakemake_dry_run(folder, "--rerun-triggers=mtime", *targets)
    rig = folder / "results" / "demo" / "personalize" / "rig.npz"
    assert rig.exists()
    os.utime(rig, (now + 10, now + 10))
    return planned_jobs(snakemake_dry_run(folder, "--rerun-triggers=mtime", *targets))
