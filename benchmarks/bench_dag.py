"""DAG build time of each config (`snakemake -n`): how long a user waits before the first job of a tier starts.
Goal (architecture issue): config/ict-large.yaml (1,186 jobs, 16 cameras x 900 ROM frames) in < 30 s.

    .venv/bin/python benchmarks/bench_dag.py
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import print_table, write_result  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ["config/config.yaml", "config/demo-clean.yaml", "config/ict.yaml", "config/ict-large.yaml"]


def dry_run_seconds(config: str) -> tuple[float, int | None, str]:
    """Wall seconds of ``snakemake -n --configfile config``, the job count it plans, and its status."""
    snakemake = str(Path(sys.executable).with_name("snakemake"))
    t0 = time.perf_counter()
    r = subprocess.run([snakemake, "-n", "--cores", "1", "--configfile", config], cwd=ROOT, capture_output=True,
                       text=True, timeout=1200)
    seconds = time.perf_counter() - t0
    m = re.search(r"^total\s+(\d+)", r.stdout, re.M)
    return seconds, int(m.group(1)) if m else None, "ok" if r.returncode == 0 else (r.stdout + r.stderr)[-200:]


def main() -> None:
    rows = []
    for config in CONFIGS:
        seconds, jobs, status = dry_run_seconds(config)
        rows.append({"config": config, "seconds": seconds, "jobs": jobs, "status": status,
                     "goal_s": 30.0 if "ict-large" in config else None})
    print_table(rows, ["config", "seconds", "jobs", "goal_s", "status"])
    write_result("dag", {"dry_runs": rows})


if __name__ == "__main__":
    main()
