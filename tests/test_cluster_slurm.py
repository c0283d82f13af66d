"""A real SLURM run: the tiny synthetic session of tests/test_workflow_e2e.py, end to end through
``workflow/profiles/slurm`` (snakemake-executor-plugin-slurm) on a one-node cluster on this machine.

tests/cluster/slurm_up.sh starts munged, MariaDB + slurmdbd, slurmctld and slurmd (``make cluster-deps``
installs them from Debian); the module stops what it started. The local run it is compared with is the
e2e tests' own run of the session (the session-scoped ``e2e_run`` fixture, tests/e2e_run.py: interrupted,
then resumed), built while the SLURM run idles between its status checks, so the
suite builds the session's results twice, not three times.
Checks: every job but the local ``all`` target went through sbatch and sacct (from the accounting database)
lists it COMPLETED in partition ``cpu`` with its rule in the job comment; the SLURM run finished the same jobs
as the local one; its metrics equal the local run's within the pipeline's run-to-run noise (:data:`TOLERANCES`).

Skips (with the reason) when the plugin is not installed or this machine cannot host the cluster (not root,
or SLURM not installed); a cluster that is installed but does not come up fails.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from rigbuild.io.metrics import flatten_metrics
from rigbuild.paths import PROJECT_ROOT
from e2e_run import e2e_config, finished_rules, job_env
from test_workflow_e2e import out_of_bounds

SNAKEMAKE = str(Path(sys.executable).with_name("snakemake"))
CLUSTER = PROJECT_ROOT / "tests" / "cluster"
PROFILE = PROJECT_ROOT / "workflow" / "profiles" / "slurm"
STATE = Path(os.environ.get("RIGBUILD_SLURM_DIR", "/var/lib/rigbuild-slurm"))
#: wall-clock metrics (seconds, seconds_per_frame, runtime_s, build_s, frames_per_s, qp_median_ms, ...): not results
TIMING = re.compile(r"(^|_)(seconds|s|ms)(_|$)")
#: (pattern on the flat key, relative tolerance, absolute tolerance), first match wins; None: compared for
#: presence only. Runs are reproducible (rigbuild.determinism: OpenCV's calibration and open3d's Poisson on one
#: thread, seeded global generators): two local runs of this session at one commit gave bit-identical results,
#: 0 of 316 result metrics differing, and a SLURM job gets the same ``threads`` (hence BLAS threads) as a local
#: one. The tolerance only absorbs the JSON round trip. (Before the fix: cameras 5e-5 relative apart, a
#: tracking p95 16 % apart.)
TOLERANCES = [
    (r".", 1e-9, 1e-12),
]


@pytest.fixture(scope="module")
def cluster():
    pytest.importorskip("snakemake_executor_plugin_slurm",
                        reason="snakemake-executor-plugin-slurm is not installed: pip install -e '.[cluster]'")
    ours = not (STATE / "started").exists()  # a cluster someone else started stays up
    r = subprocess.run(["bash", str(CLUSTER / "slurm_up.sh")], capture_output=True, text=True, timeout=300)
    if r.returncode == 77:
        pytest.skip(f"no SLURM cluster on this machine: {r.stderr.strip()}")
    assert r.returncode == 0, f"tests/cluster/slurm_up.sh failed:\n{r.stdout}\n{r.stderr}"
    yield r.stdout
    if ours:
        subprocess.run(["bash", str(CLUSTER / "slurm_down.sh")], capture_output=True, timeout=120)


def _cmd(tmp: Path, *extra: str) -> list[str]:
    return [SNAKEMAKE, "--snakefile", str(PROJECT_ROOT / "Snakefile"), "--directory", str(tmp),
            "--configfile", str(tmp / "config.yaml"), *extra]


@pytest.fixture(scope="module")
def runs(cluster, tmp_path_factory, request):
    """The SLURM run of the e2e session, and as the local run the e2e tests' own run of it (``e2e_run``:
    interrupted, then resumed), built while the SLURM run waits on its status checks."""
    tmp = tmp_path_factory.mktemp("slurm")
    (tmp / "config.yaml").write_text(yaml.safe_dump(e2e_config(tmp)))
    # the plugin's default first status check is 40 s after each finish: fine on a farm, most of the run
    # time on 40 short jobs
    cmd = _cmd(tmp, "--profile", str(PROFILE), "--jobs", "2", "--slurm-init-seconds-before-status-checks", "2")
    with open(tmp / "run.log", "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=tmp, env=job_env())
        try:
            local = request.getfixturevalue("e2e_run")
            rc = proc.wait(timeout=3000)
        finally:
            if proc.poll() is None:
                proc.kill()
    r2 = local["run2"]
    return {"slurm": {"rc": rc, "tmp": tmp, "log": (tmp / "run.log").read_text(), "results": tmp / "results" / "e2e"},
            "local": {"rc": r2.returncode, "tmp": local["tmp"], "log": local["run1_log"] + r2.stdout + r2.stderr,
                      "results": local["results"]}}


def _sacct(ids: list[str]) -> list[dict]:
    r = subprocess.run(["sacct", "-X", "-P", "-j", ",".join(ids),
                        "-o", "JobID,JobName,State,ExitCode,Partition,AllocCPUS,Comment"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    keys = lines[0].split("|")
    return [dict(zip(keys, line.split("|", len(keys) - 1))) for line in lines[1:]]


def _rules_run(log: str) -> list[str]:
    return [m for m in re.findall(r"^(?:local)?rule (\w+):", log, flags=re.M) if m != "all"]


def test_both_runs_finish(runs):
    for name in ("local", "slurm"):
        assert runs[name]["rc"] == 0, f"{name} run failed:\n{runs[name]['log'][-5000:]}"


def test_every_job_went_through_sbatch_and_sacct_lists_it(runs):
    log = runs["slurm"]["log"]
    assert runs["slurm"]["rc"] == 0, log[-5000:]
    submitted = re.findall(r"Job (\d+) has been submitted with SLURM jobid (\d+)", log)
    rules = _rules_run(log)
    assert len(submitted) == len(rules) > 20, (len(submitted), len(rules))
    # the SLURM run ran the same jobs as the local one (before and after its interruption)
    assert finished_rules(log) == finished_rules(runs["local"]["log"]) == sorted(rules)
    rows = _sacct([sid for _, sid in submitted])
    assert len(rows) == len(submitted), rows
    assert {r["State"] for r in rows} == {"COMPLETED"}, [r for r in rows if r["State"] != "COMPLETED"]
    assert {r["Partition"] for r in rows} == {"cpu"}
    assert len({r["JobName"] for r in rows}) == 1  # the plugin names every job of a run by the run's uuid
    sacct_rules = sorted(re.match(r"rule_(\w+?)(_wildcards_.*)?$", r["Comment"]).group(1) for r in rows)
    assert sacct_rules == sorted(rules)


def _result_metrics(results: Path) -> dict:
    flat = flatten_metrics(json.loads((results / "metrics.json").read_text()))
    return {k: v for k, v in flat.items() if not TIMING.search(k.rsplit(".", 1)[-1])}


def _tolerance(key: str) -> tuple[float, float] | None:
    for pattern, rel, abs_ in TOLERANCES:
        if re.search(pattern, key):
            return None if rel is None else (rel, abs_)
    raise KeyError(f"{key}: no row of TOLERANCES covers it")


def metric_differences(local: dict, other: dict) -> list[str]:
    """The result metrics (flat, timings left out) of ``other`` that differ from ``local`` beyond
    :data:`TOLERANCES`, a key present in one only, or a non-numeric value that differs."""
    differ = [f"{k}: only in one run" for k in sorted(set(local) ^ set(other))]
    for k in sorted(set(local) & set(other)):
        a, b = local[k], other[k]
        numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (a, b))
        if not numeric:
            if a != b:
                differ.append(f"{k}: {a!r} vs {b!r}")
            continue
        tol = _tolerance(k)
        if tol is not None and abs(a - b) > tol[0] * max(abs(a), abs(b)) + tol[1]:
            differ.append(f"{k}: {a!r} vs {b!r} (tolerance {tol[0]:g} relative + {tol[1]:g})")
    return differ


def test_slurm_metrics_equal_the_local_run(runs):
    assert runs["slurm"]["rc"] == 0 and runs["local"]["rc"] == 0
    local = _result_metrics(runs["local"]["results"])
    slurm = _result_metrics(runs["slurm"]["results"])
    assert len(local) > 100
    differ = metric_differences(local, slurm)
    assert not differ, f"{len(differ)} of {len(local)} metrics differ: " + "; ".join(differ[:30])
    assert not out_of_bounds(flatten_metrics(json.loads((runs["slurm"]["results"] / "metrics.json").read_text())))
