"""Compare two metrics.json files value by value (a refactor must leave every number as it was).

    python scripts/dev/compare_metrics.py BEFORE.json AFTER.json [--renames RENAMES.json] [--rtol 1e-9]
        [--merge-before PREFIX=FILE[:KEY] ...]

RENAMES.json maps an old flat key prefix to its new one ({"tracking.rom00_lost_frames":
"tracking.sequences.rom00.lost_frames"}); the longest matching prefix is applied to BEFORE's keys.
``--merge-before`` adds the scalars of another JSON file of the BEFORE run (its ``KEY`` member) under ``PREFIX``,
for values that run kept in a job's own file and the AFTER run also gathers into metrics.json (``tracking.per_sequence=
results/demo/track/track_summary.json:sequences``, renamed to ``tracking.sequences`` by
benchmarks/out/architecture/renames.json). Wall-clock keys (seconds, *_s, *_ms, frames_per_s) are left
out. Exit status 1 when a value differs or a key is missing on either side.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from rigbuild.io.metrics import flatten_metrics  # noqa: E402

TIMING = re.compile(r"(seconds|_s$|_ms$|_s_|frames_per_s|timings)")


def renamed(key: str, renames: dict[str, str]) -> str:
    for old in sorted(renames, key=len, reverse=True):
        if key == old or key.startswith(old + "."):
            return renames[old] + key[len(old):]
    return key


def same(a, b, rtol: float) -> bool:
    if isinstance(a, bool) or isinstance(b, bool) or not isinstance(a, (int, float)) or not isinstance(b, (int, float)):
        return a == b
    if math.isnan(a) and math.isnan(b):
        return True
    return abs(a - b) <= rtol * max(abs(a), abs(b), 1e-300)


def compare(before: dict, after: dict, renames: dict[str, str], rtol: float) -> list[str]:
    b = {renamed(k, renames): v for k, v in flatten_metrics(before).items() if not TIMING.search(k.split(".")[-1])}
    a = {k: v for k, v in flatten_metrics(after).items() if not TIMING.search(k.split(".")[-1])}
    problems = [f"missing after: {k} = {b[k]!r}" for k in sorted(set(b) - set(a))]
    problems += [f"new after: {k} = {a[k]!r}" for k in sorted(set(a) - set(b))]
    problems += [f"differs: {k}: {b[k]!r} -> {a[k]!r}" for k in sorted(set(a) & set(b)) if not same(b[k], a[k], rtol)]
    return problems


def merged_before(before: dict, spec: str) -> dict:
    """``before`` with the scalars of ``FILE[:KEY]`` under the dotted ``PREFIX`` (spec ``PREFIX=FILE[:KEY]``)."""
    prefix, _, source = spec.partition("=")
    path, _, member = source.partition(":")
    extra = json.loads(Path(path).read_text())
    extra = extra[member] if member else extra
    node = before
    for part in prefix.split("."):
        if not isinstance(node.get(part), dict):
            node[part] = {}
        node = node[part]
    for k, v in flatten_metrics(extra).items():
        if isinstance(v, (int, float, str, bool)) or v is None:
            node[k] = v
    return before


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before")
    ap.add_argument("after")
    ap.add_argument("--renames", help="JSON file: old flat key prefix -> new prefix")
    ap.add_argument("--rtol", type=float, default=1e-9)
    ap.add_argument("--merge-before", action="append", default=[], metavar="PREFIX=FILE[:KEY]")
    args = ap.parse_args(argv)
    renames = json.loads(Path(args.renames).read_text()) if args.renames else {}
    before = json.loads(Path(args.before).read_text())
    for spec in args.merge_before:
        before = merged_before(before, spec)
    after = json.loads(Path(args.after).read_text())
    problems = compare(before, after, renames, args.rtol)
    n = len(flatten_metrics(after))
    for p in problems:
        print(p)
    print(f"{n} keys after; {len(problems)} differences (timing keys left out)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
