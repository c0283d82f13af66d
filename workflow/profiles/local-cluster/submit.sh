#!/usr/bin/env bash
# Submit a Snakemake jobscript as a detached background process and print its id (the PID).
set -euo pipefail
jobscript="${@: -1}"
mkdir -p logs/cluster
out="logs/cluster/$(basename "$jobscript").out"
nohup bash "$jobscript" >"$out" 2>&1 </dev/null &
echo $!
