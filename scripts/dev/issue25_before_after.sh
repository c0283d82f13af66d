#!/usr/bin/env bash
# Issue 25: run a tier before or after the architecture refactor (cd5dd59; before it: 3b138e2), each with the
# reproducibility fix of dab17d0 applied on top (issue25-reproducibility.patch; without it neither commit repeats
# its own numbers), in a git worktree of its own, with this checkout's virtual environment.
#   scripts/dev/issue25_before_after.sh before|after CONFIG [WORKTREE] [snakemake options...]
#   e.g. scripts/dev/issue25_before_after.sh after config/ict.yaml /work/wt-after --cores 2
# Then: scripts/dev/compare_metrics.py BEFORE/results/<s>/metrics.json AFTER/results/<s>/metrics.json
#   --renames benchmarks/out/architecture/renames.json
#   --merge-before tracking.per_sequence=BEFORE/results/<s>/track/track_summary.json:sequences
set -euo pipefail
side=${1:?before or after}; config=${2:?a config file, e.g. config/ict.yaml}
top=$(git rev-parse --show-toplevel)
case "$side" in
  before) commit=3b138e2 ;;
  after) commit=cd5dd59 ;;
  *) echo "first argument: before or after, not '$side'" >&2; exit 2 ;;
esac
tree=${3:-$top/../wt-issue25-$side}
shift $(( $# < 3 ? $# : 3 ))
if [ ! -d "$tree" ]; then
  git -C "$top" worktree add --detach "$tree" "$commit"
  git -C "$tree" apply "$top/scripts/dev/issue25-reproducibility.patch"
  # an old mtime on every tracked file: nothing is re-run for being older than the checkout
  git -C "$tree" ls-files -z | (cd "$tree" && xargs -0 touch -h -d '2026-12-01')
fi
cd "$tree"
export PATH="$top/.venv/bin:$PATH" PYTHONPATH="$tree" OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1
export RIGBUILD_DATA="${RIGBUILD_DATA:-$(cd "$top/.." && pwd)/shared/data}"  # the checkout's data, not the worktree's
[ $# -gt 0 ] || set -- --cores 2
exec snakemake --configfile "$config" --rerun-incomplete "$@"
