"""The tiny synthetic session of the end-to-end tests and its one run, shared by tests/test_workflow_e2e.py and
tests/test_cluster_slurm.py (the session-scoped ``e2e_run`` fixture of tests/conftest.py runs it once per test
session): started, interrupted with SIGINT while reconstruction runs, and resumed as a user would (the same
command again). Every job as a separate process from files alone is shown by the SLURM run
(tests/test_cluster_slurm.py) and by one job through workflow/profiles/local-cluster (tests/test_workflow_e2e.py);
a whole resume through cluster-generic cost a snakemake start-up (about 4 s of CPU) per job."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml

from rigbuild.paths import PROJECT_ROOT

SNAKEMAKE = str(Path(sys.executable).with_name("snakemake"))
SUBMIT = str(PROJECT_ROOT / "workflow" / "profiles" / "local-cluster" / "submit.sh")


def e2e_config(tmp: Path) -> dict:
    base = yaml.safe_load((PROJECT_ROOT / "config" / "config.yaml").read_text())
    return {
        "sessions": {"e2e": {"path": str(tmp / "sessions" / "e2e"), "synthetic": {
            # the demo session's rig and cameras (config/config.yaml), fewer poses, frames and seconds
            **base["sessions"]["demo"]["synthetic"],
            "calib_poses": 12,
            "rom": {"n_sequences": 2, "frames_per_sequence": 5, "coverage": 1},
            "performance": {"n": 1, "duration_s": 3.0, "fps": 30.0, "noise_mm": 0.1, "gap_fraction": 0.01},
        }}},
        "characters": {"template": {"rig": "procedural", "kind": "template"}},
        "params": base["params"],
    }


def snakemake_cmd(tmp: Path, *extra: str) -> list[str]:
    return [SNAKEMAKE, "--snakefile", str(PROJECT_ROOT / "Snakefile"), "--directory", str(tmp),
            "--configfile", str(tmp / "config.yaml"), "--cores", "2", *extra]


def job_env() -> dict:
    return {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}


def run_e2e(tmp_path_factory) -> dict:
    """Run the session as described above; returns the folder, results, both runs' logs and what the checks need."""
    tmp = tmp_path_factory.mktemp("e2e")
    (tmp / "config.yaml").write_text(yaml.safe_dump(e2e_config(tmp)))
    results = tmp / "results" / "e2e"
    # 1. start, and interrupt while the reconstruction runs
    log1 = open(tmp / "run1.log", "w")
    # a shell starting pytest in the background makes it ignore SIGINT, and children inherit that:
    # give snakemake the default disposition back so Ctrl-C reaches it however the suite was started
    proc = subprocess.Popen(snakemake_cmd(tmp), stdout=log1, stderr=subprocess.STDOUT, env=job_env(),
                            start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 900
    interrupted = False
    while time.time() < deadline and proc.poll() is None:
        if (results / "calib" / "cameras.json").exists() and any((tmp / "logs" / "e2e").glob("reconstruct*/**/*.log")):
            # Ctrl-C; snakemake swallows a SIGINT that lands while it writes a log line, so press again
            # (as a user would) until it stops
            for _ in range(10):
                os.killpg(proc.pid, signal.SIGINT)
                interrupted = True
                try:
                    proc.wait(timeout=10)
                    break
                except subprocess.TimeoutExpired:
                    continue
            break
        time.sleep(1)
    proc.wait(timeout=300)
    log1.close()
    first = {p: p.stat().st_mtime_ns for p in (results / "calib").glob("*") if p.is_file()}
    locks = list((tmp / ".snakemake" / "locks").glob("*")) if (tmp / ".snakemake" / "locks").exists() else []
    # 2. resume: the same command again
    r2 = subprocess.run(snakemake_cmd(tmp), capture_output=True, text=True, env=job_env(), cwd=tmp, timeout=3000)
    return {"tmp": tmp, "results": results, "interrupted": interrupted, "first_calib": first, "locks": locks,
            "run2": r2, "run1_log": (tmp / "run1.log").read_text()}


def finished_rules(log: str) -> list[str]:
    """The rule of every job a Snakemake log reports finished (the ``all`` target left out), sorted."""
    return sorted(r for r in re.findall(r"^Finished jobid: \d+ \(Rule: (\w+)\)", log, flags=re.M) if r != "all")
