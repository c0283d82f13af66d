"""`make demo` resumes after an interruption and `make unlock` clears a stale lock (make -n: the commands only)."""

from __future__ import annotations

import shutil
import subprocess

import pytest

from rigbuild.paths import PROJECT_ROOT

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="GNU make is not installed")


def _make_n(target: str) -> list[str]:
    r = subprocess.run(["make", "-n", "--no-print-directory", target], cwd=PROJECT_ROOT, capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    return [line for line in r.stdout.splitlines() if "bin/snakemake" in line]


def test_demo_reruns_incomplete_jobs():
    runs = [line for line in _make_n("demo") if "--unlock" not in line]
    assert runs and all("--rerun-incomplete" in line for line in runs), runs


def test_unlock_target_runs_snakemake_unlock():
    assert any(line.rstrip().endswith("snakemake --unlock") for line in _make_n("unlock"))
